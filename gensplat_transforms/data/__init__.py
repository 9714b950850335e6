"""The dataset stage: what a dataset carries for GenSplat, and the built-in scene.

:mod:`.format` (calibration and depth in a LeRobot dataset: ``CameraCalibration``,
``DepthSensor``, the depth sidecars ``save_depth``/``load_depth``), :mod:`.depth_import`
(recorded depth into sidecars, ``gensplat import-depth``), :mod:`.registration` (a depth
sensor's maps onto its colour camera), :mod:`.outputs` (where the commands may write) and
:mod:`.scenes` (the procedural tabletop: ``TabletopScene``, ``default_cameras``). Imports
only the core.
"""

from .format import CameraCalibration, DepthSensor, load_depth, save_depth
from .scenes import TabletopScene, default_cameras

__all__ = ["CameraCalibration", "DepthSensor", "TabletopScene", "default_cameras", "load_depth", "save_depth"]
