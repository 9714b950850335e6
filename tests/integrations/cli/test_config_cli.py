"""gensplat cache's transform flags come from GenSplatConfig's fields: defaults, types and
parsing agree with the config, so the two cannot drift apart."""

import argparse
from dataclasses import fields

import pytest
from gensplat_cli import build_parser

from gensplat_transforms.settings import GenSplatConfig, add_config_arguments, config_from_arguments

BASE = ["cache", "--root", "r", "--repo-id", "x/y"]


def test_no_flags_give_the_configs_defaults():
    args = build_parser().parse_args(BASE)
    assert config_from_arguments(args, cameras=("left", "right")) == GenSplatConfig(cameras=("left", "right"))


def test_every_flag_reaches_its_field():
    args = build_parser().parse_args([
        *BASE, "--replace", "left", "--probability", "0.25", "--level", "small", "--mode", "frame",
        "--views-per-source", "5", "--seed", "7", "--keep-depth-maps", "--backend", "reference", "--no-fill-holes",
        "--render-in", "batch", "--render-scale", "0.5",
    ])  # fmt: skip
    got = config_from_arguments(args, cameras=("left", "right"))
    assert got == GenSplatConfig(cameras=("left", "right"), replace=("left",), probability=0.25, level="small",
                                 mode="frame", views_per_source=5, seed=7, depth_unit="keep", backend="reference",
                                 fill_holes=False, render_in="batch", render_scale=0.5)  # fmt: skip


def test_each_field_with_a_flag_is_on_the_parser_with_its_default():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    flagged = {f.name: f.default for f in fields(GenSplatConfig) if "cli" in f.metadata}
    assert len(flagged) == 17
    assert vars(parser.parse_args([])) == flagged
    zoom = vars(parser.parse_args(["--sampler", "arc", "--focal-scale", "0.8", "1.25"]))
    assert GenSplatConfig(**zoom).focal_scale == (0.8, 1.25) and GenSplatConfig(**zoom).sampler == "arc"
    assert GenSplatConfig(**vars(parser.parse_args(["--sampler", "tilt,arc"]))).sampler == "tilt,arc"


def test_a_bad_choice_or_type_is_a_usage_error():
    for bad in (["--mode", "sometimes"], ["--probability", "half"], ["--render-in", "gpu"], ["--sampler", "orbit"],
                ["--sampler", "tilt,tilt"],
                ["--focal-scale", "0.8"]):  # fmt: skip
        with pytest.raises(SystemExit):
            build_parser().parse_args([*BASE, *bad])
