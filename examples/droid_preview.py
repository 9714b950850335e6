"""One real DROID timestep through the geometry path, perturbed at every evaluation level.

The two external 1280x720 ZED views of the DROID sample (with their calibration, no depth)
are resized to 224x126, their depth is predicted by the shipped small model (trained only on
procedural and simulated tabletops at 112x112, never on real images), and the RGB-D surface
discs built from it are rendered from the first camera moved about the pivot of the two cameras at every
level of ``EVAL_LEVELS`` (fixed seed), hole-filled as the training transform does.

Why 224x126 and ``scale="metric"``: the model was trained on 8x8 patches (112x112); at 448x252
(32x18 patches) its depth breaks into patch-sized blocks, at 224x126 (16x9) it still shows the
table's near-to-far gradient (the size is given as ``max_pixels``: by default the model would
run within the 12,544 pixels it was trained at). The model predicts the two cameras about 0.2 m and 30 deg apart
where the calibration says 1.0 m and 81 deg, so ``"fit"`` (depth times the calibrated /
predicted baseline) puts the table 4x too far (median depth ~4.8 m); ``"metric"`` keeps the
predicted ~1.1 m, which matches the rig (the pivot is 0.74 m from the first camera).

Writes ``droid_preview.png``: one row per level with the source image and the rendered view;
the first row also shows both predicted depth maps (yellow near, purple far, 0 = no depth in
black) and the second camera's image. There is no ground truth at the new poses, so there is
no PSNR: the script prints each render's coverage (the fraction of pixels with alpha > 0.5)
and the times.

    .venv/bin/python examples/droid_preview.py [--out DIR]

Runs from any folder; the default output folder is the repository's outputs/droid_preview
(files replaced on a rerun).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.images import save_grid
from gensplat_transforms.geometry.base import Views
from gensplat_transforms.geometry.geometry import GeometryReconstructor
from gensplat_transforms.transform import GenSplatConfig, render_view
from gensplat_transforms.views.perturbation import EVAL_LEVELS, PaperSampler, pivot_point

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "droid_sample"
#: viridis at 0, 1/4, 1/2, 3/4, 1 (purple -> yellow)
VIRIDIS = torch.tensor([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]]) / 255


def load_views(data: Path, width: int, height: int) -> tuple[Views, list[str]]:
    """The sample's images resized to ``width x height`` and its cameras (OpenGL -> OpenCV)."""
    frames = json.loads((data / "transforms.json").read_text())["frames"]
    images, K, c2w = [], [], []
    for f in frames:
        image = Image.open(data / f["file_path"]).convert("RGB").resize((width, height), Image.BICUBIC)
        images.append(torch.from_numpy(np.array(image)).permute(2, 0, 1).float() / 255)
        i = f["intrinsics"]
        K.append([[i["fl_x"], 0.0, i["cx"]], [0.0, i["fl_y"], i["cy"]], [0.0, 0.0, 1.0]])
        c2w.append(f["transform_matrix"])
    size = frames[0]["intrinsics"]["w"], frames[0]["intrinsics"]["h"]
    cameras = Cameras.from_opengl(torch.tensor(K), torch.tensor(c2w), *size).resize(width, height)
    names = [Path(f["file_path"]).stem for f in frames]
    return Views(torch.stack(images).clamp(0, 1), cameras.to(dtype=torch.float32)), names


