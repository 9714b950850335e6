"""The cache: depth and Gaussian encodings, staleness, and that nothing wrong ever passes."""

import json
import os
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from gensplat_transforms import render
from gensplat_transforms.cache import depth_codec as dc
from gensplat_transforms.cache import store as cache_module
from gensplat_transforms.cache.builder import SceneEpisodes, build_cache
from gensplat_transforms.cache.store import (
    CorruptCacheError,
    SceneCache,
    StaleCacheError,
    dequantize,
    quantize,
)
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.geometry import Reconstruction, Reconstructor, RGBDReconstructor


@pytest.fixture(scope="module")
def source():
    return SceneEpisodes(num_episodes=2, num_frames=3, size=48)


class Replay(Reconstructor):
    """A non-depth reconstructor (as the model's Gaussian head): returns prepared frames in order."""

    name = "replay"

    def __init__(self, frames):
        self.frames, self.calls = frames, 0

    def config(self):
        return {"frames": len(self.frames)}

    def reconstruct(self, views):
        self.calls += 1
        return self.frames[(self.calls - 1) % len(self.frames)]


class CountingSource:
    """Wraps a source; counts ``views`` calls and can sleep in them (a slow build)."""

    def __init__(self, source, sleep=0.0):
        self.source, self.sleep, self.calls = source, sleep, 0
        self.camera_names, self.fingerprint = source.camera_names, source.fingerprint

    def num_frames(self, episode):
        return self.source.num_frames(episode)

    def views(self, episode, frame):
        self.calls += 1
        time.sleep(self.sleep)
        return self.source.views(episode, frame)


@pytest.fixture
def built(tmp_path, source):
    cache = SceneCache(tmp_path / "cache", RGBDReconstructor(), source.fingerprint)
    stats = build_cache(cache, source, range(2), progress=False)
    return cache, stats


@pytest.fixture
def built_gaussians(tmp_path, source):
    frames = [RGBDReconstructor()(source.views(0, t)) for t in range(3)]
    cache = SceneCache(tmp_path / "gcache", Replay(frames), source.fingerprint)
    cache.ensure(0, source)
    return cache, frames


def fresh(cache):
    return SceneCache(cache.root, cache.reconstructor, cache.dataset)


# ---------------------------------------------------------------------------- depth codec


def test_depth_codec_error_is_bounded_and_invalid_stays_invalid():
    g = torch.Generator().manual_seed(0)
    d = torch.exp(torch.empty(4, 2, 16, 16).uniform_(-13, 13, generator=g))  # 2 um .. 400 km
    d[0, 0, 0, :5] = torch.tensor([0.0, -1.0, float("nan"), float("inf"), 2e6])  # no depth / out of range
    ref, blobs = dc.encode_episode(d)
    rows = dc.reference_rows(ref, (2, 16, 16))
    out = torch.stack([dc.decode_frame(rows, b)[:, 0] for b in blobs])
    ok = (d >= dc.D_MIN) & (d <= dc.D_MAX)
    assert torch.equal(out > 0, ok)
    rel = ((out - d).abs() / d)[ok]
    assert rel.max() <= dc.MAX_RELATIVE_ERROR * 1.001 + 1e-7  # float32 output
    # decoding is exact: codes survive the reference + residual + zlib path unchanged
    assert np.array_equal(dc.quantize_depth(out), dc.quantize_depth(d))


@pytest.mark.parametrize("frames", [1, 4, 7])
def test_depth_codec_reference_is_the_per_pixel_median_rounded_down(frames, monkeypatch):
    monkeypatch.setattr(dc, "_MEDIAN_BLOCK", 100)  # several blocks, the last one partial
    g = torch.Generator().manual_seed(frames)
    d = torch.exp(torch.empty(frames, 2, 9, 17).uniform_(-3, 3, generator=g))
    d[0, 1, 2, :4] = torch.tensor([0.0, float("nan"), -1.0, 3e6])
    ref, blobs = dc.encode_episode(d)
    codes = dc.quantize_depth(d)
    assert np.array_equal(dc.decode_reference(ref, (2, 9, 17)), np.median(codes, axis=0).astype(np.uint16))
    assert dc.encode_episode(list(d)) == (ref, blobs)  # frames one by one: the same bytes
    decoded = [dc.decode_codes(dc.reference_rows(ref, (2, 9, 17)), b) for b in blobs]
    assert np.array_equal(np.stack(decoded), codes)


def test_depth_codec_takes_an_iterator_of_frames_with_their_count():
    d = torch.rand(5, 2, 6, 7) + 0.5
    assert dc.encode_episode(iter(d), 5) == dc.encode_episode(d)
    with pytest.raises(TypeError, match="needs num_frames"):
        dc.encode_episode(iter(d))
    with pytest.raises(ValueError, match="4 frames, 5 announced"):
        dc.encode_episode(iter(d[:4]), 5)
    with pytest.raises(ValueError, match="more than the 4 frames announced"):
        dc.encode_episode(iter(d), 4)
    with pytest.raises(ValueError, match="an episode of 0 frames"):
        dc.encode_episode(d[:0])


