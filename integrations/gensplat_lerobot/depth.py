"""A camera's recorded depth as a LeRobot dataset's depth sidecars (``gensplat import-depth``)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from gensplat_transforms.calibration.files import load_calibration
from gensplat_transforms.data.depth_import import ImportedEpisode, import_depth
from gensplat_transforms.data.format import IMAGE_KEY_PREFIX

from .source import episode_table, read_info


def import_dataset_depth(root: str | Path, repo_id: str, camera: str, source: str, units: str | float | None = None,
                         episodes: Iterable[int] | None = None, overwrite: bool = False,
                         progress: bool = True) -> dict[int, ImportedEpisode]:  # fmt: skip
    """:func:`gensplat_transforms.data.depth_import.import_depth` for ``camera`` of the LeRobot
    dataset at ``root``: its episodes' lengths (default: every episode) and its images' size
    (its depth sensor's, where the calibration has one: the depth is registered when read)
    are the dataset's. Raises ``ValueError`` naming the dataset's cameras or episodes when
    ``camera`` or an episode is not in it."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    root = Path(root)
    features = read_info(root)["features"]
    key = IMAGE_KEY_PREFIX + camera
    if key not in features:
        names = [k[len(IMAGE_KEY_PREFIX) :] for k in features if k.startswith(IMAGE_KEY_PREFIX)]
        raise ValueError(f"{root}: no camera {camera!r}; its cameras: {names}")
    height, width = features[key]["shape"][:2]
    sensor = getattr(load_calibration(features, root).get(camera), "depth", None)
    if sensor is not None:
        width, height = sensor.width, sensor.height
    table = episode_table(LeRobotDatasetMetadata(repo_id, root=root))
    lengths = dict(zip(table["episode_index"], table["length"]))
    if episodes is not None:
        missing = sorted(set(episodes) - set(lengths))
        if missing:
            raise ValueError(f"{root}: episode(s) {missing} are not in the dataset (episodes 0..{len(lengths) - 1})")
        lengths = {e: lengths[e] for e in episodes}
    return import_depth(root, camera, source, lengths, (width, height), units, overwrite, progress)
