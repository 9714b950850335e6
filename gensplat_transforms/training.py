"""Training the GenSplat model with 3D-prior distillation (DESIGN.md section 1).

    L = L_rgb + l_depth L_depth + l_3D L_3D + l_cam L_cam

L_rgb (L1 + SSIM, or LPIPS; see ``model.losses``) and L_depth compare the *context* views rendered
from the predicted Gaussians with the input images and with the predicted point maps' z. Each
sample's Gaussians are rendered into its predicted source cameras (poses from the camera head;
the calibrated intrinsics, or for uncalibrated data the focal the point maps imply, as
:class:`GenSplatReconstructor` does) with the differentiable reference renderer at the
training resolution. Its cost grows with the (splat, pixel) pairs, so two options cut CPU
time: ``render_views`` renders a random subset of each sample's views and ``render_crop``
only a random square window of them (a random subset of the pixels, with the intrinsics
cropped to match). L_3D and L_cam distil a :class:`Teacher` (true geometry or Pi3); a metric
teacher is compared without scale alignment, so the student learns metres. Terms with zero
weight are skipped; with l1 = perceptual = depth = 0 nothing is rendered (a geometry-only
run, which stands in for Pi3 pre-training when no Pi3 weights fit the model size).

Optimisation: AdamW, linear warm-up then cosine decay, 0.1x learning rate for parameters
loaded from Pi3 weights, EMA of the weights (exported), gradient clipping, optional bf16
autocast and gradient checkpointing. A run directory holds ``log.jsonl`` (one JSON object per
``log_every`` steps), ``checkpoint.pt`` (model, EMA, optimizer, scheduler and step; written
atomically; a rerun with the same directory resumes) and, at the end, ``model/`` (the EMA
weights, loadable with :meth:`GenSplatModel.from_pretrained`).
"""

from __future__ import annotations

import json
import math
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch.optim.swa_utils import AveragedModel
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from .core.atomic import atomic_write, atomic_write_json
from .core.cameras import Cameras
from .core.config_flags import flag, nested
from .core.views import Views
from .geometry.model.checkpoints import GAUSSIAN_PREFIX, load_pi3_weights
from .geometry.model.config import ModelConfig
from .geometry.model.frames import estimate_focal
from .geometry.model.gensplat import GenSplatModel, to_gaussians
from .geometry.model.losses import LossWeights, camera_loss, depth_loss, points_loss, rgb_loss
from .geometry.model.teacher import Teacher
from .rendering import render

CHECKPOINT_FILE = "checkpoint.pt"
LOG_FILE = "log.jsonl"
EXPORT_DIR = "model"