def colorize(depth: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """(H, W) depth -> (3, H, W) viridis of inverse depth, yellow at ``near``, purple at ``far``;
    pixels without depth (0) are black."""
    t = ((1 / depth.clamp_min(1e-6) - 1 / far) / (1 / near - 1 / far)).clamp(0, 1) * (len(VIRIDIS) - 1)
    lo = t.floor().long().clamp(max=len(VIRIDIS) - 2)
    rgb = torch.lerp(VIRIDIS[lo], VIRIDIS[lo + 1], (t - lo)[..., None])
    return torch.where(depth[..., None] > 0, rgb, torch.zeros(3)).permute(2, 0, 1)


def main(argv: list[str] | None = None) -> dict:
    """Run the preview; return what ``droid_preview.json`` holds plus ``renders``, the
    (levels, 3, H, W) rendered views."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the droid_sample folder")
    parser.add_argument("--out", type=Path, default=REPO / "outputs" / "droid_preview", help="output folder")
    parser.add_argument("--width", type=int, default=224, help="size the model and renders run at")
    parser.add_argument("--height", type=int, default=126)
    parser.add_argument(
        "--scale",
        default="metric",
        choices=["metric", "fit"],
        help="depth as predicted, or scaled by the calibrated / predicted camera baseline",
    )
    parser.add_argument("--seed", type=int, default=0, help="perturbation seed")
    parser.add_argument("--tile-width", type=int, default=224, help="width of each picture in the figure")
    args = parser.parse_args(argv)

    views, names = load_views(args.data, args.width, args.height)
    t0 = time.perf_counter()
    reconstructor = GeometryReconstructor(scale=args.scale, max_pixels=args.width * args.height)  # this size
    with_depth = reconstructor.predict_depth(views)
    t_depth = time.perf_counter() - t0
    t0 = time.perf_counter()
    rec = reconstructor.assemble(with_depth)
    t_discs = time.perf_counter() - t0
    depths = with_depth.depths[:, 0]
    valid = depths[depths > 0]
    near, far = (float(q) for q in torch.quantile(valid, torch.tensor([0.02, 0.98])))
    h, w = depths.shape[-2:]
    print(f"{args.scale} depth at {w}x{h}: {t_depth:.1f} s model, {t_discs:.2f} s discs, "
          f"{rec.gaussians.means.shape[0]} Gaussians, depth 2-98 % {near:.2f}-{far:.2f} m, median "
          f"{float(valid.median()):.2f} m")  # fmt: skip
    pivot = pivot_point(rec.cameras.c2w[0], rec.cameras.c2w[1])
    print(f"pivot {[round(x, 3) for x in pivot.tolist()]}; camera {names[0]} is "
          f"{float((rec.cameras.c2w[0, :3, 3] - pivot).norm()):.2f} m from it")  # fmt: skip
    print("no ground truth at the new poses: coverage (alpha > 0.5), no PSNR")

    cfg = GenSplatConfig()
    render_view(rec, rec.cameras[0], cfg)  # warm-up: loads the compiled renderer
    tile = (round(args.tile_width * h / w), args.tile_width)

    def to_tile(image: torch.Tensor) -> torch.Tensor:
        return F.interpolate(image[None], size=tile, mode="bilinear", antialias=True, align_corners=False)[0]

    source = to_tile(with_depth.images[0])
    rows, labels, levels, renders = [], [], {}, []
    for level in EVAL_LEVELS:
        p = PaperSampler(level, seed=args.seed).sample(0)
        t0 = time.perf_counter()
        out = render_view(rec, p.move(rec.cameras, 0), cfg)
        ms = (time.perf_counter() - t0) * 1e3
        coverage = float((out.alpha > 0.5).float().mean())
        renders.append(out.rgb[0])
        levels[level] = {**p.as_dict(), "coverage": round(coverage, 4), "render_ms": round(ms, 1)}
        print(f"{level:>8}: rotate {p.theta_deg:+6.1f} deg about world {p.axis}, forward {p.mu_m * 100:4.1f} cm"
              f" -> coverage {coverage:.1%}, render {ms:.0f} ms")  # fmt: skip
        rows.append([source, to_tile(out.rgb[0])])
        labels.append(
            f"{level}\n{p.theta_deg:+.1f} deg {p.axis}\n{p.mu_m * 100:.1f} cm\ncover {coverage:.0%}"
        )
    rows[0] += [to_tile(colorize(d, near, far)) for d in depths] + [to_tile(with_depth.images[1])]
    columns = [f"source {names[0]}", "render at new pose", f"{args.scale} depth {names[0]}",
               f"depth {names[1]}: {near:.1f}-{far:.1f} m", f"second view {names[1]}"]  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "droid_preview.png"
    save_grid(rows, path, labels, columns)
    summary = {"size": [w, h], "scale": args.scale, "seed": args.seed, "depth_s": round(t_depth, 2),
               "discs_s": round(t_discs, 3), "depth_range_m": [round(near, 3), round(far, 3)],
               "levels": levels, "figure": str(path)}  # fmt: skip
    (args.out / "droid_preview.json").write_text(json.dumps(summary, indent=2))
    print(f"wrote {path}")
    return {**summary, "renders": torch.stack(renders)}


if __name__ == "__main__":
    main()
