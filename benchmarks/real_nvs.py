"""Novel views of a real stereo pair with known cameras and depth: the RGB-D path against a
forward warp of the same depth.

    python benchmarks/real_nvs.py [--quick] [--scales 0.25 0.5] [--out results/real_nvs.json]

scikit-image's Middlebury "motorcycle" pair (741x500, rectified, its true focal length,
principal points and 193 mm baseline; the left view's depth from the ground-truth disparity;
``real_geometry.middlebury``), at each scale (images bicubic, depth at the nearest pixels, the
intrinsics scaled alike). The left view alone is reconstructed and rendered at the right
camera, then compared with the real right image, on the pixels the forward warp of the same
depth fills (``warp``) and on all pixels (``all``), in PSNR and SSIM:

* ``source_image``: the left image unchanged (what an unaugmented policy sees);
* ``forward_warp``: every left pixel with depth moved to the nearest right pixel (a z-buffer),
  nothing elsewhere (:func:`gensplat_transforms.rendering.warp.forward_warp`);
* one row per RGB-D reconstructor setting, each drawn as the transform draws it
  (``render_scenes``) over black (``fill: false``) and with the holes filled (``fill: true``,
  the transform's default), and its time: discs built (``build_ms``) and drawn with the holes
  filled (``render_ms``, the fast CPU renderer, one thread; medians of ``REPEATS``).

No other real RGB-D pair ships in a package on PyPI as far as we found (scikit-image's is the
one), so the pair is this one at several scales. Writes benchmarks/results/real_nvs.json
(outputs/benchmarks_quick/ with ``--quick``, or ``--out``).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from machine import cpu_model, default_out, out_help, write_result
from real_geometry import middlebury

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.metrics import psnr, ssim
from gensplat_transforms.core.scenes import Scenes
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.rendering.scenes import render_scenes
from gensplat_transforms.rendering.warp import forward_warp
from gensplat_transforms.settings import GenSplatConfig

#: reconstructor settings compared (RGBDConfig overrides): the default first, then its disc
#: size, edge shrinking and cover changed one at a time, and wider discs that shrink more at
#: edges (sigma_px 0.4, edge_scale 0.25) together
SETTINGS = {
    "rgbd": {},
    "rgbd_sigma_0.4_edge_scale_0.25": {"sigma_px": 0.4, "edge_scale": 0.25},
    "rgbd_sigma_0.4": {"sigma_px": 0.4},
    "rgbd_sigma_0.25": {"sigma_px": 0.25},
    "rgbd_edge_scale_0.25": {"edge_scale": 0.25},
    "rgbd_edge_scale_1": {"edge_scale": 1.0},
    "rgbd_cover_1": {"cover": 1.0},
    "rgbd_no_soften": {"soften_noise": False},
}
QUICK_SETTINGS = ("rgbd", "rgbd_sigma_0.4_edge_scale_0.25")
#: how the transform draws views: holes left over black, or filled (its default)
DRAWN = {False: GenSplatConfig(fill_holes=False), True: GenSplatConfig()}
REPEATS = 7


def pair(scale: float) -> tuple[torch.Tensor, torch.Tensor, Cameras]:
    """(2, 3, H, W) images in [0, 1], (2, 1, H, W) depth in metres and the two cameras."""
    p = middlebury(scale)
    images = torch.from_numpy(p["images"]).permute(0, 3, 1, 2).float() / 255
    depths = torch.from_numpy(p["depths"])[:, None]
    return images, depths, Cameras(p["K"], p["c2w"], depths.shape[-1], depths.shape[-2])


def scores(view: torch.Tensor, truth: torch.Tensor, warp_mask: torch.Tensor) -> dict:
    """PSNR and SSIM of (3, H, W) ``view`` against ``truth`` on the warp's pixels and on all."""
    return {"psnr_warp": round(psnr(view, truth, warp_mask), 2), "psnr_all": round(psnr(view, truth), 2),
            "ssim_warp": round(ssim(view, truth, warp_mask), 4), "ssim_all": round(ssim(view, truth), 4)}  # fmt: skip


def ms_since(t0: float) -> float:
    return 1000 * (time.perf_counter() - t0)


def compare(scale: float, settings: dict[str, dict]) -> dict:
    """The rows of one scale (module docstring). The settings take turns, one build and draw
    each per round, so that a load on the machine weighs on all of them alike."""
    images, depths, cameras = pair(scale)
    left, target, truth = Views(images[:1], cameras[:1], depths[:1]), cameras[1:], images[1]
    warp, mask = forward_warp(images[:1], depths[:1], cameras[:1], target)
    rows = {"source_image": scores(images[0], truth, mask[0]), "forward_warp": scores(warp[0], truth, mask[0])}
    reconstructors = {name: RGBDReconstructor(**overrides) for name, overrides in settings.items()}
    times: dict = {name: ([], []) for name in settings}
    for _ in range(REPEATS):
        for name, reconstructor in reconstructors.items():
            t0 = time.perf_counter()
            rec = reconstructor.reconstruct(left)
            times[name][0].append(ms_since(t0))
            t0 = time.perf_counter()
            filled = render_scenes(Scenes.of([rec]), target, DRAWN[True])
            times[name][1].append(ms_since(t0))
            black = render_scenes(Scenes.of([rec]), target, DRAWN[False])
            rows[name] = {"fill": {fill: scores(v.rgb[0, 0], truth, mask[0]) for fill, v in ((False, black), (True, filled))},
                          "gaussians": len(rec.gaussians)}  # fmt: skip
    for name, (build, draw) in times.items():
        rows[name].update(build_ms=round(statistics.median(build), 2), render_ms=round(statistics.median(draw), 2))
    return {"size": [images.shape[-1], images.shape[-2]], "warp_coverage": round(float(mask.float().mean()), 4),
            "rows": rows}  # fmt: skip


def table(result: dict) -> str:
    """The results as a markdown table (one line per scale and row)."""
    lines = ["| size | view | fill | PSNR warp px | PSNR all | SSIM warp px | build ms | render ms |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for scale in result["scales"].values():
        size = "x".join(map(str, scale["size"]))
        for name, row in scale["rows"].items():
            for fill, s in (row["fill"].items() if "fill" in row else [("-", row)]):
                timing = (row["build_ms"], row["render_ms"]) if "fill" in row else ("-", "-")
                lines.append(f"| {size} | {name} | {fill} | {s['psnr_warp']:.2f} | {s['psnr_all']:.2f} | "
                             f"{s['ssim_warp']:.4f} | {timing[0]} | {timing[1]} |")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one scale (0.125), two settings (seconds)")
    parser.add_argument("--scales", type=float, nargs="+", default=[0.25, 0.5], help="sizes of the pair (fraction)")
    parser.add_argument("--out", type=Path, help=out_help("real_nvs.json"))
    args = parser.parse_args()
    for s in args.scales:
        if not 0 < s <= 1:
            parser.error(f"--scales: each in (0, 1], got {s}")
    torch.set_num_threads(1)
    scales = [0.125] if args.quick else args.scales
    settings = {k: SETTINGS[k] for k in QUICK_SETTINGS} if args.quick else SETTINGS
    t0 = time.perf_counter()
    result = {"pair": "skimage.data.stereo_motorcycle (Middlebury 2014 motorcycle)", "quick": args.quick,
              "settings": settings, "scales": {str(s): compare(s, settings) for s in scales},
              "machine": cpu_model(), "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    print(table(result))
    write_result(result, args.out or default_out("real_nvs.json", args.quick))


if __name__ == "__main__":
    main()
