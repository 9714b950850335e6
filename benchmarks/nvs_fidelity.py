"""Novel-view fidelity against the simulator's truth, per perturbation level and method.

    python benchmarks/nvs_fidelity.py [--quick] [--samplers] [--root DATASET] [--model WEIGHTS_DIR]

Held-out simulated pick-and-place episodes are recorded (run seed 1000; training datasets
use other seeds) unless ``--root`` names a recorded simulated dataset. At sampled frames the
left external camera is moved by ``draws`` perturbations per level (one for ``none``), and
each method's view at that pose is compared with ``GroundTruth.render`` there:

* ``rgbd``: Gaussians from the calibrated left + right RGB-D views (``RGBDReconstructor``),
  rendered with the fast CPU renderer at the perturbed pose as the transform draws them
  (sharp discs, the closest camera's in front: :func:`draw`);
* ``rgbd_plain``: the same discs drawn as plain Gaussians (the renderer's 0.3 px^2
  dilation, unsaturated alpha, every camera's discs alike: ``PLAIN``);
* ``rgbd_fill``: the same render with the uncovered pixels filled from their surroundings
  (``holes.fill_holes``, what the training transform does by default);
* ``rgbd_sensor``: ``rgbd`` on the depth a real RGB-D camera would give
  (``gensplat_sim.sensor.sensor_depth`` with the default, RealSense D435-like ``SensorDepthConfig``,
  seeded per timestep); ``rgbd_sensor_fill``: with the uncovered pixels filled, as the
  transform shows it; ``rgbd_sensor_depth_fill``: the same with the sensor's holes given depth
  before the discs are built (``RGBDConfig.fill_depth_px`` = ``FILL_DEPTH_PX``, ``gensplat cache
  --fill-depth``);
* ``forward_warp`` / ``forward_warp_sensor``: every left + right pixel forward-projected with
  its clean / sensor depth to the perturbed camera (``warp.forward_warp``: nearest pixel,
  z-buffer, no Gaussians), the baseline the RGB-D path must beat;
* ``gensplat_small``: the feed-forward model (``GenSplatReconstructor``) on the left + right
  RGB images only; like the training transform, it perturbs the camera it predicted about
  the pivot of its predicted cameras. Included when the weights exist (default: the
  package's ``weights/small``), reported under ``unavailable`` otherwise;
* ``geometry_small`` / ``geometry_small_metric``: the same model through the geometry path
  (``GeometryReconstructor``: only its depth, on the calibrated rays, scale fitted to the
  calibrated camera baseline / kept as predicted; the RGB-D discs coloured by the images),
  the depth predicted at the model's input size (its ``max_pixels``: 112x112 for the shipped
  model), the discs built at the frame size from the frames' colours and that depth (taken
  at the nearest pixels), as the transform builds them from such a cache;
  ``geometry_small_metric_fill``: the metric one with its holes filled, as the transform
  shows it;
* ``source_image``: the unchanged left image (what a policy sees without augmentation);
* ``homography``: the left image warped by the homography that the table plane z = 0
  induces between the source and the perturbed camera (exact for the table top, which
  covers most pixels; a rotation-only homography K R K^-1 would also ignore the camera's
  motion along the arc about the pivot, which dominates the image shift here).

Metrics: PSNR and SSIM over the whole image and over the pixels the source cameras saw
(alpha > 0.5 of the RGB-D render at that pose; for SSIM, windows centred on those pixels),
averaged over comparisons (PSNR null: identical images, +inf dB); ``coverage`` is that
pixel fraction. ``psnr_warp_mask``: PSNR over exactly the pixels the forward warp fills
(of the sensor depth for the ``*_sensor`` methods, of the clean depth for the others), the
fraction of which is ``warp_coverage``. Times (ms per novel view,
one CPU thread, as in a dataloader worker): ``reconstruct_ms`` once per timestep (cached in
training), ``render_ms`` per view (the warp for ``homography`` and ``forward_warp``), ``ms``
their sum.

``--samplers`` draws the wider moves instead of the paper's levels (``level_samplers``, the
settings of ``policy_robustness.py``'s wider arms): ``tilt`` (up to 10 deg about a random
axis through the camera, 3 cm shifts), ``arc`` (up to +-45 deg about the vertical through the
pivot) and ``zoom`` (the focal length scaled log-uniformly in 0.8-1.25, the camera in place),
beside ``none``: how faithful the views are that those arms train on.

Writes ``benchmarks/results/nvs_fidelity.json`` (``nvs_fidelity_samplers.json`` with
``--samplers``; ``{method: {level: {psnr, ssim, ms, ...}}}`` plus ``settings`` and
``unavailable``) and a plot beside it (PSNR vs level); into ``--out`` when given, and into
``outputs/benchmarks_quick/`` with ``--quick``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import torch
import torch.nn.functional as F
from gensplat_lerobot import LeRobotSource
from gensplat_sim.evaluate import FOV_RANGE
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.sensor import SensorDepthConfig, sensor_depth
from gensplat_sim.truth import GroundTruth
from gensplat_sim.world import WorldConfig
from machine import default_out, out_help
from plotting import Panel, line_panels
from policy_robustness import SAMPLER_ARMS

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.metrics import psnr, ssim
from gensplat_transforms.core.scenes import Scenes
from gensplat_transforms.geometry import (
    GenSplatReconstructor,
    GeometryReconstructor,
    Reconstruction,
    RGBDReconstructor,
    Views,
)
from gensplat_transforms.geometry.base import nearest_pixels
from gensplat_transforms.rendering import RenderOutput
from gensplat_transforms.rendering.scenes import render_scenes
from gensplat_transforms.rendering.warp import forward_warp
from gensplat_transforms.transform import GenSplatConfig
from gensplat_transforms.views.perturbation import EVAL_LEVELS, PaperSampler
from gensplat_transforms.weights import DEFAULT_MODEL_DIR

REPO = "gensplat/sim_pick_place_heldout"
HELDOUT_SEED = 1000
METHODS = ("rgbd", "rgbd_plain", "rgbd_fill", "rgbd_sensor", "rgbd_sensor_fill", "rgbd_sensor_depth_fill", "forward_warp",
           "forward_warp_sensor", "gensplat_small",
           "geometry_small", "geometry_small_metric", "geometry_small_metric_fill", "source_image", "homography")  # fmt: skip
SENSOR = SensorDepthConfig()
FILL_DEPTH_PX = 8  # rgbd_sensor_depth_fill: the sensor's holes filled before the discs (gensplat cache --fill-depth 8)
PLOT_MAX_DB = 40.0


def level_samplers(args: argparse.Namespace) -> dict:
    """{level: sampler} of the run: the paper's levels, or with ``--samplers`` ``none``, the
    ``gensplat-tilt`` and ``gensplat-arc`` arms' training moves and the ``fov`` protocol's focal
    change alone (policy_robustness.py's ``SAMPLER_ARMS``; gensplat_sim.evaluate's ``FOV_RANGE``)."""
    if args.samplers:
        arm = {kind: GenSplatConfig(**SAMPLER_ARMS[f"gensplat-{kind}"], seed=args.seed).perturbations()
               for kind in ("tilt", "arc")}  # fmt: skip
        return {"none": PaperSampler("none", seed=args.seed), **arm,
                "zoom": PaperSampler("none", seed=args.seed, focal_scale=FOV_RANGE)}  # fmt: skip
    return {level: PaperSampler(level, seed=args.seed) for level in EVAL_LEVELS}


def _plane_to_pixels(cam: Cameras) -> torch.Tensor:
    """(3, 3) map from points (X, Y, 1) of the plane z = 0 to homogeneous pixels (u z, v z, z)
    of one camera: K [r1 r2 t] with [R | t] its world-to-camera transform."""
    w2c = cam.w2c()[0].double()
    return cam.K[0].double() @ torch.stack([w2c[:3, 0], w2c[:3, 1], w2c[:3, 3]], 1)


def homography_warp(image: torch.Tensor, src: Cameras, dst: Cameras) -> torch.Tensor:
    """Warp the (3, H, W) image of camera ``src`` into camera ``dst`` (one camera each) by the
    homography H = P_src P_dst^-1 that the table plane z = 0 induces (P: plane to pixels).
    Pixels whose plane point lies behind either camera, or outside the source image, are
    black, as unseen pixels are in the renders."""
    p_src, p_dst = _plane_to_pixels(src), _plane_to_pixels(dst)
    uv = dst.pixel_centers().double()
    plane = torch.linalg.solve(p_dst, torch.cat([uv, torch.ones_like(uv[:, :1])], 1).T)
    plane = plane / plane[2:]  # (3, H*W) plane points (X, Y, 1)
    z_dst = (p_dst @ plane)[2]
    pix = p_src @ plane  # third row of K is (0, 0, 1): pix[2] is the source camera's z
    xy = (pix[:2] / pix[2:]).T
    grid = torch.stack([xy[:, 0] / src.width, xy[:, 1] / src.height], -1) * 2 - 1
    grid = grid.reshape(1, dst.height, dst.width, 2).to(image.dtype)
    out = F.grid_sample(image[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]
    return out * ((z_dst > 0) & (pix[2] > 0)).reshape(1, dst.height, dst.width)


def heldout_dataset(size: int, episodes: int) -> Path:
    """Record ``episodes`` held-out demonstrations at ``size`` x ``size`` into a temp folder."""
    root = Path(tempfile.mkdtemp(prefix="nvs_fidelity_")) / "sim"
    record(RecordConfig(root, "pick_place", episodes, HELDOUT_SEED, use_videos=False, repo_id=REPO,
                        world=WorldConfig(width=size, height=size)), progress=False)  # fmt: skip
    return root


def load_model(path: Path) -> GenSplatReconstructor | str:
    """The feed-forward reconstructor, or why it is unavailable."""
    if not (path / "model.safetensors").is_file():
        return f"no weights at {path} (train them with gensplat_transforms.training)"
    return GenSplatReconstructor(path)


def sensor_views(views: Views, seed: int) -> Views:
    """``views`` with each depth map as the simulated RGB-D sensor (``SENSOR``) measures it."""
    gen = torch.Generator().manual_seed(seed)
    depths = [sensor_depth(d[0], image, K, SENSOR, gen)[None]
              for d, image, K in zip(views.depths, views.images, views.cameras.K)]  # fmt: skip
    return Views(views.images, views.cameras, torch.stack(depths))


def _shown(path: Path) -> str:
    """``path`` relative to the repository when inside it (results hold no machine's paths)."""
    repo = Path(__file__).resolve().parents[1]
    path = Path(path).resolve()
    return str(path.relative_to(repo)) if path.is_relative_to(repo) else path.name


def timed(fn, *args, **kwargs):
    """(result, milliseconds)."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, (time.perf_counter() - t0) * 1e3


def score(pred: torch.Tensor, truth: torch.Tensor, seen: torch.Tensor, filled: torch.Tensor) -> dict:
    """Metrics of (3, H, W) ``pred`` against ``truth``; ``seen`` (1, H, W) marks the pixels the
    source cameras saw, ``filled`` (1, H, W) those the forward warp fills."""
    pred = pred.clamp(0, 1)
    return {"psnr": psnr(pred, truth), "ssim": ssim(pred, truth),
            "psnr_visible": psnr(pred, truth, seen), "ssim_visible": ssim(pred, truth, seen),
            "psnr_warp_mask": psnr(pred, truth, filled), "warp_coverage": float(filled.float().mean())}  # fmt: skip


def warm_up(views: Views, model) -> None:
    """Run every timed step once (compiled-code cache, first-call allocations)."""
    cams = views.cameras
    draw(RGBDReconstructor().reconstruct(views), cams[0])
    homography_warp(views.images[0], cams[0], cams[0])
    forward_warp(views.images, views.depths, cams, cams[0])
    if not isinstance(model, str):
        model.reconstruct(Views(views.images, cams))
        GeometryReconstructor(model.model).reconstruct(Views(views.images, cams))


def frame_size_geometry(rec: GeometryReconstructor, images: torch.Tensor, cameras: Cameras) -> Reconstruction:
    """The geometry path's discs as the transform builds them from its cache: depth predicted
    at the model's size, discs at the frames' size (depth at the nearest pixels)."""
    out = rec.predict_depth(Views(images, cameras))
    width, height = images.shape[-1], images.shape[-2]
    return rec.assemble(Views(images, out.cameras.resize(width, height), nearest_pixels(out.depths, width, height)))


#: RGBDConfig settings that draw the discs as plain Gaussians (the ``rgbd_plain`` method)
PLAIN = {"dilation": 0.3, "saturation": 1.0, "view_preference": 0.0}


#: how the transform draws views: holes left over black, or filled (its default)
DRAWN = {False: GenSplatConfig(fill_holes=False), True: GenSplatConfig()}


def draw(rec: Reconstruction, target: Cameras, fill: bool = False) -> RenderOutput:
    """``rec`` rendered into one camera as the transform draws it (:func:`render_scenes`, the
    fast backend: its Gaussians as that camera composites them, with its render options), the
    holes over black or filled, without depth."""
    views = render_scenes(Scenes.of([rec]), target, DRAWN[fill])
    return RenderOutput(rgb=views.rgb[0], alpha=views.alpha[0])


def compare_frame(views: Views, truth: GroundTruth, ep: int, fr: int, model, args, rows: list) -> None:
    """Append one row per (method, level, draw) for one timestep: metrics and times."""
    cams = views.cameras
    rgbd, rgbd_ms = timed(RGBDReconstructor().reconstruct, views)
    plain = RGBDReconstructor(**PLAIN).reconstruct(views)
    sensor = sensor_views(views, seed=1000 * ep + fr)
    rgbd_s, rgbd_s_ms = timed(RGBDReconstructor().reconstruct, sensor)
    rgbd_sd, rgbd_sd_ms = timed(RGBDReconstructor(fill_depth_px=FILL_DEPTH_PX).reconstruct, sensor)
    if not isinstance(model, str):
        mrec, model_ms = timed(model.reconstruct, Views(views.images, cams))  # RGB only
        geometry = {name: timed(frame_size_geometry, GeometryReconstructor(model.model, scale=scale), views.images, cams)
                    for name, scale in (("geometry_small", "fit"), ("geometry_small_metric", "metric"))}  # fmt: skip
    for level, sampler in level_samplers(args).items():
        for d in range(1 if level == "none" else args.draws):
            p = sampler.sample(ep, view=d)
            target = p.move(cams, 0)
            gt = truth.render(ep, fr, target)[0][0]
            out, ms = timed(draw, rgbd, target)
            seen = out.alpha[0] > 0.5
            views_of = {"rgbd": (out.rgb[0], rgbd_ms, ms), "source_image": (views.images[0], 0.0, 0.0)}
            out_p, ms_p = timed(draw, plain, target)
            views_of["rgbd_plain"] = (out_p.rgb[0], rgbd_ms, ms_p)
            filled, fill_ms = timed(draw, rgbd, target, True)
            views_of["rgbd_fill"] = (filled.rgb[0], rgbd_ms, fill_ms)
            warped, ms = timed(homography_warp, views.images[0], cams[0], target)
            views_of["homography"] = (warped, 0.0, ms)
            out_s, ms = timed(draw, rgbd_s, target)
            views_of["rgbd_sensor"] = (out_s.rgb[0], rgbd_s_ms, ms)
            filled_s, ms = timed(draw, rgbd_s, target, True)
            views_of["rgbd_sensor_fill"] = (filled_s.rgb[0], rgbd_s_ms, ms)
            filled_sd, ms = timed(draw, rgbd_sd, target, True)
            views_of["rgbd_sensor_depth_fill"] = (filled_sd.rgb[0], rgbd_sd_ms, ms)
            (fw, warp_mask), ms = timed(forward_warp, views.images, views.depths, cams, target)
            views_of["forward_warp"] = (fw[0], 0.0, ms)
            (fw_s, warp_mask_s), ms = timed(forward_warp, sensor.images, sensor.depths, cams, target)
            views_of["forward_warp_sensor"] = (fw_s[0], 0.0, ms)
            if not isinstance(model, str):
                mtarget = p.move(mrec.cameras, 0)
                out_m, ms = timed(draw, mrec, mtarget)
                views_of["gensplat_small"] = (out_m.rgb[0], model_ms, ms)
                for name, (grec, grec_ms) in geometry.items():  # calibrated cameras: move them as for rgbd
                    gtarget = p.move(grec.cameras, 0)
                    out_g, ms = timed(draw, grec, gtarget)
                    views_of[name] = (out_g.rgb[0], grec_ms, ms)
                    if name == "geometry_small_metric":  # what the transform shows: holes filled
                        filled_g, ms = timed(draw, grec, gtarget, True)
                        views_of[name + "_fill"] = (filled_g.rgb[0], grec_ms, ms)
            coverage = float(seen.float().mean())
            for method, (image, rec_ms, ren_ms) in views_of.items():
                mask = warp_mask_s[0] if "_sensor" in method else warp_mask[0]
                rows.append({"method": method, "level": level, "episode": ep, "frame": fr, **p.as_dict(),
                             **score(image, gt, seen, mask), "coverage": coverage,
                             "reconstruct_ms": rec_ms, "render_ms": ren_ms})  # fmt: skip


def summarise(rows: list) -> dict:
    """{method: {level: mean metrics over the comparisons, median times, coverage, n}}."""
    out: dict = {}
    for r in rows:
        out.setdefault(r["method"], {}).setdefault(r["level"], []).append(r)
    table = {}
    for method in METHODS:
        if method not in out:
            continue
        table[method] = {}
        for level, rs in out[method].items():
            entry = {k: _mean([r[k] for r in rs])
                     for k in ("psnr", "ssim", "psnr_visible", "ssim_visible", "psnr_warp_mask")}  # fmt: skip
            rec, ren = (statistics.median(r[k] for r in rs) for k in ("reconstruct_ms", "render_ms"))
            entry.update(ms=round(rec + ren, 1), reconstruct_ms=round(rec, 1), render_ms=round(ren, 1),
                         coverage=_mean([r["coverage"] for r in rs]),
                         warp_coverage=_mean([r["warp_coverage"] for r in rs]), n=len(rs))  # fmt: skip
            table[method][level] = entry
    return table


def _mean(values: list[float]) -> float | None:
    """Mean rounded to 4 decimals; None when it is +inf (a PSNR of identical images)."""
    m = float(np.mean(values))
    return round(m, 4) if np.isfinite(m) else None


def plot(table: dict, path: Path) -> None:
    """Three panels, PSNR over the whole image, the visible pixels and the pixels the forward
    warp fills, against the level; values above ``PLOT_MAX_DB`` (exact baselines at "none") are
    drawn at the top edge."""
    panels = (("psnr", "PSNR, whole image (dB)"), ("psnr_visible", "PSNR, pixels seen by the sources (dB)"),
              ("psnr_warp_mask", "PSNR, pixels the forward warp fills (dB)"))  # fmt: skip
    colours = {"rgbd": (31, 119, 180), "rgbd_plain": (158, 218, 229), "rgbd_fill": (255, 127, 14), "rgbd_sensor": (23, 190, 207),
               "rgbd_sensor_fill": (31, 60, 110), "rgbd_sensor_depth_fill": (0, 150, 120),
               "forward_warp": (140, 86, 75), "forward_warp_sensor": (227, 119, 194),
               "gensplat_small": (44, 160, 44), "geometry_small": (90, 90, 90),
               "geometry_small_metric": (188, 189, 34), "geometry_small_metric_fill": (107, 110, 207),
               "source_image": (214, 39, 40), "homography": (148, 103, 189)}  # fmt: skip
    values = [e[k] for m in table.values() for e in m.values() for k, _ in panels if e[k] is not None]
    lo, hi = np.floor(min(values) / 5) * 5, min(np.ceil(max(values) / 5) * 5, PLOT_MAX_DB)
    x_ticks = list(enumerate(next(iter(table.values()))))

    def series(key: str) -> dict:
        return {m: [(j, hi if levels[lv][key] is None else levels[lv][key], "") for j, lv in x_ticks]
                for m, levels in table.items()}  # fmt: skip

    y_ticks = [(t, f"{t:.0f}") for t in np.arange(lo, hi + 1e-9, 5)]
    plots = [Panel(title, series(key), (-0.5, len(x_ticks) - 0.5), (lo, hi), x_ticks, y_ticks)
             for key, title in panels]  # fmt: skip
    note = f"Values above {PLOT_MAX_DB:.0f} dB (exact copies of the truth) are drawn at {PLOT_MAX_DB:.0f}."
    line_panels(path, plots, {m: colours[m] for m in table}, note)


def sampling_parser(description: str) -> argparse.ArgumentParser:
    """The options shared with ``nvs_warp_gap.py``: dataset, sampled frames and draws, output."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help="1 episode, 2 frames, 2 draws at 112 px")
    parser.add_argument(
        "--root", type=Path, help="a recorded simulated dataset (default: record held-out episodes)"
    )
    parser.add_argument("--repo-id", default=REPO)
    parser.add_argument("--size", type=int, help="image size when recording (default 224; quick 112)")
    parser.add_argument("--episodes", type=int, help="episodes (default 3; quick 1)")
    parser.add_argument("--frames", type=int, help="frames per episode (default 4; quick 2)")
    parser.add_argument("--draws", type=int, help="perturbations per level and frame (default 4; quick 2)")
    parser.add_argument("--seed", type=int, default=0, help="perturbation seed")
    parser.add_argument("--out", type=Path, help=out_help(""))
    return parser


def with_defaults(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the unset sizes, counts and output folder (full or ``--quick``); torch on one thread."""
    defaults = (112, 1, 2, 2) if args.quick else (224, 3, 4, 4)
    for k, v in zip(("size", "episodes", "frames", "draws"), defaults):
        setattr(args, k, getattr(args, k) or v)
    args.out = args.out or default_out("", args.quick)
    torch.set_num_threads(1)
    return args


def sampled_frames(source: LeRobotSource, episodes: int, frames: int):
    """(episode, frame) pairs: ``frames`` evenly spaced inner frames of each episode."""
    for ep in range(episodes):
        length = source.num_frames(ep)
        for fr in np.linspace(0, length - 1, frames + 2)[1:-1].round().astype(int).tolist():
            yield ep, fr


def main() -> None:
    parser = sampling_parser(__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL_DIR, help="GenSplat weights directory")
    parser.add_argument("--samplers", action="store_true",
                        help="the wider arms' moves (tilt, arc, zoom) instead of the paper's levels")  # fmt: skip
    args = with_defaults(parser.parse_args())

    t0 = time.perf_counter()
    root = args.root or heldout_dataset(args.size, args.episodes)
    source = LeRobotSource(root, args.repo_id, ("left", "right"))
    truth = GroundTruth(root)
    model = load_model(args.model)
    warm_up(source.views(0, 0), model)
    rows: list = []
    for ep, fr in sampled_frames(source, args.episodes, args.frames):
        compare_frame(source.views(ep, fr), truth, ep, fr, model, args, rows)
    table = summarise(rows)
    result = {
        **table,
        "unavailable": {} if not isinstance(model, str) else {m: model for m in METHODS if "_small" in m},
        "settings": {
            "quick": args.quick, "dataset": "recorded held-out" if args.root is None else str(root),
            "heldout_seed": HELDOUT_SEED if args.root is None else None,
            "image_size": [source.cameras.height, source.cameras.width], "episodes": args.episodes,
            "frames_per_episode": args.frames, "draws_per_level": args.draws, "perturbed_camera": "left",
            "levels": "samplers: none, gensplat-tilt, gensplat-arc, fov zoom" if args.samplers else "paper",
            "source_cameras": ["left", "right"], "perturbation_seed": args.seed, "torch_threads": 1,
            "model": None if isinstance(model, str) else _shown(args.model),
            "homography": "plane-induced, table plane z = 0", "visible": "alpha > 0.5 of the rgbd render",
            "forward_warp": "left + right pixels, nearest target pixel, z-buffer",
            "warp_mask": "pixels the forward warp fills (sensor depth for *_sensor methods)",
            "sensor_depth": asdict(SENSOR), "sensor_seed": "1000 * episode + frame",
            "seconds": round(time.perf_counter() - t0, 1),
        },
    }  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / ("nvs_fidelity_samplers.json" if args.samplers else "nvs_fidelity.json")
    path.write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    plot(table, path.with_suffix(".png"))

    print(f"{'method':>19} {'level':>8} {'PSNR':>7} {'SSIM':>6} {'PSNR vis':>8} {'SSIM vis':>8} "
          f"{'PSNR warp':>9} {'ms':>8}")  # fmt: skip
    for method, levels in table.items():
        for level, e in levels.items():
            db = [
                f"{e[k]:.2f}" if e[k] is not None else "exact"
                for k in ("psnr", "psnr_visible", "psnr_warp_mask")
            ]
            print(f"{method:>19} {level:>8} {db[0]:>7} {e['ssim']:6.3f} {db[1]:>8} "
                  f"{e['ssim_visible']:8.3f} {db[2]:>9} {e['ms']:8.1f}")  # fmt: skip
    for method, reason in result["unavailable"].items():
        print(f"{method}: unavailable, {reason}")
    print(f"wrote {path} and {path.with_suffix('.png')} ({result['settings']['seconds']} s)")


if __name__ == "__main__":
    main()