def test_a_depth_build_holds_one_frames_views_at_a_time(tmp_path, source):
    """An episode's views are encoded as they come (a 640x480 frame's images are 7 MB of
    float32; an episode of a thousand of them would not fit in memory): when the source
    gives a frame, at most the frame before it is still alive. A source that gives fewer
    frames than the episode has fails the build, writing nothing."""
    import weakref

    class Streaming(CountingSource):
        def __init__(self, source, frames=None):
            super().__init__(source)
            self.alive, self.frames = [], frames

        def episode_views(self, episode):
            refs = []
            for frame in range(self.frames or self.num_frames(episode)):
                self.alive.append(sum(r() is not None for r in refs))
                views = self.views(episode, frame)
                refs.append(weakref.ref(views.images))
                yield views

    streaming = Streaming(source)
    cache = SceneCache(tmp_path / "a", RGBDReconstructor(), source.fingerprint)
    cache.ensure(0, streaming)
    assert streaming.calls == source.num_frames(0) > 2 and max(streaming.alive) <= 1
    plain = SceneCache(tmp_path / "b", RGBDReconstructor(), source.fingerprint)
    plain.ensure(0, source)
    from safetensors.torch import load_file

    streamed, listed = load_file(cache.path(0)), load_file(plain.path(0))
    assert streamed.keys() == listed.keys() and all(torch.equal(streamed[k], listed[k]) for k in listed)
    short = SceneCache(tmp_path / "c", RGBDReconstructor(), source.fingerprint)
    with pytest.raises(ValueError, match=f"{source.num_frames(0) - 1} frames, {source.num_frames(0)} announced"):
        short.ensure(0, Streaming(source, frames=source.num_frames(0) - 1))
    assert short.status(0) == "missing" and not list((tmp_path / "c").glob("*.tmp"))


def test_depth_codec_row_sums_wrap_modulo_2_16():
    """Codes far apart side by side (0 = no depth, 1 and the largest in range): their row
    differences wrap, and so must the sums that undo them (frame and reference differences
    added before one prefix sum)."""
    top = int(dc.quantize_depth(torch.tensor(dc.D_MAX)))
    g = np.random.default_rng(0)
    frames = g.choice(np.array([0, 1, 2, top - 1, top, 40000], np.uint16), size=(3, 2, 5, 300))
    depth = dc.dequantize_depth(frames)  # exactly these codes back from quantize_depth
    ref, blobs = dc.encode_episode(depth)
    rows = dc.reference_rows(ref, frames.shape[1:])
    for want, blob in zip(frames, blobs):
        assert np.array_equal(dc.decode_codes(rows, blob), want)
    assert np.array_equal(dc.reference_rows(ref, frames.shape[1:]), rows)  # decoding left it untouched


def test_depth_words_decode_codes_and_float16_bits_alike():
    """Two bytes a pixel either way: log codes give dequantize's metres, float16 bits their
    float16 value; a batch mixes both by its per-sample flag; other dtypes are refused."""
    d = torch.tensor([[0.0, 1e-3, 0.5], [1.25, 7.0, 6e4]])
    codes = torch.from_numpy(dc.quantize_depth(d).view(np.int16))
    assert torch.equal(dc.depth_from_words(codes, True), dc.dequantize_depth(dc.quantize_depth(d)))
    half = d.half().view(torch.int16)
    assert torch.equal(dc.depth_from_words(half, False), d.half().float())
    mixed = dc.depth_from_words(torch.stack([codes, half]), torch.tensor([True, False])[:, None, None])
    assert torch.equal(mixed, torch.stack([dc.depth_from_words(codes, True), d.half().float()]))
    with pytest.raises(ValueError, match="expected int16 words, got torch.float16"):
        dc.depth_from_words(d.half(), False)


@pytest.mark.parametrize("kind", ["stored", "linked"])
def test_depth_words_are_the_depth_as_stored(kind, built, linked):
    """read_depth_words decodes to read_depth's metres (uncleaned for a linked file) in half
    the bytes, and says how it is coded."""
    cache = built[0] if kind == "stored" else linked[0]
    for t in range(2):
        (words, coded), cameras = cache.read_depth_words(0, t)
        assert words.dtype == torch.int16 and coded == (kind == "stored")
        want = cache._file(0).depth(t, clean=False)[:, 0]
        assert torch.equal(dc.depth_from_words(words, coded), want)
        assert torch.equal(cameras.c2w, cache.read_depth(0, t)[1].c2w)


def test_a_depth_file_of_another_dtype_is_refused(tmp_path):
    from safetensors.torch import save_file

    from gensplat_transforms.data.format import DEPTH_FORMAT, open_depth

    path = tmp_path / "episode_000000.safetensors"
    save_file({"depth": torch.ones(2, 4, 4)}, str(path), metadata={"format": DEPTH_FORMAT})
    with pytest.raises(ValueError, match="depth of dtype float32, expected float16"):
        open_depth(path)


def test_depth_codec_names_what_it_cannot_decode():
    ref, _ = dc.encode_episode(torch.ones(2, 1, 4, 4))
    with pytest.raises(ValueError, match="undecodable depth blob"):
        dc.decode_reference(b"not a zstd frame", (2, 4, 4))
    with pytest.raises(ValueError, match="undecodable depth blob"):
        dc.decode_reference(ref, (2, 4, 4), "zlib")  # a zstd blob read as zlib
    with pytest.raises(ValueError, match="unknown depth compression 'lz4'"):
        dc.decode_reference(ref, (2, 4, 4), "lz4")


def test_a_cache_written_with_zlib_still_reads(tmp_path, source, built, monkeypatch):
    """Episode files from before Zstandard (zlib blobs, no "compression" in the header) give
    the same depth as new ones; a header naming an unknown compression is corrupt."""
    import zlib

    def zlib_pack(codes):
        return zlib.compress(np.diff(codes, axis=-1, prepend=np.uint16(0)).tobytes(), 6)

    def old_header(frames, num_frames, encode=cache_module.encode_depth):
        tensors, meta = encode(frames, num_frames)
        meta["depth_codec"] = json.dumps({k: v for k, v in json.loads(meta["depth_codec"]).items() if k != "compression"})
        return tensors, meta

    with monkeypatch.context() as m:
        m.setattr(dc, "_pack", zlib_pack)
        m.setattr(cache_module, "encode_depth", old_header)
        old = SceneCache(tmp_path / "old", RGBDReconstructor(), source.fingerprint)
        build_cache(old, source, range(1), progress=False)
    assert "compression" not in old.path(0).read_bytes()[:4096].decode(errors="replace")
    new = built[0]
    assert old.path(0).stat().st_size != new.path(0).stat().st_size
    for t in range(3):
        assert torch.equal(fresh(old).read_depth(0, t)[0], new.read_depth(0, t)[0])
    edit_header(old.path(0), set_meta("depth_codec", json.dumps({"compression": "lz4"})))
    edit_header(old.path(0), _header_is_still_consistent)
    assert fresh(old).status(0) == "corrupt"


