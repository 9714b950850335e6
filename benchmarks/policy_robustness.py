"""Policy robustness under camera perturbation: the paper's first experiment, in simulation,
with the 2D augmentations users already have as the alternatives to GenSplat.

    python benchmarks/policy_robustness.py [--quick] [--arms A,B,...] [--work DIR] [--steps N] ...

Stages (each is skipped when its output already exists in ``--work``, so a stopped run
resumes where it was: a training from its last checkpoint, every ``CHECKPOINT_EVERY`` steps,
an evaluation at the levels it had not finished; a ``--work`` made with other settings is
refused):

1. record ``--demos`` scripted demonstrations of ``--task`` at ``--size`` px (run seed
   ``--seed``; lossless PNG frames, calibration and depth sidecars);
2. when a GenSplat arm is trained: write the GenSplat settings beside the dataset and build
   its Gaussian cache (RGB-D reconstruction of the left + right cameras);
3. train Diffusion Policy once per arm (``--arms``, default all) with LeRobot's stock
   trainer through ``policies/train.sh``: same data, seed, steps, batch and policy settings;
   the policy sees ``--cameras`` and the robot state. The arms differ only in the training
   augmentation (``augmentation`` and ``train_command`` give what each passes):

   * ``baseline``: none;
   * ``lerobot2d``: LeRobot's own image augmentation, ``--dataset.image_transforms.enable=true``
     with 3 of these 7 transforms per sample (LeRobot's default count, equal weights): its
     default colour jitter (brightness and contrast 0.8-1.2, saturation 0.5-1.5, hue
     +-0.05) and sharpness jitter (0.5-1.5), its ``RandomAffine`` widened to the camera
     moves GenSplat trains on (rotation +-20 deg, scale 0.98-1.08, LeRobot's translation
     +-5 %, bilinear) and a square ``RandomResizedCrop`` of 85-100 % of the area back to
     full size. Tuned once, from geometry, not from success rates: a similarity fitted to
     the workspace's image points (the table, 0-20 cm above it) under 500 moves of
     GenSplat's training range (level ``train``) rotates the image by 7.6 deg (median) and
     18.8 deg (95th percentile) and scales it by 0.98-1.08 (5th-95th), and moves it by
     less than 1 % (the cameras turn about the point they look at, the image centre);
   * ``perspective``: a random homography of the external camera, torchvision's
     ``RandomPerspective(distortion_scale=0.25, p=--probability)`` (bilinear, black
     corners) as LeRobot's only image transform: with the probability GenSplat replaces a
     camera (one draw per sample and camera, the same warp for a temporal stack); the
     distortion moves the workspace's image points by 4.2 % of the width on average, as
     GenSplat's training moves do (4.0 %). LeRobot warps every camera it loads, each with its
     own draw, so this arm refuses a policy that sees the wrist camera;
   * ``gensplat``: GenSplat's one added line; the policy's external cameras (left by
     default) are replaced with probability ``--probability`` (default 0.25) by a view
     from the training range (|theta| <= 30 deg, 0.5-6 cm), one camera per trajectory,
     ``--views-per-source`` (default 3) distinct cameras per source trajectory;
   * ``gensplat+lerobot2d``: both; LeRobot's transforms apply after GenSplat's views;
   * ``gensplat+color``: GenSplat with only the colour and sharpness jitter of ``lerobot2d``
     (3 of those 5 per sample), no affine or crop;
   * ``gensplat-wide``: ``gensplat`` with the ``mix`` sampler (``SAMPLER_ARMS``): each camera
     moved by the paper's training range, a tilt about a random axis of up to 10 deg with a
     shift of up to 3 cm per axis, or a turn of up to +-45 deg about the vertical through the
     pivot, one of the three chosen per camera;
   * ``gensplat-fov``: ``gensplat`` with the focal length scaled log-uniformly in 0.8-1.25
     (the ``fov`` protocol's range) on top of the paper's moves;
   * ``gensplat-tilt``, ``gensplat-arc``: ``gensplat-wide``'s tilts alone and its arcs alone
     (``tilt`` and ``arc`` samplers with the same ranges), for what each kind of move gains
     under its VISTA protocol and costs at the training camera;
   * ``gensplat-fov-p0.5``, ``gensplat-arc-p0.5``: ``gensplat-fov`` and ``gensplat-arc`` with
     GenSplat replacing the camera with probability 0.5 (``MORE_OFTEN``), whatever
     ``--probability`` says;
   * ``gensplat-tiltarc``: the tilts and the arcs (sampler ``tilt,arc``: one of them per
     camera) with probability 0.5, so that each kind moves a quarter of the samples, as in
     ``gensplat-tilt`` and ``gensplat-arc``: the candidate for both VISTA protocols at once;
   * ``gensplat-zoom``: ``gensplat-fov``'s focal lengths alone, the camera in place (a tilt
     sampler with no turn and no shift): only the effect the ``fov`` protocol calls for;
   * ``gensplat-unmoved``: a control, the camera rendered where it is (no move, no zoom) on
     half the samples: what replacing real images with renders costs the policy, apart from
     any move (the arms moving half the samples pay 14-19 points at the training camera);
   * ``gensplat-wide-p0.5``: ``gensplat-wide``'s moves (the paper's, tilts and arcs, one kind
     per camera) on half the samples, so each kind moves a sixth of them; trained for twice
     the steps (``--steps 5000``), each kind moves more samples than it did in the arm that
     gained with it alone at 2500 steps, and the real camera is seen in as many samples as the
     baseline's at 2500.

   A replicate ``<arm>@s<N>`` (N >= 1, e.g. ``gensplat-zoom@s1``, ``baseline@s1``) trains
   ``<arm>``'s augmentation again with the training seed ``--seed + N`` (LeRobot's, and the
   GenSplat settings' seed, which draws its moves); recording and evaluation keep ``--seed``,
   so a replicate meets the same episodes and is paired with every arm like any other: the
   difference between an arm and its replicate is what retraining alone moves.

   The wider arms and the GenSplat replicates train on their own dataset roots
   (``work/dataset_<arm>``, links to ``work/dataset`` beside their own ``gensplat`` settings
   and cache), since LeRobot's GenSplat line reads the settings from the dataset root;

4. evaluate every arm's checkpoint in ``PerturbedCameraEnv`` with the left external camera
   moved once per episode, under three protocols (``PROTOCOLS``): ``paper`` (the paper's:
   rotation about the pivot of the external cameras and a forward move, levels none / small /
   medium / large) and ``vista`` (VISTA's camera samplers, ``gensplat_sim.vista``:
   ``small_perturb``, 3 cm position and 0.075 rad rotation noise; ``arc_90deg``, the camera
   anywhere on a +-45 deg arc about the point it looks at), and ``fov`` (level ``zoom``: the
   camera in place, its focal length scaled log-uniformly in 0.8-1.25). Episode layouts come
   from the evaluation stream (never a training layout), the same under every protocol, and every
   policy meets the same layouts, camera moves and sampling noise (torch is seeded per
   episode).

Defaults, sized for this 2-core CPU: the ``reach_solo`` task (bring the open gripper 2 cm
above the one 5 cm cube on the table, placed at random; the policy must find it in the
image), 300 demonstrations at 96x96, the policy sees the left camera and the state;
Diffusion Policy as in ``policies/diffusion.json`` (ResNet-18 encoder from scratch, U-Net
``down_dims`` 64-128-256, horizon 16, 8 executed actions) with 1 observation step, DDIM and
10 inference steps; 2500 steps at batch 32 (warm-up a tenth of the steps, at most 500); 100
evaluation episodes per level of at most 50 control steps (the demonstrations take 15-18),
7 levels per arm. Measured on a 2-core AMD EPYC (Zen 5) with no other job: 1.09 s per
training step for the baseline and 1.05 s for GenSplat (46 and 44 min per policy),
evaluation 10.5 min per arm in two processes (0.05 s per control step), recording 4 min; on
an older, busier 2-core EPYC 1.29-2.35 s per step (the 2D arms and GenSplat within 5 % of
the baseline in 40-step runs). The eight arms thus take 8-16 h; ``timing`` in the result
holds the measured values. Harder tasks did not train at this budget: ``reach`` (a 4 cm cube
among two distractors of random colours) stayed at about 10 % success at every level, and
``pick_place`` (``--cameras left,right,wrist``) lifted no cube after 1500 steps at batch 8 (see the README); ``--device cuda --steps 20000`` is the
setting to aim for on a GPU. Measured on one H100 machine (16 cores): with
``--parallel-train --workers 6`` each policy ran at 3-4 steps/s, bound by the dataloader
(LeRobot decoding PNG frames), so 20000 steps take about 1.5 h there.

``--reuse-from RESULT.json`` (repeatable) reuses the arms of earlier results instead of
training and evaluating them again (an hour each here): the evaluation is seeded and
reproducible, so an arm's episode records stand for its checkpoint. An arm is reused when
the settings that shape it and its evaluation match (the common ones, its augmentation and
the episodes per level; checked, and the arms whose settings differ are named and trained),
under the protocols its file evaluated it (it is left out of the others' tables);
``settings["reused"]`` names the file of each reused arm. Within one ``--work``, a trained
checkpoint is not trained again (its augmentation is checked), so adding an arm later trains
only that arm. ``--table RESULT.json`` prints a result's tables in Markdown (benchmarks/README.md's), the
training range of each arm against its success (``range_markdown``) and the success against
the size of the move within the wider levels (``move_markdown``).
``--quick`` (a few minutes): 2 demos, 4 steps at batch 4, a smaller U-Net, 2 episodes per
level of at most 20 steps: it checks the pipeline end to end, its success rates mean nothing.

Writes ``benchmarks/results/policy_robustness.json`` (``outputs/benchmarks_quick/policy_robustness.json``
with ``--quick``) and a plot beside it (success and closest approach of every arm under both
protocols): ``{"arms": {arm: {level: success %}}, "levels", "progress": {arm: {level:
{lift_percent, median_reach_cm}}}, "difference": {"vs_baseline": {arm: {level: {points,
ci95, a_only, b_only, mcnemar_p}}}, "vs_2d": {2D arm: {GenSplat arm: {...}}}}, "best_2d",
"episodes_per_level": n,
"quick", "protocols": {"vista" / "fov": {the same keys from "arms" to "best_2d", and "episodes"}},
"settings", "timing", "episodes": {arm: [per-episode records]}}``, the top level for the
paper protocol.
``difference`` compares two arms episode by episode (they met the same episodes): every arm
against the baseline, and the GenSplat arms against each 2D arm (``vs_2d``); ``best_2d``
names the 2D arm (``lerobot2d``, ``perspective``) with the highest mean success over the
perturbed levels (chosen on the same episodes, so the comparison with it favours it); in
points (arm minus reference), a
paired-bootstrap 95 % interval, and an exact McNemar test on the episodes only one of them
solved. ``progress`` tells apart policies that do not succeed yet: the share of episodes
that lifted the cube (pick and place) and the median closest approach of the pinch point to
the cube's centre (to the reach goal in a reach).
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import multiprocessing
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from gensplat_lerobot import prepare
from gensplat_sim.evaluate import (
    FOV_RANGE,
    EvalConfig,
    PerturbedCameraEnv,
    evaluate,
    paired_difference,
)
from gensplat_sim.policy_adapter import LeRobotPolicy
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.tasks import TASKS
from gensplat_sim.vista import SAMPLERS
from gensplat_sim.world import CAMERA_NAMES, EXTERNAL_CAMERAS, STATE_NAMES, WorldConfig
from machine import default_out
from plotting import Panel, line_panels

from gensplat_transforms.core.atomic import atomic_write_json, read_json_object
from gensplat_transforms.transform import GenSplatConfig
from gensplat_transforms.views.perturbation import KEY_LIMIT

LEVELS = ("none", "small", "medium", "large")
#: The evaluation protocols and their levels (``PerturbedCameraEnv``'s ``protocol``).
PROTOCOLS = {"paper": LEVELS, "vista": SAMPLERS, "fov": ("zoom",)}
ARMS = ("baseline", "lerobot2d", "perspective", "gensplat", "gensplat+lerobot2d", "gensplat+color", "gensplat-wide",
        "gensplat-fov", "gensplat-tilt", "gensplat-arc", "gensplat-fov-p0.5", "gensplat-arc-p0.5",
        "gensplat-tiltarc", "gensplat-zoom", "gensplat-unmoved", "gensplat-wide-p0.5")  # fmt: skip
TWO_D_ARMS = ("lerobot2d", "perspective")
GENSPLAT_ARMS = ARMS[ARMS.index("gensplat"):]
#: The GenSplat settings the wider arms change (the others draw the paper's moves).
SAMPLER_ARMS = {"gensplat-wide": {"sampler": "mix", "tilt_deg": 10.0, "arc_deg": 45.0, "shift_m": 0.03},
                "gensplat-fov": {"focal_scale": FOV_RANGE},
                "gensplat-tilt": {"sampler": "tilt", "tilt_deg": 10.0, "shift_m": 0.03},
                "gensplat-arc": {"sampler": "arc", "arc_deg": 45.0, "shift_m": 0.03},
                "gensplat-tiltarc": {"sampler": "tilt,arc", "tilt_deg": 10.0, "arc_deg": 45.0, "shift_m": 0.03,
                                     "probability": 0.5},
                "gensplat-zoom": {"sampler": "tilt", "tilt_deg": 0.0, "shift_m": 0.0, "focal_scale": FOV_RANGE},
                "gensplat-unmoved": {"sampler": "tilt", "tilt_deg": 0.0, "shift_m": 0.0, "probability": 0.5}}  # fmt: skip
#: Arms that draw another arm's moves, more often: {arm: (that arm, the chance GenSplat replaces a camera)}.
MORE_OFTEN = {"gensplat-fov-p0.5": ("gensplat-fov", 0.5), "gensplat-arc-p0.5": ("gensplat-arc", 0.5),
              "gensplat-wide-p0.5": ("gensplat-wide", 0.5)}  # fmt: skip
SAMPLER_ARMS |= {arm: {**SAMPLER_ARMS[like], "probability": p} for arm, (like, p) in MORE_OFTEN.items()}
#: A replicate of an arm: ``<arm>@s<N>``, trained with the seed ``--seed + N`` (module docstring).
REPLICATE = re.compile(r"^(?P<arm>.+)@s(?P<n>[1-9][0-9]*)$")


def arm_kind(arm: str) -> str:
    """The arm (of ``ARMS``) whose augmentation ``arm`` trains: itself, or a replicate's arm."""
    m = REPLICATE.match(arm)
    return m["arm"] if m else arm


