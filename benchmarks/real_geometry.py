"""Real images with known cameras: the calibration estimate and a geometry model against them.

    python benchmarks/real_geometry.py [--quick] [--model WEIGHTS_DIR_OR_HUB_ID] [--droid DIR] [--out DIR]

Two real pairs with known cameras:

* ``middlebury``: scikit-image's Middlebury "motorcycle" pair (741x500, rectified: the right
  camera 193 mm to the right, same orientation, f = 994.978 px, principal point 59 px left of
  the image centre), with ground-truth disparity for the left image (depth Z = f B / (d +
  doffs); the right image's depth is the left's moved by its disparity, nearest pixel);
* ``droid``: one DROID timestep (``../shared/data/droid_sample``, two ZED cameras 1280x720,
  81 deg apart, calibrated, no depth; DROID's own extrinsics are known to be off by a few
  degrees in places).

Calibration estimate (``calibration.estimate.estimate_rig``, as ``gensplat calibrate estimate``):
with the Middlebury depth and no focal length (a rectified pair: expected to be refused, as
depth tells only focal length x distance there), with its depth and the focal length given,
with its depth, the focal length and the true principal points given (``--principal-point``:
the images are cropped, their principal points 59 and 28 px off centre), and from the images
alone with the focal length and the cameras' distance given. Errors of
the right camera's pose seen from the left: rotation (deg), centre (mm), the direction of the
centre (deg).

Geometry model (``--model``, default the shipped small model; any checkpoint the geometry path
loads): on both views without calibration, the relative pose it predicts (rotation error,
direction of the centre), its focal length (relative error, where it predicts one), and on the
Middlebury left view its depth against the ground truth (AbsRel after the median ratio, and as
predicted where the model is metric).

Writes ``benchmarks/results/real_geometry.json`` (into ``--out`` when given). ``--quick`` is a smoke
run whose figures mean little: both pairs at half their size, written to
``outputs/benchmarks_quick/real_geometry.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from machine import cpu_model, default_out, out_help, write_result
from PIL import Image

from gensplat_transforms.calibration.estimate import estimate_rig, rotation_angle_deg
from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.geometry import Views
from gensplat_transforms.geometry.geometry import GeometryReconstructor
from gensplat_transforms.weights import DEFAULT_MODEL_DIR

REPO = Path(__file__).resolve().parents[1]
DROID = REPO.parent / "shared" / "data" / "droid_sample"


def middlebury(scale: float = 1.0) -> dict:
    """Images (2, H, W, 3) uint8, depths (2, H, W) metres, K (2, 3, 3), c2w (2, 4, 4); at
    ``scale`` times the size (bicubic images, nearest depth, the intrinsics scaled alike)."""
    from skimage.data import stereo_motorcycle

    left, right, disp = stereo_motorcycle()
    f, cx, cy, doffs, baseline = 994.978, 311.193, 254.877, 31.086, 0.193001
    depth = np.where(np.isfinite(disp) & (disp > 0), f * baseline / (disp + doffs), 0).astype(np.float32)
    moved = np.zeros_like(depth)  # the right view's depth: each left pixel at x - d, the nearest kept
    ys, xs = np.nonzero(depth > 0)
    xr = np.round(xs - disp[ys, xs]).astype(int)
    ok = (xr >= 0) & (xr < depth.shape[1])
    far_first = np.argsort(-depth[ys[ok], xs[ok]])
    moved[ys[ok][far_first], xr[ok][far_first]] = depth[ys[ok], xs[ok]][far_first]
    K = torch.tensor([[[f, 0, cx + 0.5], [0, f, cy + 0.5], [0, 0, 1]],
                      [[f, 0, cx + doffs + 0.5], [0, f, cy + 0.5], [0, 0, 1]]], dtype=torch.float64)  # fmt: skip
    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c2w[1, 0, 3] = baseline
    images, depths = [left, right], [depth, moved]
    if scale != 1.0:
        (h, w), size = depth.shape, (round(depth.shape[1] * scale), round(depth.shape[0] * scale))
        images = [np.array(Image.fromarray(im).resize(size, Image.BICUBIC)) for im in images]
        depths = [np.array(Image.fromarray(d).resize(size, Image.NEAREST)) for d in depths]
        K[:, 0], K[:, 1] = K[:, 0] * size[0] / w, K[:, 1] * size[1] / h
    return {"images": np.stack(images), "depths": np.stack(depths), "K": K, "c2w": c2w}


def droid(width: int = 1280, height: int = 720, folder: Path = DROID) -> dict:
    """The DROID sample (in ``folder``) at ``width x height``: images, K, c2w (OpenCV), no depth."""
    frames = json.loads((folder / "transforms.json").read_text())["frames"]
    images, K, c2w = [], [], []
    for fr in frames:
        image = Image.open(folder / fr["file_path"]).convert("RGB")
        sx, sy = width / image.width, height / image.height
        images.append(np.array(image.resize((width, height), Image.BICUBIC)))
        i = fr["intrinsics"]
        K.append([[i["fl_x"] * sx, 0, i["cx"] * sx], [0, i["fl_y"] * sy, i["cy"] * sy], [0, 0, 1]])
        c2w.append(np.array(fr["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenGL -> OpenCV
    return {"images": np.stack(images), "depths": None, "K": torch.tensor(K, dtype=torch.float64),
            "c2w": torch.tensor(np.stack(c2w), dtype=torch.float64)}  # fmt: skip


def pose_errors(c2w_est: torch.Tensor, c2w_true: torch.Tensor) -> dict:
    """The right camera seen from the left one: rotation error (deg), centre error (mm, where
    the estimate is metric) and the angle between the centres' directions (deg)."""
    rel_e, rel_t = (torch.linalg.inv(c[0]) @ c[1] for c in (c2w_est, c2w_true))
    ce, ct = rel_e[:3, 3], rel_t[:3, 3]
    cos = float(ce @ ct / (ce.norm() * ct.norm()).clamp_min(1e-12))
    return {"rotation_error_deg": float(rotation_angle_deg(rel_e[:3, :3] @ rel_t[:3, :3].T)),
            "center_error_mm": float((ce - ct).norm()) * 1000,
            "direction_error_deg": math.degrees(math.acos(max(-1.0, min(1.0, cos))))}  # fmt: skip


