"""``python -m gensplat_cli``: the ``gensplat`` command (``torchrun ... -m gensplat_cli cache``)."""

import sys

from .commands import main

sys.exit(main())