def train_seed(arm: str, args) -> int:
    """The seed ``arm`` trains with: ``--seed``, plus N for a replicate ``<arm>@s<N>``."""
    m = REPLICATE.match(arm)
    return args.seed + (int(m["n"]) if m else 0)


def ordered(arms) -> tuple[str, ...]:
    """``arms`` in ``ARMS`` order, each arm's replicates after it by N (arms of no known kind last)."""
    def key(arm: str) -> tuple[int, int]:
        kind = arm_kind(arm)
        return (ARMS.index(kind) if kind in ARMS else len(ARMS), int(REPLICATE.match(arm)["n"]) if kind != arm else 0)

    return tuple(sorted(dict.fromkeys(arms), key=key))


#: RandomPerspective's distortion_scale of the perspective arm (see the module docstring).
PERSPECTIVE_DISTORTION = 0.25
ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
#: ``camera_motion.py``'s result: how far each arm's training draws move the camera
MOTION = RESULTS / "camera_motion.json"


def repo_id(task: str) -> str:
    return f"gensplat/sim_{task}"


#: (full, quick) defaults of the settings that size the experiment.
DEFAULTS = {
    "demos": (300, 2), "size": (96, 96), "steps": (2500, 4), "batch_size": (32, 4), "workers": (0, 0),
    "down_dims": ("64,128,256", "32,64,128"), "episodes": (100, 2), "max_steps": (None, 20),
}  # fmt: skip


#: Settings that shape the recorded data and the trained policies (kept in ``work/settings.json``).
RUN_SETTINGS = ("task", "cameras", "demos", "size", "steps", "batch_size", "workers", "down_dims",
                "n_obs_steps", "views_per_source", "probability", "fill_holes", "seed", "device")  # fmt: skip


def lerobot2d_transforms(size: int, geometric: bool = True) -> dict:
    """LeRobot ``ImageTransformsConfig`` fields of the lerobot2d arms, as plain values (see the
    module docstring); ``size``: the image side, which the crop returns to. Without
    ``geometric``, only the colour and sharpness jitter (the ``gensplat+color`` arm)."""
    def tf(kind: str, kwargs: dict) -> dict:
        return {"type": kind, "kwargs": kwargs}

    tfs = {
        "brightness": tf("ColorJitter", {"brightness": [0.8, 1.2]}),
        "contrast": tf("ColorJitter", {"contrast": [0.8, 1.2]}),
        "saturation": tf("ColorJitter", {"saturation": [0.5, 1.5]}),
        "hue": tf("ColorJitter", {"hue": [-0.05, 0.05]}),
        "sharpness": tf("SharpnessJitter", {"sharpness": [0.5, 1.5]}),
        "affine": tf("RandomAffine", {"degrees": [-20.0, 20.0], "translate": [0.05, 0.05],
                                      "scale": [0.98, 1.08], "interpolation": 2}),  # 2: bilinear
        "crop": tf("RandomResizedCrop", {"size": [size, size], "scale": [0.85, 1.0], "ratio": [1.0, 1.0]}),
    }  # fmt: skip
    if not geometric:
        tfs = {name: t for name, t in tfs.items() if name not in ("affine", "crop")}
    return {"max_num_transforms": 3, "tfs": tfs}


def perspective_transforms(probability: float) -> dict:
    """LeRobot ``ImageTransformsConfig`` fields of the perspective arm: one random homography
    applied with ``probability``."""
    kwargs = {"distortion_scale": PERSPECTIVE_DISTORTION, "p": probability}
    return {"max_num_transforms": 1, "tfs": {"perspective": {"type": "RandomPerspective", "kwargs": kwargs}}}


def gensplat_config(args, arm: str = "gensplat") -> GenSplatConfig:
    """The GenSplat settings of the GenSplat arm ``arm`` (written beside its dataset root)."""
    replace = tuple(c for c in args.cameras if c in EXTERNAL_CAMERAS)
    common = {"replace": replace, "views_per_source": args.views_per_source, "probability": args.probability,
              "fill_holes": args.fill_holes, "backend": "fast", "seed": train_seed(arm, args)}  # fmt: skip
    return GenSplatConfig(**common | SAMPLER_ARMS.get(arm_kind(arm), {}))


def dataset_root(work: Path, arm: str) -> Path:
    """The dataset root ``arm`` trains on: ``work/dataset``, or for an arm with its own GenSplat
    settings (``SAMPLER_ARMS``, a GenSplat replicate's seed) ``work/dataset_<arm>``, whose entries
    link to ``work/dataset``'s but for its own ``gensplat`` folder (LeRobot's plugin reads the
    settings from the root)."""
    kind = arm_kind(arm)
    own = kind in SAMPLER_ARMS or (kind != arm and kind in GENSPLAT_ARMS)
    return work / f"dataset_{arm}" if own else work / "dataset"


def link_dataset(root: Path, linked: Path) -> None:
    """Make ``linked`` a dataset root whose entries are links to ``root``'s, ``gensplat`` aside."""
    linked.mkdir(parents=True, exist_ok=True)
    for entry in root.iterdir():
        if entry.name != "gensplat" and not (linked / entry.name).exists():
            (linked / entry.name).symlink_to(entry.resolve(), target_is_directory=entry.is_dir())


def augmentation(arm: str, args) -> dict:
    """What ``arm`` adds to the baseline's training, as plain values: ``gensplat`` (the GenSplat
    settings), ``image_transforms`` (LeRobot's) and a replicate's ``train_seed``, each only where
    the arm has it."""
    kind = arm_kind(arm)
    out = {"train_seed": train_seed(arm, args)} if kind != arm else {}
    if kind in GENSPLAT_ARMS:
        g = gensplat_config(args, arm)
        out["gensplat"] = {"cameras": list(g.cameras), "replace": list(g.replace), "probability": g.probability,
                           "level": g.level, "mode": g.mode, "views_per_source": g.views_per_source,
                           "fill_holes": g.fill_holes}  # fmt: skip
        out["gensplat"] |= {k: list(v) if isinstance(v, tuple) else v for k, v in SAMPLER_ARMS.get(kind, {}).items()}
    if kind.endswith("lerobot2d"):
        out["image_transforms"] = lerobot2d_transforms(args.size)
    elif kind == "gensplat+color":
        out["image_transforms"] = lerobot2d_transforms(args.size, geometric=False)
    elif kind == "perspective":
        out["image_transforms"] = perspective_transforms(args.probability)
    return out


def arm_arguments(arm: str, args) -> list[str]:
    """``policies/train.sh``'s mode for ``arm`` and the ``lerobot-train`` arguments it adds."""
    aug = augmentation(arm, args)
    out = ["gensplat" if "gensplat" in aug else "baseline"]
    if "image_transforms" in aug:
        t = aug["image_transforms"]
        out += ["--dataset.image_transforms.enable=true",
                f"--dataset.image_transforms.max_num_transforms={t['max_num_transforms']}",
                "--dataset.image_transforms.tfs=" + json.dumps(t["tfs"], separators=(",", ":"))]  # fmt: skip
    return out


#: Every arm's training reads only the columns its frame queries need (LeRobot 0.6.1 decodes
#: every image of the 16 action frames of an item otherwise: 70 % of a step here); the items are
#: unchanged. Workers are forked so that they inherit it.
FAST_ROWS = "gensplat_lerobot.fast_rows"


def train_command(arm: str, root: Path, out: Path, config: Path, args) -> list[str]:
    """The command that trains ``arm`` on the dataset at ``root`` into ``out``, with the policy
    config ``config``: ``bash policies/train.sh CONFIG MODE <arguments>``."""
    mode, *extra = arm_arguments(arm, args)
    return [
        "bash", str(ROOT / "policies" / "train.sh"), str(config), mode,
        f"--dataset.repo_id={repo_id(args.task)}", f"--dataset.root={root}", f"--output_dir={out}",
        f"--steps={args.steps}", f"--batch_size={args.batch_size}", f"--num_workers={args.workers}",
        f"--seed={train_seed(arm, args)}", f"--save_freq={min(CHECKPOINT_EVERY, args.steps)}", f"--log_freq={max(1, args.steps // 50)}",
        f"--policy.down_dims=[{args.down_dims}]", f"--policy.n_obs_steps={args.n_obs_steps}",
        "--policy.noise_scheduler_type=DDIM", f"--policy.num_inference_steps={args.inference_steps}",
        f"--policy.scheduler_warmup_steps={min(500, args.steps // 10)}",
        f"--policy.device={args.device}", f"--fast_rows.discover_packages_path={FAST_ROWS}",
        *(["--dataloader_multiprocessing_context=fork"] if args.workers else []), *extra,
    ]  # fmt: skip