def test_a_depth_file_is_read_frame_by_frame_and_checked(tmp_path):
    """Slices read only their frames and equal the stored ones; a file cut short or with a
    damaged header is refused when opened, and one cut short later when read."""
    from gensplat_transforms.data.format import depth_path, open_depth, save_depth

    depth = torch.rand(5, 6, 7) * 3
    path = save_depth(tmp_path, "left", 0, depth)
    f = open_depth(path)
    assert f.get_shape() == (5, 6, 7)
    assert torch.equal(f[1:3], depth[1:3].half()) and f[4:9].shape == (1, 6, 7) and f[9:10].shape == (0, 6, 7)
    data = path.read_bytes()
    path.write_bytes(data[:-10])
    with pytest.raises(ValueError, match="its tensors end at byte 420 of 410 data bytes"):
        open_depth(path)
    path.write_bytes(data)
    f = open_depth(path)
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="changed since it was opened"):
        f[4:5]
    path.write_bytes(b"\xff" * 8 + data[8:])
    with pytest.raises(ValueError, match="unreadable depth file"):
        open_depth(depth_path(tmp_path, "left", 0))


def test_a_linked_depth_file_cut_short_while_open_is_stale(linked):
    cache = linked[0]
    cache.read_depth(0, 0)  # the episode is open
    path = cache._file(0).links[0][0]
    data = path.read_bytes()
    path.write_bytes(data[:200])
    with pytest.raises(StaleCacheError, match=r"changed since it was linked \(\d+ -> 200 bytes\)"):
        cache.read_depth(0, 2)
    path.unlink()
    with pytest.raises(StaleCacheError, match="depth file it links changed"):
        cache.read_depth(0, 2)


def test_a_linked_depth_file_copied_again_while_open_reads_on(linked):
    """A sidecar rewritten with the same size and shape (copied again: a new inode and
    modification time) is opened again and read, not reported as a changed dataset."""
    cache = linked[0]
    want = cache.read_depth(0, 2)[0]
    path = cache._file(0).links[0][0]
    data = path.read_bytes()
    path.unlink()
    path.write_bytes(data)
    assert torch.equal(cache.read_depth(0, 2)[0], want)


def _held(cache) -> tuple[int, int]:
    """(file descriptors, memory maps) this process holds on the cache's folder."""
    fds = sum(str(cache.root) in os.path.realpath(f"/proc/self/fd/{fd}") for fd in os.listdir("/proc/self/fd"))
    with open("/proc/self/maps") as f:
        maps = sum(str(cache.root) in line for line in f)
    return fds, maps


def test_kept_episodes_stay_within_the_memory_budget(linked, built):
    """Parsed episodes are kept least recently read first out, within keep_bytes (their
    cameras, headers and decoded depth references), never dropping the one being read; a
    linked episode takes a few kB, so many stay parsed where stored ones do not. Kept files
    hold no file descriptor and no memory map, and a kept linked episode still verifies."""
    stored = fresh(built[0])
    for e in (0, 1):
        stored.read_depth(e, 1)
    sizes = {e: f.nbytes for e, f in stored._kept.items()}
    assert all(n > 2 * 48 * 48 * 2 for n in sizes.values())  # the decoded reference counts
    assert stored._kept_bytes == sum(sizes.values())
    one = max(sizes.values()) + 1  # room for one stored episode
    stored = SceneCache(stored.root, stored.reconstructor, stored.dataset, keep_bytes=one)
    for e in (0, 1, 0):
        stored.read_depth(e, 2)
    assert list(stored._kept) == [0] and stored._kept_bytes == stored._kept[0].nbytes
    stored = SceneCache(stored.root, stored.reconstructor, stored.dataset, keep_bytes=1)  # room for none:
    stored.read_depth(1, 0)  # the file being read stays
    assert list(stored._kept) == [1]
    cache = linked[0]
    linked_cache = SceneCache(cache.root, cache.reconstructor, cache.dataset, keep_bytes=one)
    for e in (0, 1, 0):
        linked_cache.read_depth(e, 1)
    assert list(linked_cache._kept) == [1, 0] and linked_cache._kept_bytes < 4000
    assert _held(stored) == (0, 0) and _held(linked_cache) == (0, 0)
    assert linked_cache.verify(0) and linked_cache.verify(1)


def test_a_kept_episode_rebuilt_by_another_process_is_read_again(built, source):
    """A file replaced since this process parsed it (another process rebuilt it, e.g. for
    another image content) is parsed again and its new data returned, not reported corrupt;
    one removed since is "not cached"."""
    cache, _ = built
    reader = fresh(cache)
    before = reader.read_depth(0, 1)[0]
    other = SceneEpisodes(num_episodes=2, num_frames=3, size=48, seed=5)
    other.fingerprint = source.fingerprint  # same dataset label, other depth
    writer = fresh(cache)
    with writer.lock(0):
        writer._build(0, other)
    after = reader.read_depth(0, 1)[0]
    want = fresh(cache).read_depth(0, 1)[0]
    assert torch.equal(after, want) and not torch.equal(after, before)
    assert reader.verify(0)
    cache.path(0).unlink()
    with pytest.raises(FileNotFoundError, match="not cached"):
        reader.read_depth(0, 2)


