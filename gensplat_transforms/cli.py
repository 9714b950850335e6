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

    args = parser.parse_args(argv)
    if args.command == "demo":
        from .demo import run_demo

        run_demo(args.out, size=args.size, seed=args.seed, backend=args.backend)
    return 0


if __name__ == "__main__":
    sys.exit(main())
