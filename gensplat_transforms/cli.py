"""Command-line entry point: ``gensplat <command>``."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="gensplat", description="GenSplat camera-pose augmentation tools")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="render perturbed views of the built-in RGB-D scene at every level")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: outputs/demo)")
    demo.add_argument("--size", type=int, default=224, help="image size in pixels (default: 224)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--backend", default="reference", help="render backend (default: reference)")

    cache = sub.add_parser("cache", help="write GenSplat settings beside a LeRobot dataset and build its Gaussian cache")
    cache.add_argument("--root", required=True, help="local LeRobot dataset root")
    cache.add_argument("--repo-id", required=True, help="the dataset's repo id")
    cache.add_argument("--cameras", nargs="+", default=None, help="external cameras to reconstruct (default: all)")
    cache.add_argument("--replace", nargs="+", default=None, help="cameras whose image is replaced (default: all)")
    cache.add_argument("--level", default="train", help="perturbation level (default: train)")
    cache.add_argument("--probability", type=float, default=0.5, help="chance a sample is augmented")
    cache.add_argument("--mode", choices=["episode", "frame"], default="episode")
    cache.add_argument("--views-per-source", type=int, default=3)
    cache.add_argument("--seed", type=int, default=0)
    cache.add_argument("--backend", default="reference", help="render backend used in the workers")
    cache.add_argument("--episodes", type=int, nargs="+", default=None, help="only these episodes")

    record = sub.add_parser("record", help="record scripted demonstrations of the simulated tabletop (LeRobot v3)")
    record.add_argument("--out", required=True, help="dataset root to create (must not exist)")
    record.add_argument("--task", default="pick_place", help="pick_place or stack (default: pick_place)")
    record.add_argument("--episodes", type=int, default=10)
    record.add_argument("--seed", type=int, default=0)
    record.add_argument("--size", type=int, default=224, help="image size in pixels (default: 224)")
    record.add_argument("--fps", type=int, default=10)
    record.add_argument("--images", action="store_true", help="store lossless PNG images instead of MP4 video")
    record.add_argument("--shadows", action="store_true", help="render shadows and reflections (slower)")

    args = parser.parse_args(argv)
    if args.command == "record":
        from .sim.record import record_from_cli

        record_from_cli(args)
    elif args.command == "demo":
        from .demo import run_demo

        run_demo(args.out, size=args.size, seed=args.seed, backend=args.backend)
    elif args.command == "cache":
        _cache(args)
    return 0


def _cache(args) -> None:
    try:
        from gensplat_lerobot import LeRobotSource, prepare
    except ImportError as e:
        raise SystemExit(f"gensplat cache needs the LeRobot extra: pip install 'gensplat-transforms[lerobot]' ({e})")
    from .transform import GenSplatConfig

    cameras = tuple(args.cameras or LeRobotSource(args.root, args.repo_id).camera_names)
    config = GenSplatConfig(
        cameras=cameras, replace=args.replace, level=args.level, probability=args.probability, mode=args.mode,
        views_per_source=args.views_per_source, seed=args.seed, backend=args.backend,
    )  # fmt: skip
    stats = prepare(args.root, args.repo_id, config)
    built = {e: s for e, s in stats.items() if s is not None}
    size = sum(s.bytes for s in built.values())
    frames = sum(s.num_frames for s in built.values())
    print(f"cached {len(built)} episode(s) ({len(stats) - len(built)} already valid): {frames} timesteps, "
          f"{size / 1e6:.1f} MB, {size / max(frames, 1) / 1e3:.0f} kB per timestep")


if __name__ == "__main__":
    sys.exit(main())
