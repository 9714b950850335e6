"""Atomic writes: whole files with the umask's mode, nothing left behind when a write fails."""

import os
import stat
from pathlib import Path

import pytest
import torch

from gensplat_transforms.core.atomic import atomic_write, atomic_write_json, read_json_object, stat_stamp
from gensplat_transforms.data.format import load_depth, save_depth


@pytest.fixture
def umask():
    """Sets the process umask for one test and restores it."""
    saved = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(saved)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_the_file_gets_the_mode_of_a_plain_open(tmp_path, umask, mask):
    umask(mask)
    atomic_write(tmp_path / "a" / "f.json", lambda tmp: Path(tmp).write_text("{}"))
    with open(tmp_path / "plain", "w") as fh:
        fh.write("{}")
    assert mode(tmp_path / "a" / "f.json") == mode(tmp_path / "plain") == 0o666 & ~mask


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "f.txt"
    path.write_text("old")

    def half_then_fail(tmp):
        Path(tmp).write_text("new, cut")
        raise KeyboardInterrupt  # a user stopping the process mid-write

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, half_then_fail)
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["f.txt"]


def test_depth_sidecars_are_readable_as_the_umask_allows(tmp_path, umask):
    umask(0o022)  # a shared dataset: other users read what one records
    path = save_depth(tmp_path, "left", 0, torch.full((2, 4, 5), 1.5))
    assert mode(path) == 0o644
    assert load_depth(tmp_path, "left", 0).shape == (2, 1, 4, 5)


def test_json_read_back_is_an_object_or_nothing(tmp_path):
    path = tmp_path / "a.json"
    assert read_json_object(path) == {}  # missing
    for text in ("{not json", "[1, 2]", "3"):
        path.write_text(text)
        assert read_json_object(path) == {}, text
    path.write_bytes(b"\xff\xfe\x00")  # not UTF-8
    assert read_json_object(path) == {}
    atomic_write_json(path, {"k": [1, 2]})
    assert read_json_object(path) == {"k": [1, 2]}


def test_a_rewritten_file_gets_another_stamp(tmp_path):
    path = tmp_path / "f"
    path.write_bytes(b"ab")
    first = stat_stamp(path.stat())
    assert stat_stamp(path.stat()) == first
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(b"ab"))  # same bytes, a new file
    assert stat_stamp(path.stat()) != first