def test_depth_codec_rejects_a_blob_of_the_wrong_size():
    ref, _ = dc.encode_episode(torch.ones(2, 1, 4, 4))
    with pytest.raises(ValueError, match="expected 32"):
        dc.decode_reference(ref, (2, 4, 4))


# ---------------------------------------------------------------------------- depth cache


def test_depth_cache_round_trip_is_small_and_faithful(built, source):
    cache, stats = built
    assert cache.kind == "depth"
    rec = RGBDReconstructor()
    for ep in range(2):
        assert stats[ep].num_frames == 3
        # 2 views of 48x48: the quantised Gaussians took 23 B per pixel; depth codes a small fraction
        assert stats[ep].bytes_per_timestep < 0.15 * 2 * 48 * 48 * 23
        for t in range(3):
            views = source.views(ep, t)
            direct, cached = rec(views), cache.read(ep, t, views.images)
            assert torch.equal(cached.pixel_ids, direct.pixel_ids)
            torch.testing.assert_close(cached.cameras.c2w, direct.cameras.c2w.double())
            a = render(direct.gaussians, direct.cameras[:1]).rgb
            b = render(cached.gaussians, cached.cameras[:1]).rgb
            assert psnr(b, a) > 45.0


def test_depth_cache_needs_images_of_the_right_shape(built, source):
    cache, _ = built
    with pytest.raises(ValueError, match="needs the views' images"):
        cache.read(0, 0)
    with pytest.raises(ValueError, match="images of shape"):
        cache.read(0, 0, torch.rand(1, 3, 48, 48))


def test_resumable_build_skips_valid_episodes(built, source):
    cache, _ = built
    mtime = cache.path(0).stat().st_mtime_ns
    cache.path(1).unlink()
    stats = build_cache(cache, source, range(2), progress=False)
    assert stats[0] is None and stats[1] is not None
    assert cache.path(0).stat().st_mtime_ns == mtime


def test_stale_cache_is_detected(built):
    cache, _ = built
    other_rec = SceneCache(cache.root, RGBDReconstructor(max_depth=5.0), cache.dataset)
    other_data = SceneCache(cache.root, cache.reconstructor, "another-dataset")
    for c in (other_rec, other_data):
        assert c.status(0) == "stale"
        with pytest.raises(StaleCacheError):
            c.read(0, 0, torch.zeros(2, 3, 48, 48))


def counting_status(cache, monkeypatch) -> list[int]:
    """Episodes whose header ``cache.status`` reads, in order."""
    opened, status = [], cache.status
    monkeypatch.setattr(cache, "status", lambda e: opened.append(e) or status(e))
    return opened


def test_statuses_open_only_files_not_checked_before(built, source, monkeypatch):
    cache, _ = built
    first = fresh(cache)
    opened = counting_status(first, monkeypatch)
    assert first.statuses([0, 1, 2]) == {0: "ok", 1: "ok", 2: "missing"} and opened == [0, 1, 2]
    again = fresh(cache)
    opened = counting_status(again, monkeypatch)
    assert again.statuses(range(3)) == {0: "ok", 1: "ok", 2: "missing"} and opened == [2]  # from the index
    cache.path(1).write_bytes(cache.path(1).read_bytes()[:-7])  # cut short: new size and time
    cache.ensure(2, source)
    later = fresh(cache)
    opened = counting_status(later, monkeypatch)
    assert later.statuses(range(3)) == {0: "ok", 1: "corrupt", 2: "ok"} and opened == [1, 2]
    files = json.loads((cache.root / cache_module.INDEX_NAME).read_text())["files"]
    assert sorted(files) == [cache.path(0).name, cache.path(2).name]  # the corrupt file left out
    cache.ensure(1, source)  # rebuilt: a new file, checked again
    last = fresh(cache)
    opened = counting_status(last, monkeypatch)
    assert last.statuses(range(3)) == {0: "ok", 1: "ok", 2: "ok"} and opened == [1]


def test_an_index_for_other_settings_or_unreadable_is_not_used(built, monkeypatch):
    cache, _ = built
    cache.statuses(range(2))
    index = cache.root / cache_module.INDEX_NAME
    others = [SceneCache(cache.root, RGBDReconstructor(max_depth=5.0), cache.dataset),
              SceneCache(cache.root, cache.reconstructor, "another-dataset")]  # fmt: skip
    for other in others:
        opened = counting_status(other, monkeypatch)
        assert other.statuses(range(2)) == {0: "stale", 1: "stale"} and opened == [0, 1]
    cache.statuses(range(2))  # lists them again for this cache
    valid = index.read_text()
    for text in ("{not json", "[]", '{"for": 1, "files": {}}', valid.replace('"files":{', '"files":{"x":1,'),
                 valid.replace(cache.dataset, "another-dataset")):  # fmt: skip
        index.write_text(text)
        checker = fresh(cache)
        opened = counting_status(checker, monkeypatch)
        assert checker.statuses(range(2)) == {0: "ok", 1: "ok"}
        assert opened == ([] if text.startswith(valid[:20]) and "another-dataset" not in text else [0, 1]), text
        assert {cache.path(0).name, cache.path(1).name} <= json.loads(index.read_text())["files"].keys()


def test_an_index_that_cannot_be_written_only_costs_the_speed_up(built, monkeypatch):
    cache, _ = built
    (cache.root / cache_module.INDEX_NAME).mkdir()  # in the way of the index file
    for _ in range(2):
        checker = fresh(cache)
        opened = counting_status(checker, monkeypatch)
        assert checker.statuses(range(2)) == {0: "ok", 1: "ok"} and opened == [0, 1]


