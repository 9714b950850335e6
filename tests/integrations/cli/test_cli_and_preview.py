"""The command-line demo and help, and the episode preview."""

import argparse
import importlib.metadata
import importlib.util
import json
import os
import subprocess
import tomllib
from pathlib import Path

import pytest
from gensplat_cli import build_parser, main
from PIL import Image

import gensplat_transforms
from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.rendering.preview import write_preview
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform
from gensplat_transforms.views.perturbation import EVAL_LEVELS


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
    cache = SceneCache(tmp_path / "c", rec, source.fingerprint)
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


def test_version_has_one_source(capsys):
    """``gensplat --version``, the installed distribution's metadata and pyproject.toml all read
    ``gensplat_transforms.__version__``."""
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out == f"gensplat-transforms {gensplat_transforms.__version__}\n"
    project = tomllib.loads((Path(__file__).parents[3] / "pyproject.toml").read_text())
    assert "version" not in project["project"] and project["project"]["dynamic"] == ["version"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "gensplat_transforms.__version__"}
    assert importlib.metadata.version("gensplat-transforms") == gensplat_transforms.__version__


def _default_text(default) -> str:
    return " ".join(map(str, default)) if isinstance(default, list | tuple) else str(default)


def test_every_option_says_what_it_does_and_its_default():
    parser = build_parser()
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert {"demo", "record", "cache", "train-model", "preview", "export-ply"} <= set(commands.choices)
    problems, subcommands = [], list(commands.choices.items())
    for name, sub in subcommands:
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            if isinstance(action, argparse._SubParsersAction):  # calibrate from-file, from-features, estimate
                subcommands += [(f"{name} {way}", parser) for way, parser in action.choices.items()]
                continue
            option = f"{name} {'/'.join(action.option_strings)}"
            text = (action.help or "") % {**vars(action), "prog": sub.prog}
            if not text.strip():
                problems.append(f"{option}: no help")
            elif action.nargs != 0 and action.default is not None and _default_text(action.default) not in text:
                problems.append(f"{option}: default {action.default!r} not in {text!r}")
    assert not problems, "\n".join(problems)


REPO = Path(__file__).resolve().parents[3]


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_preview_example_runs_twice_from_any_folder(tmp_path, monkeypatch):
    example = load_example("preview_episode")
    assert example.OUT == REPO / "outputs" / "preview"  # the default does not depend on the folder
    monkeypatch.chdir(tmp_path)
    for _ in range(2):  # the second run replaces the files in the existing folder
        paths = example.main(["--out", "out", "--level", "small", "--frames", "3", "--size", "32"])
        assert {p.resolve() for p in paths.values()} == {tmp_path / "out" / "preview.png", tmp_path / "out" / "preview.mp4"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_dataloader_example_runs_twice_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    example = load_example("custom_dataloader")
    for _ in range(2):
        batches = example.main(["--workers", "0", "--size", "24"])
        assert sum(len(b["frame_index"]) for b in batches) == 16  # 2 episodes x 8 frames
    assert not list(tmp_path.iterdir())  # nothing left behind


STUB = """#!/usr/bin/env bash
printf '%s\\0' "$(basename "$0")" "$@" --- >> "$STUB_LOG"
if [ "$(basename "$0")" = python ]; then mkdir -p "$3"; fi
for a in "$@"; do case "$a" in --output_dir=*)
  [ -e "${a#*=}" ] && { echo "output directory exists" >&2; exit 1; }; mkdir -p "${a#*=}" ;; esac; done
"""


def test_lerobot_example_uses_the_project_environment_from_any_folder_twice(tmp_path):
    """The shell example with stand-ins for the environment's python, gensplat and lerobot-train
    (each logs its arguments; lerobot-train refuses an existing output folder, as LeRobot's does)."""
    repo = tmp_path / "repo"
    (repo / "examples").mkdir(parents=True)
    (repo / "examples" / "lerobot_one_line.sh").write_text((REPO / "examples" / "lerobot_one_line.sh").read_text())
    (repo / ".venv" / "bin").mkdir(parents=True)
    for name in ("python", "gensplat", "lerobot-train"):
        (repo / ".venv" / "bin" / name).write_text(STUB)
        (repo / ".venv" / "bin" / name).chmod(0o755)
    log, cwd = tmp_path / "log", tmp_path / "elsewhere"
    cwd.mkdir()
    env = {**os.environ, "STUB_LOG": str(log), "PATH": "/usr/bin:/bin"}  # no python, gensplat on PATH
    for _ in range(2):
        run = subprocess.run(["bash", str(repo / "examples" / "lerobot_one_line.sh")], cwd=cwd, env=env,
                             capture_output=True, text=True, check=False)  # fmt: skip
        assert run.returncode == 0, run.stderr
    calls = [c.split("\0") for c in log.read_text().split("\0---\0")[:-1]]  # NUL-separated
    assert [c[0] for c in calls] == ["python", "gensplat", "lerobot-train", "gensplat", "lerobot-train"]
    root = repo / "outputs" / "scene_dataset"
    assert calls[1][:5] == ["gensplat", "cache", "--root", str(root), "--repo-id"]
    train = [dict(a.split("=", 1) for a in c[1:] if "=" in a) for c in calls if c[0] == "lerobot-train"]
    assert {t["--config_path"] for t in train} == {str(repo / "policies" / "diffusion.json")}
    assert train[0]["--output_dir"] != train[1]["--output_dir"]
    assert not list(cwd.iterdir())  # nothing written into the working folder
