"""Former public names that still import, with a DeprecationWarning naming the new one.

A module that held a renamed name sets ``__getattr__ = renamed(__name__, {"Old": "New"})``
(PEP 562: called only for names the module does not have).

Example:
    >>> import warnings
    >>> import gensplat_transforms
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     gensplat_transforms.GaussianCache is gensplat_transforms.SceneCache
    True
    >>> str(caught[0].message)
    'gensplat_transforms.GaussianCache is renamed gensplat_transforms.SceneCache'
"""

from __future__ import annotations

import sys
import warnings

#: former name -> current name, for every module that exported the former one
RENAMED = {"GaussianCache": "SceneCache", "PerturbationSampler": "PaperSampler"}


def renamed(module: str, names: dict[str, str] = RENAMED):
    """A module ``__getattr__`` resolving the former ``names`` of ``module`` to the current ones
    (those the module holds: a name it never exported stays an AttributeError)."""

    def __getattr__(name: str):
        new = names.get(name)
        if new is None or new not in vars(sys.modules[module]):
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warnings.warn(f"{module}.{name} is renamed {module}.{new}", DeprecationWarning, stacklevel=2)
        return getattr(sys.modules[module], new)

    return __getattr__
