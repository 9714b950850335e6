"""Draw docs/images/samplers.png: one draw of each perturbation sampler on a recorded dataset.

    python scripts/sampler_figure.py --root DATASET --repo-id ID [--frame 20] [--out docs/images/samplers.png]

``DATASET``: a copy of a simulated recording with depth (``gensplat record``; the figure's
is ``benchmarks/nvs_fidelity.py``'s held-out pick-and-place recording at 224x224): the
GenSplat settings of each sampler are written into it in turn (the cache is shared, the
settings do not change it). Each row is one draw of ``gensplat preview`` at ``--frame`` of
episode 0: the left camera's image and the left and right cameras' GenSplat views.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from gensplat_lerobot import prepare
from gensplat_lerobot.training_preview import open_dataset, write_lerobot_preview

from gensplat_transforms.core.images import save_grid
from gensplat_transforms.rendering.preview import as_frame
from gensplat_transforms.settings import GenSplatConfig

#: row label -> the settings that differ from GenSplatConfig's defaults
ROWS = {
    "paper (level train)": {},
    "tilt (10 deg, 3 cm)": {"sampler": "tilt"},
    "arc (45 deg)": {"sampler": "arc"},
    "paper, focal 0.8-1.25": {"focal_scale": (0.8, 1.25)},
}
LEFT, RIGHT = "observation.images.left", "observation.images.right"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--repo-id", required=True)
    parser.add_argument("--frame", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path(__file__).parents[1] / "docs" / "images" / "samplers.png")
    args = parser.parse_args()
    dataset, grid = None, []
    for settings in ROWS.values():
        prepare(args.root, args.repo_id, GenSplatConfig(**settings), progress=False)
        with tempfile.TemporaryDirectory() as out:
            shown = write_lerobot_preview(args.root, args.repo_id, out, frames=[args.frame], draws=1)
        dataset = dataset or open_dataset(args.root, args.repo_id)
        original = dataset[shown.indices[0]][LEFT]
        grid.append([as_frame(original), as_frame(shown.items[0][LEFT]), as_frame(shown.items[0][RIGHT])])
    save_grid(grid, args.out, list(ROWS), ["left original", "left GenSplat", "right GenSplat"])
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
