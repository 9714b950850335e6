"""numba's ``njit`` as every compiled kernel of the package uses it (the renderer, the RGB-D
discs, hole filling, depth registration): compiled code cached on disk next to the module
that defines it (see :mod:`.render.fast` for where numba writes it)."""

from __future__ import annotations

import numba


def _jit(parallel: bool = False, inline: bool = False, fastmath=False):
    """``njit`` with an on-disk cache; without a writable cache location, no cache."""
    inline = "always" if inline else "never"
    options = {"parallel": parallel, "fastmath": fastmath, "error_model": "numpy", "inline": inline}

    def wrap(fn):
        try:
            return numba.njit(cache=True, **options)(fn)
        except RuntimeError:  # numba found no writable cache directory
            return numba.njit(cache=False, **options)(fn)

    return wrap
