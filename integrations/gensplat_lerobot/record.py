"""Record the built-in procedural episodes as a local LeRobot dataset (with calibration
and depth in the GenSplat dataset format): test and demo data that needs no simulator."""

from __future__ import annotations

from pathlib import Path

import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm.auto import tqdm

from gensplat_transforms.dataset_format import camera_info, save_depth
from gensplat_transforms.episodes import SceneEpisodes

from .source import video_backend


def record_scene_dataset(root: str | Path, source: SceneEpisodes, repo_id: str = "local/gensplat_scene",
                         fps: int = 10, progress: bool = True) -> LeRobotDataset:
    """Write ``source``'s episodes to ``root`` (which must not exist).

    Cameras ``left`` and ``right`` are external and get depth sidecars; ``front`` is an
    extra static camera the policy also sees. ``observation.state`` is the moving object's
    position, ``action`` its next position.
    """
    s = source.size
    names = ("left", "right", "front")
    features = {
        f"observation.images.{n}": {
            "dtype": "image", "shape": (s, s, 3), "names": ["height", "width", "channels"],
            "info": camera_info(source.cameras.K[i], source.cameras.c2w[i], "external"),
        }
        for i, n in enumerate(names)
    }  # fmt: skip
    features["observation.state"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]}
    features["action"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]}
    ds = LeRobotDataset.create(repo_id, fps, features, root=root, use_videos=False, video_backend=video_backend())
    for ep in tqdm(range(source.num_episodes), desc="recording", unit="episode", disable=not progress):
        depths = []
        positions = [torch.tensor(source.scene(ep, t).objects[0].center) for t in range(source.frames + 1)]
        for t in range(source.frames):
            rgb, depth = source.render(ep, t)
            frame = {f"observation.images.{n}": rgb[i].permute(1, 2, 0).numpy() for i, n in enumerate(names)}
            frame["observation.state"] = positions[t].float().numpy()
            frame["action"] = positions[t + 1].float().numpy()
            frame["task"] = "push the object along the table"
            ds.add_frame(frame)
            depths.append(depth[:2, 0])
        ds.save_episode()
        depth = torch.stack(depths, 1)  # (2, T, H, W)
        for i, n in enumerate(names[:2]):
            save_depth(root, n, ep, depth[i])
    ds.finalize()
    return ds
