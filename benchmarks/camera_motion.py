"""How far each camera move shifts the workspace in the image: the evaluation levels of the
robustness protocols against what the policies are trained on.

Usage: python benchmarks/camera_motion.py [--quick] [--episodes N] [--size S] [--out PATH]

On the simulated left camera at S x S (default 96, the robustness study's), workspace points
(a 9 x 9 grid over the table workspace ``WORKSPACE_LOW .. WORKSPACE_HIGH`` at heights 0, 10
and 20 cm) are projected with the nominal camera and with each moved one. Rows:

* ``paper/<level>``, ``vista/<level>`` and ``fov/zoom``: the moves of evaluation episodes 0..N-1, exactly
  those ``PerturbedCameraEnv`` (seed 0) gives the robustness study's policies;
* ``train/gensplat``: GenSplat's training moves (level ``train``, seed 0, episodes 0..N-1,
  views 0-2), about the pivot of the external cameras, as the transform draws them;
  ``train/gensplat-wide``, ``train/gensplat-fov``, ``train/gensplat-tilt`` and the other
  ``train/gensplat-<arm>`` rows: those of the wider arms (``SAMPLER_ARMS``; the arms that
  draw one of them more often have its row);
* ``train/perspective``: the perspective arm's warps, torchvision's
  ``RandomPerspective(distortion_scale)`` corner draws (seeded) applied to the image points.

Per move: the median displacement of the points in the image (% of the width), the share
of the points that leave the image, and the viewpoint change: the angle at the workspace's
centre between the nominal and the moved camera centres (parallax and occlusion grow with it,
which image motion alone does not show). The table gives the median and 95th percentile
over the moves; ``benchmarks/results/camera_motion.json`` (or ``--out``) holds them. Image
motion is what a policy's encoder meets; neither figure says how hard a move is for the task.
``--quick`` is a smoke run (2 moves per level at 32x32, written to
outputs/benchmarks_quick/camera_motion.json).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from torchvision.transforms import RandomPerspective

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gensplat_sim.evaluate import EvalConfig, PerturbedCameraEnv
from gensplat_sim.scene import WORKSPACE_HIGH, WORKSPACE_LOW
from gensplat_sim.world import WorldConfig
from machine import default_out, out_help, write_result
from policy_robustness import MORE_OFTEN, PERSPECTIVE_DISTORTION, PROTOCOLS, SAMPLER_ARMS

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.transform import GenSplatConfig
from gensplat_transforms.views.perturbation import PaperSampler, scale_focal


def workspace_points() -> torch.Tensor:
    """(243, 3) world points: a 9 x 9 grid over the workspace at heights 0, 0.1 and 0.2 m."""
    x = torch.linspace(WORKSPACE_LOW[0], WORKSPACE_HIGH[0], 9, dtype=torch.float64)
    y = torch.linspace(WORKSPACE_LOW[1], WORKSPACE_HIGH[1], 9, dtype=torch.float64)
    z = torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64)
    return torch.cartesian_prod(x, y, z)


#: the workspace's centre at mid-height, where the viewpoint change is measured
CENTRE = torch.tensor([(WORKSPACE_LOW[0] + WORKSPACE_HIGH[0]) / 2, (WORKSPACE_LOW[1] + WORKSPACE_HIGH[1]) / 2, 0.1],
                      dtype=torch.float64)  # fmt: skip


def motion(before: torch.Tensor, after: torch.Tensor, size: int, eyes: tuple | None = None) -> tuple:
    """(median displacement in % of the width, % of the points outside the image, viewpoint
    change in degrees or nan) of (P, 2) pixel positions before and after a move; ``eyes``: the
    (3,) camera centres before and after (None for an image warp)."""
    shift = (after - before).norm(dim=-1)
    outside = ((after < 0) | (after > size)).any(-1)
    angle = float("nan")
    if eyes is not None:
        a, b = (eye - CENTRE for eye in eyes)
        angle = float(torch.rad2deg(torch.arccos((a @ b / (a.norm() * b.norm())).clamp(-1, 1))))
    return 100 * float(shift.median()) / size, 100 * float(outside.double().mean()), angle


def homography(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """(3, 3) homography taking the (4, 2) ``src`` corners to ``dst`` (direct linear solve)."""
    rows, rhs = [], []
    for (x, y), (u, v) in zip(src.tolist(), dst.tolist()):
        rows += [[x, y, 1, 0, 0, 0, -u * x, -u * y], [0, 0, 0, x, y, 1, -v * x, -v * y]]
        rhs += [u, v]
    h = torch.linalg.solve(torch.tensor(rows, dtype=torch.float64), torch.tensor(rhs, dtype=torch.float64))
    return torch.cat([h, h.new_ones(1)]).reshape(3, 3)


def summary(rows: list[tuple]) -> dict:
    """Median and 95th percentile of each figure of :func:`motion` over the moves (None: no
    viewpoint change, an image warp)."""
    out = {"moves": len(rows)}
    for name, values in zip(("shift_pct", "outside_pct", "view_change_deg"), np.array(rows).T):
        finite = not np.isnan(values).any()
        out[f"{name}_median"] = round(float(np.median(values)), 2) if finite else None
        out[f"{name}_p95"] = round(float(np.percentile(values, 95)), 2) if finite else None
    return out


def camera_move(left, c2w: torch.Tensor, points: torch.Tensor, before: torch.Tensor, size: int,
                focal_scale: float = 1.0) -> tuple:  # fmt: skip
    """:func:`motion` of the left camera moved to the (4, 4) ``c2w``, its focal length scaled
    by ``focal_scale``."""
    after = Cameras(scale_focal(left.K, torch.tensor([focal_scale])), c2w[None], left.width, left.height)
    return motion(before, after.project(points)[0][0], size, (left.centers[0], after.centers[0]))


def run(episodes: int, size: int) -> dict:
    world = WorldConfig(height=size, width=size)
    envs = {f"{protocol}/{level}": PerturbedCameraEnv(EvalConfig("reach_solo", level, protocol=protocol, world=world))
            for protocol, levels in PROTOCOLS.items() for level in levels}  # fmt: skip
    first = next(iter(envs.values()))
    left, points = first.world.cameras(("left",)), workspace_points()
    before = left.project(points)[0][0]
    result = {}
    for name, env in envs.items():
        moves = [env.sampler.sample(i) for i in range(episodes)]  # a fov move scales the focal length
        result[name] = summary([camera_move(left, m.apply(env.nominal_c2w["left"], env.centre["left"]), points, before,
                                            size, getattr(m, "focal_scale", 1.0)) for m in moves])  # fmt: skip
        env.close()
    samplers = {"gensplat": PaperSampler("train", seed=0)}
    samplers |= {arm: GenSplatConfig(**settings, seed=0).perturbations() for arm, settings in SAMPLER_ARMS.items()
                 if arm not in MORE_OFTEN}  # those draw another arm's moves  # fmt: skip
    for arm, sampler in samplers.items():
        moves = [sampler.sample(i, view=v) for i in range(episodes) for v in range(3)]
        result[f"train/{arm}"] = summary([camera_move(left, m.apply(left.c2w[0], first.pivot), points, before, size,
                                                      m.focal_scale) for m in moves])  # fmt: skip
    torch.manual_seed(0)
    rows = []
    for _ in range(3 * episodes):
        start, end = RandomPerspective.get_params(size, size, PERSPECTIVE_DISTORTION)
        H = homography(torch.tensor(start, dtype=torch.float64), torch.tensor(end, dtype=torch.float64))
        moved = torch.cat([before, before.new_ones(len(before), 1)], 1) @ H.T
        rows.append(motion(before, moved[:, :2] / moved[:, 2:], size))
    result["train/perspective"] = summary(rows)
    return {"size": size, "episodes": episodes, "points": len(points), "camera": "left", "rows": result}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 moves per level at 32x32")
    parser.add_argument("--episodes", type=int, default=100, help="moves per level (default 100)")
    parser.add_argument("--size", type=int, default=96, help="image side in pixels (default 96)")
    parser.add_argument("--out", type=Path, help=out_help("camera_motion.json"))
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.size = 2, 32
    args.out = args.out or default_out("camera_motion.json", args.quick)
    result = run(args.episodes, args.size)
    print("median (95th percentile) over the moves")
    print(f"{'moves':<22}{'shift % of width':>20}{'points outside %':>20}{'view change deg':>20}")
    for name, r in result["rows"].items():
        cells = [(r[f"{k}_median"], r[f"{k}_p95"]) for k in ("shift_pct", "outside_pct", "view_change_deg")]
        print(f"{name:<22}" + "".join(f"{'-':>20}" if m is None else f"{m:>12.1f} ({p:5.1f})" for m, p in cells))
    write_result(result, args.out)


if __name__ == "__main__":
    main()
