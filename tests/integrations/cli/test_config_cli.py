"""The commands' flags come from their config dataclasses' fields (gensplat cache: GenSplatConfig;
record: RecordConfig and WorldConfig; demo: DemoConfig; train-model: TrainConfig and
LossWeights; calibrate estimate: EstimateConfig): defaults, types and parsing agree with the configs, no flag is declared twice, and
``gensplat calibrate``'s old spelling still works."""

import argparse
import ast
import inspect
import re
from dataclasses import fields
from pathlib import Path

import pytest
from gensplat_cli import build_parser, main
from gensplat_cli.commands import CALIBRATE_WAYS, _current_spelling

from gensplat_transforms.calibration.estimate import EstimateConfig
from gensplat_transforms.core import config_flags
from gensplat_transforms.core.config_flags import config_from_flags, field_default, flag_fields, flag_options
from gensplat_transforms.geometry.rgbd import RGBDConfig
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


def _configs() -> list[tuple[str, type]]:
    """(command, config dataclass) pairs: the config's fields with a flag (nested ones included)
    are flags of the command."""
    from gensplat_sim.demo import DemoConfig
    from gensplat_sim.record import RecordConfig

    from gensplat_transforms.training import TrainConfig

    return [("cache", GenSplatConfig), ("cache", RGBDConfig), ("demo", DemoConfig), ("record", RecordConfig),
            ("train-model", TrainConfig), ("calibrate estimate", EstimateConfig)]  # fmt: skip


