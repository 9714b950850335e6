"""Building a cache with several processes, GPUs and nodes on torch.distributed.

The launcher (``torchrun``, or SLURM's ``srun``) starts the processes and sets their rank
in the environment; :class:`Shard` reads it and deals this process its share of the
episodes. Shards are static and disjoint, and the cache's per-episode locks make a second
run over the same folder skip valid episodes, so every episode is built exactly once with
no coordination during the build. torch.distributed (gloo) is only used at the end, to
collect every process's stats on rank 0 (see :func:`gather`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist

from ..geometry import Reconstruction, Reconstructor, Views

#: How long :func:`gather` waits for the slowest process to finish its shard.
GATHER_TIMEOUT = timedelta(hours=12)


@dataclass(frozen=True)
class Shard:
    """This process's place among ``world`` processes (rank ``rank``; ``local_rank`` on its node)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.rank < self.world or self.local_rank < 0:
            raise ValueError(f"Shard: rank {self.rank} (local {self.local_rank}) of {self.world} processes")

    @classmethod
    def from_env(cls, env: Mapping[str, str] = os.environ) -> Shard:
        """From torchrun (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``), else SLURM (``SLURM_PROCID``,
        ``SLURM_NTASKS``, ``SLURM_LOCALID``), else a single process."""
        for rank, world, local in (("RANK", "WORLD_SIZE", "LOCAL_RANK"),
                                   ("SLURM_PROCID", "SLURM_NTASKS", "SLURM_LOCALID")):  # fmt: skip
            if rank in env and world in env:
                return cls(int(env[rank]), int(env[world]), int(env.get(local, 0)))
        return cls()

    def select(self, episodes: Iterable[int], length: Callable[[int], int]) -> list[int]:
        """This shard's episodes, longest first: all episodes sorted by length (longest first,
        then by index) and dealt round-robin, so shards differ by at most one episode in
        count and by at most the longest episode in timesteps."""
        order = sorted(set(episodes), key=lambda e: (-length(e), e))
        return order[self.rank :: self.world]

    @property
    def device(self) -> torch.device:
        """``cuda:<local rank>`` (modulo the visible GPUs) when CUDA is available, else the CPU."""
        if not torch.cuda.is_available():
            return torch.device("cpu")
        return torch.device("cuda", self.local_rank % torch.cuda.device_count())


def gather(shard: Shard, value: object) -> list | None:
    """Every process's ``value`` on rank 0, in rank order (None on the other ranks).

    Uses torch.distributed (gloo) when there are several processes and the launcher set
    ``MASTER_ADDR`` and ``MASTER_PORT`` (torchrun does); otherwise each process gets
    ``[value]``, its own only."""
    if shard.world == 1 or not {"MASTER_ADDR", "MASTER_PORT"} <= os.environ.keys():
        return [value]
    dist.init_process_group("gloo", rank=shard.rank, world_size=shard.world, timeout=GATHER_TIMEOUT)
    try:
        out = [None] * shard.world if shard.rank == 0 else None
        dist.gather_object(value, out, dst=0)
    finally:
        dist.destroy_process_group()
    return out


class OnDevice(Reconstructor):
    """A model reconstructor (anything with a ``model`` module) run on ``device``, its
    results returned on the CPU, where the cache encodes them. Same name and identity as
    ``inner``: its cache files are the ones a CPU build would check and skip."""

    def __init__(self, inner: Reconstructor, device: torch.device | str) -> None:
        inner.model.to(device)
        self.inner, self.name = inner, inner.name

    def config(self) -> dict:
        return self.inner.config()

    def reconstruct(self, views: Views) -> Reconstruction:
        r = self.inner(views)
        ids = None if r.pixel_ids is None else r.pixel_ids.cpu()
        return Reconstruction(r.gaussians.to("cpu"), r.cameras.to("cpu"), ids)