@dataclass
class TrainConfig:
    """Settings of a training run (the paper's values where it gives them).

    Attributes:
        out: run directory (log, checkpoint, exported model).
        steps, batch_size: optimiser steps and samples per step.
        lr: peak learning rate.
        pretrained_lr_scale: multiplies ``lr`` for the parameters initialised from Pi3 weights.
        weight_decay: AdamW decay of weight matrices (not of biases, norms, tokens, embeddings).
        warmup_steps: linear warm-up length; then cosine decay to ``min_lr_ratio * lr``.
        min_lr_ratio: the learning rate at the end of the cosine decay, as a fraction of ``lr``.
        ema_decay: EMA decay (ramped up as min(decay, (1 + n) / (10 + n)) over the first updates).
        grad_clip: maximum global gradient norm.
        bf16: run the model under bfloat16 autocast (heads, losses and rendering stay float32).
        grad_checkpointing: recompute transformer activations in the backward pass.
        loss: the weights l1, perceptual (inside L_rgb), depth, points (L_3D) and camera.
        render_views: context views rendered per sample for L_rgb / L_depth (None: all).
        render_crop: side of the random square window rendered of those views (None: whole
            view); at least the 11-pixel SSIM window.
        background: render background colour.
        depth_min_alpha: L_depth counts pixels whose rendered alpha exceeds this.
        seed: model initialisation, data order and view subsets.
        log_every, save_every: steps between log lines and between checkpoints.
        threads: torch CPU threads (None: leave torch's default).
    """

    # the flags of ``gensplat train-model`` (:mod:`.core.config_flags`)
    out: str | Path = field(metadata=flag("run directory (resumes when it holds a checkpoint)"))
    steps: int = field(default=1000, metadata=flag("optimiser steps", required=True))
    batch_size: int = field(default=4, metadata=flag("samples per step"))
    lr: float = field(default=2e-4, metadata=flag("peak learning rate, cosine decay after the warm-up"))
    pretrained_lr_scale: float = field(default=0.1, metadata=flag(
        "learning-rate factor of the parts initialised from --init-weights"))
    weight_decay: float = 0.05
    warmup_steps: int = field(default=100, metadata=flag("linear warm-up steps", flag="--warmup"))
    min_lr_ratio: float = 0.01
    ema_decay: float = field(default=0.999, metadata=flag(
        "decay of the exported exponential moving average of the weights"))
    grad_clip: float = 1.0
    bf16: bool = field(default=False, metadata=flag("bfloat16 autocast", action="store_true"))
    grad_checkpointing: bool = field(default=False, metadata=flag(
        "recompute transformer activations in the backward pass (less memory, slower)", action="store_true"))
    loss: LossWeights = field(default_factory=LossWeights, metadata=nested())
    render_views: int | None = field(default=None, metadata=flag(
        "context views rendered per sample", type=int, shown="all"))
    render_crop: int | None = field(default=None, metadata=flag(
        "render only a random square window of this side", type=int, shown="whole views"))
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    depth_min_alpha: float = 0.5
    seed: int = field(default=0, metadata=flag("seed of the initialisation, data order and view subsets"))
    log_every: int = field(default=10, metadata=flag("steps between log lines"))
    save_every: int = field(default=100, metadata=flag("steps between checkpoints"))
    threads: int | None = field(default=None, metadata=flag("torch CPU threads", type=int,
                                                            shown="torch's own choice"))

    def __post_init__(self) -> None:
        if isinstance(self.loss, dict):
            self.loss = LossWeights(**self.loss)
        ok = {
            "steps >= 1": self.steps >= 1, "batch_size >= 1": self.batch_size >= 1, "lr > 0": self.lr > 0,
            "warmup_steps >= 0": self.warmup_steps >= 0, "0 <= min_lr_ratio <= 1": 0 <= self.min_lr_ratio <= 1,
            "0 <= ema_decay < 1": 0 <= self.ema_decay < 1, "grad_clip > 0": self.grad_clip > 0,
            "render_views >= 1": self.render_views is None or self.render_views >= 1,
            "render_crop >= 11": self.render_crop is None or self.render_crop >= 11,
            "log_every, save_every >= 1": self.log_every >= 1 and self.save_every >= 1,
        }  # fmt: skip
        bad = [k for k, v in ok.items() if not v]
        if not (self.distills or self.renders):
            bad.append("a positive loss weight")
        if bad:
            raise ValueError(f"TrainConfig: need {', '.join(bad)}")

    @property
    def distills(self) -> bool:
        """Whether any term needs the teacher (L_3D or L_cam)."""
        return self.loss.points > 0 or self.loss.camera > 0

    @property
    def renders(self) -> bool:
        """Whether any term needs the rendered context views (L_rgb or L_depth)."""
        return self.loss.l1 > 0 or self.loss.perceptual > 0 or self.loss.depth > 0

    def to_dict(self) -> dict:
        return {**asdict(self), "out": str(self.out)}


