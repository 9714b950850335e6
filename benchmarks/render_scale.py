"""What rendering the augmented views at a fraction of the image size (``render_scale``) saves
in time and costs in fidelity, at the sizes policies shrink 640x480 frames to.

    python benchmarks/render_scale.py [--quick] [--reconstructor rgbd|geometry]
        [--scales 1 0.75 0.5 0.35 0.25] [--episodes N] [--samples N] [--out PATH]

Held-out simulated pick-and-place episodes are recorded at 640x480 with MP4 video, as LeRobot
datasets hold them (320x240 and one episode with --quick), and their cache built as
``gensplat cache`` builds it: RGB-D (the recorded depth, at the frame size), or with
``--reconstructor geometry`` the RGB-only path (the shipped model's depth, held at its 126x98
input size; the views are still built from the frames' colours at the render size). The
training transform (probability 1, level "train", both
external cameras replaced) runs on the same samples with the same draws at every scale:

* ``ms``: its CPU time per sample in this thread, one thread as in a dataloader worker, for
  everything it does (depth read, resizes, discs, both renders, hole filling, resize back to
  the frame size, uint8); ``wall_ms`` beside it. Medians over samples, the scales run in
  turn on each sample (load changes touch them alike).
* Fidelity of each replaced view against the simulator's true image at the perturbed pose,
  at the frame size and at the sizes policies shrink such frames to before reading them:
  320x240 (e.g. Diffusion Policy with ``resize_shape=(240, 320)``) and 224x168 (pi0 and pi0.5
  shrink 640x480 to fit 224x224, keeping the aspect). Every image is shrunk alike (bilinear,
  antialiased); mean PSNR and SSIM over views, ``sharpness`` (the view's detail over the true
  image's, :func:`~gensplat_transforms.core.metrics.sharpness_ratio`: below 1 is blurrier, which
  PSNR rewards) and ``psnr_vs_full``: PSNR against the scale-1 view (what the scale alone
  loses).

Writes benchmarks/results/render_scale.json (render_scale_geometry.json for the geometry
path; under outputs/benchmarks_quick/ with --quick; or --out) and prints a table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as in render_speed.py

import torch
import torch.nn.functional as F
from gensplat_lerobot import enable_gensplat, prepare, video_backend
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.truth import GroundTruth
from gensplat_sim.world import WorldConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.core.metrics import psnr, sharpness_ratio, ssim
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform, render_size
from gensplat_transforms.views.perturbation import AXES, Perturbation

REPO = "gensplat/sim_pick_place_heldout"
HELDOUT_SEED = 1000  # as nvs_fidelity.py: training recordings use other seeds
POLICY_WIDTHS = (320, 224)  # policy input widths compared besides the frame's own


def shrink(image: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(3, H, W) float image at ``width x height`` (bilinear, antialiased), as policies resize."""
    if image.shape[-2:] == (height, width):
        return image
    return F.interpolate(image[None], size=(height, width), mode="bilinear", antialias=True, align_corners=False)[0]


def as_float(image: torch.Tensor) -> torch.Tensor:
    return image.float() / 255 if image.dtype == torch.uint8 else image.float()


