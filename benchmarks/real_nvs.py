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
* one row per RGB-D reconstructor setting, each rendered over black (``fill: false``) and
  with the holes filled as the transform does (``fill: true``), and its time: discs built
  (``build_ms``) and rendered (``render_ms``, the fast CPU renderer, one thread; medians of
  ``REPEATS``).

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
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.rendering import render
from gensplat_transforms.rendering.holes import fill_holes
from gensplat_transforms.rendering.warp import forward_warp

#: reconstructor settings compared (RGBDConfig overrides), the default first
SETTINGS = {
    "rgbd": {},
    "rgbd_no_soften": {"soften_noise": False},
    "rgbd_edge_scale_1": {"edge_scale": 1.0},
    "rgbd_edge_scale_1_no_soften": {"edge_scale": 1.0, "soften_noise": False},
    "rgbd_sigma_0.3_edge_scale_1_no_soften": {"sigma_px": 0.3, "edge_scale": 1.0, "soften_noise": False},
}
QUICK_SETTINGS = ("rgbd", "rgbd_edge_scale_1_no_soften")
REPEATS = 3


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


def timed(fn):
    """``fn()`` and the median of its wall times over ``REPEATS`` calls, in ms."""
    times, out = [], None
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        out = fn()
        times.append(1000 * (time.perf_counter() - t0))
    return out, round(statistics.median(times), 2)


def compare(scale: float, settings: dict[str, dict]) -> dict:
    """The rows of one scale (module docstring)."""
    images, depths, cameras = pair(scale)
    left, target, truth = Views(images[:1], cameras[:1], depths[:1]), cameras[1:], images[1]
    warp, mask = forward_warp(images[:1], depths[:1], cameras[:1], target)
    rows = {"source_image": scores(images[0], truth, mask[0]), "forward_warp": scores(warp[0], truth, mask[0])}
    for name, overrides in settings.items():
        reconstructor = RGBDReconstructor(**overrides)
        rec, build_ms = timed(lambda r=reconstructor: r.reconstruct(left))
        out, render_ms = timed(lambda r=rec: render(r.gaussians, target, backend="fast", **r.render_options))
        filled = fill_holes(out.rgb, out.alpha)[0]
        timing = {"build_ms": build_ms, "render_ms": render_ms, "gaussians": len(rec.gaussians)}
        rows[name] = {"fill": {False: scores(out.rgb[0], truth, mask[0]), True: scores(filled, truth, mask[0])},
                      **timing}  # fmt: skip
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
