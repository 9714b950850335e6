"""Atomic file writes (readers see the old file or the whole new one, never a part), and
reading back the JSON files written that way without trusting them."""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Callable
from pathlib import Path


def atomic_write(path: str | Path, write: Callable[[str], object]) -> Path:
    """Write ``path`` through ``write(tmp)`` on a temporary file beside it, then rename.

    The file gets the mode a plain ``open(path, "w")`` would, 0o666 less the umask, whatever
    mode ``write`` leaves (safetensors makes its files private to their owner). The temporary
    file is removed when ``write`` fails. Returns ``path``; ``ValueError`` where a folder is in
    its way (:func:`replaceable`)."""
    path = replaceable(Path(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)  # the umask applies
    mode = os.fstat(fd).st_mode
    os.close(fd)
    try:
        write(str(tmp))
        os.chmod(tmp, mode)  # writers that replace the file (safetensors does) make it private
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def replaceable(path: Path) -> Path:
    """``path``, once a new file can be renamed over whatever is there (nothing, a file, a
    symbolic link); a folder there is refused with ``ValueError``, before any work is done."""
    if path.is_dir() and not path.is_symlink():
        raise ValueError(f"{path} is a folder where GenSplat writes a file: move it away")
    return path


def atomic_write_json(path: str | Path, data) -> Path:
    """:func:`atomic_write` of ``data`` as indented JSON. Returns ``path``."""
    text = json.dumps(data, indent=2) + "\n"
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def read_json_object(path: str | Path) -> dict:
    """The JSON object in ``path``; {} when it is missing, unreadable, not JSON or not an object."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        return {}
    return data if isinstance(data, dict) else {}


def stat_stamp(st: os.stat_result) -> list[int]:
    """[size, modification time in ns, inode] of a file: what changes when it is rewritten,
    replaced or edited (as JSON lists it), for records that trust a file while it is unchanged."""
    return [st.st_size, st.st_mtime_ns, st.st_ino]
