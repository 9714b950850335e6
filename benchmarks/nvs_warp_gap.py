"""Where the RGB-D render gains or loses against the forward warp, on the pixels the warp fills.

    python benchmarks/nvs_warp_gap.py [--quick] [--root DATASET] [--out DIR]

The held-out episodes, frames and perturbations of ``nvs_fidelity.py`` (left camera moved,
clean depth). On the pixels the forward warp of the left + right views fills, PSNR against
the simulator's truth, over all of them (``warp_mask``) and split into ``edge`` (within 2 px
of a depth discontinuity of the true view: a relative depth step > 3 % in a 3x3 window) and
``interior`` (the rest), for one factor changed at a time:

* ``forward_warp``, ``rgbd``, ``rgbd_plain``: as in ``nvs_fidelity.py`` (left + right views);
* ``forward_warp_left``, ``rgbd_left``: the left view only (no fusion of two views);
* ``rgbd_no_preference``: every camera's discs composited alike (``view_preference`` 0);
* ``rgbd_no_soften``: every disc sharp, also where the depth reads as rough (``soften_noise``
  off);
* ``rgbd_unsaturated``: plain alpha (``saturation`` 1);
* ``rgbd_dilation_0.3``: the renderer's usual 0.3 px^2 dilation;
* ``rgbd_sigma_0.4``: wider footprints (``RGBDConfig.sigma_px``, 0.3 by default);
* ``rgbd_edge_scale_1``: splats not shrunk across depth edges (``edge_scale`` 1, 0.5 by
  default);
* ``rgbd_sigma_0.4_edge_scale_0.25``: wider footprints shrunk more at edges, together;
* ``rgbd_cover_1``: partly covered pixels as composited (``cover`` 1; the views here are not
  hole-filled).

Writes ``benchmarks/results/nvs_warp_gap.json``: ``{variant: {level: {warp_mask, interior,
edge}}}`` (mean PSNR in dB over comparisons; null: identical images), ``edge_share`` (the edge pixels' share of the
warp mask per level) and ``settings``; into ``--out`` when given, and into ``outputs/benchmarks_quick/``
with ``--quick``.
"""

from __future__ import annotations

import json
import time

import numpy as np
import torch
import torch.nn.functional as F
from gensplat_lerobot import LeRobotSource
from gensplat_sim.truth import GroundTruth
from nvs_fidelity import PLAIN, _mean, draw, heldout_dataset, sampled_frames, sampling_parser, with_defaults

from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.rendering.warp import forward_warp
from gensplat_transforms.views.perturbation import EVAL_LEVELS, PaperSampler

RGBD = {"rgbd": {}, "rgbd_plain": PLAIN, "rgbd_left": {}, "rgbd_no_preference": {"view_preference": 0.0},
        "rgbd_no_soften": {"soften_noise": False},
        "rgbd_unsaturated": {"saturation": 1.0}, "rgbd_dilation_0.3": {"dilation": 0.3},
        "rgbd_sigma_0.4": {"sigma_px": 0.4}, "rgbd_edge_scale_1": {"edge_scale": 1.0},
        "rgbd_sigma_0.4_edge_scale_0.25": {"sigma_px": 0.4, "edge_scale": 0.25}, "rgbd_cover_1": {"cover": 1.0}}  # fmt: skip


def depth_edges(depth: torch.Tensor) -> torch.Tensor:
    """(1, H, W) bool: pixels within 2 px of a relative depth step > 3 % of (1, 1, H, W) depth."""
    hi, lo = F.max_pool2d(depth, 3, 1, 1), -F.max_pool2d(-depth, 3, 1, 1)
    step = ((hi - lo) > 0.03 * lo.clamp_min(1e-6)).float()
    return F.max_pool2d(step, 5, 1, 2)[0] > 0


def compare_frame(views: Views, truth: GroundTruth, ep: int, fr: int, args, rows: list) -> None:
    """Append one row per (variant, level, draw) for one timestep."""
    cams, left = views.cameras, Views(views.images[:1], views.cameras[:1], views.depths[:1])
    recs = {name: RGBDReconstructor(**cfg).reconstruct(left if name == "rgbd_left" else views)
            for name, cfg in RGBD.items()}  # fmt: skip
    for level in EVAL_LEVELS:
        sampler = PaperSampler(level, seed=args.seed)
        for d in range(1 if level == "none" else args.draws):
            target = sampler.sample(ep, view=d).move(cams, 0)
            gt, gt_depth = truth.render(ep, fr, target)
            fw, mask = forward_warp(views.images, views.depths, cams, target)
            fw_left, _ = forward_warp(left.images, left.depths, left.cameras, target)
            edge = depth_edges(gt_depth)
            masks = {"warp_mask": mask[0], "interior": mask[0] & ~edge, "edge": mask[0] & edge}
            images = {"forward_warp": fw[0], "forward_warp_left": fw_left[0]}
            images.update({n: draw(r, target).rgb[0] for n, r in recs.items()})
            share = float(masks["edge"].float().sum() / mask.float().sum())
            for name, image in images.items():
                rows.append({"variant": name, "level": level, "edge_share": share,
                             **{k: psnr(image.clamp(0, 1), gt[0], m) for k, m in masks.items()}})  # fmt: skip


def main() -> None:
    args = with_defaults(sampling_parser(__doc__.splitlines()[0]).parse_args())

    t0 = time.perf_counter()
    root = args.root or heldout_dataset(args.size, args.episodes)
    source = LeRobotSource(root, args.repo_id, ("left", "right"))
    truth = GroundTruth(root)
    rows: list = []
    for ep, fr in sampled_frames(source, args.episodes, args.frames):
        compare_frame(source.views(ep, fr), truth, ep, fr, args, rows)
    table: dict = {}
    for r in rows:
        table.setdefault(r["variant"], {}).setdefault(r["level"], []).append(r)
    table = {v: {lv: {k: _mean([r[k] for r in rs]) for k in ("warp_mask", "interior", "edge")}
                 for lv, rs in levels.items()} for v, levels in table.items()}  # fmt: skip
    share = {
        lv: round(float(np.mean([r["edge_share"] for r in rows if r["level"] == lv])), 3)
        for lv in EVAL_LEVELS
    }
    result = {**table, "edge_share": share, "settings": {
        "quick": args.quick, "dataset": "recorded held-out" if args.root is None else str(root),
        "image_size": [source.cameras.height, source.cameras.width],
        "episodes": args.episodes, "frames_per_episode": args.frames, "draws_per_level": args.draws,
        "perturbed_camera": "left", "perturbation_seed": args.seed, "edge": "within 2 px of a > 3 % depth step",
        "seconds": round(time.perf_counter() - t0, 1)}}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "nvs_warp_gap.json").write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")

    print(f"{'variant':>18} " + " ".join(f"{lv:>20}" for lv in EVAL_LEVELS) + "  (mask / interior / edge)")
    for name, levels in table.items():
        cells = ["/".join("exact" if e[k] is None else f"{e[k]:.2f}" for k in ("warp_mask", "interior", "edge"))
                 for e in levels.values()]  # fmt: skip
        print(f"{name:>18} " + " ".join(f"{c:>20}" for c in cells))
    print(f"edge share of the warp mask: {share}; wrote {args.out / 'nvs_warp_gap.json'}")


if __name__ == "__main__":
    main()
