"""GenSplat for LeRobot.

Enable in the stock trainer with one added command-line argument::

    lerobot-train ... --gensplat.discover_packages_path=gensplat_lerobot.plugin

LeRobot imports the ``plugin`` package for any argument whose key contains
``discover_packages_path`` (and removes the argument); importing it wraps the training
dataset that ``lerobot-train`` builds. The GenSplat settings and the Gaussian cache live
beside the dataset (``<root>/gensplat/``), written by ``gensplat cache``. Importing this
package itself has no side effects.
"""

from .dataset import GenSplatLeRobotDataset, enable_gensplat, load_settings, prepare, save_settings
from .source import LeRobotSource, LeRobotViews, video_backend

__all__ = [
    "GenSplatLeRobotDataset", "LeRobotSource", "LeRobotViews", "enable_gensplat", "load_settings", "prepare",
    "save_settings", "video_backend",
]  # fmt: skip
