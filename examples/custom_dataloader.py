"""GenSplat in a plain PyTorch DataLoader (no LeRobot): spawn workers, cached Gaussians.

    .venv/bin/python examples/custom_dataloader.py [--workers N] [--size PX]

Runs from any folder; the cache lives in a temporary folder removed at the end.
"""

import argparse
import tempfile

import torch
from torch.utils.data import DataLoader

from gensplat_transforms import (
    AugmentedDataset,
    GenSplatConfig,
    GenSplatTransform,
    RGBDReconstructor,
    SceneCache,
    build_cache,
)
from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes


def main(argv: list[str] | None = None) -> list[dict]:
    """Iterate one epoch; return its batches."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=2, help="DataLoader spawn workers (default: 2)")
    parser.add_argument("--size", type=int, default=96, help="image side in pixels (default: 96)")
    args = parser.parse_args(argv)
    # Any map-style dataset of dicts works; items need the camera images, episode_index and
    # frame_index. An EpisodeSource gives the calibrated RGB-D views to reconstruct.
    source = SceneEpisodes(num_episodes=2, num_frames=8, size=args.size)
    dataset = SceneDataset(source)
    with tempfile.TemporaryDirectory() as folder:
        cache = SceneCache(folder, RGBDReconstructor(), source.fingerprint)
        build_cache(cache, source, range(source.num_episodes))

        config = GenSplatConfig(cameras=("left", "right"), probability=0.5, level="train", report=True)
        augmented = AugmentedDataset(dataset, GenSplatTransform(config, cache))
        torch.manual_seed(0)  # DataLoader derives each worker's seed from this: reproducible runs
        context = "spawn" if args.workers else None
        loader = DataLoader(augmented, batch_size=4, shuffle=True, num_workers=args.workers,
                            multiprocessing_context=context)  # fmt: skip
        batches = []
        for batch in loader:
            theta = batch["gensplat.theta_deg"][:, 0]
            applied = batch["gensplat.applied"][:, 0]
            print(f"episode {batch['episode_index'].tolist()} frame {batch['frame_index'].tolist()} "
                  f"augmented {applied.tolist()} theta {[round(t, 1) for t in theta.tolist()]}")  # fmt: skip
            batches.append(batch)
    return batches


if __name__ == "__main__":
    main()
