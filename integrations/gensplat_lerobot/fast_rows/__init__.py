"""Decode only the columns a LeRobot 0.6.1 frame query reads (a training-speed fix, opt-in).

LeRobot 0.6.1's ``DatasetReader._query_hf_dataset`` reads the frames of a delta-timestamp
query (Diffusion Policy's 16 actions per item) through the dataset's torch transform, which
decodes whole rows: every image of every queried frame, to keep one non-image column. With
three PNG cameras and a 16-step action horizon that is 51 image decodes per item where 3 are
used, 70 % of a training step on a 2-core CPU (benchmarks/README.md, "Policy robustness").
Importing this module replaces that method with one that reads each queried column alone;
the items are unchanged (``tests/integrations/lerobot/test_fast_rows.py``). LeRobot fixed this after 0.6.1, so the
replacement applies to 0.6.1 only and leaves any other version as it is.

Turn it on in ``lerobot-train`` with ``--fast_rows.discover_packages_path=gensplat_lerobot.fast_rows``
(DataLoader workers must inherit it: ``--num_workers=0``, or
``--dataloader_multiprocessing_context=fork``), or call :func:`install` in your own script.
"""

from __future__ import annotations

import logging

import lerobot
import torch
from lerobot.datasets.dataset_reader import DatasetReader

log = logging.getLogger(__name__)

#: The LeRobot version whose frame queries decode whole rows.
FIXED_VERSION = "0.6.1"


def _query_hf_dataset(self, query_indices: dict[str, list[int]]) -> dict:
    """LeRobot's ``DatasetReader._query_hf_dataset``, reading each queried column alone:
    {key: (len(indices), ...) tensor} for every key of ``query_indices`` that is not a video."""
    columns = self.__dict__.setdefault("_gensplat_columns", {})
    result = {}
    for key, q_idx in query_indices.items():
        if key in self._meta.video_keys:
            continue
        rows = q_idx if self._absolute_to_relative_idx is None else [self._absolute_to_relative_idx[i] for i in q_idx]
        source, column = columns.get(key, (None, None))
        if source is not self.hf_dataset:  # built once per loaded dataset; the transform is kept
            source, column = self.hf_dataset, self.hf_dataset.select_columns([key])
            columns[key] = (source, column)
        result[key] = torch.stack(column[rows][key])
    return result


#: LeRobot's own method, before :func:`install`.
_ORIGINAL = DatasetReader._query_hf_dataset


def install() -> bool:
    """Replace LeRobot 0.6.1's frame query (see the module docstring); True when it was
    replaced now or before, False on another LeRobot version (left as it is)."""
    if lerobot.__version__ != FIXED_VERSION:
        log.info("gensplat_lerobot.fast_rows: LeRobot %s is not %s; its frame queries are left as they are",
                 lerobot.__version__, FIXED_VERSION)  # fmt: skip
        return False
    DatasetReader._query_hf_dataset = _query_hf_dataset
    return True


install()
