"""Preview of original versus augmented views along an episode (PNG grid and MP4)."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import torch

from ..core.atomic import atomic_write
from ..core.images import save_grid, to_uint8


def as_frame(image: torch.Tensor) -> torch.Tensor:
    """A camera image of an item, (3, H, W) or a temporal stack (T, 3, H, W), uint8 or float,
    as the (3, H, W) float image in [0, 1] of its current (last) frame."""
    image = image[-1] if image.ndim == 4 else image
    return image.float() / 255 if image.dtype == torch.uint8 else image.float()


def save_video(frames: Iterable[torch.Tensor], path: str | Path, fps: int) -> bool:
    """Write (3, H, W) float frames in [0, 1] (all the same size; an odd side loses its last
    pixel; a generator is encoded as it yields) as an MP4 with PyAV (H.264, or MPEG-4 without
    libx264), atomically (:func:`.atomic.atomic_write`). Returns False, writing nothing, when PyAV
    is not installed."""
    try:
        import av
    except ImportError:
        return False
    frames = iter(frames)
    first = next(frames)
    h, w = first.shape[-2:]

    def write(tmp: str) -> None:
        with av.open(tmp, mode="w", format="mp4") as container:
            stream = container.add_stream("libx264" if "libx264" in av.codecs_available else "mpeg4", rate=fps)
            stream.width, stream.height, stream.pix_fmt = w - w % 2, h - h % 2, "yuv420p"
            for f in itertools.chain([first], frames):
                img = to_uint8(f)[: h - h % 2, : w - w % 2].numpy()
                for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)

    atomic_write(path, write)
    return True


def write_preview(
    items: Sequence[dict],
    transform: Callable[[dict], dict],
    cameras: Sequence[str],
    out_dir: str | Path,
    image_key: str = "observation.images.{name}",
    max_rows: int = 8,
    fps: int = 10,
) -> dict[str, Path]:
    """Apply ``transform`` to every item and write ``preview.png`` (up to ``max_rows``
    evenly spaced frames; columns: original and augmented per camera) and, when PyAV is
    installed, ``preview.mp4`` with every frame side by side."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for item in items:
        aug = transform(item)
        row = []
        for name in cameras:
            key = image_key.format(name=name)
            row += [as_frame(item[key]), as_frame(aug[key])]
        rows.append(row)
    step = max(1, -(-len(rows) // max_rows))
    picked = list(range(0, len(rows), step))[:max_rows]
    cols = [f"{n}: {kind}" for n in cameras for kind in ("original", "GenSplat")]
    labels = [f"frame {int(items[i]['frame_index'])}" for i in picked]
    paths = {"png": out_dir / "preview.png"}
    save_grid([rows[i] for i in picked], paths["png"], labels, cols)
    if save_video([torch.cat(r, dim=2) for r in rows], out_dir / "preview.mp4", fps):  # (3, H, W * 2 * cameras)
        paths["mp4"] = out_dir / "preview.mp4"
    return paths
