"""Original versus GenSplat views along an episode: writes preview.png and preview.mp4.

    .venv/bin/python examples/preview_episode.py [--out DIR] [--level LEVEL] [--frames N] [--size PX]

Runs from any folder; the default output folder is the repository's outputs/preview (files
replaced on a rerun).
"""

import argparse
import tempfile
from pathlib import Path

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.rendering.preview import write_preview
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform

OUT = Path(__file__).resolve().parents[1] / "outputs" / "preview"


def main(argv: list[str] | None = None) -> dict[str, Path]:
    """Write the preview; return the paths written (``png``, and ``mp4`` with PyAV)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=OUT, help=f"output folder (default: {OUT})")
    parser.add_argument("--level", default="large", help="perturbation level (default: large)")
    parser.add_argument("--frames", type=int, default=12, help="frames of the episode (default: 12)")
    parser.add_argument("--size", type=int, default=128, help="image side in pixels (default: 128)")
    args = parser.parse_args(argv)
    source = SceneEpisodes(num_episodes=1, num_frames=args.frames, size=args.size)
    with tempfile.TemporaryDirectory() as folder:
        cache = SceneCache(folder, RGBDReconstructor(), source.fingerprint)
        build_cache(cache, source, [0])
        config = GenSplatConfig(probability=1.0, level=args.level, views_per_source=1)
        dataset = SceneDataset(source)
        items = [dataset[i] for i in range(len(dataset))]
        paths = write_preview(items, GenSplatTransform(config, cache), ["left", "right"], args.out)
    print("wrote", *paths.values())
    return paths


if __name__ == "__main__":
    main()