def test_a_source_of_another_dataset_is_refused(tmp_path, source):
    cache = SceneCache(tmp_path, RGBDReconstructor(), "not-this-dataset")
    with pytest.raises(StaleCacheError, match="fingerprint"):
        cache.ensure(0, source)


def test_the_compiled_and_reference_rgbd_share_a_cache(built):
    cache, _ = built
    assert fresh(cache).status(0) == "ok"
    assert SceneCache(cache.root, RGBDReconstructor(fast=False), cache.dataset).status(0) == "ok"


# ---------------------------------------------------------------------------- gaussians cache


def test_gaussian_cache_round_trip(built_gaussians):
    cache, frames = built_gaussians
    assert cache.kind == "gaussians"
    for t, f in enumerate(frames):
        got = cache.read(0, t)
        a = render(f.gaussians, f.cameras[:1]).rgb
        assert psnr(render(got.gaussians, got.cameras[:1]).rgb, a) > 45.0


def test_quantisation_costs_far_less_than_a_tenth_of_a_db(source):
    rec = RGBDReconstructor()(source.views(0, 1))
    g = rec.gaussians
    lo, hi = g.means.amin(0), g.means.amax(0)
    gq = dequantize(quantize(g, lo, hi), lo, hi)
    assert (gq.means - g.means).abs().max() <= (hi - lo).max() / 65535
    assert psnr(render(gq, rec.cameras).rgb, render(g, rec.cameras).rgb) > 45.0


def _frame(gaussians, cameras, ids):
    return Reconstruction(gaussians, cameras, torch.tensor(ids, dtype=torch.int64))


def test_two_gaussians_at_one_pixel_are_never_static(tmp_path, source):
    """Frame 0 holds A and B at pixel 0, frame 1 holds C and B: each frame reads back as written."""
    full = RGBDReconstructor()(source.views(0, 0))
    cams, g = full.cameras, full.gaussians
    a, b, c = (g[i : i + 1] for i in (0, 100, 200))
    frames = [_frame(Gaussians.cat([a, b]), cams, [0, 0]), _frame(Gaussians.cat([c, b]), cams, [0, 0])]
    two = SceneEpisodes(num_episodes=1, num_frames=2, size=48)
    cache = SceneCache(tmp_path, Replay(frames), two.fingerprint)
    cache.ensure(0, two)
    for t, f in enumerate(frames):
        torch.testing.assert_close(cache.read(0, t).gaussians.means, f.gaussians.means, atol=1e-3, rtol=0)


def test_an_empty_frame_is_stored_and_read_back(tmp_path, source):
    full = RGBDReconstructor()(source.views(0, 0))
    cache = SceneCache(tmp_path, Replay([full, _frame(Gaussians.empty(), full.cameras, []), full]), source.fingerprint)
    cache.ensure(0, source)
    assert len(cache.read(0, 1).gaussians) == 0
    assert len(cache.read(0, 2).gaussians) == len(full.gaussians)
    out = render(cache.read(0, 1).gaussians, full.cameras[:1])
    assert torch.isfinite(out.rgb).all() and out.alpha.max() == 0


# ---------------------------------------------------------------------------- corruption


def read_header(path):
    data = path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8 : 8 + n]), data[8 + n :]


def write_header(path, header, body):
    raw = json.dumps(header).encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + body)


def edit_header(path, fn):
    header, body = read_header(path)
    fn(header)
    write_header(path, header, body)


def set_meta(key, value):
    def fn(h):
        if value is None:
            h["__metadata__"].pop(key)
        else:
            h["__metadata__"][key] = value

    return fn


def relabel(dtype, prefix=""):
    """Relabel the first tensor (whose name starts with ``prefix``) with another dtype of the same size."""

    def fn(h):
        name = next(k for k in sorted(h) if k != "__metadata__" and k.startswith(prefix))
        h[name]["dtype"] = dtype

    return fn


def shift_bbox(h):
    lo, hi = json.loads(h["__metadata__"]["bbox"])
    h["__metadata__"]["bbox"] = json.dumps([[x + 0.3 for x in lo], [x + 0.3 for x in hi]])


HEADER_EDITS = {
    "image_size changed": set_meta("image_size", "[40, 40]"),
    "num_frames lowered": set_meta("num_frames", "2"),
    "num_frames missing": set_meta("num_frames", None),
    "num_frames not a number": set_meta("num_frames", "abc"),
    "crc missing": set_meta("crc", None),
    "crc not JSON": set_meta("crc", "{not json"),
    "c2w relabelled I64": relabel("I64", "c2w"),
    "depth blob relabelled I8": relabel("I8", "depth.f1"),
    "header checksum removed": set_meta("header_crc", None),
}
GAUSSIAN_EDITS = {
    "bbox shifted by 0.3 m": shift_bbox,
    "bbox garbage": set_meta("bbox", "garbage"),
    "bbox too short": set_meta("bbox", "[[0, 0], [1, 1]]"),
    "scales relabelled F16 -> BF16": relabel("BF16", "f1.scales"),
    "opacities relabelled U8 -> I8": relabel("I8", "f1.opacities"),
}


def _header_is_still_consistent(header):
    """Recompute the header checksum after an edit, as a forger would: the tensor checksums still catch it."""
    from gensplat_transforms.cache.format import header_crc

    header["__metadata__"]["header_crc"] = header_crc(header["__metadata__"])


@pytest.mark.parametrize("edit", list(HEADER_EDITS))
def test_every_header_edit_of_a_depth_file_is_corrupt(built, edit):
    cache, _ = built
    edit_header(cache.path(0), HEADER_EDITS[edit])
    c = fresh(cache)
    assert c.status(0) == "corrupt"
    assert not c.verify(0)
    with pytest.raises(CorruptCacheError):
        c.read(0, 1, torch.zeros(2, 3, 48, 48))


