"""The arms of benchmarks/policy_robustness.py: what each passes to lerobot-train (and that
LeRobot's config accepts it), the perspective arm's transform, the comparisons, and the
settings checks of --reuse-from and of a resumed --work."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import policy_robustness as pr
from lerobot.configs.default import DatasetConfig
from lerobot.transforms import ImageTransforms, ImageTransformsConfig
from lerobot.transforms.transforms import ImageTransformConfig, make_transform_from_config

ROOT, OUT, CONFIG = Path("/data/ds"), Path("/work/arm"), Path("/work/diffusion.json")


def image_transforms(extra: list[str]) -> ImageTransformsConfig:
    """LeRobot's image-transforms config parsed from an arm's ``--dataset.*`` arguments."""
    import draccus

    args = [a.removeprefix("--dataset.") for a in extra]
    return draccus.parse(DatasetConfig, args=["--repo_id=x", *(f"--{a}" for a in args)]).image_transforms


def test_each_arm_passes_its_augmentation_to_lerobot_train():
    args = pr.parse_args([])
    assert args.arms == pr.ARMS and args.episodes == 100 and args.probability == 0.25
    commands = {arm: pr.train_command(arm, ROOT, OUT, CONFIG, args) for arm in pr.ARMS}
    base = commands["baseline"]
    assert base[:4] == ["bash", str(pr.ROOT / "policies" / "train.sh"), str(CONFIG), "baseline"]
    assert (
        f"--steps={args.steps}" in base and f"--dataset.root={ROOT}" in base and f"--output_dir={OUT}" in base
    )
    assert not any("image_transforms" in a for a in base)
    for arm, cmd in commands.items():  # the same training but for the mode and the added arguments
        mode = "gensplat" if arm in pr.GENSPLAT_ARMS else "baseline"
        assert cmd[3] == mode and cmd[: len(base)] == [*base[:3], mode, *base[4:]], arm
        extra = cmd[len(base) :]
        assert extra == pr.arm_arguments(arm, args)[1:]
        if arm == "baseline" or arm == "gensplat" or arm in pr.SAMPLER_ARMS:
            assert extra == []
            continue
        config = image_transforms(extra)
        assert config.enable
        transforms = ImageTransforms(config)  # every transform exists in LeRobot / torchvision
        if arm == "perspective":
            assert config.max_num_transforms == 1 and list(config.tfs) == ["perspective"]
            tf = config.tfs["perspective"]
            assert tf.type == "RandomPerspective"
            assert tf.kwargs == {"distortion_scale": pr.PERSPECTIVE_DISTORTION, "p": args.probability}
        elif arm == "gensplat+color":  # the colour and sharpness jitter of lerobot2d alone
            assert config.max_num_transforms == 3
            assert set(config.tfs) == {"brightness", "contrast", "saturation", "hue", "sharpness"}
        else:  # lerobot2d and gensplat+lerobot2d: the same 2D augmentation
            assert config.max_num_transforms == 3
            assert set(config.tfs) == {
                "brightness",
                "contrast",
                "saturation",
                "hue",
                "sharpness",
                "affine",
                "crop",
            }
            assert config.tfs["affine"].kwargs["degrees"] == [-20.0, 20.0]
            assert config.tfs["crop"].kwargs["size"] == [args.size, args.size]
        for image in (torch.rand(3, 96, 96), torch.randint(0, 256, (2, 3, 96, 96), dtype=torch.uint8)):
            out = transforms(image)
            assert out.shape == image.shape and out.dtype == image.dtype
    augment = pr.result_settings(args)["augmentation"]
    assert augment["baseline"] == {} and set(augment["gensplat+lerobot2d"]) == {
        "gensplat",
        "image_transforms",
    }
    assert (
        augment["gensplat"]["gensplat"]["replace"] == ["left"]
        and augment["gensplat"]["gensplat"]["probability"] == 0.25
    )
    # the wider arms: the same settings but for their sampler, each on its own dataset root
    paper, wide, fov = (pr.gensplat_config(args, arm) for arm in ("gensplat", "gensplat-wide", "gensplat-fov"))
    assert (paper.sampler, paper.focal_scale) == ("paper", (1.0, 1.0))
    assert (wide.sampler, wide.arc_deg, wide.tilt_deg, wide.focal_scale) == ("mix", 45.0, 10.0, (1.0, 1.0))
    assert (fov.sampler, fov.focal_scale) == ("paper", (0.8, 1.25))
    assert replace(wide, sampler="paper", tilt_deg=paper.tilt_deg, arc_deg=paper.arc_deg) == paper
    assert augment["gensplat-wide"]["gensplat"] == {**augment["gensplat"]["gensplat"], "sampler": "mix",
                                                    "tilt_deg": 10.0, "arc_deg": 45.0, "shift_m": 0.03}  # fmt: skip
    assert augment["gensplat-fov"]["gensplat"] == {**augment["gensplat"]["gensplat"], "focal_scale": [0.8, 1.25]}
    for arm, kind in (("gensplat-tilt", "tilt"), ("gensplat-arc", "arc")):  # the wide arm's moves, one kind each
        config = pr.gensplat_config(args, arm)
        assert (config.sampler, config.tilt_deg, config.arc_deg, config.shift_m) == (kind, wide.tilt_deg, wide.arc_deg,
                                                                                      wide.shift_m)  # fmt: skip
        assert replace(config, sampler="mix") == wide
    for arm, (like, probability) in pr.MORE_OFTEN.items():  # another arm's moves, drawn more often
        config = pr.gensplat_config(args, arm)
        assert config.probability == probability != args.probability
        assert replace(config, probability=args.probability) == pr.gensplat_config(args, like)
        assert augment[arm]["gensplat"] == {**augment[like]["gensplat"], "probability": probability}
        assert pr.dataset_root(work := Path("work"), arm) == work / f"dataset_{arm}"
    assert pr.gensplat_config(pr.parse_args(["--probability", "0.1"]), "gensplat-arc-p0.5").probability == 0.5
    work = Path("work")
    assert {pr.dataset_root(work, a) for a in pr.ARMS if a not in pr.SAMPLER_ARMS} == {work / "dataset"}
    assert pr.dataset_root(work, "gensplat-fov") == work / "dataset_gensplat-fov"
    assert pr.parse_args(["--arms", "gensplat,baseline"]).arms == ("baseline", "gensplat")  # in ARMS order
    with pytest.raises(SystemExit):
        pr.parse_args(["--arms", "baseline,mixup"])
    with pytest.raises(SystemExit):  # LeRobot would warp the wrist camera too
        pr.parse_args(["--cameras", "left,wrist", "--arms", "perspective"])
    assert pr.parse_args(["--cameras", "left,wrist", "--arms", "lerobot2d"]).arms == ("lerobot2d",)


def perspective(distortion: float, probability: float = 1.0):
    kwargs = {
        **pr.perspective_transforms(probability)["tfs"]["perspective"]["kwargs"],
        "distortion_scale": distortion,
    }
    return make_transform_from_config(ImageTransformConfig(type="RandomPerspective", kwargs=kwargs))


def test_perspective_transform():
    torch.manual_seed(0)
    image = torch.rand(3, 96, 96)
    torch.testing.assert_close(perspective(0.0)(image), image, atol=1e-5, rtol=0)  # zero distortion: identity
    warp = perspective(pr.PERSPECTIVE_DISTORTION)
    for x in (image, (image * 255).to(torch.uint8)):
        out = warp(x)
        assert out.shape == x.shape and out.dtype == x.dtype and not torch.equal(out, x)
        if x.is_floating_point():
            assert torch.isfinite(out).all() and 0 <= out.min() and out.max() <= 1
    stack = warp(image.expand(2, 3, 96, 96))  # a temporal stack: one warp for every frame
    assert stack.shape == (2, 3, 96, 96) and torch.equal(stack[0], stack[1])
    sometimes = perspective(pr.PERSPECTIVE_DISTORTION, probability=0.25)  # GenSplat's default probability
    warped = sum(not torch.equal(sometimes(image), image) for _ in range(800)) / 800
    assert abs(warped - 0.25) < 0.05


def records(successes: list[bool], level: str) -> dict:
    episodes = [{"level": level, "episode": i, "success": s} for i, s in enumerate(successes)]
    return {"success": 100 * sum(successes) / len(successes), "episodes": episodes,
            "progress": {"lift_percent": 0.0, "median_reach_cm": 3.0}}  # fmt: skip


def evaluation(solved: dict[str, int], episodes: int) -> dict:
    """{protocol: {arm: {level: record}}} in which each arm solves its first ``solved[arm]``
    episodes at every level."""
    return {protocol: {arm: {lv: records([i < k for i in range(episodes)], lv) for lv in levels}
                       for arm, k in solved.items()} for protocol, levels in pr.PROTOCOLS.items()}  # fmt: skip


def test_result_compares_every_arm_under_both_protocols(tmp_path, capsys):
    solved = {"baseline": 2, "lerobot2d": 4, "perspective": 6, "gensplat": 9, "gensplat+lerobot2d": 7, "gensplat+color": 8,
              "gensplat-wide": 5, "gensplat-fov": 3, "gensplat-tilt": 4, "gensplat-arc": 6, "gensplat-fov-p0.5": 4,
              "gensplat-arc-p0.5": 5, "gensplat-tiltarc": 6, "gensplat-zoom": 7, "gensplat-unmoved": 5,
              "gensplat-wide-p0.5": 6}  # fmt: skip
    args = pr.parse_args(["--episodes", "10"])
    result = pr.build_result(evaluation(solved, 10), 10, False, pr.result_settings(args), {})
    assert list(result["protocols"]) == ["vista", "fov"] and result["episodes_per_level"] == 10
    for part, levels in ((result, pr.LEVELS), (result["protocols"]["vista"], ("small_perturb", "arc_90deg")),
                         (result["protocols"]["fov"], ("zoom",))):  # fmt: skip
        assert part["levels"] == list(levels) and list(part["arms"]) == list(pr.ARMS)
        assert part["arms"]["gensplat"] == dict.fromkeys(levels, 90.0) and part["best_2d"] == "perspective"
        diff = part["difference"]
        assert set(diff) == {"vs_baseline", "vs_2d"} and set(diff["vs_baseline"]) == set(pr.ARMS) - {"baseline"}
        assert set(diff["vs_2d"]) == set(pr.TWO_D_ARMS) and set(diff["vs_2d"]["perspective"]) == set(pr.GENSPLAT_ARMS)
        assert all(diff["vs_baseline"]["gensplat"][lv]["points"] == 70.0 for lv in levels)
        best = diff["vs_2d"][part["best_2d"]]
        assert best["gensplat+lerobot2d"][levels[-1]] == {
            "points": 10.0, "ci95": best["gensplat+lerobot2d"][levels[-1]]["ci95"],
            "a_only": 0, "b_only": 1, "mcnemar_p": 1.0}  # fmt: skip
        assert all(diff["vs_2d"]["lerobot2d"]["gensplat"][lv]["points"] == 50.0 for lv in levels)
        assert {e["level"] for e in part["episodes"]["lerobot2d"]} == set(levels) and len(
            part["episodes"]["lerobot2d"]
        ) == 10 * len(levels)
    pr.print_summary(result)
    out = capsys.readouterr().out
    assert "gensplat - perspective (best 2D)" in out and "gensplat - lerobot2d:" in out
    table = pr.markdown(result)  # the tables of benchmarks/README.md
    assert "| gensplat | 90 (+70 [" in table and "| baseline | 20 | 20 | 20 | 20 |" in table
    assert "| gensplat+lerobot2d - perspective, the best 2D arm | +10 [" in table
    assert table.count("| arm |") == len(pr.PROTOCOLS)
    pr.plot(result, tmp_path / "plot.png")  # every arm's line, in its colour
    image = np.asarray(Image.open(tmp_path / "plot.png").convert("RGB")).astype(int)
    for rgb in pr.COLOURS.values():
        assert (np.abs(image - rgb).sum(-1) < 10).sum() > 50, rgb


def test_best_2d_and_missing_references():
    rates = {"baseline": {"none": 50, "large": 0}, "lerobot2d": {"none": 90, "large": 10},
             "perspective": {"none": 10, "large": 20}}  # fmt: skip
    assert pr.best_2d(rates) == "perspective"  # over the perturbed levels only
    assert pr.best_2d({"baseline": rates["baseline"]}) is None
    evaluated = evaluation({"lerobot2d": 1, "gensplat": 2}, 4)["paper"]  # no baseline
    assert set(pr.comparisons(evaluated)) == {"vs_2d"} and set(pr.comparisons(evaluated)["vs_2d"]) == {"lerobot2d"}
    assert pr.comparisons(evaluation({"gensplat": 2}, 4)["paper"]) == {}


def earlier_result(path: Path, args, arms: tuple[str, ...], episodes: int, quick: bool = False) -> Path:
    """A result file as the script writes it, for ``arms`` evaluated under ``args``."""
    timing = {f"train_{a}": {"s_per_step": 1.0} for a in arms}
    evaluated = evaluation(dict.fromkeys(arms, episodes // 2), episodes)
    path.write_text(json.dumps(pr.build_result(evaluated, episodes, quick, pr.result_settings(args), timing)))
    return path


def test_reuse_checks_the_settings(tmp_path, capsys, monkeypatch):
    args = pr.parse_args(["--episodes", "4"])
    old = earlier_result(tmp_path / "old.json", args, ("baseline", "gensplat"), 4)
    settings = pr.result_settings(args)
    reused, timing, sources = pr.reused_arms([old], args.arms, settings, 4)
    assert sources == {"baseline": "old.json", "gensplat": "old.json"}
    assert set(reused["paper"]) == set(reused["vista"]) == {"baseline", "gensplat"}
    assert [e["episode"] for e in reused["vista"]["gensplat"]["arc_90deg"]["episodes"]] == [0, 1, 2, 3]
    assert reused["paper"]["baseline"]["small"]["success"] == 50.0 and timing["train_gensplat"] == {
        "s_per_step": 1.0
    }
    # another GenSplat probability: the baseline is reused, GenSplat is named and trained again
    other = pr.parse_args(["--episodes", "4", "--probability", "0.5"])
    _, _, sources = pr.reused_arms([old], other.arms, pr.result_settings(other), 4)
    assert sources == {"baseline": "old.json"} and "not reusing gensplat" in capsys.readouterr().out
    # other common settings or another episode count: nothing is reused
    for argv, episodes in ((["--episodes", "4", "--steps", "100"], 4), (["--episodes", "5"], 5)):
        changed = pr.parse_args(argv)
        assert pr.reused_arms([old], changed.arms, pr.result_settings(changed), episodes)[2] == {}
    # the first file that holds an arm with matching settings decides
    newer = earlier_result(tmp_path / "newer.json", args, ("lerobot2d", "gensplat"), 4)
    _, _, sources = pr.reused_arms([newer, old], args.arms, settings, 4)
    assert sources == {"lerobot2d": "newer.json", "gensplat": "newer.json", "baseline": "old.json"}
    # an arm a file did not evaluate under every protocol is reused under those it has
    partial = json.loads(old.read_text())
    del partial["protocols"]["fov"]
    del partial["protocols"]["vista"]["arms"]["gensplat"]
    (tmp_path / "partial.json").write_text(json.dumps(partial))
    capsys.readouterr()
    reused, _, sources = pr.reused_arms([tmp_path / "partial.json"], args.arms, settings, 4)
    assert sources == {"baseline": "partial.json", "gensplat": "partial.json"}
    assert set(reused["paper"]) == {"baseline", "gensplat"} and set(reused["vista"]) == {"baseline"}
    assert reused["fov"] == {}
    out = capsys.readouterr().out
    assert "reusing gensplat from" in out and "(not evaluated under vista, fov: left out of those tables)" in out
    # not reusable at all: a quick check, a file that is not a result, episodes missing, a broken file
    quick = earlier_result(tmp_path / "quick.json", args, ("baseline",), 4, quick=True)
    legacy = tmp_path / "legacy.json"
    legacy.write_text(json.dumps({"baseline": {}, "quick": False}))
    gap = json.loads(old.read_text())
    gap["protocols"]["vista"]["episodes"]["baseline"].pop(2)
    (tmp_path / "gap.json").write_text(json.dumps(gap))
    (tmp_path / "cut.json").write_text(old.read_text()[:200])  # a copy cut short
    for path, message in (
        (quick, "quick"),
        (legacy, "not a result of policy_robustness.py"),
        (tmp_path / "gap.json", "not all there"),
        (tmp_path / "cut.json", "cut.json: not JSON"),
        (tmp_path / "missing.json", "missing.json: cannot read it"),
    ):
        with pytest.raises(SystemExit, match=message):
            pr.reused_arms([path], args.arms, settings, 4)
    for path in (legacy, tmp_path / "cut.json", tmp_path / "missing.json"):  # --table reads them the same way
        monkeypatch.setattr(sys, "argv", ["policy_robustness.py", "--table", str(path)])
        with pytest.raises(SystemExit, match=f"--table {path}: (not a result|not JSON|cannot read it)"):
            pr.main()


def test_a_run_of_reused_arms_only_trains_and_evaluates_nothing(tmp_path, monkeypatch):
    args = pr.parse_args(["--episodes", "4"])
    old = earlier_result(tmp_path / "old.json", args, ("baseline", "perspective", "gensplat"), 4)
    out, work = tmp_path / "new.json", tmp_path / "work"
    argv = [
        "--episodes",
        "4",
        "--arms",
        "gensplat,baseline",
        "--reuse-from",
        str(old),
        "--out",
        str(out),
        "--work",
        str(work),
    ]
    monkeypatch.setattr(sys, "argv", ["policy_robustness.py", *argv])
    pr.main()
    assert not work.exists()  # no recording, no training
    result, before = json.loads(out.read_text()), json.loads(old.read_text())
    assert result["settings"]["reused"] == {"baseline": "old.json", "gensplat": "old.json"}
    assert list(result["arms"]) == ["baseline", "gensplat"] and result["best_2d"] is None
    assert result["episodes"]["gensplat"] == before["episodes"]["gensplat"]
    assert (
        result["protocols"]["vista"]["episodes"]["baseline"]
        == before["protocols"]["vista"]["episodes"]["baseline"]
    )
    assert set(result["difference"]) == {"vs_baseline"} and out.with_suffix(".png").is_file()


def test_a_stopped_result_write_keeps_the_file_it_reused(tmp_path, monkeypatch):
    args = pr.parse_args(["--episodes", "4"])
    old = earlier_result(tmp_path / "old.json", args, ("baseline", "gensplat"), 4)
    before = old.read_text()
    argv = ["--episodes", "4", "--arms", "baseline,gensplat", "--reuse-from", str(old), "--out", str(old),
            "--work", str(tmp_path / "work")]  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["policy_robustness.py", *argv])
    write_text = Path.write_text

    def stopped(self, text, *a, **k):
        write_text(self, text[: len(text) // 2])  # half the file, then the process stops
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(Path, "write_text", stopped)
        with pytest.raises(KeyboardInterrupt):
            pr.main()
    assert old.read_text() == before and sorted(p.name for p in tmp_path.iterdir()) == ["old.json"]
    pr.main()  # the same command, not stopped: the file it read, written again whole
    assert list(json.loads(old.read_text())["arms"]) == ["baseline", "gensplat"]


def test_work_refuses_another_augmentation(tmp_path, monkeypatch):
    args = pr.parse_args(["--work", str(tmp_path)])
    pr.check_work(tmp_path, ("baseline", "perspective"), args)
    pr.check_work(tmp_path, ("gensplat",), args)  # adding an arm later
    assert set(json.loads((tmp_path / "settings.json").read_text())["augmentation"]) == {
        "baseline", "perspective", "gensplat"}  # fmt: skip
    with pytest.raises(SystemExit, match="other settings"):
        pr.check_work(tmp_path, ("baseline",), pr.parse_args(["--work", str(tmp_path), "--steps", "10"]))
    monkeypatch.setattr(pr, "PERSPECTIVE_DISTORTION", 0.4)  # the perspective arm's checkpoint no longer fits
    pr.check_work(tmp_path, ("baseline", "gensplat"), args)
    with pytest.raises(SystemExit, match="perspective"):
        pr.check_work(tmp_path, ("perspective",), args)


def test_an_arm_a_protocol_lacks_is_left_out_of_its_tables(tmp_path, monkeypatch):
    args = pr.parse_args(["--episodes", "4"])
    old = json.loads(earlier_result(tmp_path / "old.json", args, ("baseline", "gensplat"), 4).read_text())
    del old["protocols"]["fov"]["arms"]["gensplat"]  # a result from before the fov protocol, for one arm
    (tmp_path / "old.json").write_text(json.dumps(old))
    out = tmp_path / "new.json"
    argv = ["--episodes", "4", "--arms", "baseline,gensplat", "--reuse-from", str(tmp_path / "old.json"),
            "--out", str(out), "--work", str(tmp_path / "work")]  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["policy_robustness.py", *argv])
    pr.main()
    result = json.loads(out.read_text())
    assert list(result["arms"]) == ["baseline", "gensplat"]
    assert list(result["protocols"]["fov"]["arms"]) == ["baseline"] and result["protocols"]["fov"]["difference"] == {
        "vs_baseline": {}
    }
    fov_table = pr.markdown(result).split("fov protocol")[1]
    assert "| baseline |" in fov_table and "| gensplat |" not in fov_table
    assert out.with_suffix(".png").is_file()


def test_range_table_puts_each_arms_training_draws_beside_its_success(tmp_path):
    args = pr.parse_args(["--episodes", "4"])
    result = json.loads(earlier_result(tmp_path / "r.json", args, ("baseline", "perspective", "gensplat", "gensplat+color",
                                                                  "gensplat-arc", "gensplat-arc-p0.5"), 4).read_text())
    del result["protocols"]["fov"]["arms"]["gensplat"]  # evaluated without the fov protocol
    draws = {"shift_pct_median": 3.77, "shift_pct_p95": 7.75, "view_change_deg_median": 12.54,
             "view_change_deg_p95": 24.32}  # fmt: skip
    warp = {**draws, "view_change_deg_median": None, "view_change_deg_p95": None}
    arc = {**draws, "view_change_deg_p95": 39.9}
    table = pr.range_markdown(result, {"rows": {"train/gensplat": draws, "train/perspective": warp, "train/gensplat-arc": arc}})
    rows = {line.split(" | ")[0].strip("| "): line.strip("|").split("|") for line in table.splitlines()
            if line.startswith("| ") and not line.startswith("| arm")}  # fmt: skip
    assert list(rows) == ["baseline", "perspective", "gensplat", "gensplat+color", "gensplat-arc", "gensplat-arc-p0.5"]
    assert rows["gensplat+color"][1:4] == rows["gensplat"][1:4]  # the same camera moves, as often
    assert rows["gensplat-arc-p0.5"][2:4] == rows["gensplat-arc"][2:4] != rows["gensplat"][2:4]
    assert [rows[arm][1].strip() for arm in ("gensplat-arc", "gensplat-arc-p0.5")] == ["25 %", "50 %"]
    rates = lambda arm, protocol, level: f"{pr.protocol_part(result, protocol)['arms'][arm][level]:.0f}"
    assert [c.strip() for c in rows["gensplat"][1:]] == [
        "25 %", "3.8 (7.8)", "12.5 (24.3)", rates("gensplat", "paper", "none"), rates("gensplat", "paper", "large"),
        rates("gensplat", "vista", "small_perturb"), rates("gensplat", "vista", "arc_90deg"), ""]  # fmt: skip
    assert [c.strip() for c in rows["baseline"][1:4]] == ["0 %", "0.0 (0.0)", "0.0 (0.0)"]
    assert rows["baseline"][-1].strip() == rates("baseline", "fov", "zoom")
    assert [c.strip() for c in rows["perspective"][1:4:2]] == ["25 %", "-"]  # an image warp moves no camera
    del result["settings"]["augmentation"]  # a result that does not say: the share is blank
    unsaid = [r for r in pr.range_markdown(result, {"rows": {}}).splitlines() if r.startswith("| baseline")]
    assert len(unsaid) == 1 and unsaid[0].split("|")[2].strip() == ""
    only_baseline = [r for r in pr.range_markdown(result, {"rows": {}}).splitlines() if r.startswith("| ")]
    assert [r.split(" | ")[0] for r in only_baseline] == ["| arm", "| baseline"]  # draws not measured: left out


def test_a_replicate_trains_its_arm_again_with_another_seed_and_is_paired_like_any_arm(tmp_path):
    args = pr.parse_args(["--arms", "gensplat-zoom@s2,baseline@s1,gensplat-zoom,baseline", "--seed", "3"])
    assert args.arms == ("baseline", "baseline@s1", "gensplat-zoom", "gensplat-zoom@s2")
    for arm, n in (("baseline@s1", 1), ("gensplat-zoom@s2", 2)):  # the same training but for the seed
        kind = pr.arm_kind(arm)
        cmd, base = (pr.train_command(a, ROOT, OUT, CONFIG, args) for a in (arm, kind))
        assert [a for a in cmd if a not in base] == [f"--seed={3 + n}"] and len(cmd) == len(base)
        assert pr.augmentation(arm, args) == {**pr.augmentation(kind, args), "train_seed": 3 + n}
    zoom, again = pr.gensplat_config(args, "gensplat-zoom"), pr.gensplat_config(args, "gensplat-zoom@s2")
    assert (zoom.seed, again.seed) == (3, 5) and replace(again, seed=3) == zoom  # GenSplat draws other moves
    work = Path("work")
    assert pr.dataset_root(work, "baseline@s1") == work / "dataset"
    assert pr.dataset_root(work, "gensplat@s1") == work / "dataset_gensplat@s1"  # its own GenSplat settings
    for bad in ("gensplat@s0", "gensplat@s", "gensplat@1", "gensplat@s-1", "mixup@s1", "gensplat@s1@s1",
                "gensplat@s4294967296"):  # a seed GenSplat's sampler refuses: 2**32
        with pytest.raises(SystemExit):
            pr.parse_args(["--arms", bad])
    with pytest.raises(SystemExit):
        pr.parse_args(["--arms", "baseline", "--seed", "-1"])
    arms = ("baseline", "baseline@s1", "perspective", "gensplat", "gensplat@s1")
    args = pr.parse_args(["--arms", ",".join(arms), "--episodes", "10"])
    solved = {"baseline": 2, "baseline@s1": 3, "perspective": 1, "gensplat": 5, "gensplat@s1": 4}
    result = pr.build_result(evaluation(solved, 10), 10, False, pr.result_settings(args), {})
    diff = result["difference"]
    assert list(result["arms"]) == list(arms) and set(diff["vs_baseline"]) == set(arms[1:])
    assert set(diff["vs_2d"]["perspective"]) == {"gensplat", "gensplat@s1"}
    assert all(diff["vs_baseline"]["baseline@s1"][lv]["points"] == 10.0 for lv in pr.LEVELS)
    assert "| gensplat@s1 | 40 (+20 [" in pr.markdown(result)
    table = pr.range_markdown(result, {"rows": {"train/gensplat": {k: 1.0 for k in (
        "shift_pct_median", "shift_pct_p95", "view_change_deg_median", "view_change_deg_p95")}}})  # fmt: skip
    rows = [line.split(" | ")[1:4] for line in table.splitlines() if line.startswith("| gensplat")]
    assert len(rows) == 2 and rows[0] == rows[1]  # the replicate draws its arm's moves
    pr.plot(result, tmp_path / "plot.png")  # a replicate's line in its arm's colour, halfway to white
    image = np.asarray(Image.open(tmp_path / "plot.png").convert("RGB")).astype(int)
    assert pr.colour("gensplat@s1") == tuple((c + 255) // 2 for c in pr.COLOURS["gensplat"])
    for arm in arms:
        assert (np.abs(image - pr.colour(arm)).sum(-1) < 10).sum() > 50, arm


def test_link_dataset_shares_everything_but_the_gensplat_settings(tmp_path):
    root, linked = tmp_path / "dataset", tmp_path / "dataset_gensplat-wide"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text("{}")
    (root / "gensplat").mkdir()
    (root / "gensplat" / "config.json").write_text('{"sampler": "paper"}')
    (root / "notes.txt").write_text("x")
    for _ in range(2):  # linking again keeps what is there
        pr.link_dataset(root, linked)
    assert sorted(p.name for p in linked.iterdir()) == ["meta", "notes.txt"]
    assert (linked / "meta").is_symlink() and (linked / "meta" / "info.json").read_text() == "{}"
    assert (linked / "notes.txt").resolve() == (root / "notes.txt").resolve()


def test_move_table_splits_each_wider_level_by_the_size_of_its_moves():
    evaluated = evaluation({"baseline": 2, "gensplat": 4}, 6)
    moves = {"small_perturb": [{"angle_rad": a} for a in (0.01, -0.04, 0.07, -0.08, 0.2, 0.0)],
             "arc_90deg": [{"azimuth_deg": a} for a in (-44.0, 45.0, 3.0, -15.0, 29.9, 0.0)],
             "zoom": [{"focal_scale": f} for f in (0.8, 1.25, 0.95, 1.0, 1.1, 0.85)]}  # fmt: skip
    for protocol in ("vista", "fov"):
        for per_level in evaluated[protocol].values():
            for level, record in per_level.items():
                for e in record["episodes"]:
                    e |= moves[level][e["episode"]]
    result = pr.build_result(evaluated, 6, False, pr.result_settings(pr.parse_args(["--episodes", "6"])), {})
    tables = pr.move_markdown(result).split("\n\n")
    rows = lambda i: [line.split(" | ") for line in tables[i].splitlines() if line.startswith("| ")]
    assert tables[0] == "vista small_perturb, success % by rotation (deg):"
    # rotations 0.6, 2.3 | 4.0, 4.6 | 11.5, 0.0 deg: the baseline solves episodes 0-1, gensplat 0-3
    assert rows(1) == [["| arm", "0-3 (3 ep.)", "3-6 (2 ep.)", "6-90 (1 ep.) |"], ["| baseline", "67", "0", "0 |"],
                       ["| gensplat", "67", "100", "0 |"]]  # fmt: skip
    # |azimuth| 44, 45 (the closed last bin), 3, 15, 29.9, 0
    assert rows(3)[0][1:] == ["0-15 (2 ep.)", "15-30 (2 ep.)", "30-45 (2 ep.) |"]
    assert rows(3)[1][1:] == ["0", "0", "100 |"] and rows(3)[2][1:] == ["50", "50", "100 |"]
    # focal scales 0.8, 1.25, 0.95, 1.0, 1.1, 0.85
    assert rows(5)[0][1:] == ["0.8-0.9 (2 ep.)", "0.9-1 (1 ep.)", "1-1.1 (1 ep.)", "1.1-1.25 (2 ep.) |"]
    assert rows(5)[2][1:] == ["50", "100", "100", "50 |"]
    del result["protocols"]["fov"]  # a result from before the fov protocol: no zoom table
    assert "fov zoom" not in pr.move_markdown(result) and "arc_90deg" in pr.move_markdown(result)


def test_the_gensplat_arms_draw_the_study_discs_whatever_the_library_defaults(tmp_path, monkeypatch):
    """Units of one study run at different commits: their GenSplat arms prepare the same discs,
    whose cache is the default one (the disc shape is not part of its identity)."""
    from gensplat_transforms.geometry import RGBDReconstructor, make_reconstructor

    prepared = []
    monkeypatch.setattr(pr, "prepare", lambda root, repo, config, reconstructor, **kw: prepared.append(reconstructor))
    args = pr.parse_args([])
    for arm in ("baseline", "perspective", "gensplat"):
        pr.prepare_arm(tmp_path, arm, args)
    assert prepared == [pr.STUDY_RECONSTRUCTOR]
    study = make_reconstructor(pr.STUDY_RECONSTRUCTOR)
    assert (study.cfg.sigma_px, study.cfg.edge_scale, study.cfg.cover) == (0.4, 0.25, 1.0)
    assert study.identity() == RGBDReconstructor().identity()
