"""What a policy trained with GenSplat receives from a LeRobot dataset (``gensplat preview``).

The dataset is opened as ``lerobot-train`` opens it (uint8 images; LeRobot's 2D image
transforms with their default config when asked), GenSplat enabled on it with the settings
``gensplat cache`` wrote, augmentation forced on (probability 1) and rendered in the item
(``render_in="worker"``; the batch mode renders the same images on the training GPU).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.transforms import ImageTransforms, ImageTransformsConfig

from gensplat_transforms.core.images import save_grid
from gensplat_transforms.data.outputs import check_output
from gensplat_transforms.rendering.preview import as_frame, save_video
from gensplat_transforms.views.perturbation import AXES

from .dataset import enable_gensplat, load_settings
from .export import timestep_indices
from .source import video_backend

#: grid tiles smaller than this are enlarged (nearest, integer factor) so the row labels fit
MIN_TILE_HEIGHT = 96


@dataclass
class Preview:
    """What :func:`write_lerobot_preview` wrote and showed.

    Attributes:
        png: the grid: a row per (frame, draw), original and policy input per camera.
        mp4: every frame of the episode side by side like a grid row (None without PyAV).
        indices: the dataset index of each grid row, in the order the rows were drawn.
        items: the dataset's item of each grid row, as the policy gets it.
    """

    png: Path
    mp4: Path | None
    indices: list[int]
    items: list[dict]


def open_dataset(root: str | Path, repo_id: str, image_transforms: bool = False) -> LeRobotDataset:
    """The dataset as ``lerobot-train`` opens it (uint8 images), with LeRobot's
    ``ImageTransforms`` at their default config (``--dataset.image_transforms.enable=true``)
    when ``image_transforms``."""
    two_d = ImageTransforms(ImageTransformsConfig(enable=True)) if image_transforms else None
    return LeRobotDataset(repo_id, root=root, image_transforms=two_d, video_backend=video_backend(),
                          return_uint8=True)  # fmt: skip


#: The most draws (grid rows) per frame a preview shows.
MAX_DRAWS = 32


def write_lerobot_preview(
    root: str | Path,
    repo_id: str,
    out_dir: str | Path,
    episode: int = 0,
    frames: Sequence[int] | None = None,
    draws: int = 3,
    image_transforms: bool = False,
    seed: int = 0,
) -> Preview:
    """Write ``preview.png`` and ``preview.mp4`` to ``out_dir`` (created; files replaced atomically;
    :func:`~gensplat_transforms.data.outputs.check_output`'s rule against the dataset ``root``).

    The grid has ``draws`` rows per frame of ``frames`` (default: 4 evenly spaced frames of
    ``episode``): row d shows view d of the trajectory's ``views_per_source`` (cycling when
    ``draws`` is larger), so the rows show distinct moves, and a fresh draw of the 2D
    transforms, labelled with each replaced camera's axis, rotation theta and forward move mu;
    columns: every camera's original image and the image the policy gets.
    The video then has every frame of the episode, one draw each. Draws come from torch's
    generator seeded with ``seed`` (the caller's generator state is restored afterwards), in
    the order of :attr:`Preview.indices`, then the video's frames.
    """
    if not 1 <= draws <= MAX_DRAWS:
        raise ValueError(f"gensplat preview: draws must be in 1..{MAX_DRAWS} (rows per frame of the grid), got {draws}")
    if not 0 <= seed < 2**64:
        raise ValueError(f"gensplat preview: seed must be in [0, 2**64) (a torch seed), got {seed}")
    out_dir = check_output(out_dir, root, folder=True)
    png, mp4 = (check_output(out_dir / name, root) for name in ("preview.png", "preview.mp4"))
    config, reconstructor = load_settings(root, repo_id)
    dataset = enable_gensplat(open_dataset(root, repo_id, image_transforms),
                              replace(config, probability=1.0, report=True, render_in="worker"),
                              reconstructor)  # fmt: skip
    every = timestep_indices(dataset.meta, episode)
    frames = list(frames) if frames is not None else sorted({round(k * (len(every) - 1) / 3) for k in range(4)})
    rows = [(i, f, d) for i, f in zip(timestep_indices(dataset.meta, episode, frames), frames) for d in range(draws)]
    keys = [k for k in dataset.meta.camera_keys if k not in dataset.meta.depth_keys]
    names = [k.removeprefix("observation.images.") for k in keys]
    replaced = [config.image_key.format(name=n) for n in config.replace]
    size = as_frame(LeRobotDataset.__getitem__(dataset, rows[0][0])[replaced[0]]).shape[-2:]
    mp4.unlink(missing_ok=True)  # not left from an earlier run when PyAV is missing
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        items = [dataset.augmented(i, view=d % config.views_per_source) for i, _, d in rows]
        video = (torch.cat(_tiles(dataset, i, dataset[i], keys, size), dim=2) for i in every)  # encoded as drawn
        written = save_video(video, mp4, int(dataset.meta.fps))
    scale = -(-MIN_TILE_HEIGHT // size[0])
    grid = [[F.interpolate(t[None], scale_factor=scale)[0] for t in _tiles(dataset, i, item, keys, size)]
            for (i, _, _), item in zip(rows, items)]  # fmt: skip
    labels = [_label(item, f, d % config.views_per_source, config.replace) for (_, f, d), item in zip(rows, items)]
    gensplat = "GenSplat+2D" if image_transforms else "GenSplat"
    columns = [f"{n}: {kind}" for k, n in zip(keys, names)
               for kind in ("original", gensplat if k in replaced else "2D" if image_transforms else "as is")]  # fmt: skip
    save_grid(grid, png, labels, columns)
    return Preview(png, mp4 if written else None, [i for i, _, _ in rows], items)


def _tiles(dataset, index: int, item: dict, keys: list[str], size: torch.Size) -> list[torch.Tensor]:
    """Original and policy input of each camera: (3, H, W) float images resized to ``size``."""
    original = LeRobotDataset.__getitem__(dataset, index)  # GenSplat's dataset holds the 2D transforms apart
    tiles = [as_frame(image[key]) for key in keys for image in (original, item)]
    return [t if t.shape[-2:] == size else F.interpolate(t[None], size=tuple(size), mode="bilinear", antialias=True)[0]
            for t in tiles]  # fmt: skip


def _label(item: dict, frame: int, view: int, cameras: Sequence[str]) -> str:
    """Row label: frame, view and each replaced camera's axis, rotation and forward move (and
    its centre of rotation, shift and focal-length change where they are not the pivot, none
    and none)."""
    lines = [f"frame {frame}, view {view + 1}"]
    for c, name in enumerate(cameras):
        index, move = int(item["gensplat.axis"][c]), item["gensplat.move"][c]
        if index >= 0:
            lines.append(f"{name}: {AXES[index]} {float(move[3]):+.1f} deg")
        else:  # a direction: on a line of its own
            lines += [f"{name}: {float(move[3]):+.1f} deg", "  about {:+.1f},{:+.1f},{:+.1f}".format(*move[:3].tolist())]
        if float(move[9]) == 0.0:  # turned about its own centre, not the pivot
            lines.append("  through the camera")
        lines.append(f"  mu {float(move[4]) * 100:.1f} cm")
        if bool(move[5:8].any()):
            lines.append("  shift {:+.1f},{:+.1f},{:+.1f} cm".format(*(move[5:8] * 100).tolist()))
        if float(move[8]) != 1.0:
            lines.append(f"  focal x{float(move[8]):.3g}")  # 1.2, 0.812, 1e+30: any scale readable
    return "\n".join(lines)