def lr_factor(step: int, warmup: int, total: int, min_ratio: float) -> float:
    """Learning-rate multiplier at ``step`` (for ``torch.optim.lr_scheduler.LambdaLR``):
    (step + 1) / warmup during warm-up, then cosine from 1 down to ``min_ratio`` at ``total``.

    The floor is relative to each parameter group's rate (pretrained groups run at 0.1x),
    which ``CosineAnnealingLR``'s absolute ``eta_min`` and diffusers' floor-less schedule
    cannot express; both also start the warm-up at 0 instead of 1 / warmup."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def param_groups(model: torch.nn.Module, config: TrainConfig, pretrained: set[str]) -> list[dict]:
    """AdamW groups: pretrained (lr x ``pretrained_lr_scale``) or new, with or without weight decay."""
    groups: dict[tuple[bool, bool], list] = defaultdict(list)
    for name, p in model.named_parameters():
        if p.requires_grad:
            decay = p.ndim >= 2 and not any(s in name for s in ("token", "pos_embed"))
            groups[(name in pretrained, decay)].append(p)
    return [
        {"params": params, "name": f"{'pretrained' if pre else 'new'}/{'decay' if decay else 'no_decay'}",
         "lr": config.lr * (config.pretrained_lr_scale if pre else 1.0),
         "weight_decay": config.weight_decay if decay else 0.0}
        for (pre, decay), params in sorted(groups.items())
    ]  # fmt: skip


def ema_model(model: torch.nn.Module, decay: float) -> AveragedModel:
    """Exponential moving average of ``model``'s parameters and buffers: every
    ``update_parameters(model)`` moves the copy ``.module`` by 1 - d towards the model, with
    d = min(decay, (1 + n) / (10 + n)) at the n-th update (integer buffers are copied)."""

    def average(ema: torch.Tensor, new: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        if not ema.is_floating_point():
            return new
        return ema.lerp(new, 1 - min(decay, (1 + float(n)) / (10 + float(n))))

    ema = AveragedModel(model, avg_fn=average, use_buffers=True)
    ema.update_parameters(model)  # copies the starting weights; n counts the updates from here
    return ema


class Trainer:
    """Trains ``model`` on ``dataset`` items (:class:`Views` of one timestep, same V and size).

    Args:
        model: the student.
        dataset: map-style dataset of :class:`Views`; step s uses the shuffled items
            ``s * batch_size ... (s + 1) * batch_size - 1`` (reshuffled every epoch), so runs are
            reproducible and resumable.
        teacher: needed when ``config.distills``.
        config: the run settings.
        pretrained: names of parameters loaded from Pi3 weights (0.1x learning rate).
    """

    def __init__(self, model: GenSplatModel, dataset: Dataset, teacher: Teacher | None, config: TrainConfig,
                 pretrained: set[str] = frozenset()) -> None:  # fmt: skip
        if config.distills and teacher is None:
            raise ValueError(
                "Trainer: the loss weights need a teacher (set points = camera = 0 to train without)"
            )
        self.model, self.dataset, self.teacher, self.config = model.train(), dataset, teacher, config
        model.set_gradient_checkpointing(config.grad_checkpointing)
        self.optimizer = torch.optim.AdamW(param_groups(model, config, set(pretrained)), lr=config.lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: lr_factor(s, config.warmup_steps, config.steps, config.min_lr_ratio)
        )
        self.ema = ema_model(model, config.ema_decay)
        self.step = 0
        self.out = Path(config.out)

    # ------------------------------------------------------------------ data
    def batch(self, step: int) -> list[Views]:
        n, bs = len(self.dataset), self.config.batch_size
        items = []
        for k in range(step * bs, (step + 1) * bs):
            epoch, pos = divmod(k, n)
            perm = torch.randperm(
                n, generator=torch.Generator().manual_seed(self.config.seed * 100_003 + epoch)
            )
            items.append(self.dataset[int(perm[pos])])
        return items

    # ------------------------------------------------------------------ objective
    def losses(self, views: list[Views], step: int) -> dict[str, torch.Tensor]:
        """Loss terms of one batch; ``total`` is the objective. Terms with zero weight are skipped."""
        cfg, w = self.config, self.config.loss
        images = torch.stack([v.images for v in views]).float()
        B = images.shape[0]
        with torch.autocast("cpu" if images.device.type == "cpu" else images.device.type,
                            dtype=torch.bfloat16, enabled=cfg.bf16):  # fmt: skip
            out = self.model(images)
        local, poses = out["local_points"].float(), out["camera_poses"].float()
        terms: dict[str, torch.Tensor] = {}
        if cfg.distills:
            with torch.no_grad():
                geo = [self.teacher.geometry(v) for v in views]
            t_points = torch.stack([g[0] for g in geo]).to(local)
            t_poses = torch.stack([g[1] for g in geo]).to(poses)
            if w.points > 0:
                terms["points"] = points_loss(local, t_points, t_points[..., 2] > 0,
                                              align_scale=not self.teacher.metric)  # fmt: skip
            if w.camera > 0:
                scale = torch.ones(B, device=poses.device) if self.teacher.metric else None
                terms["cam_rot"], terms["cam_trans"] = camera_loss(poses, t_poses, scale=scale)

        if cfg.renders:
            terms.update(self._render_terms(views, images, out, step))
        cam = (terms["cam_rot"], terms["cam_trans"]) if "cam_rot" in terms else None
        terms["total"] = w.combine(rgb=terms.get("rgb"), depth=terms.get("depth"), points=terms.get("points"),
                                   camera=cam)  # fmt: skip
        return terms

    def _render_terms(self, views: list[Views], images: torch.Tensor, out: dict, step: int) -> dict:
        """L_rgb and L_depth of the rendered context views."""
        cfg, w = self.config, self.config.loss
        B, V, _, H, W = images.shape
        local, poses = out["local_points"].float(), out["camera_poses"].float()
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
        pred, target, r_depth, p_depth, alpha = [], [], [], [], []
        for b in range(B):
            cams = _context_cameras(views[b], local[b], out["conf"][b], poses[b])
            gaussians = to_gaussians(out, b)
            chosen = torch.randperm(V, generator=gen)[: cfg.render_views or V].sort().values.tolist()
            ch, cw = min(cfg.render_crop or H, H), min(cfg.render_crop or W, W)
            top = int(torch.randint(H - ch + 1, (), generator=gen))
            left = int(torch.randint(W - cw + 1, (), generator=gen))
            rows, cols = slice(top, top + ch), slice(left, left + cw)
            r = render(gaussians, cams[chosen].crop(left, top, cw, ch), background=cfg.background,
                       backend="reference", return_depth=w.depth > 0)  # fmt: skip
            pred.append(r.rgb)
            target.append(images[b, chosen][..., rows, cols])
            if w.depth > 0:
                r_depth.append(r.depth[:, 0])
                p_depth.append(local[b, chosen, rows, cols, 2])
                alpha.append(r.alpha[:, 0] > cfg.depth_min_alpha)
        terms = {"rgb": rgb_loss(torch.cat(pred), torch.cat(target), w)}
        if w.depth > 0:
            terms["depth"] = depth_loss(torch.cat(r_depth), torch.cat(p_depth), torch.cat(alpha))
        return terms

    def train_step(self) -> dict[str, float]:
        """One optimiser step; returns the detached loss terms, grad norm and learning rate."""
        terms = self.losses(self.batch(self.step), self.step)
        self.optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip)
        stats = {k: float(v.detach()) for k, v in terms.items()}
        cfg = self.config
        stats["lr"] = cfg.lr * lr_factor(self.step, cfg.warmup_steps, cfg.steps, cfg.min_lr_ratio)
        stats["grad_norm"] = float(norm)
        stats["skipped"] = float(not torch.isfinite(norm))
        if torch.isfinite(norm):  # a non-finite batch leaves weights, EMA and moments untouched
            self.optimizer.step()
            self.ema.update_parameters(self.model)
        self.scheduler.step()
        self.step += 1
        return stats

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        return {
            "step": self.step, "model": self.model.state_dict(), "ema": self.ema.state_dict(),
            "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
            "config": self.config.to_dict(), "model_config": self.model.config.to_dict(),
        }  # fmt: skip

    def save(self) -> Path:
        """Write ``checkpoint.pt`` atomically (temporary file + rename)."""
        return atomic_write(self.out / CHECKPOINT_FILE, lambda tmp: torch.save(self.state_dict(), tmp))

    def load(self, path: str | Path) -> None:
        """Resume from a checkpoint written by :meth:`save`. Only tensors and plain containers
        are read (``weights_only``): a file holding any other object is refused with
        ``ValueError``, never executed."""
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises several types for refused or unreadable files
            raise ValueError(
                f"{path}: refused to load: not a training checkpoint of tensors and plain containers "
                f"({type(e).__name__}; a file holding other objects could run code)"
            ) from e
        keys = {"step", "model", "ema", "optimizer", "scheduler", "model_config"}
        if not isinstance(state, dict) or not keys <= set(state):
            raise ValueError(f"{path}: not a training checkpoint (expected the keys {sorted(keys)})")
        if state["model_config"] != self.model.config.to_dict():
            raise ValueError(f"{path}: checkpoint of another model configuration")
        self.model.load_state_dict(state["model"])
        self.ema.load_state_dict(state["ema"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.step = state["step"]

    def export(self) -> Path:
        """The EMA weights as a ``from_pretrained`` directory ``<out>/model``."""
        model = GenSplatModel(self.model.config)
        model.load_state_dict(self.ema.module.state_dict())
        height, width = self.dataset[0].images.shape[-2:]
        model.max_pixels = height * width  # the size it was trained at, which the geometry path keeps to
        return model.save_pretrained(self.out / EXPORT_DIR)

    # ------------------------------------------------------------------ loop
    def fit(self, progress: bool = True) -> Path:
        """Train to ``config.steps`` (resuming from ``<out>/checkpoint.pt`` when present), export
        the EMA model and return its directory."""
        cfg = self.config
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        self.out.mkdir(parents=True, exist_ok=True)
        if (self.out / CHECKPOINT_FILE).is_file():
            self.load(self.out / CHECKPOINT_FILE)
        atomic_write_json(self.out / "train_config.json", {"train": cfg.to_dict(), "model": self.model.config.to_dict()})
        sums: dict[str, float] = defaultdict(float)
        count, t0 = 0, time.perf_counter()
        bar = tqdm(total=cfg.steps, initial=self.step, desc="train", unit="step", disable=not progress,
                   mininterval=5.0)  # fmt: skip
        with open(self.out / LOG_FILE, "a") as log:
            while self.step < cfg.steps:
                for k, v in self.train_step().items():
                    sums[k] += v
                count += 1
                bar.update(1)
                bar.set_postfix(loss=f"{sums['total'] / count:.4f}", refresh=False)
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    now = time.perf_counter()
                    record = {"step": self.step, **{k: v / count for k, v in sums.items()},
                              "sec_per_step": (now - t0) / count}  # fmt: skip
                    log.write(json.dumps(record) + "\n")
                    log.flush()
                    sums, count, t0 = defaultdict(float), 0, now
                if self.step % cfg.save_every == 0 or self.step == cfg.steps:
                    self.save()
        bar.close()
        return self.export()


def _context_cameras(views: Views, local: torch.Tensor, conf: torch.Tensor, poses: torch.Tensor) -> Cameras:
    """Predicted poses (V, 4, 4) with the calibrated intrinsics, or, for uncalibrated views, the
    focal the point maps (V, H, W, 3) imply (principal point at the centre)."""
    _, H, W, _ = local.shape
    if views.cameras is not None:
        return Cameras(views.cameras.K.to(poses), poses, W, H)
    focal = estimate_focal(local.detach(), torch.sigmoid(conf.detach().float()))
    return Cameras.from_intrinsics(focal.clamp_min(1.0), focal.clamp_min(1.0), W / 2, H / 2, poses, W, H)


def pretrained_names(model: torch.nn.Module, weights: str | Path) -> set[str]:
    """Load Pi3 weights (or a GenSplat checkpoint) into ``model`` and return the names of the
    Pi3-architecture parameters they set (the Gaussian head, new in GenSplat, never counts)."""
    missing = set(load_pi3_weights(model, weights).missing)
    return {n for n, _ in model.named_parameters() if n not in missing and not n.startswith(GAUSSIAN_PREFIX)}


def train(config: TrainConfig, model_config: ModelConfig, dataset: Dataset, teacher: Teacher | None = None,
          init_weights: str | Path | None = None, progress: bool = True) -> Path:  # fmt: skip
    """Build a model (optionally initialised from Pi3 weights), train it and return the exported
    EMA model directory."""
    torch.manual_seed(config.seed)
    model = GenSplatModel(model_config)
    pretrained = pretrained_names(model, init_weights) if init_weights else set()
    return Trainer(model, dataset, teacher, config, pretrained).fit(progress)
