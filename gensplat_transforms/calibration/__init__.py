"""The calibration stage: each camera's intrinsics and pose, for datasets that carry none.

:mod:`.files` reads a calibration file (three conventions) or the dataset's own pose features,
checks it and stores it beside the dataset (``calibrate``, ``calibrate_from_features``), and
gives a dataset's cameras, from its features or that stored file (``load_calibration``);
:mod:`.estimate` estimates the calibration from the dataset's own frames (``estimate_rig``,
``gensplat calibrate estimate``). Imports only the core and the data stage.
"""

from .estimate import estimate_rig
from .files import calibrate, calibrate_from_features, load_calibration, read_calibration

__all__ = ["calibrate", "calibrate_from_features", "estimate_rig", "load_calibration", "read_calibration"]
