"""Building a cache with several processes: shards, the torchrun path, the model on a device."""

import copy
import itertools
import json
import os
import random
import re
import subprocess
import sys

import pytest
import torch
from safetensors import safe_open
from tiny_model import TINY

from gensplat_transforms.cache.builder import SceneEpisodes, build_cache
from gensplat_transforms.cache.distributed import OnDevice, Shard, gather
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.geometry import GenSplatReconstructor, RGBDReconstructor
from gensplat_transforms.geometry.model import GenSplatModel

REPO = "local/gensplat_scene"


def test_shards_partition_the_episodes_and_balance_them():
    rng = random.Random(0)
    lengths = {e: rng.randint(20, 400) for e in range(103)}
    for world in (1, 2, 3, 8):
        shards = [Shard(r, world).select(lengths, lengths.get) for r in range(world)]
        flat = [e for s in shards for e in s]
        assert sorted(flat) == sorted(lengths)  # every episode exactly once
        counts = [len(s) for s in shards]
        assert max(counts) - min(counts) <= 1
        steps = [sum(lengths[e] for e in s) for s in shards]
        assert max(steps) - min(steps) <= max(lengths.values())
        assert all(lengths[a] >= lengths[b] for s in shards for a, b in itertools.pairwise(s))  # longest first
    # deterministic whatever the input order; a subset is dealt on its own
    assert Shard(1, 3).select(reversed(range(103)), lengths.get) == Shard(1, 3).select(range(103), lengths.get)
    assert set(Shard(0, 2).select([4, 5], lengths.get)) | set(Shard(1, 2).select([4, 5], lengths.get)) == {4, 5}


def test_shard_reads_torchrun_then_slurm_then_defaults_to_one_process():
    torchrun = {"RANK": "3", "WORLD_SIZE": "8", "LOCAL_RANK": "1"}
    slurm = {"SLURM_PROCID": "5", "SLURM_NTASKS": "16", "SLURM_LOCALID": "2"}
    assert Shard.from_env(torchrun) == Shard(3, 8, 1)
    assert Shard.from_env(slurm) == Shard(5, 16, 2)
    assert Shard.from_env({**slurm, **torchrun}) == Shard(3, 8, 1)  # torchrun started under srun
    assert Shard.from_env({}) == Shard(0, 1, 0)
    with pytest.raises(ValueError, match="rank 4"):
        Shard.from_env({"RANK": "4", "WORLD_SIZE": "4"})
    assert Shard().device == (torch.device("cuda", 0) if torch.cuda.is_available() else torch.device("cpu"))


def test_gather_without_a_launcher_returns_its_own_value(monkeypatch):
    monkeypatch.delenv("MASTER_ADDR", raising=False)
    assert gather(Shard(), {"a": 1}) == [{"a": 1}]
    assert gather(Shard(1, 2), "x") == ["x"]  # e.g. srun without MASTER_ADDR: no collective


def test_build_cache_builds_only_its_shard_and_resumes(tmp_path):
    source = SceneEpisodes(num_episodes=3, num_frames=2, size=24)
    cache = SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)
    first = build_cache(cache, source, range(3), progress=False, shard=Shard(0, 2))
    assert set(first) == set(Shard(0, 2).select(range(3), source.num_frames)) and None not in first.values()
    second = build_cache(cache, source, range(3), progress=False, shard=Shard(1, 2))
    assert set(first) | set(second) == {0, 1, 2} and None not in second.values()
    assert build_cache(cache, source, range(3), progress=False) == {0: None, 1: None, 2: None}  # resumed


def test_on_device_keeps_the_identity_and_returns_cpu_results():
    torch.manual_seed(0)
    model = GenSplatModel(TINY)
    views = SceneEpisodes(num_episodes=1, size=28).views(0, 0)
    ref = GenSplatReconstructor(copy.deepcopy(model))(views)  # unwrapped, on a model OnDevice never saw
    inner = GenSplatReconstructor(model)
    rec = OnDevice(inner, "cpu")
    assert rec.identity() == inner.identity() and rec.name == "gensplat"
    out = rec(views)
    assert out.gaussians.means.device.type == "cpu"
    # the same arithmetic on the CPU: equal to the bit
    torch.testing.assert_close(out.gaussians.tensors(), ref.gaussians.tensors(), rtol=0, atol=0)
    torch.testing.assert_close(out.cameras.c2w, ref.cameras.c2w, rtol=0, atol=0)


def test_two_torchrun_processes_build_what_one_process_builds(scene_dataset, dataset_copy, tmp_path):
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
    os.environ["HF_HUB_OFFLINE"] = "1"
    from gensplat_lerobot import prepare

    from gensplat_transforms.transform import GenSplatConfig

    recorded = scene_dataset(REPO, episodes=4, frames=8, size=48)
    one, two = dataset_copy(recorded, "one"), dataset_copy(recorded, "two")
    single = prepare(one, REPO, GenSplatConfig(), progress=False)
    assert set(single) == {0, 1, 2, 3} and None not in single.values()

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "gensplat_cli", "cache", "--root", str(two), "--repo-id", REPO]  # fmt: skip
    run = subprocess.run(cmd, check=False, capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    summary = re.findall(r"^cached .*$", run.stdout, re.MULTILINE)  # rank 0 alone prints, for both processes
    assert len(summary) == 1, run.stdout
    # four builds for four episodes, all valid afterwards: each was built exactly once
    assert "cached 4 episode(s) (0 already valid) on 2 process(es)" in summary[0]
    assert "[built per process: 2, 2]" in summary[0]

    files = sorted(p.relative_to(one) for p in (one / "gensplat").rglob("*") if p.is_file() and p.suffix != ".lock")
    assert files == sorted(p.relative_to(two) for p in (two / "gensplat").rglob("*")
                           if p.is_file() and p.suffix != ".lock")  # fmt: skip
    assert len([f for f in files if f.suffix == ".safetensors"]) == 4
    for f in files:
        if f.name == "digests.json":  # the same digests, of files with other inodes and times
            digests = [{k: v["digest"] for k, v in json.loads((r / f).read_text()).items()} for r in (one, two)]
            assert digests[0] == digests[1] and digests[0]
            continue
        if f.suffix != ".safetensors":
            assert (one / f).read_bytes() == (two / f).read_bytes()  # the settings
            continue
        # the header's key order varies between processes (safetensors keeps it in a hash
        # map), so the bytes may differ; the header fields and every tensor are identical
        a, b = safe_open(one / f, "pt"), safe_open(two / f, "pt")
        names = a.keys()
        assert a.metadata() == b.metadata() and set(names) == set(b.keys())
        for k in names:
            assert torch.equal(a.get_tensor(k), b.get_tensor(k)), (f, k)
    # an overlapping single-process run over the same folder skips every episode
    assert prepare(two, REPO, GenSplatConfig(), progress=False) == dict.fromkeys(range(4))
