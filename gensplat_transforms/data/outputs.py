"""Where the ``gensplat`` commands may write (docs/reliability.md).

The rule: an output path (a file, or a folder) given by the user is refused with ``ValueError``
when it lies inside the dataset the command reads, taken literally or with every symbolic link
in it followed (a final one included), except under ``<dataset>/gensplat/``, GenSplat's own
folder (which may be a link to another disk), where the entries GenSplat keeps itself
(``GENSPLAT_OWNED``: settings, calibration, cache, ...) are refused too; a folder where a file
is expected, a file where a folder is expected (or in the way of one), and a device, pipe or
socket where a file is written (the rename would replace ``/dev/null`` itself) are refused as well.
Files are then written with :func:`.atomic.atomic_write`, which replaces a symbolic link instead
of writing through it. GenSplat's own folders below ``<dataset>/gensplat/`` (the cache) are used
only where every link in them followed keeps them in the real ``gensplat/`` folder
(:func:`gensplat_subfolder`).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .format import GENSPLAT_DIR, GENSPLAT_OWNED


def check_output(path: str | Path, dataset: str | Path | None = None, folder: bool = False) -> Path:
    """``path`` made absolute, once the rule of this module allows writing a file (or a
    ``folder``) there for a command reading the dataset rooted at ``dataset`` (None: none)."""
    path = Path(os.path.abspath(path))
    if dataset is not None:
        for p, root in ((path, Path(os.path.abspath(dataset))),
                        (Path(os.path.realpath(path)), Path(os.path.realpath(dataset)))):  # fmt: skip
            if p.is_relative_to(root) and not p.is_relative_to(root / GENSPLAT_DIR):
                via = "" if p == path else f" (through a symbolic link, it is {p})"
                raise ValueError(f"{path} is inside the dataset {dataset}{via}, which is never written to: "
                                 "give an output path outside the dataset")  # fmt: skip
        for p, own in ((path, Path(os.path.abspath(dataset)) / GENSPLAT_DIR),
                       (Path(os.path.realpath(path)), Path(os.path.realpath(Path(dataset) / GENSPLAT_DIR)))):  # fmt: skip
            if p.is_relative_to(own) and p != own and p.relative_to(own).parts[0] in GENSPLAT_OWNED:
                raise ValueError(f"{path} is GenSplat's own {p.relative_to(own).parts[0]} in {own}, which an "
                                 "output never replaces: give another output path")  # fmt: skip
    if not folder and path.is_dir():
        raise ValueError(f"{path} is a folder: give the name of a file to write")
    if not folder and os.path.lexists(path) and not (path.is_symlink() or path.is_file()):
        raise ValueError(f"{path} is not a regular file (a device, a pipe or a socket), which the output would "
                         "replace: give the path of a file to write")  # fmt: skip
    for p in ([path] if folder else []) + list(path.parents):
        if p.exists() and not p.is_dir():
            raise ValueError(f"{p} is a file, not a folder: give another path than {path}")
    return path


def gensplat_folder(dataset: str | Path) -> Path:
    """``<dataset>/gensplat``, where GenSplat writes beside a dataset, once it is not (through a
    symbolic link) one of the dataset's own folders; a link to another disk is fine."""
    return check_output(Path(dataset) / GENSPLAT_DIR, dataset, folder=True)


def gensplat_subfolder(dataset: str | Path, *parts: str) -> Path:
    """``<dataset>/gensplat/<parts...>``, a folder GenSplat writes its own files in (the cache),
    once every symbolic link on the way followed (``gensplat`` itself, ``cache``, ...) it lies
    in the real ``<dataset>/gensplat/`` folder; else ``ValueError`` (a link there could lead
    the writes into the dataset's own folders)."""
    folder = gensplat_folder(dataset)
    path, base = folder.joinpath(*parts), Path(os.path.realpath(folder))
    real = Path(os.path.realpath(path))
    if not real.is_relative_to(base) or real == base:
        raise ValueError(f"{path} leads through a symbolic link to {real}, outside GenSplat's folder {base}, "
                         "the only place GenSplat writes its files: remove the link")  # fmt: skip
    for p in (path, *path.parents[: len(parts) - 1]):
        if p.exists() and not p.is_dir():
            raise ValueError(f"{p} is a file, not a folder: GenSplat keeps its own files there; move it away")
    return path


@contextmanager
def new_folder(path: str | Path) -> Iterator[Path]:
    """``path`` made absolute, for a new folder to be written in the body: refused with
    ``ValueError`` when it exists; removed again when the body fails (an error or an interrupt)."""
    path = Path(os.path.abspath(path))
    if os.path.lexists(path):
        raise ValueError(f"{path} already exists: give the path of a new folder")
    check_output(path, folder=True)
    try:
        yield path
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise
