"""Model weights shipped with the package.

``small/``: the small GenSplat model (``ModelConfig.small()``) trained on this project's
procedural tabletops with true-geometry distillation at 112x112 (see ``benchmarks/model_quality.py``
and ``benchmarks/results/model_quality.json`` for its training settings and quality). It is the
default model for RGB-only datasets.
"""

from pathlib import Path

#: ``from_pretrained`` directory of the default small model.
DEFAULT_MODEL_DIR = Path(__file__).resolve().parent / "small"