@pytest.mark.parametrize("edit", list(GAUSSIAN_EDITS))
def test_every_header_edit_of_a_gaussian_file_is_corrupt(built_gaussians, edit):
    cache, _ = built_gaussians
    edit_header(cache.path(0), GAUSSIAN_EDITS[edit])
    c = fresh(cache)
    assert c.status(0) == "corrupt"
    with pytest.raises(CorruptCacheError):
        for t in range(3):
            c.read(0, t)


def test_a_forged_header_checksum_does_not_hide_edited_data(built_gaussians):
    """An edit that also recomputes the header checksum: the tensor checksums still catch it."""
    cache, _ = built_gaussians
    header, body = read_header(cache.path(0))
    start, _ = header["f1.means"]["data_offsets"]
    body = bytearray(body)
    body[start : start + 8] = bytes(8)  # move some means
    write_header(cache.path(0), header, bytes(body))
    c = fresh(cache)
    assert c.status(0) == "ok"  # the header checks out...
    assert not c.verify(0)  # ...the data does not
    with pytest.raises(CorruptCacheError, match="checksum"):
        c.read(0, 1)
    _header_is_still_consistent(header)  # a forged header checksum changes nothing
    write_header(cache.path(0), header, bytes(body))
    assert not fresh(cache).verify(0)


def test_invalid_json_header_is_corrupt_not_a_crash(built):
    cache, _ = built
    data = cache.path(0).read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    cache.path(0).write_bytes(data[:8] + b"{" * n + data[8 + n :])
    assert fresh(cache).status(0) == "corrupt"


def test_truncated_flipped_and_foreign_files_are_detected(built):
    cache, _ = built
    path = cache.path(0)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    assert fresh(cache).status(0) == "corrupt"
    corrupted = bytearray(data)
    for i in range(len(data) - 60, len(data) - 20):
        corrupted[i] ^= 0xFF
    path.write_bytes(bytes(corrupted))
    assert fresh(cache).status(0) == "ok"  # the header is intact, the data is not
    assert not fresh(cache).verify(0)
    path.write_bytes(b"not a safetensors file at all")
    assert fresh(cache).status(0) == "corrupt"


def test_an_old_format_file_is_stale(built):
    cache, _ = built
    edit_header(cache.path(0), set_meta("format_version", "1"))
    assert fresh(cache).status(0) == "stale"


def test_build_rebuilds_every_bad_file_and_keeps_good_ones(built, source):
    """`gensplat cache` reads every checksum: a file failing one is rebuilt, not reported valid."""
    cache, _ = built
    data = bytearray(cache.path(0).read_bytes())
    data[-30] ^= 0xFF
    cache.path(0).write_bytes(bytes(data))
    edit_header(cache.path(1), HEADER_EDITS["num_frames lowered"])
    counting = CountingSource(source)
    stats = build_cache(fresh(cache), counting, range(2), progress=False)
    assert stats[0] is not None and stats[1] is not None and counting.calls == 6
    assert build_cache(fresh(cache), counting, range(2), progress=False) == {0: None, 1: None}
    assert counting.calls == 6


def test_a_resume_that_trusts_headers_reads_no_data_and_reads_still_verify(built, source, monkeypatch):
    """build_cache(verify=False) (`gensplat cache --trust-headers`): a file with a valid header is
    skipped without reading its data; a bad header is still rebuilt; damaged data is caught
    when the frame is read."""
    cache, _ = built
    data = bytearray(cache.path(0).read_bytes())
    data[-30] ^= 0xFF  # inside the last frame's data
    cache.path(0).write_bytes(bytes(data))
    edit_header(cache.path(1), HEADER_EDITS["num_frames lowered"])
    read = []
    tensor = cache_module.EpisodeFile.tensor
    monkeypatch.setattr(cache_module.EpisodeFile, "tensor", lambda f, name: read.append(name) or tensor(f, name))
    counting = CountingSource(source)
    stats = build_cache(fresh(cache), counting, range(2), progress=False, verify=False)
    assert stats[0] is None and stats[1] is not None and counting.calls == 3  # only episode 1 rebuilt
    assert not [name for name in read if name.startswith("depth")]  # no depth data was read
    c = fresh(cache)
    with pytest.raises(CorruptCacheError, match="checksum"):
        for t in range(3):
            c.read_depth(0, t)
    assert build_cache(fresh(cache), counting, range(2), progress=False)[0] is not None  # a full check rebuilds it


def test_a_second_resume_that_trusts_headers_opens_no_file(built, source, monkeypatch):
    cache, _ = built
    assert build_cache(fresh(cache), source, range(2), progress=False, verify=False) == {0: None, 1: None}
    again = fresh(cache)
    opened = counting_status(again, monkeypatch)
    assert build_cache(again, source, range(2), progress=False, verify=False) == {0: None, 1: None}
    assert opened == []  # both found in the index the first resume wrote


def test_missing_episode_and_frame_raise(built):
    cache, _ = built
    with pytest.raises(FileNotFoundError):
        cache.read(7, 0, torch.zeros(2, 3, 48, 48))
    with pytest.raises(IndexError):
        cache.read(0, 3, torch.zeros(2, 3, 48, 48))


def test_a_file_renamed_to_another_episode_is_corrupt(built):
    cache, _ = built
    cache.path(0).replace(cache.path(5))
    assert cache.status(5) == "corrupt"
    with pytest.raises(CorruptCacheError, match="holds episode 0"):
        cache.read(5, 0, torch.zeros(2, 3, 48, 48))


def test_written_files_follow_the_umask(built):
    cache, _ = built
    mask = os.umask(0)
    os.umask(mask)
    assert cache.path(0).stat().st_mode & 0o777 == 0o666 & ~mask