def calibration_rows(name: str, pair: dict) -> dict:
    """The estimate with what the pair offers: depth alone, depth and focal, depth, focal and
    principal points, images, focal and distance."""
    images, depths, K, c2w = pair["images"], pair["depths"], pair["K"], pair["c2w"]
    h, w = images.shape[1:3]
    focals = [float(K[0, 0, 0]), float(K[1, 0, 0])]
    baseline = float((c2w[1, :3, 3] - c2w[0, :3, 3]).norm())
    step = {n: (images[i], None if depths is None else depths[i]) for i, n in enumerate(("left", "right"))}
    rgb = {n: (im, None) for n, (im, _) in step.items()}
    cases = {"rgb_focal_and_distance_given": (rgb, {"focals": focals, "scale": ("baseline", baseline)})}
    if depths is not None:
        points = [tuple(K[i, :2, 2].tolist()) for i in range(2)]
        cases = {"depth": (step, {}), "depth_focal_given": (step, {"focals": focals}),
                 "depth_focal_principal_point_given": (step, {"focals": focals, "principal_points": points}),
                 **cases}  # fmt: skip
    rows = {}
    for case, (sample, given) in cases.items():
        t0 = time.perf_counter()
        try:
            rig = estimate_rig(("left", "right"), [(w, h)] * 2, [sample], [0], **given)
        except ValueError as e:
            rows[case] = {"refused": str(e), "seconds": round(time.perf_counter() - t0, 1)}
            continue
        rows[case] = {**pose_errors(rig.c2w, c2w), "focal_error": [abs(float(rig.K[i, 0, 0]) / focals[i] - 1)
                      for i in range(2)], "matches": rig.matches[1], "rms_px": rig.rms_px[1],
                      "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
        print(f"{name} {case}: rotation {rows[case]['rotation_error_deg']:.2f} deg, centre "
              f"{rows[case]['center_error_mm']:.1f} mm (direction {rows[case]['direction_error_deg']:.2f} deg), "
              f"focal {max(rows[case]['focal_error']):.1%}, {rig.matches[1]} matches")  # fmt: skip
    return rows


def model_rows(name: str, pair: dict, reconstructor: GeometryReconstructor) -> dict:
    """The model's relative pose, focal length and (with ground truth) depth on both views."""
    images = torch.from_numpy(pair["images"]).permute(0, 3, 1, 2).float() / 255
    t0 = time.perf_counter()
    out = reconstructor.predict_depth(Views(images, None))
    seconds = time.perf_counter() - t0
    cams: Cameras = out.cameras
    focal = [float(cams.K[i, 0, 0]) * images.shape[-1] / cams.width / float(pair["K"][i, 0, 0]) - 1 for i in range(2)]
    row = {**pose_errors(cams.c2w.double(), pair["c2w"]), "focal_error": [abs(f) for f in focal],
           "model_size": [cams.width, cams.height], "seconds": round(seconds, 2)}  # fmt: skip
    row.pop("center_error_mm")  # the model's poses are at its own scale
    if pair["depths"] is not None:
        truth = torch.from_numpy(pair["depths"][0])[None, None]
        pred = F.interpolate(out.depths[:1].float(), size=truth.shape[-2:], mode="nearest")
        valid = (truth > 0) & (pred > 0)
        t, p = truth[valid].double(), pred[valid].double()
        row["depth_absrel_median_scaled"] = float(((p * (t / p).median() - t).abs() / t).mean())
        row["depth_absrel_as_predicted"] = float(((p - t).abs() / t).mean())
    print(f"{name} model: rotation {row['rotation_error_deg']:.1f} deg, direction {row['direction_error_deg']:.1f} "
          f"deg, focal {max(row['focal_error']):.0%}" + (f", depth AbsRel {row['depth_absrel_median_scaled']:.3f} "
          "(median-scaled)" if "depth_absrel_median_scaled" in row else ""))  # fmt: skip
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: both pairs at half their size")
    parser.add_argument("--model", default=str(DEFAULT_MODEL_DIR), help="geometry model weights (dir or hub id)")
    parser.add_argument("--droid", type=Path, default=DROID, help=f"the DROID sample (default: {DROID})")
    parser.add_argument("--out", type=Path, help=out_help(""))
    args = parser.parse_args()
    if not (args.droid / "transforms.json").is_file():
        parser.error(f"no DROID sample at {args.droid} (transforms.json and images/: the shared data folder "
                     "beside the repository); --droid names its folder")  # fmt: skip
    torch.set_num_threads(1)
    scale = 0.5 if args.quick else 1.0
    droid_size = [round(1280 * scale), round(720 * scale)]
    reconstructor = GeometryReconstructor(args.model)
    result = {}
    pairs = {"middlebury": lambda: middlebury(scale), "droid": lambda: droid(*droid_size, args.droid)}
    for name, load in pairs.items():
        pair = load()
        result[name] = {"calibration": calibration_rows(name, pair), "model": model_rows(name, pair, reconstructor)}
    model = Path(args.model)
    shown = str(model.relative_to(REPO)) if model.is_absolute() and model.is_relative_to(REPO) else args.model
    result["settings"] = {"quick": args.quick, "model": shown, "droid_size": droid_size, **cpu_model(),
                          "torch_threads": 1}  # fmt: skip
    write_result(result, (args.out or default_out("", args.quick)) / "real_geometry.json")


if __name__ == "__main__":
    main()
