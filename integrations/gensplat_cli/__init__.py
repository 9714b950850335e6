"""The ``gensplat`` command (``[project.scripts] gensplat = "gensplat_cli:main"``, or
``python -m gensplat_cli``): :mod:`.commands` parses and runs its subcommands (cache, calibrate,
preview, train, record, demo, ...). The top layer: it imports ``gensplat_transforms``,
``gensplat_lerobot`` and ``gensplat_sim``, each only inside the command that needs it.
"""

from .commands import build_parser, main

__all__ = ["build_parser", "main"]