# ---------------------------------------------------------------------------- concurrency


def test_concurrent_builders_build_once(tmp_path, source):
    counting = CountingSource(source)
    cache = SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)
    threads = [threading.Thread(target=lambda: fresh(cache).ensure(0, counting)) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert counting.calls == 3  # one build of 3 frames
    assert cache.status(0) == "ok"
    assert not list(tmp_path.glob("*.tmp"))


def test_concurrent_builds_with_verify_build_once(tmp_path, source):
    """Two `gensplat cache` runs at once: the second re-checks inside the lock and skips."""
    counting = CountingSource(source, sleep=0.05)
    cache = SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)
    threads = [threading.Thread(target=lambda: build_cache(fresh(cache), counting, [0], progress=False))
               for _ in range(2)]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert counting.calls == 3


KILLED_BUILDER = """
import sys, time
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.geometry import RGBDReconstructor
src = SceneEpisodes(num_episodes=2, num_frames=3, size=48)
slow = type("Slow", (), {"camera_names": src.camera_names, "fingerprint": src.fingerprint,
                         "num_frames": src.num_frames, "views": lambda self, e, t: time.sleep(60)})()
SceneCache(sys.argv[1], RGBDReconstructor(), src.fingerprint).ensure(0, slow)
"""


def test_a_killed_builders_temporary_file_is_removed(tmp_path, source):
    proc = subprocess.Popen([sys.executable, "-c", KILLED_BUILDER, str(tmp_path)])
    deadline = time.time() + 60
    while not list(tmp_path.glob("*.tmp")) and time.time() < deadline:
        time.sleep(0.05)
    proc.kill()  # SIGKILL in the middle of the build
    proc.wait()
    assert len(list(tmp_path.glob("*.tmp"))) == 1
    cache = SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)
    cache.ensure(0, source)
    assert cache.status(0) == "ok"
    assert not list(tmp_path.glob("*.tmp"))


def test_deleting_the_lock_file_of_a_running_build_does_not_let_a_second_builder_in(tmp_path, source):
    slow = CountingSource(source, sleep=0.3)
    cache = SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)
    first = threading.Thread(target=lambda: fresh(cache).ensure(0, slow))
    first.start()
    lock = tmp_path / ".episode_000000.lock"
    deadline = time.time() + 10
    while not list(tmp_path.glob("*.tmp")) and time.time() < deadline:  # the first builder is writing
        time.sleep(0.01)
    lock.unlink()
    fresh(cache).ensure(0, slow)  # takes a new lock file, then waits for the first builder's file
    first.join()
    assert slow.calls == 3
    assert cache.status(0) == "ok"


# ---------------------------------------------------------------------------- linked depth


class SidecarSource:
    """A source whose depth lives in depth files (as a recorded dataset's sidecars)."""

    def __init__(self, source, root):
        from gensplat_transforms.data.format import save_depth

        self.source, self.root = source, root
        self.camera_names, self.fingerprint = ("left", "right"), source.fingerprint
        for e in range(source.num_episodes):
            depths = torch.stack([source.views(e, t).depths[:, 0] for t in range(source.num_frames(e))], 1)
            for name, d in zip(self.camera_names, depths):
                save_depth(root, name, e, d)

    def num_frames(self, episode):
        return self.source.num_frames(episode)

    def views(self, episode, frame):
        from gensplat_transforms.data.format import load_depth
        from gensplat_transforms.geometry import Views

        v = self.source.views(episode, frame)
        depths = torch.stack([load_depth(self.root, n, episode, frame) for n in self.camera_names])
        return Views(v.images, v.cameras, depths)

    def depth_files(self, episode):
        from gensplat_transforms.cache.store import DepthFiles
        from gensplat_transforms.data.format import depth_path

        paths = tuple(depth_path(self.root, n, episode) for n in self.camera_names)
        return DepthFiles(paths, self.source.views(episode, 0).cameras)


@pytest.fixture
def linked(tmp_path, source):
    sidecars = SidecarSource(source, tmp_path / "dataset")
    cache = SceneCache(tmp_path / "dataset" / "gensplat" / "cache", RGBDReconstructor(), source.fingerprint)
    return cache, sidecars, build_cache(cache, sidecars, range(2), progress=False)


def test_the_datasets_own_depth_is_linked_not_copied(linked, tmp_path):
    cache, sidecars, stats = linked
    header, _ = read_header(cache.path(0))
    links = json.loads(header["__metadata__"]["depth_links"])
    assert [link["path"] for link in links] == [os.path.join("..", "..", "depth", n, "episode_000000.safetensors")
                                                for n in ("left", "right")]  # fmt: skip
    assert stats[0].bytes < 2000 and not any(k.startswith("depth.") for k in header)  # cameras and header only
    copy = SceneCache(tmp_path / "copy", RGBDReconstructor(), sidecars.fingerprint, link_depth=False)
    copy.ensure(0, sidecars)
    assert copy.path(0).stat().st_size > 4 * stats[0].bytes
    for t in range(3):
        views = sidecars.views(0, t)
        want = RGBDReconstructor()(views)  # the uncompressed reconstruction: linking loses nothing
        got = cache.read(0, t, views.images)
        for name in ("means", "quats", "scales", "sh"):
            assert torch.equal(getattr(got.gaussians, name), getattr(want.gaussians, name))
        assert torch.equal(got.cameras.c2w, want.cameras.c2w.double()) and torch.equal(got.cameras.K, want.cameras.K.double())
        depth, _ = cache.read_depth(0, t)
        assert torch.equal(depth, RGBDReconstructor().clean_depth(views.depths))