def run(args: argparse.Namespace) -> dict:
    width, height, episodes = (320, 240, 1) if args.quick else (640, 480, args.episodes)
    root = Path(tempfile.mkdtemp(prefix="render_scale_")) / "ds"
    print(f"recording {episodes} episode(s) at {width}x{height} (MP4) ...", flush=True)
    record(RecordConfig(root, "pick_place", episodes, HELDOUT_SEED, use_videos=True, repo_id=REPO,
                        world=WorldConfig(width=width, height=height)), progress=False)  # fmt: skip
    prepare(root, REPO, GenSplatConfig(probability=1.0, level="train", report=True, render_in="worker"),
            {"name": args.reconstructor}, progress=False)  # fmt: skip
    ds = enable_gensplat(LeRobotDataset(REPO, root=root, video_backend=video_backend()))
    base = ds.gensplat
    transforms = {s: GenSplatTransform(replace(base.cfg, render_scale=s), base.cache, base.source)
                  for s in args.scales}  # fmt: skip
    sizes = {"frame": (width, height), **{f"w{w}": (w, round(height * w / width)) for w in POLICY_WIDTHS}}
    truth = GroundTruth(root)
    cfg = base.cfg
    keys = [cfg.image_key.format(name=n) for n in cfg.replace]
    times = {s: {"ms": [], "wall_ms": []} for s in args.scales}
    scores = {s: {at: {"psnr": [], "ssim": [], "sharpness": [], "psnr_vs_full": []} for at in sizes} for s in args.scales}
    indices = torch.linspace(0, len(ds) - 1, args.samples).long().tolist()
    first = LeRobotDataset.__getitem__(ds, indices[0])
    for tf in transforms.values():  # warm-up: first reads, first calls
        tf(first)
    for n, idx in enumerate(indices):
        item = LeRobotDataset.__getitem__(ds, idx)
        ep, fr = int(item["episode_index"]), int(item["frame_index"])
        outs = {}
        for s in args.scales[n % len(args.scales) :] + args.scales[: n % len(args.scales)]:
            torch.manual_seed(n)  # the same draws at every scale
            t0, c0 = time.perf_counter(), time.thread_time()
            outs[s] = transforms[s](item)
            times[s]["ms"].append((time.thread_time() - c0) * 1e3)
            times[s]["wall_ms"].append((time.perf_counter() - t0) * 1e3)
        report = outs[args.scales[0]]
        cameras = base.source.cameras  # calibrated, at the frame size
        for r, (name, key) in enumerate(zip(cfg.replace, keys)):
            p = Perturbation(AXES[int(report["gensplat.axis"][r])], float(report["gensplat.theta_deg"][r]),
                             float(report["gensplat.mu_m"][r]))  # fmt: skip
            true_rgb = truth.render(ep, fr, p.move(cameras, cfg.cameras.index(name)))[0][0]
            for at, (w, h) in sizes.items():
                target, full = shrink(true_rgb, w, h), shrink(as_float(outs[1.0][key]), w, h)
                for s in args.scales:
                    view = shrink(as_float(outs[s][key]), w, h)
                    scores[s][at]["psnr"].append(psnr(view, target))
                    scores[s][at]["ssim"].append(ssim(view, target))
                    scores[s][at]["sharpness"].append(sharpness_ratio(view, target))
                    scores[s][at]["psnr_vs_full"].append(psnr(view, full))
        print(f"  sample {n + 1}/{len(indices)}", flush=True)
    truth.close()
    rows = {}
    for s in args.scales:
        w, h = render_size(width, height, s)
        row = {"render_size": [w, h], **{k: round(statistics.median(v), 2) for k, v in times[s].items()}}
        for at, metrics in scores[s].items():
            for k, v in metrics.items():
                finite = [x for x in v if x != float("inf")]
                row[f"{k}_{at}"] = round(statistics.mean(finite), 3) if finite else None  # None: identical
        rows[str(s)] = row
    return {
        "quick": args.quick, "reconstructor": base.cache.identity, "cached_size": list(base.cache.image_size(0)),
        "frame_size": [width, height], "episodes": episodes, "samples": len(indices),
        "views_compared": len(indices) * len(cfg.replace), "level": cfg.level, "cameras_replaced": list(cfg.replace),
        "compared_at": {at: list(wh) for at, wh in sizes.items()}, "scales": rows,
        "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg(),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one 320x240 episode, 4 samples (about a minute)")
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.75, 0.5, 0.35, 0.25],
                        help="render scales; 1 is added when missing (default: 1 0.75 0.5 0.35 0.25)")
    parser.add_argument("--episodes", type=int, default=2, help="episodes recorded (default: 2)")
    parser.add_argument("--samples", type=int, default=None, help="samples compared (default: 16, 4 with --quick)")
    parser.add_argument("--reconstructor", choices=("rgbd", "geometry"), default="rgbd",
                        help="rgbd: the recorded depth; geometry: RGB only, the shipped model's depth (default: rgbd)")
    parser.add_argument("--out", type=Path, help=out_help("render_scale[_geometry].json"))
    args = parser.parse_args()
    name = "render_scale" + ("" if args.reconstructor == "rgbd" else f"_{args.reconstructor}")
    args.out = args.out or default_out(f"{name}.json", args.quick)
    args.scales = [1.0, *(s for s in args.scales if s != 1.0)]
    args.samples = args.samples or (4 if args.quick else 16)
    torch.set_num_threads(1)  # as in a dataloader worker
    result = run(args)
    sizes = list(result["compared_at"])
    print(f"{'scale':>6} {'render':>9} {'ms':>7} {'wall ms':>8}  " + "  ".join(f"{'PSNR/SSIM/sharp @' + a:>28}" for a in sizes)
          + f"  {'PSNR vs scale 1 @' + sizes[-1]:>22}")  # fmt: skip
    for s, row in result["scales"].items():
        cells = "  ".join(f"{row[f'psnr_{a}']:>13.2f} / {row[f'ssim_{a}']:.3f} / {row[f'sharpness_{a}']:.2f}" for a in sizes)
        vs_full = row[f"psnr_vs_full_{sizes[-1]}"]
        print(f"{s:>6} {'x'.join(map(str, row['render_size'])):>9} {row['ms']:>7.1f} {row['wall_ms']:>8.1f}  {cells}  "
              f"{'exact' if vs_full is None else f'{vs_full:.2f}':>22}")  # fmt: skip
    write_result(result, args.out)


if __name__ == "__main__":
    main()
