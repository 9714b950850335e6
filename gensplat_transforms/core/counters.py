"""What the transform did, counted across DataLoader workers."""

from __future__ import annotations

import torch
from torch.utils.data import get_worker_info


class SampleCounters:
    """Samples transformed, samples augmented and seconds spent, summed over DataLoader workers.

    The counts live in a shared-memory tensor ``table`` (rows, 3) float64 made before the
    workers start (fork or spawn: torch shares it when the dataset is sent to them). Worker
    ``w`` adds to row ``w % rows``, the main process to row 0, so with ``rows`` >= workers
    no update races another. Give it to a transform as ``transform.counters``.

    Example:
        >>> counters = SampleCounters(rows=2)
        >>> counters.add(applied=True, seconds=0.03)
        >>> counters.add(applied=False, seconds=0.01)
        >>> counters.window()  # samples, augmented, seconds since the last call
        (2, 1, 0.04)
        >>> counters.window()
        (0, 0, 0.0)
    """

    def __init__(self, rows: int = 1) -> None:
        self.table = torch.zeros(max(rows, 1), 3, dtype=torch.float64).share_memory_()
        self._seen = torch.zeros(3, dtype=torch.float64)

    def add(self, applied: bool, seconds: float) -> None:
        """Count one transformed sample."""
        info = get_worker_info()
        row = 0 if info is None else info.id % len(self.table)
        self.table[row] += torch.tensor([1.0, float(applied), seconds], dtype=torch.float64)

    def window(self) -> tuple[int, int, float]:
        """(samples, augmented samples, seconds) added since the previous call, all workers."""
        total = self.table.sum(0)
        samples, applied, seconds = (total - self._seen).tolist()
        self._seen = total
        return int(samples), int(applied), round(seconds, 9)
