"""SampleCounters: what the transform did, counted in DataLoader workers, read in the main process."""

import tempfile

import torch
from torch.utils.data import DataLoader

from gensplat_transforms import (
    AugmentedDataset,
    GenSplatConfig,
    GenSplatTransform,
    RGBDReconstructor,
    SceneCache,
)
from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes
from gensplat_transforms.core.counters import SampleCounters


def test_counts_from_spawned_workers_reach_the_main_process():
    source = SceneEpisodes(num_episodes=1, num_frames=8, size=16)
    with tempfile.TemporaryDirectory() as folder:
        cache = SceneCache(folder, RGBDReconstructor(), source.fingerprint)
        transform = GenSplatTransform(GenSplatConfig(probability=0.5, report=True), cache, source)
        transform.counters = SampleCounters(rows=2)
        loader = DataLoader(AugmentedDataset(SceneDataset(source), transform), batch_size=2, num_workers=2,
                            multiprocessing_context="spawn", generator=torch.Generator().manual_seed(0))  # fmt: skip
        applied = sum(int(b["gensplat.applied"].all(1).sum()) for b in loader)
        samples, augmented, seconds = transform.counters.window()
    assert (samples, augmented) == (8, applied) and 0 < applied < 8
    assert (transform.counters.table[:, 0] > 0).all()  # both workers wrote their own row
    assert seconds > 0 and transform.counters.window() == (0, 0, 0.0)
