"""Original versus GenSplat views along an episode: writes preview.png and preview.mp4.

    python examples/preview_episode.py --out outputs/preview
"""

import argparse
import tempfile

from gensplat_transforms.cache import GaussianCache
from gensplat_transforms.episodes import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.preview import write_preview
from gensplat_transforms.reconstruction import RGBDReconstructor
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="outputs/preview")
    parser.add_argument("--level", default="large")
    args = parser.parse_args()
    source = SceneEpisodes(num_episodes=1, num_frames=12, size=128)
    reconstructor = RGBDReconstructor()
    cache = GaussianCache(tempfile.mkdtemp(), reconstructor, source.fingerprint)
    build_cache(cache, source, [0])
    transform = GenSplatTransform(GenSplatConfig(probability=1.0, level=args.level, views_per_source=1), cache)
    dataset = SceneDataset(source)
    paths = write_preview([dataset[i] for i in range(len(dataset))], transform, ["left", "right"], args.out)
    print("wrote", *paths.values())


if __name__ == "__main__":
    main()
