"""GenSplat in a plain PyTorch DataLoader (no LeRobot): spawn workers, cached Gaussians.

    python examples/custom_dataloader.py
"""

import tempfile

import torch
from torch.utils.data import DataLoader

from gensplat_transforms import (
    AugmentedDataset,
    GaussianCache,
    GenSplatConfig,
    GenSplatTransform,
    RGBDReconstructor,
    build_cache,
)
from gensplat_transforms.episodes import SceneDataset, SceneEpisodes


def main() -> None:
    # Any map-style dataset of dicts works; items need the camera images, episode_index and
    # frame_index. An EpisodeSource gives the calibrated RGB-D views to reconstruct.
    source = SceneEpisodes(num_episodes=2, num_frames=8, size=96)
    dataset = SceneDataset(source)
    reconstructor = RGBDReconstructor()
    cache = GaussianCache(tempfile.mkdtemp(), reconstructor, source.fingerprint)
    build_cache(cache, source, range(source.num_episodes))

    config = GenSplatConfig(cameras=("left", "right"), probability=0.5, level="train", report=True)
    augmented = AugmentedDataset(dataset, GenSplatTransform(config, cache))
    torch.manual_seed(0)  # DataLoader derives each worker's seed from this: reproducible runs
    loader = DataLoader(augmented, batch_size=4, shuffle=True, num_workers=2, multiprocessing_context="spawn")
    for batch in loader:
        theta = batch["gensplat.theta_deg"][:, 0]
        applied = batch["gensplat.applied"][:, 0]
        print(f"episode {batch['episode_index'].tolist()} frame {batch['frame_index'].tolist()} "
              f"augmented {applied.tolist()} theta {[round(t, 1) for t in theta.tolist()]}")


if __name__ == "__main__":
    main()