def _commands(parser: argparse.ArgumentParser, path: tuple = ()) -> dict:
    """Every (sub)command's parser by its words, e.g. ("calibrate", "estimate")."""
    found = {path: parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.update(_commands(sub, (*path, name)))
    return found


def _declarations() -> list[tuple[str, tuple[str, ...], str, str | None]]:
    """(parser prog, option strings, declaring file, help) of every add_argument while the
    ``gensplat`` parser is built."""
    seen, add = [], argparse._ActionsContainer.add_argument

    def recording(self, *names, **options):
        caller = inspect.stack()[1]
        seen.append((self.prog, names, Path(caller.filename).resolve(), options.get("help")))
        return add(self, *names, **options)

    argparse._ActionsContainer.add_argument = recording
    try:
        build_parser()
    finally:
        argparse._ActionsContainer.add_argument = add
    return seen


#: flag names that several commands use for settings of their own (a literal declaration each)
SAME_NAME_OTHER_SETTING = {
    "--model": "cache: the reconstructor's checkpoint; calibrate estimate: a model for focal lengths and "
               "scale, alone the shipped one; train-model: the architecture's size",
    "--out": "preview: a folder; export-ply: a PLY file",
    "--episode": "preview: the episode shown (default 0); export-ply: the episode written (required)",
    "--size": "record: the recorded images' side; train-model: the training images' side",
}  # fmt: skip


def test_each_field_with_a_flag_has_exactly_one_with_the_fields_default():
    commands = _commands(build_parser())
    for command, config in _configs():
        parser = commands[tuple(command.split())]
        for f in flag_fields(config):
            flag, _options = flag_options(f)
            actions = [a for a in parser._actions if a.dest == f.name]
            assert [a.option_strings for a in actions] == [[flag]], (command, f.name)
            stated = "default" in f.metadata["cli"] or actions[0].required  # the flag states another default
            assert stated or actions[0].default == field_default(f), (command, f.name)
    parse = lambda *argv: commands[argv[:1]].parse_args(argv[1:])
    demo, train = dict(_configs())["demo"], dict(_configs())["train-model"]
    assert config_from_flags(parse("demo"), demo) == demo()
    assert config_from_flags(parse("train-model", "--out", "run", "--steps", "5"), train) == train(out="run", steps=5)
    changed = config_from_flags(parse("train-model", "--out", "r", "--steps", "5", "--warmup", "3", "--l-3d", "0.5"),
                                train)  # fmt: skip
    assert changed.warmup_steps == 3 and changed.loss.points == 0.5 and changed.loss.depth == 0.1
    cache = parse("cache", "--root", "r", "--repo-id", "x", "--fill-depth", "8")
    assert config_from_flags(cache, RGBDConfig) == RGBDConfig(fill_depth_px=8)
    estimate = commands["calibrate", "estimate"]
    assert config_from_flags(estimate.parse_args(["--root", "r"]), EstimateConfig) == EstimateConfig()
    given = estimate.parse_args(["--root", "r", "--fov", "69.4", "--table-distance", "0.5", "--timesteps", "4",
                                 "--principal-point", "311.7,255.4", "--per-episode"])  # fmt: skip
    assert config_from_flags(given, EstimateConfig) == EstimateConfig(
        timesteps=4, fov_deg=69.4, table_m=0.5, principal_point=((311.7, 255.4),), per_episode=True)
    assert estimate.parse_args(["--root", "r", "--model"]).model == "shipped"  # alone: the shipped model


def test_from_features_takes_the_estimates_intrinsics_flags():
    """``calibrate from-features``'s --fov and --focal are EstimateConfig's, made by the generator."""
    declared = _declarations()
    generated = Path(config_flags.__file__).resolve()
    mine = {names[0]: file for prog, names, file, _ in declared if prog == "gensplat calibrate from-features"}
    assert mine["--fov"] == generated and mine["--focal"] == generated
    args = _commands(build_parser())["calibrate", "from-features"].parse_args(["--root", "r", "--focal", "600"])
    assert (args.fov_deg, args.focal_px) == (None, 600.0)


def test_derived_flags_keep_their_help_and_defaults():
    commands = _commands(build_parser())
    options = {(c, o): a for c, p in commands.items() for a in p._actions for o in a.option_strings}
    assert options[("train-model",), "--lr"].help == "peak learning rate, cosine decay after the warm-up (default: 0.0002)"
    assert options[("train-model",), "--render-views"].help == "context views rendered per sample (default: all)"
    assert options[("train-model",), "--steps"].required and options[("train-model",), "--out"].required
    assert options[("record",), "--height"].help == "image height in pixels (default: --size)"
    assert options[("record",), "--height"].default is None and options[("record",), "--size"].default == 224
    assert options[("demo",), "--out"].help == "output folder (default: outputs/demo)"
    args = commands[("record",)].parse_args(["--out", "ds", "--images", "--sensor-depth", "--size", "96"])
    assert args.use_videos is False and args.sensor_depth is not None and args.height is None and args.size == 96


def test_no_flag_is_declared_twice():
    """A (sub)command's flag has one declaration: a config field's flag is made by the generator
    (never written in the CLI's source), and a flag name written in several add_argument calls
    of the source names a different setting in each (SAME_NAME_OTHER_SETTING)."""
    declared = _declarations()
    per_command = {}
    for prog, names, _, _ in declared:
        for name in names:
            per_command[prog, name] = per_command.get((prog, name), 0) + 1
    assert {k: n for k, n in per_command.items() if n > 1} == {}
    generated = {(prog, names[0]) for prog, names, file, _ in declared if file == Path(config_flags.__file__).resolve()}
    for command, config in _configs():
        for f in flag_fields(config):
            assert (f"gensplat {command}", flag_options(f)[0]) in generated, (command, f.name)
    sources = {file for _, _, file, _ in declared if file != Path(config_flags.__file__).resolve()}
    literal = {}
    for file in sources:
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
                for arg in node.args:
                    if isinstance(arg, ast.Constant) and str(arg.value).startswith("-"):
                        literal.setdefault(arg.value, []).append(f"{file.name}:{node.lineno}")
    twice = {name: where for name, where in literal.items() if len(where) > 1}
    assert set(twice) <= set(SAME_NAME_OTHER_SETTING), twice
    helps = {}
    for prog, names, _, help in declared:
        helps.setdefault(names[0], set()).add(help)
    for name in SAME_NAME_OTHER_SETTING:  # a different setting each time: no two with the same help
        assert len(helps[name]) == sum(n == name for _, names, _, _ in declared for n in names[:1]), name


def test_calibrate_has_a_subcommand_per_source_each_with_its_own_options():
    commands = _commands(build_parser())
    options = {way: {o for a in commands[("calibrate", way)]._actions for o in a.option_strings} - {"-h", "--help"}
               for way in CALIBRATE_WAYS}  # fmt: skip
    assert options == {
        "from-file": {"--root", "--convention"},
        "from-features": {"--root", "--intrinsics", "--fov", "--focal", "--cameras"},
        "estimate": {"--root", "--repo-id", "--fov", "--focal", "--model", "--per-episode", "--principal-point",
                     "--cameras", "--timesteps", "--baseline", "--table-distance"},
    }  # fmt: skip


@pytest.mark.parametrize("old, new", [
    (["--root", "r", "--from", "c.json", "--convention", "gensplat"],
     ["from-file", "c.json", "--root", "r", "--convention", "gensplat"]),
    (["--from=c.yaml", "--root", "r"], ["from-file", "c.yaml", "--root", "r"]),
    (["--root", "r", "--from-features", "--fov", "60"], ["from-features", "--root", "r", "--fov", "60"]),
    (["--root", "r", "--estimate", "--cameras", "a", "b"], ["estimate", "--root", "r", "--cameras", "a", "b"]),
])  # fmt: skip
def test_the_old_calibrate_spelling_is_rewritten_with_a_note(old, new, capsys):
    assert _current_spelling(["calibrate", *old]) == ["calibrate", *new]
    err = capsys.readouterr().err
    assert re.fullmatch(rf"gensplat: note: `calibrate --[a-z-]+( FILE)?` is deprecated; it is now `gensplat calibrate "
                        rf"{new[0]}( FILE)?`\n", err), err  # fmt: skip
    assert _current_spelling(["calibrate", *new]) == ["calibrate", *new] and capsys.readouterr().err == ""


@pytest.mark.parametrize("old", [["--from", "c.json"], ["--from-features", "--fov", "60"], ["--estimate"]])
def test_the_old_calibrate_spelling_still_runs(old, tmp_path, capsys):
    """The old spelling reaches the new subcommand: here its refusal of a folder that is no dataset."""
    assert main(["calibrate", "--root", str(tmp_path / "none"), *old]) == 2
    note, error = capsys.readouterr().err.splitlines()
    assert note.startswith("gensplat: note: `calibrate --") and "is deprecated" in note
    assert error.startswith("gensplat: error: ") and "not a local LeRobot dataset" in error
