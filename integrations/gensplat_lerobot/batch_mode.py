"""GenSplat's views rendered on the training device, a batch at a time (``render_in="batch"``).

The workers only read the cache and draw the perturbations; ``lerobot-train``'s main loop
renders each batch's views right after the DataLoader has moved it to the device, before the
preprocessor normalises it (:func:`install` wraps the ``cycle`` that loop draws its batches
from). LeRobot's 2D image transforms move to the batch side with it, so they still apply to
the rendered views, never to the images the Gaussians are rebuilt from.
"""

from __future__ import annotations

import logging

import torch

from gensplat_transforms.cache.reader import disc_builder
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import GenSplatTransform

from .dataset import GenSplatLeRobotDataset

log = logging.getLogger(__name__)


class BatchRenderer:
    """Called on each collated batch (on the training device): renders the augmented views
    (:func:`~gensplat_transforms.rendering.batched.render_batch`), then applies LeRobot's 2D image
    transforms to every camera of every sample, as the dataset does in the worker mode."""

    def __init__(self, transform: GenSplatTransform, image_transforms, camera_keys: list[str]) -> None:
        self.transform = transform
        self.image_transforms = image_transforms
        self.camera_keys = camera_keys
        self.batches = 0

    def __call__(self, batch: dict) -> dict:
        rendered = render_batch(batch, self.transform)
        if self.batches == 0:
            log.info("GenSplat rendered its first batch on %s: %d of %d samples augmented",
                     batch["gensplat.depth"].device, int(batch["gensplat.render"].sum()),
                     len(batch["gensplat.render"]))  # fmt: skip
        self.batches += 1
        if self.image_transforms is not None:
            for key in self.camera_keys:
                if key in rendered:
                    rendered[key] = torch.stack([self.image_transforms(image) for image in rendered[key]])
        return rendered


def settled_render_in(mode: str, cfg) -> str:
    """``GenSplatConfig.render_in`` for the ``lerobot-train`` run ``cfg``: "auto" becomes
    "batch" when CUDA is available and the policy trains on CUDA, else "worker"; "worker" and
    "batch" stay as they are."""
    if mode != "auto":
        return mode
    device = getattr(getattr(cfg, "trainable_config", None), "device", None) or "cpu"
    return "batch" if torch.cuda.is_available() and torch.device(device).type == "cuda" else "worker"


def attach_batch_renderer(dataset: GenSplatLeRobotDataset) -> str:
    """Where ``dataset`` renders (its transform's settled ``render_in``), returned; in batch
    mode the dataset gets a :class:`BatchRenderer` (``gensplat_batch``, used by the loop
    :func:`install` wraps) and hands it its 2D image transforms."""
    transform = dataset.gensplat
    mode = transform.cfg.render_in
    if mode not in ("worker", "batch"):
        raise ValueError(f"attach_batch_renderer: render_in {mode!r} is not settled (settled_render_in)")
    if mode == "batch":
        disc_builder(transform.cache.reconstructor)  # fails here, not in a worker, for caches it cannot render
        cameras = [key for key in dataset.meta.camera_keys if key not in dataset.meta.depth_keys]
        dataset.gensplat_batch = BatchRenderer(transform, dataset.gensplat_image_transforms, cameras)
        dataset.gensplat_image_transforms = None
    log.info("GenSplat renders %s", "each batch on the training device, after collation" if mode == "batch"
             else "in the dataloader workers")  # fmt: skip
    return mode


def install(module) -> None:
    """Make ``module`` (the running ``lerobot_train``) render the batches of a dataset that
    :func:`attach_batch_renderer` put in batch mode: its ``cycle`` yields them rendered."""
    original = module.cycle
    if getattr(original, "gensplat", False):
        return

    def cycle(iterable, _original=original):
        renderer = getattr(getattr(iterable, "dataset", None), "gensplat_batch", None)
        for batch in _original(iterable):
            yield batch if renderer is None else renderer(batch)

    cycle.gensplat = True
    module.cycle = cycle