def record_dataset(work: Path, args) -> None:
    """Record the demonstrations into ``work/dataset`` unless it is there. The recording is made
    in ``work/dataset.partial`` and renamed when whole, so a run killed while recording leaves no
    ``work/dataset`` (LeRobot writes ``meta/info.json`` first: its presence proves nothing)."""
    root, partial = work / "dataset", work / "dataset.partial"
    if root.is_dir():
        return
    shutil.rmtree(partial, ignore_errors=True)
    res = record(RecordConfig(partial, args.task, args.demos, args.seed, use_videos=False, repo_id=repo_id(args.task),
                              world=WorldConfig(height=args.size, width=args.size)), progress=False)  # fmt: skip
    partial.rename(root)
    print(f"recorded {res.episodes} demonstrations, {res.frames} frames, in {res.seconds:.0f} s", flush=True)


#: the RGB-D discs every GenSplat arm of the study draws, fixed here rather than taken from the
#: library's defaults so that units run at different commits train on the same views (wider
#: discs than the default, partly covered pixels as composited)
STUDY_RECONSTRUCTOR = {"name": "rgbd", "config": {"sigma_px": 0.4, "edge_scale": 0.25, "cover": 1.0}}


def prepare_arm(work: Path, arm: str, args) -> None:
    """For a GenSplat arm: its dataset root (:func:`dataset_root`), GenSplat settings and cache."""
    if arm_kind(arm) not in GENSPLAT_ARMS:
        return
    if dataset_root(work, arm) != work / "dataset":
        link_dataset(work / "dataset", dataset_root(work, arm))
    prepare(dataset_root(work, arm), repo_id(args.task), gensplat_config(args, arm), STUDY_RECONSTRUCTOR,
            progress=False)


def check_work(work: Path, arms: tuple[str, ...], args) -> None:
    """Record the run settings and the arms' augmentation in ``work``, or refuse to resume a
    ``work`` made with other settings or another augmentation of one of ``arms``."""
    settings = {k: list(v) if isinstance(v, tuple) else v for k in RUN_SETTINGS for v in [getattr(args, k)]}
    augment = {arm: augmentation(arm, args) for arm in arms}
    path = work / "settings.json"
    if path.is_file():
        old = json.loads(path.read_text())
        changed = {k: (old.get(k), v) for k, v in settings.items() if old.get(k) != v}
        before = old.get("augmentation", {})  # absent in works from before the arms
        changed |= {arm: "augmentation" for arm in arms if arm in before and before[arm] != augment[arm]}
        if changed:
            raise SystemExit(f"{work} holds a run with other settings {changed} (was, now): "
                             "pass a new --work or delete it")  # fmt: skip
        augment = {**before, **augment}
    work.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, {**settings, "augmentation": augment})


