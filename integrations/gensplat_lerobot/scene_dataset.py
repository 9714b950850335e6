"""Record the built-in procedural episodes as a local LeRobot dataset (with calibration
and depth in the GenSplat dataset format): test and demo data that needs no simulator."""

from __future__ import annotations

from pathlib import Path

import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm.auto import tqdm

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.data.format import camera_info, save_depth
from gensplat_transforms.data.outputs import new_folder

from .source import video_backend

DEPTH_AS = ("sidecars", "feature", "video")


def record_scene_dataset(root: str | Path, source: SceneEpisodes, repo_id: str = "local/gensplat_scene",
                         fps: int = 10, progress: bool = True, depth_as: str = "sidecars") -> LeRobotDataset:
    """Write ``source``'s episodes to ``root`` (which must not exist; removed again when this fails).

    Cameras ``left`` and ``right`` are external and get depth: sidecars, or with
    ``depth_as="feature"`` LeRobot's own depth-map features ``observation.images.<camera>_depth``
    (uint16 millimetres, as LeRobot records a RealSense: PNG images), or with
    ``depth_as="video"`` the same features as LeRobot's 12-bit log-quantised HEVC depth video
    beside MP4 colour video (every camera then video-encoded); ``front`` is an extra static
    camera the policy also sees. ``observation.state`` is the moving object's position, ``action``
    its next position.
    """
    if depth_as not in DEPTH_AS:
        raise ValueError(f"record_scene_dataset: depth_as must be one of {DEPTH_AS}, got {depth_as!r}")
    visual = "video" if depth_as == "video" else "image"
    s = source.size
    names = ("left", "right", "front")
    features = {
        f"observation.images.{n}": {
            "dtype": visual, "shape": (s, s, 3), "names": ["height", "width", "channels"],
            "info": camera_info(source.cameras.K[i], source.cameras.c2w[i], "external"),
        }
        for i, n in enumerate(names)
    }  # fmt: skip
    if depth_as != "sidecars":
        for n in names[:2]:
            features[f"observation.images.{n}_depth"] = {"dtype": visual, "shape": (s, s, 1), "info": {"is_depth_map": True},
                                                          "names": ["height", "width", "channels"]}  # fmt: skip
    features["observation.state"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]}
    features["action"] = {"dtype": "float32", "shape": (3,), "names": ["x", "y", "z"]}
    with new_folder(root):  # removed again when recording fails
        ds = LeRobotDataset.create(repo_id, fps, features, root=root, use_videos=visual == "video",
                                   video_backend=video_backend())  # fmt: skip
        for ep in tqdm(range(source.num_episodes), desc="recording", unit="episode", disable=not progress):
            depths = []
            positions = [torch.tensor(source.scene(ep, t).objects[0].center) for t in range(source.frames + 1)]
            for t in range(source.frames):
                rgb, depth = source.render(ep, t)
                frame = {f"observation.images.{n}": rgb[i].permute(1, 2, 0).numpy() for i, n in enumerate(names)}
                if depth_as != "sidecars":
                    for i, n in enumerate(names[:2]):
                        frame[f"observation.images.{n}_depth"] = (depth[i].permute(1, 2, 0) * 1000).round().numpy().astype("uint16")
                frame["observation.state"] = positions[t].float().numpy()
                frame["action"] = positions[t + 1].float().numpy()
                frame["task"] = "push the object along the table"
                ds.add_frame(frame)
                depths.append(depth[:2, 0])
            ds.save_episode()
            depth = torch.stack(depths, 1)  # (2, T, H, W)
            for i, n in enumerate(names[:2] if depth_as == "sidecars" else ()):
                save_depth(root, n, ep, depth[i])
        ds.finalize()
    return ds
