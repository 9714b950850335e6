"""The command-line demo and help, and the episode preview."""

import argparse
import json

from PIL import Image

from gensplat_transforms.cache import GaussianCache
from gensplat_transforms.cli import build_parser, main
from gensplat_transforms.episodes import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.perturbation import EVAL_LEVELS
from gensplat_transforms.preview import write_preview
from gensplat_transforms.reconstruction import RGBDReconstructor
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform


def test_demo_records_caches_and_previews(tmp_path, capfd, caplog):
    assert main(["demo", "--out", str(tmp_path), "--episodes", "1", "--size", "64"]) == 0
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert list(summary["levels"]) == list(EVAL_LEVELS)
    levels = summary["levels"]
    assert levels["none"]["coverage"] > 0.99
    assert levels["none"]["psnr_db"] > levels["extreme"]["psnr_db"] > 10
    assert 0 < summary["cache_bytes_per_timestep"] < 1e6
    for name in ("levels.png", "preview.png", "preview.mp4"):
        assert (tmp_path / name).stat().st_size > 0
    assert Image.open(tmp_path / "levels.png").height > 5 * 64  # one row per level
    out, err = capfd.readouterr()
    assert "PSNR" in out
    # no alarming traceback, e.g. LeRobot's when torchcodec cannot load FFmpeg (the decoder is chosen up front)
    assert "Traceback" not in out + err + caplog.text
    # a second run reuses the dataset and the cache
    main(["demo", "--out", str(tmp_path), "--episodes", "1", "--size", "64"])
    out, err = capfd.readouterr()
    assert "using the simulated dataset already" in out and "Traceback" not in out + err + caplog.text


def test_preview_png_and_mp4(tmp_path):
    source = SceneEpisodes(num_episodes=1, num_frames=4, size=32)
    rec = RGBDReconstructor()
    cache = GaussianCache(tmp_path / "c", rec, source.fingerprint)
    build_cache(cache, source, [0], progress=False)
    ds = SceneDataset(source)
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, level="medium"), cache)
    paths = write_preview([ds[i] for i in range(4)], tf, ["left", "right"], tmp_path / "p", max_rows=2)
    png = Image.open(paths["png"])
    assert png.width > 4 * 32 and png.height > 2 * 32
    assert paths["mp4"].stat().st_size > 0
    import av

    with av.open(str(paths["mp4"])) as f:
        assert sum(1 for _ in f.decode(video=0)) == 4


def _default_text(default) -> str:
    return " ".join(map(str, default)) if isinstance(default, list | tuple) else str(default)


def test_every_option_says_what_it_does_and_its_default():
    parser = build_parser()
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert {"demo", "record", "cache", "train-model"} <= set(commands.choices)
    problems = []
    for name, sub in commands.choices.items():
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            option = f"{name} {'/'.join(action.option_strings)}"
            text = (action.help or "") % {**vars(action), "prog": sub.prog}
            if not text.strip():
                problems.append(f"{option}: no help")
            elif action.nargs != 0 and action.default is not None and _default_text(action.default) not in text:
                problems.append(f"{option}: default {action.default!r} not in {text!r}")
    assert not problems, "\n".join(problems)