def test_a_linked_cache_moves_with_its_dataset(linked, tmp_path):
    cache, sidecars, _ = linked
    want = RGBDReconstructor().clean_depth(sidecars.views(0, 1).depths)
    (tmp_path / "dataset").rename(tmp_path / "moved")
    moved = SceneCache(tmp_path / "moved" / "gensplat" / "cache", cache.reconstructor, cache.dataset)
    assert moved.status(0) == "ok" and moved.verify(0)
    assert torch.equal(moved.read_depth(0, 1)[0], want)


def test_a_changed_or_missing_depth_file_makes_the_episode_stale(linked):
    from gensplat_transforms.data.format import depth_path, save_depth

    cache, sidecars, _ = linked
    left = depth_path(sidecars.root, "left", 0)
    save_depth(sidecars.root, "left", 0, torch.ones(2, 48, 48))  # fewer frames: another size
    assert fresh(cache).status(0) == "stale"
    left.unlink()
    assert fresh(cache).status(0) == "stale"
    # the same size and shape, other values: only full verification sees it, and relinks
    save_depth(sidecars.root, "right", 1, torch.full((3, 48, 48), 0.7))
    c = fresh(cache)
    assert c.status(1) == "ok" and not c.verify(1)
    assert c.ensure(1, sidecars, verify=True) is not None and c.verify(1)
    assert torch.equal(c.read_depth(1, 2)[0][1], torch.full((1, 48, 48), 0.7, dtype=torch.float16).float())


def test_a_copy_cache_rebuilds_linked_episodes_and_a_link_cache_reads_copies(linked):
    cache, sidecars, _ = linked
    copy = SceneCache(cache.root, cache.reconstructor, cache.dataset, link_depth=False)
    assert copy.status(0) == "stale"
    copy.ensure(0, sidecars)
    header, _ = read_header(cache.path(0))
    assert "depth_links" not in header["__metadata__"] and "depth.f0" in header
    assert fresh(cache).status(0) == "ok" and fresh(cache).verify(0)


LINK_EDITS = {
    "links not JSON": set_meta("depth_links", "[{"),
    "one link for two views": lambda h: h["__metadata__"].update(
        depth_links=json.dumps(json.loads(h["__metadata__"]["depth_links"])[:1])),
    "link without a size": lambda h: h["__metadata__"].update(
        depth_links=json.dumps([{k: v for k, v in d.items() if k != "bytes"}
                                for d in json.loads(h["__metadata__"]["depth_links"])])),
}


@pytest.mark.parametrize("edit", list(LINK_EDITS))
@pytest.mark.parametrize("forged", [False, True])
def test_malformed_links_are_corrupt_not_a_crash(linked, edit, forged):
    cache, _, _ = linked
    edit_header(cache.path(0), lambda h: (LINK_EDITS[edit](h), forged and _header_is_still_consistent(h)))
    c = fresh(cache)
    assert c.status(0) == "corrupt" and not c.verify(0)
    with pytest.raises(CorruptCacheError):
        c.read_depth(0, 0)


def test_dequantize_reads_every_integer_type_alike():
    """uint16 and int16 (the cache's words), numpy or torch, and wider integers modulo 2^16
    give the same metres; code 0 is no depth and every other code a finite positive depth."""
    codes = np.arange(2**16, dtype=np.uint16)
    want = dc.dequantize_depth(codes)
    assert want.dtype == torch.float32 and want[0] == 0 and torch.isfinite(want).all() and (want[1:] > 0).all()
    assert torch.all(want[2:] > want[1:-1])  # one step per code
    for same in (codes.view(np.int16), torch.from_numpy(codes.view(np.int16)), codes.astype(np.int32),
                 torch.from_numpy(codes.astype(np.int64) - 2**16)):  # fmt: skip
        assert torch.equal(dc.dequantize_depth(same), want)
    k = torch.arange(1, 2**16, dtype=torch.float64)
    assert torch.allclose(want[1:].double(), dc.D_MIN * torch.exp((k - 1) * dc.STEP), rtol=1e-7, atol=0)


def test_a_dropped_cache_frees_its_parsed_files_at_once(built):
    """No reference cycle between a cache and its kept files: dropping the cache frees them
    without waiting for a garbage collection (a worker's memory does not pile up)."""
    import gc
    import weakref

    cache = fresh(built[0])
    cache.read_depth(0, 1)
    kept = weakref.ref(cache._kept[0])
    gc.disable()
    try:
        del cache
        assert kept() is None
    finally:
        gc.enable()


def test_reads_during_rebuilds_give_one_version_or_the_other(built, source):
    """A reader keeps reading an episode that another thread rebuilds again and again from two
    sources: every read is one version's depth, whole (never a mix, never a checksum error);
    the one error allowed is the rare file replaced twice within one read, named as such."""
    cache, _ = built
    other = SceneEpisodes(num_episodes=2, num_frames=3, size=48, seed=5)
    other.fingerprint = source.fingerprint
    versions, writer = [], fresh(cache)
    for src in (other, source):
        with writer.lock(0):
            writer._build(0, src)
        versions.append(fresh(cache).read_depth(0, 1)[0])
    assert not torch.equal(*versions)
    stop, failures = threading.Event(), []

    def rebuild():
        for i in range(30):
            with writer.lock(0):
                writer._build(0, (other, source)[i % 2])
        stop.set()

    thread = threading.Thread(target=rebuild)
    thread.start()
    reader, reads = fresh(cache), 0
    while not stop.is_set() or reads == 0:
        try:
            depth = reader.read_depth(0, 1)[0]
            reads += 1
            if not any(torch.equal(depth, v) for v in versions):
                failures.append("a depth of neither version")
        except CorruptCacheError as e:
            if "replaced or removed since it was opened" not in str(e):
                failures.append(str(e))
        except FileNotFoundError:
            failures.append("the episode missing between rebuilds")
    thread.join()
    assert not failures and reads > 0