def lock_work(work: Path) -> int:
    """Hold ``work/.lock`` for as long as this process lives (the descriptor returned), or raise
    SystemExit when another run holds it: two runs would train into the same folders."""
    work.mkdir(parents=True, exist_ok=True)
    fd = os.open(work / ".lock", os.O_CREAT | os.O_RDWR, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise SystemExit(f"{work} is in use by another policy_robustness.py run: wait for it or pass another "
                         "--work") from None  # fmt: skip
    return fd


def policy_config(work: Path, args) -> Path:
    """``policies/diffusion.json`` with the policy's inputs limited to ``args.cameras`` and
    the state, written to ``work/diffusion.json``."""
    config = json.loads((ROOT / "policies" / "diffusion.json").read_text())
    features = {f"observation.images.{c}": {"type": "VISUAL", "shape": [3, args.size, args.size]}
                for c in args.cameras}  # fmt: skip
    features["observation.state"] = {"type": "STATE", "shape": [len(STATE_NAMES)]}
    config["policy"]["input_features"] = features
    path = work / "diffusion.json"
    return atomic_write_json(path, config)


#: Training steps between checkpoints: a stopped training resumes from its last one.
#: (Trainings run with OpenMP's passive wait policy unless the environment sets one: with its
#: threads spinning, one other process on a core slowed a step from 0.36 s to 2-6 s here; passive,
#: to 0.5 s; benchmarks/README.md.)
CHECKPOINT_EVERY = 500


def last_checkpoint(out: Path) -> Path:
    """The checkpoint LeRobot names ``last`` in the training folder ``out`` (a link to the newest)."""
    return out / "checkpoints" / "last"


def trained_steps(out: Path) -> int:
    """The step of the last checkpoint in the training folder ``out`` (0 without one). LeRobot
    points ``checkpoints/last`` at a checkpoint only once it is written whole; a step file
    without a step raises SystemExit (the run is not thrown away)."""
    last = last_checkpoint(out)
    state = last / "training_state" / "training_step.json"
    if not (state.is_file() and (last / "pretrained_model" / "train_config.json").is_file()):
        return 0
    step = read_json_object(state).get("step")
    if not isinstance(step, int) or step < 0:
        raise SystemExit(f"{state}: no step count in it; repair it or delete {out} to train the arm again")
    return step


def train(arm: str, root: Path, out: Path, args) -> dict:
    """Train one arm with :func:`train_command` unless ``out`` holds a finished run; a stopped
    run resumes from its last checkpoint (LeRobot's ``--resume``: the model, optimiser and data
    order continue, while the augmentation's draws differ from an unstopped run's). Returns
    {"seconds", "s_per_step" (start-up included), "last_loss"} of the run that finished, with
    "resumed_from_step" when it resumed; kept in ``train_<arm>.json`` beside ``out`` so that a
    later run still reports them. Only the final checkpoint is kept."""
    record = out.parent / f"train_{arm}.json"
    done = trained_steps(out)
    if done >= args.steps:
        return json.loads(record.read_text()) if record.is_file() else {}
    if done == 0:
        shutil.rmtree(out, ignore_errors=True)  # no checkpoint: lerobot-train refuses existing folders
    out.parent.mkdir(parents=True, exist_ok=True)
    if done:
        config = last_checkpoint(out) / "pretrained_model" / "train_config.json"
        cmd = [*train_command(arm, root, out, config, args), "--resume=true"]
        print(f"resuming {arm} from step {done}", flush=True)
    else:
        cmd = train_command(arm, root, out, policy_config(out.parent, args), args)
    env = {"OMP_WAIT_POLICY": "PASSIVE", **os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    log = out.parent / f"train_{arm}.log"
    t0 = time.perf_counter()
    with open(log, "a" if done else "w") as f:
        start = f.tell()
        run = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, check=False)
    seconds = time.perf_counter() - t0
    if run.returncode != 0:
        raise RuntimeError(f"training {arm} failed (exit {run.returncode}); see {log}")
    with open(log) as f:
        f.seek(start)
        losses = re.findall(r"\bloss:([0-9.]+)", f.read())
    print(f"trained {arm} in {seconds:.0f} s, last logged loss {losses[-1] if losses else '?'}", flush=True)
    timing = {"seconds": round(seconds, 1), "s_per_step": round(seconds / (args.steps - done), 2),
              "last_loss": float(losses[-1]) if losses else None} | ({"resumed_from_step": done} if done else {})  # fmt: skip
    final = last_checkpoint(out).resolve()
    for checkpoint in (out / "checkpoints").iterdir():
        if checkpoint.name != "last" and checkpoint.resolve() != final:
            shutil.rmtree(checkpoint)
    atomic_write_json(record, timing)
    return timing


def evaluate_level(checkpoint: Path, protocol: str, level: str, args) -> dict:
    """Evaluate one checkpoint at one level of one protocol (one torch thread): {"success" %,
    "progress" ({lift_percent, median_reach_cm}), "episodes" (per-episode records),
    "seconds", "steps"}."""
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    policy = LeRobotPolicy(checkpoint, device=args.device)
    env = PerturbedCameraEnv(EvalConfig(args.task, level, ("left",), seed=args.seed, max_steps=args.max_steps,
                                        world=WorldConfig(height=args.size, width=args.size), protocol=protocol))  # fmt: skip
    try:
        result = evaluate(policy, env, args.episodes, reset=policy.reset)
    finally:
        env.close()
    episodes = [{"level": level, "episode": i, "success": s, "steps": n, "reach_m": round(r, 4), "lifted": lf, **p}
                for i, (s, n, p, r, lf) in enumerate(zip(result.successes, result.steps, result.perturbations,
                                                         result.reach_m, result.lifted))]  # fmt: skip
    progress = {"lift_percent": round(100 * result.lift_rate, 2),
                "median_reach_cm": round(100 * float(np.median(result.reach_m)), 2)}  # fmt: skip
    return {"success": round(100 * result.success_rate, 2), "progress": progress, "episodes": episodes,
            "seconds": time.perf_counter() - t0, "steps": sum(result.steps)}  # fmt: skip


def checkpoint_digest(checkpoint: Path) -> str:
    """SHA-256 of the policy's config and weights in the training folder ``checkpoint``."""
    model, digest = last_checkpoint(checkpoint) / "pretrained_model", hashlib.sha256()
    for name in ("config.json", "model.safetensors"):
        digest.update((model / name).read_bytes())
    return digest.hexdigest()


def evaluation_key(digest: str, protocol: str, level: str, args) -> dict:
    """What decides one level's evaluation of the checkpoint whose :func:`checkpoint_digest` is
    ``digest``: the checkpoint, the level and the evaluation settings. The evaluation is seeded,
    so the same key gives the same episodes."""
    return {"checkpoint": digest, "protocol": protocol, "level": level, "task": args.task, "episodes": args.episodes,
            "max_steps": args.max_steps, "seed": args.seed, "size": args.size, "device": args.device}  # fmt: skip


#: What a stored evaluation record must hold to be kept.
RECORD_KEYS = {"success", "progress", "episodes", "seconds", "steps"}


def evaluate_all(work: Path, arms: tuple[str, ...], args) -> dict:
    """{protocol: {arm: {level: evaluate_level(...)}}}, ``args.eval_jobs`` (protocol, arm,
    level) jobs at a time in separate processes. Each level's record is kept in
    ``work/<arm>/evaluation/<protocol>_<level>.json`` with its :func:`evaluation_key`, so that a
    stopped evaluation resumes at the levels it had not finished."""
    jobs = [(protocol, arm, level) for protocol, levels in PROTOCOLS.items() for arm in arms for level in levels]
    out: dict = {protocol: {arm: {} for arm in arms} for protocol in PROTOCOLS}
    digests = {arm: checkpoint_digest(work / arm) for arm in arms}
    keys = {job: evaluation_key(digests[job[1]], *job[::2], args) for job in jobs}
    stored = {job: work / job[1] / "evaluation" / f"{job[0]}_{job[2]}.json" for job in jobs}

    def report(protocol: str, arm: str, level: str, kept: bool = False) -> None:
        r = out[protocol][arm][level]
        print(f"  {arm:>18} {protocol:>5} {level:>13}: {r['success']:5.1f} % success, "
              f"{r['progress']['lift_percent']:5.1f} % lifted, median closest approach "
              f"{r['progress']['median_reach_cm']:.1f} cm over {args.episodes} episodes"
              + (" (kept from a stopped run)" if kept else ""), flush=True)  # fmt: skip

    for job in jobs:
        old = read_json_object(stored[job])
        if old.get("key") == keys[job] and RECORD_KEYS <= set(old.get("record") or ()):
            out[job[0]][job[1]][job[2]] = old["record"]
            report(*job, kept=True)
    todo = [job for job in jobs if job[2] not in out[job[0]][job[1]]]
    with ProcessPoolExecutor(args.eval_jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {job: pool.submit(evaluate_level, work / job[1], *job[::2], args) for job in todo}
        for (protocol, arm, level), future in futures.items():
            out[protocol][arm][level] = future.result()
            atomic_write_json(stored[protocol, arm, level], {"key": keys[protocol, arm, level],
                                                             "record": out[protocol][arm][level]})  # fmt: skip
            report(protocol, arm, level)
    return out


#: Settings that shape every arm's policy and its evaluation (``--reuse-from`` checks them,
#: with the arm's augmentation and the episodes per level).
ARM_SETTINGS = ("task", "policy_cameras", "demos", "size", "steps", "batch_size", "workers", "down_dims",
                "n_obs_steps", "inference_steps", "max_steps", "seed", "device")  # fmt: skip


def protocol_part(result: dict, protocol: str) -> dict | None:
    """The part of a result that holds one protocol's evaluation (None when it has none)."""
    return result if protocol == "paper" else result.get("protocols", {}).get(protocol)


def read_result(path: Path, option: str) -> dict:
    """A result file of this script, or SystemExit naming ``option`` and what is wrong with it."""
    try:
        result = json.loads(path.read_text())
    except OSError as e:
        raise SystemExit(f"{option} {path}: cannot read it ({e.strerror})") from None
    except ValueError as e:
        raise SystemExit(f"{option} {path}: not JSON ({e})") from None
    if not isinstance(result, dict) or not {"arms", "levels", "settings"} <= result.keys():
        raise SystemExit(f"{option} {path}: not a result of policy_robustness.py (no arms, levels and settings)")
    return result


def reused_arms(paths: list[Path], arms: tuple[str, ...], settings: dict, episodes: int) -> tuple[dict, dict, dict]:
    """The arms of ``arms`` that earlier results hold with the same settings, under the
    protocols each file evaluated them (an arm is left out of the others' tables):
    ({protocol: {arm: {level: evaluate_level-like record}}}, {"train_<arm>" / "eval_<arm>":
    their timing}, {arm: file name}); the first file that holds an arm decides. Prints which
    arms are reused (and the protocols they lack), and why an arm a file holds is not. Raises SystemExit for a
    file that is not a result (``read_result``), a --quick result, one without arms, or missing episodes."""
    reused, timing, sources = {protocol: {} for protocol in PROTOCOLS}, {}, {}
    for path in paths:
        old = read_result(path, "--reuse-from")
        if old.get("quick") or not old["arms"]:
            why = "a --quick result" if old.get("quick") else "a result without arms"
            raise SystemExit(f"--reuse-from {path}: {why} is not reusable")
        for arm in (a for a in arms if a in old["arms"] and a not in sources):
            changed = {k: (old["settings"].get(k), settings[k]) for k in ARM_SETTINGS
                       if old["settings"].get(k) != settings[k]}  # fmt: skip
            if old["settings"]["augmentation"].get(arm) != settings["augmentation"][arm]:
                changed["augmentation"] = (old["settings"]["augmentation"].get(arm), settings["augmentation"][arm])
            if old["episodes_per_level"] != episodes:
                changed["episodes"] = (old["episodes_per_level"], episodes)
            if changed:
                print(f"not reusing {arm} from {path}: made with other settings {changed} (was, now)", flush=True)
                continue
            held = [p for p in PROTOCOLS if arm in (protocol_part(old, p) or {}).get("arms", {})]
            for protocol in held:
                levels = PROTOCOLS[protocol]
                part, reused[protocol][arm] = protocol_part(old, protocol), {}
                for level in levels:
                    records = sorted((e for e in part["episodes"][arm] if e["level"] == level), key=lambda e: e["episode"])
                    if [e["episode"] for e in records] != list(range(episodes)):
                        raise SystemExit(f"--reuse-from {path}: episodes 0-{episodes - 1} of {arm} at {protocol} "
                                         f"{level} are not all there")  # fmt: skip
                    reused[protocol][arm][level] = {"success": part["arms"][arm][level], "episodes": records,
                                                    "progress": part["progress"][arm][level]}  # fmt: skip
            timing |= {k: old["timing"][k] for k in (f"train_{arm}", f"eval_{arm}") if k in old["timing"]}
            sources[arm] = path.name
            missing = [p for p in PROTOCOLS if p not in held]
            print(f"reusing {arm} from {path}" + (f" (not evaluated under {', '.join(missing)}: left out of "
                                                  "those tables)" if missing else ""), flush=True)  # fmt: skip
    return reused, timing, sources


def best_2d(rates: dict) -> str | None:
    """The 2D arm among ``rates`` ({arm: {level: success %}}) with the highest mean success over
    the perturbed levels (the first in ``TWO_D_ARMS`` on a tie); None without a 2D arm."""
    arms = [a for a in TWO_D_ARMS if a in rates]
    return max(arms, key=lambda a: np.mean([v for lv, v in rates[a].items() if lv != "none"])) if arms else None


def comparisons(evaluated: dict) -> dict:
    """{"vs_baseline": {arm: {level: paired_difference}} for every other arm, "vs_2d": {2D arm:
    {GenSplat arm: {...}}}}: arm minus reference, on the same episodes; a comparison whose
    reference is not among ``evaluated`` ({arm: {level: record}}) is left out."""
    def successes(arm: str, level: str) -> list[bool]:
        return [e["success"] for e in evaluated[arm][level]["episodes"]]

    def against(reference: str, arms) -> dict:
        return {arm: {lv: paired_difference(successes(reference, lv), successes(arm, lv)) for lv in evaluated[arm]}
                for arm in arms if arm in evaluated and arm != reference}  # fmt: skip

    out = {}
    if "baseline" in evaluated:
        out["vs_baseline"] = against("baseline", evaluated)
    gensplat = [arm for arm in evaluated if arm_kind(arm) in GENSPLAT_ARMS]
    two_d = {reference: against(reference, gensplat) for reference in TWO_D_ARMS if reference in evaluated}
    if two_d:
        out["vs_2d"] = two_d
    return out


def protocol_result(evaluated: dict, protocol: str) -> dict:
    """One protocol's part of the result from its {arm: {level: record}}: success rates,
    progress, paired differences, the best 2D arm and the episode records."""
    rates = {arm: {lv: r["success"] for lv, r in per_level.items()} for arm, per_level in evaluated.items()}
    return {
        "arms": rates, "levels": list(PROTOCOLS[protocol]),
        "progress": {arm: {lv: r["progress"] for lv, r in per_level.items()} for arm, per_level in evaluated.items()},
        "difference": comparisons(evaluated), "best_2d": best_2d(rates),
        "episodes": {arm: [e for r in per_level.values() for e in r["episodes"]] for arm, per_level in evaluated.items()},
    }  # fmt: skip


def build_result(evaluated: dict, episodes: int, quick: bool, settings: dict, timing: dict) -> dict:
    """The result (see the module docstring) of {protocol: {arm: {level: record}}}: the paper
    protocol's part at the top, the others under ``protocols``."""
    parts = {protocol: protocol_result(evaluated[protocol], protocol) for protocol in PROTOCOLS}
    paper = parts.pop("paper")
    return {**{k: v for k, v in paper.items() if k != "episodes"}, "episodes_per_level": episodes, "quick": quick,
            "protocols": parts, "settings": settings, "timing": timing, "episodes": paper["episodes"]}  # fmt: skip


#: Line colours of the arms in the plot.
COLOURS = {"baseline": (214, 39, 40), "lerobot2d": (31, 119, 180), "perspective": (148, 103, 189),
           "gensplat": (44, 160, 44), "gensplat+lerobot2d": (255, 127, 14), "gensplat+color": (140, 86, 75),
           "gensplat-wide": (23, 190, 207), "gensplat-fov": (227, 119, 194), "gensplat-tilt": (188, 189, 34),
           "gensplat-arc": (127, 127, 127), "gensplat-fov-p0.5": (247, 182, 210),
           "gensplat-arc-p0.5": (199, 199, 199), "gensplat-tiltarc": (219, 219, 141),
           "gensplat-zoom": (158, 218, 229), "gensplat-unmoved": (0, 0, 0),
           "gensplat-wide-p0.5": (255, 187, 120)}  # fmt: skip


def colour(arm: str) -> tuple[int, int, int]:
    """``arm``'s line colour: its kind's (``COLOURS``), halfway to white for a replicate."""
    rgb = COLOURS[arm_kind(arm)]
    return rgb if arm_kind(arm) == arm else tuple((c + 255) // 2 for c in rgb)


def write_result(result: dict, out: Path) -> None:
    """Write ``result`` to ``out`` and its plot beside it, each whole or not at all: a stopped
    write keeps the old file (which ``--reuse-from`` may have read)."""
    atomic_write_json(out, result)
    plot(result, out.with_suffix(".png"))


def plot(result: dict, path: Path) -> None:
    """Two panels per protocol, a line per arm it evaluated: success % and the median closest
    approach (cm) against the level."""
    parts = {protocol: protocol_part(result, protocol) for protocol in PROTOCOLS}
    arms = ordered(a for part in parts.values() if part for a in part["arms"])
    panels = []
    for metric in ("success", "reach"):
        for protocol in PROTOCOLS:
            part = parts[protocol]
            x_ticks = list(enumerate(part["levels"]))
            x_range = (-0.5, len(x_ticks) - 0.5)
            if metric == "success":
                series = {a: [(j, part["arms"][a][lv], "") for j, lv in x_ticks] for a in part["arms"]}
                panels.append(Panel(f"success (%), {protocol}", series, x_range, (0, 100), x_ticks,
                                    [(t, str(t)) for t in range(0, 101, 20)]))  # fmt: skip
                continue
            series = {a: [(j, part["progress"][a][lv]["median_reach_cm"], "") for j, lv in x_ticks] for a in part["arms"]}
            top = float(np.ceil(max(5.0, *(y for pts in series.values() for _, y, _ in pts)) / 5) * 5)
            panels.append(Panel(f"median closest approach (cm), {protocol}", series, x_range, (0, top), x_ticks,
                                [(t, f"{t:.0f}") for t in np.arange(0, top + 1e-9, 5)]))  # fmt: skip
    s = result["settings"]
    note = (f"{s['task']}, Diffusion Policy, {s['steps']} steps at batch {s['batch_size']}, "
            f"{result['episodes_per_level']} episodes per level, left camera perturbed")  # fmt: skip
    line_panels(path, panels, {a: colour(a) for a in arms}, note, panel_size=(360, 300), legend_columns=len(arms))


def print_summary(result: dict) -> None:
    """The success tables and the paired differences, as printed at the end of a run."""
    for protocol in PROTOCOLS:
        part = protocol_part(result, protocol)
        levels = part["levels"]
        print(f"{protocol + ' success %':>18}" + "".join(f"{lv:>14}" for lv in levels))
        for arm, rates in part["arms"].items():
            print(f"{arm:>18}" + "".join(f"{rates[lv]:14.1f}" for lv in levels))
        diffs = part["difference"]
        for reference, against in (("baseline", diffs.get("vs_baseline", {})), *diffs.get("vs_2d", {}).items()):
            for arm, diff in against.items():
                best = " (best 2D)" if reference == part["best_2d"] else ""
                print(f"{arm + ' - ' + reference + best:>40}: " + ", ".join(
                    f"{lv} {diff[lv]['points']:+.1f} [{diff[lv]['ci95'][0]:+.0f}, {diff[lv]['ci95'][1]:+.0f}]"
                    for lv in levels) + " (points, paired 95 % CI)")  # fmt: skip


def markdown(result: dict) -> str:
    """The success tables of ``result`` in Markdown, one per protocol: a row per arm, each cell
    the success % and, for the other arms, the paired difference from the baseline in points
    with its 95 % interval; then the GenSplat arms against each 2D arm (McNemar p beside)."""
    lines = []
    for protocol in PROTOCOLS:
        part = protocol_part(result, protocol)
        levels, diffs = part["levels"], part["difference"]
        lines += [f"{protocol} protocol, success % (points vs baseline [paired 95 % CI]):", "",
                  "| arm | " + " | ".join(levels) + " |", "|---" * (len(levels) + 1) + "|"]  # fmt: skip
        for arm, rates in part["arms"].items():
            diff = diffs.get("vs_baseline", {}).get(arm)
            cells = [f"{rates[lv]:.0f}" + (f" ({_points(diff[lv])})" if diff else "") for lv in levels]
            lines.append(f"| {arm} | " + " | ".join(cells) + " |")
        for reference, against in diffs.get("vs_2d", {}).items():
            for arm, diff in against.items():
                best = ", the best 2D arm" if reference == part["best_2d"] else ""
                cells = [f"{_points(diff[lv])}, p = {diff[lv]['mcnemar_p']:.2g}" for lv in levels]
                lines.append(f"| {arm} - {reference}{best} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def augmented_share(augmentation: dict | None) -> str:
    """The share of training samples whose image an arm's ``augmentation`` (its entry in a
    result's settings) replaces with a render or a warp, as a percentage; "" when unknown."""
    if augmentation is None:
        return ""
    if "gensplat" in augmentation:
        return f"{100 * augmentation['gensplat']['probability']:.0f} %"
    perspective = augmentation.get("image_transforms", {}).get("tfs", {}).get("perspective")
    return f"{100 * perspective['kwargs']['p']:.0f} %" if perspective else "0 %"


def range_markdown(result: dict, motion: dict) -> str:
    """What a training range costs and gains: a row per arm of ``result`` whose training draws
    ``motion`` (``camera_motion.py``'s result) measured (``train/<arm>``, ``gensplat``'s for
    ``gensplat+color``; the baseline's range is 0), with the share of training samples whose
    camera is moved (blank where the result's settings do not say), the median (95th
    percentile) image shift and view change of its draws, and its success % at the training
    camera, the paper's large level and each VISTA and ``fov`` level its file evaluated (blank
    where it did not); "" when no arm has draws measured (nor is the baseline)."""
    columns = [("paper", "none"), ("paper", "large")] + [
        (protocol, level) for protocol in ("vista", "fov") for level in PROTOCOLS[protocol]
    ]
    zero = {f"{k}_{q}": 0.0 for k in ("shift_pct", "view_change_deg") for q in ("median", "p95")}
    lines = []
    for arm in protocol_part(result, "paper")["arms"]:
        # colour jitter on top moves nothing, a higher probability or another seed draws the same moves
        kind = arm_kind(arm)
        like = MORE_OFTEN[kind][0] if kind in MORE_OFTEN else kind.removesuffix("+color")
        draws = zero if kind == "baseline" else motion["rows"].get(f"train/{like}")
        if draws is None:
            continue
        cells = []
        for protocol, level in columns:
            rates = ((protocol_part(result, protocol) or {}).get("arms") or {}).get(arm, {})
            cells.append(f"{rates[level]:.0f}" if level in rates else "")
        ranges = [augmented_share(result.get("settings", {}).get("augmentation", {}).get(arm))]
        ranges += ["-" if draws[f"{k}_median"] is None else f"{draws[f'{k}_median']:.1f} ({draws[f'{k}_p95']:.1f})"
                  for k in ("shift_pct", "view_change_deg")]  # an image warp has no view change
        lines.append(f"| {arm} | " + " | ".join(ranges + cells) + " |")
    if not lines:
        return ""
    head = ["arm", "samples augmented", "training shift % of width", "training view change (deg)"]
    head += [f"{protocol} {level}" for protocol, level in columns]
    title = "Training range against success % (range: median (95th percentile) of the arm's training draws):"
    return "\n".join([title, "", "| " + " | ".join(head) + " |",
                      "|---" * len(head) + "|", *lines, ""])  # fmt: skip


#: How large a move of a level is, per episode record, and the bin edges ``move_markdown``
#: splits the level's episodes at: {(protocol, level): (what is measured, value of a record, edges)}.
MOVE_SIZES = {
    ("vista", "small_perturb"): ("rotation (deg)", lambda e: abs(np.degrees(e["angle_rad"])), (0, 3, 6, 90)),
    ("vista", "arc_90deg"): ("azimuth (deg)", lambda e: abs(e["azimuth_deg"]), (0, 15, 30, 45)),
    ("fov", "zoom"): ("focal length scale", lambda e: e["focal_scale"], (0.8, 0.9, 1.0, 1.1, 1.25)),
}


def move_markdown(result: dict) -> str:
    """Success against the size of the move within the wider levels (``MOVE_SIZES``): per level a
    table with a row per arm and a column per bin of the move's size (the last bin closed),
    each cell the success % over the episodes in the bin (their count in the header); "" when
    the result evaluated none of those levels."""
    lines = []
    for (protocol, level), (measure, size, edges) in MOVE_SIZES.items():
        part = protocol_part(result, protocol)
        if part is None or level not in part["levels"] or not part["arms"]:
            continue
        records = [e for e in part["episodes"][next(iter(part["arms"]))] if e["level"] == level]
        # the bin of each episode (the same move for every arm); the last bin holds its upper edge
        index = {e["episode"]: min(int(np.searchsorted(edges, size(e), side="right")) - 1, len(edges) - 2)
                 for e in records}  # fmt: skip
        cells = {arm: [[e["success"] for e in part["episodes"][arm] if e["level"] == level and index[e["episode"]] == i]
                       for i in range(len(edges) - 1)] for arm in part["arms"]}  # fmt: skip
        counts = [sum(i == j for i in index.values()) for j in range(len(edges) - 1)]
        head = [f"{lo:g}-{hi:g} ({n} ep.)" for lo, hi, n in zip(edges[:-1], edges[1:], counts)]
        lines += [f"{protocol} {level}, success % by {measure}:", "", f"| arm | {' | '.join(head)} |",
                  "|---" * len(edges) + "|"]  # fmt: skip
        for arm, per_bin in cells.items():
            lines.append(f"| {arm} | " + " | ".join(f"{100 * np.mean(c):.0f}" if c else "" for c in per_bin) + " |")
        lines.append("")
    return "\n".join(lines)


def _points(diff: dict) -> str:
    return f"{diff['points']:+.0f} [{diff['ci95'][0]:+.0f}, {diff['ci95'][1]:+.0f}]"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line with its defaults filled in (full or ``--quick``); ``arms`` and
    ``cameras`` as tuples."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny end-to-end check (a few minutes)")
    parser.add_argument(
        "--work", type=Path, help="dataset, checkpoints, logs (default outputs/policy_robustness[_quick])"
    )
    parser.add_argument("--arms", default=",".join(ARMS),
                        help=f"comma-separated arms, or replicates <arm>@s<N> (default all: {','.join(ARMS)})")  # fmt: skip
    parser.add_argument("--task", default="reach_solo", choices=sorted(TASKS), help="default reach_solo")
    parser.add_argument("--cameras", default="left",
                        help="comma-separated cameras the policy sees (default left; all: left,right,wrist)")  # fmt: skip
    parser.add_argument("--demos", type=int, help="demonstrations (default 300; quick 2)")
    parser.add_argument("--size", type=int, help="image size of every camera (default 96)")
    parser.add_argument("--steps", type=int, help="training steps per policy (default 2500; quick 4)")
    parser.add_argument("--batch-size", type=int, help="default 32; quick 4")
    parser.add_argument("--workers", type=int, help="dataloader workers (default 0: on 2 cores they only take the "
                        "training's time)")  # fmt: skip
    parser.add_argument("--down-dims", help="U-Net widths (default 64,128,256; quick 32,64,128)")
    parser.add_argument("--n-obs-steps", type=int, default=1, help="observation frames per step (default 1)")
    parser.add_argument("--inference-steps", type=int, default=10, help="DDIM steps per action chunk")
    parser.add_argument("--views-per-source", type=int, default=3, help="GenSplat cameras per trajectory")
    parser.add_argument("--probability", type=float, default=0.25,
                        help="chance that GenSplat replaces, or the perspective arm warps, a sample's camera "
                        "(default 0.25)")  # fmt: skip
    parser.add_argument("--fill-holes", action=argparse.BooleanOptionalAction, default=True,
                        help="GenSplat fills uncovered pixels from their surroundings (default; "
                        "--no-fill-holes paints them black)")  # fmt: skip
    parser.add_argument("--episodes", type=int, help="evaluation episodes per level (default 100; quick 2)")
    parser.add_argument("--max-steps", type=int, help="evaluation step budget (default the task's; quick 20)")
    parser.add_argument("--seed", type=int, default=0, help="seeds recording, training and evaluation")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--eval-jobs", type=int, default=2, help="evaluation processes (default 2)")
    parser.add_argument(
        "--parallel-train",
        action="store_true",
        help="train the arms at once (a GPU with room to spare; not on a 2-core CPU)",
    )
    parser.add_argument("--reuse-from", type=Path, action="append", default=[], metavar="RESULT.json",
                        help="reuse the arms an earlier result holds with the same settings (repeatable)")  # fmt: skip
    parser.add_argument("--table", type=Path, metavar="RESULT.json",
                        help="print a result's tables in Markdown and exit (runs nothing)")  # fmt: skip
    parser.add_argument("--out", type=Path, help="result JSON (default benchmarks/results/policy_robustness.json; "
                        "with --quick outputs/benchmarks_quick/policy_robustness.json: a check never lands "
                        "beside the committed results)")  # fmt: skip
    args = parser.parse_args(argv)
    for key, (full, quick) in DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, quick if args.quick else full)
    args.cameras = tuple(args.cameras.split(","))
    if not args.cameras or any(c not in CAMERA_NAMES for c in args.cameras):
        parser.error(f"--cameras: choose from {CAMERA_NAMES}, got {args.cameras}")
    unknown = [a for a in args.arms.split(",") if arm_kind(a) not in ARMS]
    if unknown:
        parser.error(f"--arms: unknown {unknown}; choose from {ARMS}, or a replicate <arm>@s<N> with N >= 1")
    args.arms = ordered(args.arms.split(","))
    seeds = {arm: train_seed(arm, args) for arm in args.arms}
    if not all(0 <= seed < KEY_LIMIT for seed in seeds.values()):
        parser.error(f"--seed and --arms: training seeds must be in [0, 2**32), got {seeds}")
    if "perspective" in map(arm_kind, args.arms) and "wrist" in args.cameras:
        parser.error("the perspective arm warps every camera LeRobot loads, the wrist camera too: "
                     "give it a policy that sees external cameras only")  # fmt: skip
    args.max_steps = args.max_steps or TASKS[args.task].max_steps
    args.out = args.out or default_out("policy_robustness.json", args.quick)
    args.work = args.work or ROOT / "outputs" / ("policy_robustness_quick" if args.quick else "policy_robustness")
    return args


def result_settings(args) -> dict:
    """The result's ``settings``: what shapes the arms and their evaluation."""
    settings = {k: getattr(args, k) for k in ("demos", "size", "steps", "batch_size", "workers", "down_dims",
                                             "n_obs_steps", "inference_steps", "max_steps", "seed", "device",
                                             "parallel_train")}  # fmt: skip
    settings.update(task=args.task, policy_cameras=list(args.cameras), arms=list(args.arms),
                    policy="diffusion (policies/diffusion.json + the overrides above)", perturbed_camera="left",
                    augmentation={arm: augmentation(arm, args) for arm in args.arms},
                    protocols={protocol: list(levels) for protocol, levels in PROTOCOLS.items()})  # fmt: skip
    return settings


def main() -> None:
    args = parse_args()
    if args.table:
        result = read_result(args.table, "--table")
        print(markdown(result))
        if MOTION.is_file():
            print(range_markdown(result, json.loads(MOTION.read_text())))
        print(move_markdown(result))
        return
    arms, work = args.arms, args.work
    settings = result_settings(args)
    reused, timing, sources = reused_arms(args.reuse_from, arms, settings, args.episodes)
    if sources:
        settings["reused"] = sources
    to_run = tuple(a for a in arms if a not in sources)
    if to_run:
        lock = lock_work(work)  # noqa: F841  (held until the run ends)
        check_work(work, to_run, args)
    t_start = time.perf_counter()

    if to_run:
        record_dataset(work, args)
    for arm in to_run:
        prepare_arm(work, arm, args)

    with ThreadPoolExecutor(len(to_run) if args.parallel_train and to_run else 1) as pool:  # each in a subprocess
        trained = pool.map(lambda a: train(a, dataset_root(work, a), work / a, args), to_run)
        for arm, t in zip(to_run, trained):
            timing[f"train_{arm}"] = t
    print(f"evaluating {', '.join(to_run) or 'nothing'} ({args.eval_jobs} processes)", flush=True)
    t0 = time.perf_counter()
    evaluated = evaluate_all(work, to_run, args)
    timing["eval_seconds"] = round(time.perf_counter() - t0, 1)
    for arm in to_run:
        records = [evaluated[protocol][arm][level] for protocol, levels in PROTOCOLS.items() for level in levels]
        seconds, steps = (sum(r[k] for r in records) for k in ("seconds", "steps"))
        timing[f"eval_{arm}"] = {"process_seconds": round(seconds, 1), "s_per_control_step": round(seconds / steps, 3),
                                 "s_per_episode": round(seconds / (len(records) * args.episodes), 2)}  # fmt: skip
    timing["total_seconds"] = round(time.perf_counter() - t_start, 1)
    evaluated = {p: {arm: r[arm] for arm in arms if arm in (r := {**reused[p], **evaluated[p]})} for p in PROTOCOLS}
    result = build_result(evaluated, args.episodes, args.quick, settings, timing)
    write_result(result, args.out)
    print_summary(result)
    print(
        f"wrote {args.out} ({timing['total_seconds']:.0f} s{', QUICK: not a result' if args.quick else ''})"
    )


if __name__ == "__main__":
    main()
