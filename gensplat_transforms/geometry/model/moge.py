"""MoGe-2 (microsoft/MoGe, MIT code and weights): a metric point map, a validity mask, normals and
the field of view from a single RGB image.

An own implementation of ``moge/model/v2.py`` (with ``modules.py``, the DINOv2 backbone and the
focal / shift recovery of ``utils/geometry_torch.py``) whose module and parameter names are the
published checkpoint's keys: the ``model`` state dict of ``model.pt`` in
``Ruicheng/moge-2-vits-normal`` / ``moge-2-vitl-normal`` (and the other MoGe-2 sizes) loads without
renaming, and the architecture is built from the ``model_config`` stored beside it.

Network: the image is resized to a token grid of about ``num_tokens`` patches with its aspect
ratio, a DINOv2 ViT/14 encodes it, and four of its blocks' normalised patch tokens, each projected
by a 1x1 conv, are summed. A conv "neck" upsamples them through five levels (token grid x 1, 2,
4, 8, 16; each level also gets the view-plane UV of its pixels), and conv heads read the neck's
levels: an affine-invariant point map, a mask logit and (optionally) normals, resized to the
image. An MLP on the last taken block's [cls] token gives the log metric scale.

Post-processing (:meth:`MoGe2.infer`): the focal length and the z shift that make the point map a
pinhole projection are fitted on a 64x64 subsample of the masked points; the depth is the
shifted z, the points are re-projected from it, and both are multiplied by the metric scale.

Where it departs from the official code: the fit runs scipy's Levenberg-Marquardt iteration itself,
with the exact derivative instead of finite differences (the same result to float32 noise on a
well-posed map; on a nearly flat one, such as random weights give, within about 1e-3); pixels off
the mask get 0 (the official code writes inf); log-scale outputs are clamped at 40 before ``exp``,
so no finite input gives Inf or NaN.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from ...core.atomic import atomic_write, atomic_write_json
from .checkpoints import CONFIG_FILE, WEIGHTS_FILE, check_state, read_config
from .config import PATCH_SIZE
from .encoder import PatchEmbed
from .layers import Block

OFFICIAL_FILE = "model.pt"  # the published layout: {"model_config": dict, "model": state dict}
#: backbone name -> (width, depth, heads): the DINOv2 hub models MoGe builds (``*_reg``: 4 registers)
BACKBONES = {"dinov2_vits14": (384, 12, 6), "dinov2_vitb14": (768, 12, 12), "dinov2_vitl14": (1024, 24, 16)}
POS_GRID = 37  # the learned position grid: 518 / 14
LEVELS = 5  # neck levels: token grid x 1, 2, 4, 8, 16
MASK_THRESHOLD = 0.5
FIT_GRID = (64, 64)  # the subsample the focal and shift are fitted on
LM_TOL = (1e-3, 1e-8, 1e-8)  # the official fit's ftol (relative cost reduction), xtol and gtol
LM_STEP_BOUND, LM_EVALUATIONS = 100.0, 100  # MINPACK's initial trust region (``factor``), scipy's max_nfev
EXP_MAX = 40.0  # log-scale outputs are clamped here before exp, so no finite input overflows
#: constant buffers an old checkpoint may lack; they keep the ImageNet statistics then
OPTIONAL_KEYS = ("encoder.image_mean", "encoder.image_std")
REMAPS = ("linear", "sinh", "exp", "sinh_exp")
RESAMPLERS = ("conv_transpose", "bilinear", "nearest", "pixel_shuffle")
NORMS = ("group_norm", "layer_norm", "instance_norm", "none")
ACTIVATIONS = {"relu": nn.ReLU, "leaky_relu": functools.partial(nn.LeakyReLU, 0.2), "silu": nn.SiLU,
               "elu": nn.ELU}  # fmt: skip


# ---------------------------------------------------------------- configuration
def _positive_int(x) -> bool:
    return type(x) is int and x > 0


def _per_level(value, levels: int, what: str) -> tuple:
    """An official per-level setting (one value for all levels, or a list) as a tuple of ``levels``."""
    values = tuple(value) if isinstance(value, list | tuple) else (value,) * levels
    if len(values) != levels:
        raise ValueError(f"{what}: expected {levels} values, got {len(values)}")
    return values


@dataclass(frozen=True)
class ConvStackConfig:
    """One official ``ConvStack`` (the neck or a head): per level an optional 1x1 input conv
    (``dim_in``), residual conv blocks at ``dim_res_blocks`` channels, an optional 1x1 output conv
    (``dim_out``) and, between levels, a 2x upsampler (``resamplers``)."""

    dim_in: tuple[int | None, ...]
    dim_res_blocks: tuple[int, ...]
    dim_out: tuple[int | None, ...]
    resamplers: tuple[str, ...]
    num_res_blocks: tuple[int, ...]
    dim_times_res_block_hidden: int = 1
    res_block_in_norm: str = "layer_norm"
    res_block_hidden_norm: str = "group_norm"
    activation: str = "relu"

    @classmethod
    def from_dict(cls, d: dict, what: str) -> ConvStackConfig:
        d = {"num_res_blocks": 1, **d}  # the official default
        n = len(d["dim_res_blocks"])
        for key, levels in [("dim_in", n), ("dim_out", n), ("resamplers", n - 1), ("num_res_blocks", n)]:
            d[key] = _per_level(d[key], levels, f"{what}.{key}")
        d["dim_res_blocks"] = tuple(d["dim_res_blocks"])
        cfg = cls(**d)
        widths = [*cfg.dim_res_blocks, *(x for x in cfg.dim_in + cfg.dim_out if x is not None)]
        counts_ok = all(type(n) is int and n >= 0 for n in cfg.num_res_blocks)
        if not all(_positive_int(x) for x in widths) or not counts_ok:
            raise ValueError(f"{what}: widths must be positive integers, num_res_blocks non-negative ones")
        bad = [r for r in cfg.resamplers if r not in RESAMPLERS]
        bad += [x for x in (cfg.res_block_in_norm, cfg.res_block_hidden_norm) if x not in NORMS]
        bad += [] if cfg.activation in ACTIVATIONS else [cfg.activation]
        if bad:
            raise ValueError(f"{what}: unsupported settings {bad} (resamplers {RESAMPLERS}, norms {NORMS}, "
                             f"activations {tuple(ACTIVATIONS)})")  # fmt: skip
        return cfg

    def to_dict(self) -> dict:
        """The official form (lists per level)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


def _conv_stack_dict(dims: list[int], dim_in: list[int | None], dim_out: list[int | None] | None) -> dict:
    """An official ``ConvStack`` entry: the neck (``dim_out`` None) or a head."""
    return {"dim_in": dim_in, "dim_out": dim_out, "dim_res_blocks": dims, "num_res_blocks": [0, 2, 2, 2, 0]
            if dim_out is None else [0, 1, 1, 1, 0], "res_block_in_norm": "none", "res_block_hidden_norm": "none",
            "resamplers": ["conv_transpose"] * 3 + ["bilinear"]}  # fmt: skip


def model_config(backbone: str, dims: list[int], scale_dims: list[int], layers: int | list[int],
                 normal: bool = True) -> dict:  # fmt: skip
    """A ``model_config`` of the released MoGe-2 form (the official ``configs/train/v2.json``) with
    the given widths: ``dims`` the neck's and heads' channels per level (5), ``scale_dims`` the
    scale MLP's, ``layers`` the DINOv2 blocks taken. To build or time an architecture without its
    checkpoint (:data:`VITL_CONFIG`), or a small one for tests."""
    heads = {"points_head": 3, "mask_head": 1, **({"normal_head": 3} if normal else {})}
    return {
        "encoder": {"backbone": backbone, "intermediate_layers": layers, "dim_out": dims[0]},
        "neck": _conv_stack_dict(dims, [dims[0] + 2, 2, 2, 2, 2], None),
        **{name: _conv_stack_dict(dims, dims, [None] * 4 + [out]) for name, out in heads.items()},
        "scale_head": {"dims": scale_dims},
        "remap_output": "exp",
        "num_tokens_range": [1200, 3600],
    }


#: the released MoGe-2 ViT-L (moge-2-vitl-normal: 326M parameters), configs/train/v2.json
VITL_CONFIG = model_config("dinov2_vitl14", [1024, 256, 128, 64, 32], [1024, 1024, 1024, 1], [5, 11, 17, 23])


@dataclass(frozen=True)
class MoGe2Config:
    """A MoGe-2 architecture: :meth:`from_dict` of the ``model_config`` a checkpoint stores.

    Attributes:
        backbone: DINOv2 hub name, ``dinov2_vit{s,b,l}14`` with an optional ``_reg`` suffix.
        intermediate_layers: blocks whose tokens are taken (a list), or how many last blocks (an int).
        dim_proj: channels the taken tokens are projected to (the official ``encoder.dim_out``).
        neck, points_head, mask_head, normal_head: conv stacks; ``normal_head`` None when absent.
        scale_head: MLP widths, [cls] token -> log metric scale.
        remap_output: how the points head's output becomes points (MoGe-2: ``exp`` of z, xy * z).
        num_tokens_range: the token counts of resolution levels 0 and 9.
    """

    backbone: str
    intermediate_layers: int | tuple[int, ...]
    dim_proj: int
    neck: ConvStackConfig
    points_head: ConvStackConfig
    mask_head: ConvStackConfig
    scale_head: tuple[int, ...]
    normal_head: ConvStackConfig | None = None
    remap_output: str = "linear"
    num_tokens_range: tuple[int, int] = (1200, 3600)

    @property
    def width(self) -> int:
        return BACKBONES[self.backbone.removesuffix("_reg")][0]

    @property
    def depth(self) -> int:
        return BACKBONES[self.backbone.removesuffix("_reg")][1]

    @property
    def taken_blocks(self) -> tuple[int, ...]:
        n = self.intermediate_layers
        return tuple(range(self.depth - n, self.depth)) if isinstance(n, int) else n

    @classmethod
    def from_dict(cls, d: dict) -> MoGe2Config:
        """Build from the official ``model_config``; unknown keys are ignored with a warning, as
        the official constructor does; ``ValueError`` when it is not a MoGe-2 metric config."""
        if not isinstance(d, dict):
            raise ValueError(f"model_config: expected a dict, got {type(d).__name__}")  # noqa: TRY004
        known = {"encoder", "neck", "points_head", "mask_head", "normal_head", "scale_head", "remap_output",
                 "num_tokens_range"}  # fmt: skip
        if extra := sorted(set(d) - known):
            warnings.warn(f"model_config: ignoring unknown keys {extra}", stacklevel=2)
        required = ("encoder", "neck", "points_head", "mask_head", "scale_head")
        missing = [k for k in required if d.get(k) is None]
        if missing:
            raise ValueError(f"model_config: missing {missing} (not a MoGe-2 model with a metric scale head)")
        try:
            enc = d["encoder"]
            layers = enc["intermediate_layers"]
            cfg = cls(
                backbone=enc["backbone"],
                intermediate_layers=layers if isinstance(layers, int) else tuple(layers),
                dim_proj=enc["dim_out"],
                neck=ConvStackConfig.from_dict(d["neck"], "neck"),
                points_head=ConvStackConfig.from_dict(d["points_head"], "points_head"),
                mask_head=ConvStackConfig.from_dict(d["mask_head"], "mask_head"),
                normal_head=ConvStackConfig.from_dict(d["normal_head"], "normal_head") if d.get("normal_head")
                else None,
                scale_head=tuple(d["scale_head"]["dims"]),
                remap_output=d.get("remap_output", "linear"),
                num_tokens_range=tuple(d.get("num_tokens_range", (1200, 3600))),
            )  # fmt: skip
            cfg.check()
        except (KeyError, TypeError) as e:
            raise ValueError(f"model_config: malformed ({type(e).__name__}: {e})") from None
        return cfg

    def to_dict(self) -> dict:
        """The official ``model_config`` (what ``moge.model.v2.MoGeModel(**config)`` takes)."""
        layers = self.intermediate_layers
        d = {
            "encoder": {"backbone": self.backbone, "dim_out": self.dim_proj,
                        "intermediate_layers": layers if isinstance(layers, int) else list(layers)},
            "neck": self.neck.to_dict(), "points_head": self.points_head.to_dict(),
            "mask_head": self.mask_head.to_dict(), "scale_head": {"dims": list(self.scale_head)},
            "remap_output": self.remap_output, "num_tokens_range": list(self.num_tokens_range),
        }  # fmt: skip
        if self.normal_head is not None:
            d["normal_head"] = self.normal_head.to_dict()
        return d

    def check(self) -> None:
        """``ValueError`` naming what does not fit together."""
        problems = [] if _positive_int(self.dim_proj) else [f"encoder.dim_out {self.dim_proj!r} not positive"]
        if self.backbone.removesuffix("_reg") not in BACKBONES:
            raise ValueError(f"model_config: backbone {self.backbone!r} is not one of {sorted(BACKBONES)} "
                             "(optionally with '_reg')")  # fmt: skip
        taken = self.taken_blocks
        if not taken or not all(type(i) is int and 0 <= i < self.depth for i in taken):
            problems.append(f"intermediate_layers {self.intermediate_layers} outside the {self.depth} blocks")
        neck = self.neck
        if len(neck.dim_res_blocks) != LEVELS or neck.dim_in != (self.dim_proj + 2,) + (2,) * (LEVELS - 1):
            problems.append(f"neck: needs {LEVELS} levels with dim_in [dim_out + 2, 2, 2, 2, 2]")
        levels = tuple(o or r for o, r in zip(neck.dim_out, neck.dim_res_blocks, strict=True))
        heads = {"points_head": (self.points_head, 3), "mask_head": (self.mask_head, 1),
                 "normal_head": (self.normal_head, 3)}  # fmt: skip
        for name, (head, out) in heads.items():
            if head is None:
                continue
            widths = tuple(i or r for i, r in zip(head.dim_in, head.dim_res_blocks, strict=True))
            if len(head.dim_res_blocks) != LEVELS or widths != levels[: len(widths)]:
                problems.append(f"{name}: its {LEVELS} input widths must be the neck's outputs {levels}")
            elif (head.dim_out[-1] or head.dim_res_blocks[-1]) != out:
                problems.append(f"{name}: the last level must give {out} channels")
        dims = self.scale_head
        if len(dims) < 2 or dims[0] != self.width or dims[-1] != 1 or not all(map(_positive_int, dims)):
            problems.append(f"scale_head: dims must run from {self.width} to 1, got {list(self.scale_head)}")
        if self.remap_output not in REMAPS:
            problems.append(f"remap_output {self.remap_output!r} not one of {REMAPS}")
        lo_hi = self.num_tokens_range
        if len(lo_hi) != 2 or not 1 <= lo_hi[0] <= lo_hi[1]:
            problems.append(f"num_tokens_range {list(lo_hi)} must be [min, max] with 1 <= min <= max")
        if problems:
            raise ValueError("model_config: " + "; ".join(problems))


# ---------------------------------------------------------------- backbone
class DinoViT(nn.Module):
    """DINOv2 ViT/14 as MoGe builds it (``encoder.backbone``): learned 37x37 positions, LayerScale,
    no block chunks; ``mask_token`` is kept for the checkpoint's keys but unused."""

    def __init__(self, name: str):
        super().__init__()
        dim, depth, heads = BACKBONES[name.removesuffix("_reg")]
        self.registers = 4 if name.endswith("_reg") else 0
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + POS_GRID**2, dim))
        if self.registers:
            self.register_tokens = nn.Parameter(torch.zeros(1, self.registers, dim))
        self.mask_token = nn.Parameter(torch.zeros(1, dim))
        self.patch_embed = PatchEmbed(dim)
        self.blocks = nn.ModuleList(Block(dim, heads, 4.0, layerscale=1.0) for _ in range(depth))
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def position_embedding(self, h: int, w: int) -> torch.Tensor:
        """(1, 1 + h*w, dim): the grid resized bicubically; without registers by the scale
        (h + 0.1) / 37, (w + 0.1) / 37, with them to h x w, antialiased (DINOv2's two settings)."""
        if (h, w) == (POS_GRID, POS_GRID):
            return self.pos_embed
        pe = self.pos_embed.float()
        grid = pe[:, 1:].reshape(1, POS_GRID, POS_GRID, -1).permute(0, 3, 1, 2)
        if self.registers:
            grid = F.interpolate(grid, size=(h, w), mode="bicubic", antialias=True)
        else:
            scale = ((h + 0.1) / POS_GRID, (w + 0.1) / POS_GRID)
            grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=False)
        grid = grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)
        return torch.cat([pe[:, :1], grid], dim=1).to(self.pos_embed.dtype)

    def forward(self, x: torch.Tensor, taken: tuple[int, ...]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """x: (B, 3, 14h, 14w) normalised image -> per taken block, after the final norm,
        (patch tokens (B, h*w, dim), [cls] token (B, dim))."""
        B, _, H, W = x.shape
        t = torch.cat([self.cls_token.expand(B, -1, -1), self.patch_embed(x)], dim=1)
        t = t + self.position_embedding(H // PATCH_SIZE, W // PATCH_SIZE)
        if self.registers:
            t = torch.cat([t[:, :1], self.register_tokens.expand(B, -1, -1), t[:, 1:]], dim=1)
        out = []
        for i, blk in enumerate(self.blocks[: max(taken) + 1]):
            t = blk(t)
            if i in taken:
                n = self.norm(t)
                out.append((n[:, 1 + self.registers :], n[:, 0]))
        return out


class Encoder(nn.Module):
    """``encoder``: resize, ImageNet-normalise, DINOv2, sum of the taken blocks' 1x1 projections."""

    def __init__(self, cfg: MoGe2Config):
        super().__init__()
        self.taken = cfg.taken_blocks
        self.backbone = DinoViT(cfg.backbone)
        self.output_projections = nn.ModuleList(nn.Conv2d(cfg.width, cfg.dim_proj, 1) for _ in self.taken)
        self.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))

    def forward(self, image: torch.Tensor, rows: int, cols: int) -> tuple[torch.Tensor, torch.Tensor]:
        """image: (B, 3, H, W) in [0, 1] -> features (B, dim_proj, rows, cols), [cls] token (B, width)."""
        x = F.interpolate(image, (rows * PATCH_SIZE, cols * PATCH_SIZE), mode="bilinear", align_corners=False,
                          antialias=True)  # fmt: skip
        x = (x - self.image_mean) / self.image_std
        taken = self.backbone(x, self.taken)
        grids = [p.transpose(1, 2).unflatten(2, (rows, cols)).contiguous() for p, _ in taken]
        features = torch.stack([proj(g) for proj, g in zip(self.output_projections, grids, strict=True)], 1)
        return features.sum(dim=1), taken[-1][1]


# ---------------------------------------------------------------- conv neck and heads
def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "group_norm":
        return nn.GroupNorm(channels // 32, channels)
    if kind == "layer_norm":
        return nn.GroupNorm(1, channels)
    return nn.InstanceNorm2d(channels) if kind == "instance_norm" else nn.Identity()


def _conv3(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1, padding_mode="replicate")


class ResidualConvBlock(nn.Module):
    """x + (norm, act, conv 3x3, norm, act, conv 3x3)(x); replicate padding."""

    def __init__(self, dim: int, hidden: int, in_norm: str, hidden_norm: str, activation: str):
        super().__init__()
        act = ACTIVATIONS[activation]
        self.layers = nn.Sequential(
            _norm(in_norm, dim), act(), _conv3(dim, hidden),
            _norm(hidden_norm, hidden), act(), _conv3(hidden, dim),
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.layers(x)


def _upsampler(kind: str, cin: int, cout: int) -> nn.Sequential:
    """2x upsampling followed by a 3x3 conv (the official ``Resampler``'s upsampling kinds)."""
    if kind == "conv_transpose":
        return nn.Sequential(nn.ConvTranspose2d(cin, cout, 2, stride=2), _conv3(cout, cout))
    if kind == "pixel_shuffle":
        return nn.Sequential(_conv3(cin, 4 * cout), nn.PixelShuffle(2), _conv3(cout, cout))
    align = False if kind == "bilinear" else None
    return nn.Sequential(nn.Upsample(scale_factor=2, mode=kind, align_corners=align), _conv3(cin, cout))


class ConvStack(nn.Module):
    """Levels of residual conv blocks joined by 2x upsamplers; each level may add an input."""

    def __init__(self, cfg: ConvStackConfig):
        super().__init__()
        dims = cfg.dim_res_blocks

        def conv1(cin, cout):
            return nn.Identity() if cin is None or cout is None else nn.Conv2d(cin, cout, 1)

        self.input_blocks = nn.ModuleList(conv1(i, r) for i, r in zip(cfg.dim_in, dims, strict=True))
        self.resamplers = nn.ModuleList(
            _upsampler(k, a, b) for k, a, b in zip(cfg.resamplers, dims[:-1], dims[1:], strict=True)
        )
        block = functools.partial(
            ResidualConvBlock,
            in_norm=cfg.res_block_in_norm,
            hidden_norm=cfg.res_block_hidden_norm,
            activation=cfg.activation,
        )
        self.res_blocks = nn.ModuleList(
            nn.Sequential(*(block(r, cfg.dim_times_res_block_hidden * r) for _ in range(n)))
            for r, n in zip(dims, cfg.num_res_blocks, strict=True)
        )
        self.output_blocks = nn.ModuleList(conv1(r, o) for r, o in zip(dims, cfg.dim_out, strict=True))

    def forward(self, inputs: list[torch.Tensor | None]) -> list[torch.Tensor]:
        """inputs: per level (B, C_in, h * 2^l, w * 2^l) or None -> per level its output."""
        outs, x = [], None
        for level, (inp, res, out) in enumerate(zip(self.input_blocks, self.res_blocks, self.output_blocks)):
            if inputs[level] is not None:
                feature = inp(inputs[level])
                x = feature if x is None else x + feature
            x = res(x)
            outs.append(out(x))
            if level < len(self.resamplers):
                x = self.resamplers[level](x)
        return outs


def _mlp(dims: tuple[int, ...]) -> nn.Sequential:
    layers = [m for a, b in itertools.pairwise(dims[:-1]) for m in (nn.Linear(a, b), nn.ReLU())]
    return nn.Sequential(*layers, nn.Linear(dims[-2], dims[-1]))


# ---------------------------------------------------------------- geometry
def view_plane_uv(width: int, height: int, aspect: float, dtype=None, device=None) -> torch.Tensor:
    """(height, width, 2) pixel-centre view-plane coordinates in units of half the image diagonal:
    u spans +-aspect / sqrt(1 + aspect^2), v spans +-1 / sqrt(1 + aspect^2) (edges, not centres)."""
    diag = math.sqrt(1 + aspect**2)
    su, sv = aspect / diag * (width - 1) / width, 1 / diag * (height - 1) / height
    u = torch.linspace(-su, su, width, dtype=dtype, device=device)
    v = torch.linspace(-sv, sv, height, dtype=dtype, device=device)
    return torch.stack(torch.meshgrid(u, v, indexing="xy"), dim=-1)


def token_grid(height: int, width: int, num_tokens: int) -> tuple[int, int]:
    """(rows, cols) of about ``num_tokens`` patches with the image's aspect ratio (at least 1 x 1)."""
    aspect = width / height
    return max(1, round((num_tokens / aspect) ** 0.5)), max(1, round((num_tokens * aspect) ** 0.5))


def recover_focal_shift(
    points: torch.Tensor, mask: torch.Tensor | None = None, focal: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Focal and z shift that make an affine point map a centred pinhole projection.

    Minimises sum |focal * xy / (z + shift) - uv|^2 over the masked pixels of a nearest-neighbour
    64x64 subsample (uv: :func:`view_plane_uv`), the focal in closed form for each shift, the
    shift by :func:`_fit_shift` from 0.

    Args:
        points: (B, H, W, 3); mask: (B, H, W) bool or None; focal: (B,) known focal, or None.
    Returns:
        focal (B,), relative to half the image diagonal, and shift (B,), in ``points``' dtype;
        1 (or the known focal) and 0 for a map with fewer than two usable pixels or no finite fit.
    """
    _, H, W, _ = points.shape
    uv = view_plane_uv(W, H, W / H, dtype=points.dtype, device=points.device)
    p = F.interpolate(points.permute(0, 3, 1, 2), FIT_GRID, mode="nearest").flatten(2).transpose(1, 2)
    uv = F.interpolate(uv.permute(2, 0, 1)[None], FIT_GRID, mode="nearest").flatten(2).transpose(1, 2)[0]
    keep = p.isfinite().all(-1)
    if mask is not None:
        keep &= F.interpolate(mask[:, None].float(), FIT_GRID, mode="nearest")[:, 0].flatten(1) > 0
    focals, shifts = [], []
    for i in range(len(p)):
        known = None if focal is None else float(focal[i])
        f, s = (1.0 if known is None else known), 0.0
        if keep[i].sum() >= 2:
            pi, uvi = p[i][keep[i]].double(), uv[keep[i]].double()
            fit_f, fit_s = _fit_shift(pi[:, :2], pi[:, 2], uvi, known)
            if math.isfinite(fit_f) and math.isfinite(fit_s) and fit_f != 0:
                f, s = fit_f, fit_s
        focals.append(f)
        shifts.append(s)
    as_tensor = functools.partial(torch.tensor, dtype=points.dtype, device=points.device)
    return as_tensor(focals), as_tensor(shifts)


def _fit_shift(
    xy: torch.Tensor, z: torch.Tensor, uv: torch.Tensor, focal: float | None
) -> tuple[float, float]:
    """Least squares of r(s) = f(s) * xy / (z + s) - uv over the shift s, from s = 0: xy (N, 2),
    z (N,), uv (N, 2), float64; f(s) the known focal or the optimal one for s. Returns (f, s).

    Levenberg-Marquardt as MINPACK's ``lmdif`` runs it on one unknown (what the official
    ``least_squares(method="lm", ftol=1e-3)`` calls), with the exact Jacobian and a Jacobian-scaled
    trust region; it stops on the same relative-reduction, step and gradient tests (:data:`LM_TOL`),
    so an ill-posed fit (a fronto-parallel plane) stops early rather than running along its valley.
    """
    ftol, xtol, gtol = LM_TOL

    def residual(s: float):  # -> r (N, 2), f, d r / d s (N, 2)
        d = z + s
        q = xy / d[:, None]
        dq = -q / d[:, None]
        if focal is not None:
            return focal * q - uv, focal, focal * dq
        a, c = (q * uv).sum(), (q * q).sum()
        f = a / c
        df = ((dq * uv).sum() * c - a * 2 * (q * dq).sum()) / c**2
        return f * q - uv, float(f), f * dq + df * q

    s, delta, scale = 0.0, LM_STEP_BOUND, 0.0
    r, f, J = residual(s)
    fnorm, fresh = float(r.norm()), True  # fresh: J is the Jacobian at s, not yet tested
    for evaluation in range(LM_EVALUATIONS):
        if fresh:
            g, jj = float((J * r).sum()), float((J * J).sum())
            scale = max(scale, math.sqrt(jj))
            if not (fnorm > 0 and jj > 0 and math.isfinite(g)) or abs(g) <= gtol * math.sqrt(jj) * fnorm:
                break
            fresh = False
        # the Gauss-Newton step, damped to the trust region |scale * step| <= delta when longer
        par = 0.0 if scale * abs(g / jj) <= 1.1 * delta else (abs(g) * scale / delta - jj) / scale**2
        step = -g / (jj + par * scale**2)
        pnorm = scale * abs(step)
        delta = min(delta, pnorm) if evaluation == 0 else delta
        r1, f1, J1 = residual(s + step)
        fnorm1 = float(r1.norm()) if r1.isfinite().all() else math.inf  # a pixel on the camera plane
        actred = 1 - (fnorm1 / fnorm) ** 2 if 0.1 * fnorm1 < fnorm else -1.0
        t1, t2 = math.sqrt(jj) * abs(step) / fnorm, math.sqrt(par) * pnorm / fnorm
        prered, dirder = t1**2 + t2**2 / 0.5, -(t1**2 + t2**2)
        ratio = actred / prered if prered else 0.0
        if ratio <= 0.25:
            shrink = 0.5 if actred >= 0 else 0.5 * dirder / (dirder + 0.5 * actred)
            delta = (0.1 if 0.1 * fnorm1 >= fnorm or shrink < 0.1 else shrink) * min(delta, pnorm / 0.1)
        elif par == 0 or ratio >= 0.75:
            delta = pnorm / 0.5
        if ratio >= 1e-4:  # accept
            s, r, f, J, fnorm, fresh = s + step, r1, f1, J1, fnorm1, True
        if abs(actred) <= ftol and prered <= ftol and ratio <= 2 or delta <= xtol * scale * abs(s):
            break
    return f, s


def normalized_intrinsics(fx: torch.Tensor, fy: torch.Tensor) -> torch.Tensor:
    """(B,) focal lengths in image widths / heights -> (B, 3, 3) K with the principal point at (0.5, 0.5)."""
    K = torch.zeros(*fx.shape, 3, 3, dtype=fx.dtype, device=fx.device)
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2], K[..., 2, 2] = fx, fy, 0.5, 0.5, 1.0
    return K


def intrinsics_in_pixels(K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Normalised intrinsics (..., 3, 3) -> pixel units for a width x height image (pixel centres at
    +0.5, so the principal point 0.5 becomes width / 2, height / 2)."""
    scale = torch.tensor([width, height, 1.0], dtype=K.dtype, device=K.device)
    return K * scale[:, None]


def unproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """depth (B, H, W), normalised K (B, 3, 3) -> (B, H, W, 3) camera-frame points at the pixel centres."""
    B, H, W = depth.shape
    u = (torch.arange(W, dtype=depth.dtype, device=depth.device) + 0.5) / W
    v = (torch.arange(H, dtype=depth.dtype, device=depth.device) + 0.5) / H
    x = (u[None, None, :] - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]
    y = (v[None, :, None] - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]
    return torch.stack([x * depth, y * depth, depth.expand(B, H, W)], dim=-1)


# ---------------------------------------------------------------- the model
class MoGe2(nn.Module):
    """MoGe-2: one RGB image -> metric camera-frame points, depth, mask, intrinsics (and normals).

    ``forward`` is the network (affine point map, mask probability, normals, metric scale);
    ``infer`` adds the official post-processing. Load weights with :meth:`from_pretrained`.
    """

    def __init__(self, config: MoGe2Config):
        super().__init__()
        config.check()
        self.config = config
        self.encoder = Encoder(config)
        self.neck = ConvStack(config.neck)
        self.points_head = ConvStack(config.points_head)
        self.mask_head = ConvStack(config.mask_head)
        if config.normal_head is not None:
            self.normal_head = ConvStack(config.normal_head)
        self.scale_head = _mlp(config.scale_head)

    def num_tokens(self, resolution_level: int = 9) -> int:
        """The official token count of a resolution level 0..9, interpolated in ``num_tokens_range``."""
        if type(resolution_level) is not int or not 0 <= resolution_level <= 9:
            raise ValueError(f"MoGe2: resolution_level must be an integer 0..9, got {resolution_level!r}")
        lo, hi = self.config.num_tokens_range
        return int(lo + resolution_level / 9 * (hi - lo))

    def forward(self, images: torch.Tensor, num_tokens: int) -> dict[str, torch.Tensor]:
        """The network on images (B, 3, H, W) in [0, 1], at a grid of about ``num_tokens`` patches.

        Returns:
            points: (B, H, W, 3) affine-invariant point map (up to scale and z shift).
            mask: (B, H, W) validity probability.
            normal: (B, H, W, 3) unit normals, camera frame (only with a normal head).
            metric_scale: (B,) the factor that makes the points metric.
        """
        B, _, H, W = images.shape
        rows, cols = token_grid(H, W, num_tokens)
        features, cls = self.encoder(images, rows, cols)
        uv = [view_plane_uv(cols << i, rows << i, W / H, images.dtype, images.device) for i in range(LEVELS)]
        uv = [g.permute(2, 0, 1)[None].expand(B, -1, -1, -1) for g in uv]
        neck = self.neck([torch.cat([features, uv[0]], dim=1), *uv[1:]])

        def head(module):
            return F.interpolate(module(neck)[-1], (H, W), mode="bilinear", align_corners=False)

        out = {
            "points": self._remap(head(self.points_head).permute(0, 2, 3, 1)),
            "mask": head(self.mask_head)[:, 0].sigmoid(),
            "metric_scale": self.scale_head(cls)[:, 0].clamp(max=EXP_MAX).exp(),
        }
        if hasattr(self, "normal_head"):
            out["normal"] = F.normalize(head(self.normal_head).permute(0, 2, 3, 1), dim=-1)
        return out

    def _remap(self, p: torch.Tensor) -> torch.Tensor:
        kind = self.config.remap_output
        if kind == "linear":
            return p
        if kind == "sinh":
            return torch.sinh(p.clamp(-EXP_MAX, EXP_MAX))
        xy, z = p.split([2, 1], dim=-1)
        z = z.clamp(max=EXP_MAX).exp()
        xy = xy * z if kind == "exp" else torch.sinh(xy.clamp(-EXP_MAX, EXP_MAX))
        return torch.cat([xy, z], dim=-1)

    @torch.inference_mode()
    def infer(
        self,
        images: torch.Tensor,
        num_tokens: int | None = None,
        resolution_level: int = 9,
        fov_x: float | torch.Tensor | None = None,
        fp16: bool = False,
    ) -> dict[str, torch.Tensor]:
        """Metric geometry of images (B, 3, H, W), float in [0, 1].

        Args:
            num_tokens: ViT patches to use (the grid keeps the aspect ratio); by default the
                official choice for ``resolution_level`` (0..9: ``num_tokens_range`` interpolated,
                9 = the most), whatever the image size.
            fov_x: known horizontal field of view in degrees (a number or (B,)): only the shift is fitted.
            fp16: run the network under float16 autocast (the official default; for GPUs). The
                post-processing runs in float32 always.
        Returns (float32 unless noted):
            points: (B, H, W, 3) metric camera-frame points (OpenCV axes: x right, y down, z forward),
                the pixel centres unprojected at ``depth``; 0 where ``mask`` is False.
            depth: (B, H, W) metric z, > 0 where ``mask``, 0 elsewhere.
            mask: (B, H, W) bool: predicted valid (probability > 0.5) with positive finite depth.
            intrinsics: (B, 3, 3) normalised K: fx, fy in image widths / heights, principal point
                (0.5, 0.5), so a pixel centre (u + 0.5) / W, (v + 0.5) / H maps to x / z, y / z
                (pixel units: :func:`intrinsics_in_pixels`).
            fov_x, fov_y: (B,) field of view in degrees.
            metric_scale: (B,) the factor applied to the affine points.
            normal: (B, H, W, 3) unit normals, 0 where ``mask`` is False (with a normal head only).
        """
        images = self._check_images(images)
        B, _, H, W = images.shape
        if num_tokens is None:
            num_tokens = self.num_tokens(resolution_level)
        elif type(num_tokens) is not int or num_tokens < 1:
            raise ValueError(f"MoGe2: num_tokens must be a positive integer, got {num_tokens!r}")
        aspect, diag = W / H, math.sqrt(1 + (W / H) ** 2)
        known = None if fov_x is None else self._focal_from_fov(fov_x, aspect, B, images.device)
        with torch.autocast(images.device.type, dtype=torch.float16, enabled=fp16):
            raw = self.forward(images, num_tokens)
        raw = {k: v.float() for k, v in raw.items()}
        points, mask = raw["points"], raw["mask"] > MASK_THRESHOLD
        focal, shift = recover_focal_shift(points, mask, known)
        K = normalized_intrinsics(focal / 2 * diag / aspect, focal / 2 * diag)
        depth = points[..., 2] + shift[:, None, None]
        points = unproject(depth, K) * raw["metric_scale"][:, None, None, None]
        depth = depth * raw["metric_scale"][:, None, None]
        mask = mask & (depth > 0) & depth.isfinite() & points.isfinite().all(-1)
        out = {
            "points": torch.where(mask[..., None], points, 0.0),
            "depth": torch.where(mask, depth, 0.0),
            "mask": mask,
            "intrinsics": K,
            "fov_x": torch.rad2deg(2 * torch.atan(0.5 / K[:, 0, 0])),
            "fov_y": torch.rad2deg(2 * torch.atan(0.5 / K[:, 1, 1])),
            "metric_scale": raw["metric_scale"],
        }
        if "normal" in raw:
            out["normal"] = torch.where(mask[..., None], raw["normal"].nan_to_num(0.0), 0.0)
        return out

    def _check_images(self, images: torch.Tensor) -> torch.Tensor:
        """``ValueError`` unless a finite floating (B, 3, H, W) batch in [0, 1]; moved to the model."""
        if not isinstance(images, torch.Tensor):
            what = type(images).__name__
            raise ValueError(f"MoGe2: images must be a (B, 3, H, W) tensor, got {what}")  # noqa: TRY004
        if images.ndim != 4 or images.shape[1] != 3 or 0 in images.shape:
            shape = tuple(images.shape)
            raise ValueError(f"MoGe2: images must be a non-empty (B, 3, H, W) tensor, got {shape}")
        if not images.is_floating_point():
            raise ValueError(f"MoGe2: images must be floating point in [0, 1], got {images.dtype}")
        if not images.isfinite().all():
            raise ValueError("MoGe2: images hold NaN or Inf")
        lo, hi = images.min().item(), images.max().item()
        if lo < 0 or hi > 1:
            raise ValueError(f"MoGe2: images must lie in [0, 1] (clamp them), got values in [{lo:g}, {hi:g}]")
        param = self.scale_head[0].weight
        return images.to(device=param.device, dtype=param.dtype)

    @staticmethod
    def _focal_from_fov(fov_x, aspect: float, batch: int, device) -> torch.Tensor:
        """Horizontal FoV in degrees (number or (B,)) -> (B,) focal relative to half the diagonal."""
        fov = torch.as_tensor(fov_x, dtype=torch.float32, device=device).reshape(-1)
        if fov.numel() not in (1, batch) or not (fov.isfinite() & (fov > 0) & (fov < 180)).all():
            raise ValueError(f"MoGe2: fov_x must be one or {batch} angles in (0, 180) degrees, got {fov_x!r}")
        fov = fov.expand(batch)
        return aspect / math.sqrt(1 + aspect**2) / torch.tan(torch.deg2rad(fov) / 2)

    # ------------------------------------------------------------------ checkpoints
    def save_pretrained(self, folder: str | Path) -> Path:
        """Write ``config.json`` (``{"architecture": "moge-2", "model_config": <official config>}``)
        and ``model.safetensors`` (the official state dict), each atomically. Returns the folder."""
        folder = Path(folder)
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        atomic_write(folder / WEIGHTS_FILE, lambda tmp: save_file(state, tmp))
        meta = {"architecture": "moge-2", "licence": "MIT", "model_config": self.config.to_dict()}
        atomic_write_json(folder / CONFIG_FILE, meta)
        return folder

    @classmethod
    def from_pretrained(cls, folder: str | Path, device: str | torch.device = "cpu") -> MoGe2:
        """Load ``<folder>/config.json`` + ``model.safetensors`` (:meth:`save_pretrained`) or else the
        published ``<folder>/model.pt`` (``{"model_config": ..., "model": state dict}``, read with
        ``torch.load(weights_only=True)``). Every key must be there with its shape (but for
        :data:`OPTIONAL_KEYS`); ``ValueError`` names the missing, unexpected or mis-shaped ones.
        No download. Returns the model in eval mode."""
        folder = Path(folder).expanduser()
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: no such directory (a MoGe-2 checkpoint folder)")
        if (folder / WEIGHTS_FILE).is_file():
            source, config, state = _read_converted(folder)
        elif (folder / OFFICIAL_FILE).is_file():
            source = folder / OFFICIAL_FILE
            config, state = _read_official(source)
        else:
            raise FileNotFoundError(
                f"{folder}: holds neither {OFFICIAL_FILE} nor {CONFIG_FILE} + {WEIGHTS_FILE}"
            )
        try:
            model = cls(MoGe2Config.from_dict(config))
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from None
        check_state(model, state, source, "the MoGe-2 model of its config", OPTIONAL_KEYS)
        model.load_state_dict(state, strict=False)
        return model.to(device).eval()


def _read_converted(folder: Path) -> tuple[Path, dict, dict[str, torch.Tensor]]:
    config_file, weights_file = folder / CONFIG_FILE, folder / WEIGHTS_FILE
    if not config_file.is_file():
        raise FileNotFoundError(f"{config_file}: missing (it goes with {weights_file.name})")
    meta = read_config(config_file)
    if meta.get("architecture") != "moge-2" or not isinstance(meta.get("model_config"), dict):
        raise ValueError(
            f"{config_file}: not a MoGe-2 config (needs architecture 'moge-2' and a model_config)"
        )
    try:
        state = load_file(str(weights_file))
    except (SafetensorError, OSError) as e:
        raise ValueError(f"{weights_file}: not a readable safetensors file ({e})") from None
    return weights_file, meta["model_config"], state


def _read_official(path: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - pickle's, zip's and torch's errors: not a checkpoint
        raise ValueError(f"{path}: not a readable torch checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("model"), dict) or "model_config" not in ckpt:
        raise ValueError(f"{path}: not a MoGe checkpoint (expected a dict with 'model_config' and 'model')")
    if not all(isinstance(v, torch.Tensor) for v in ckpt["model"].values()):
        raise ValueError(f"{path}: 'model' is not a state dict of tensors")
    return ckpt["model_config"], ckpt["model"]


def is_moge_checkpoint(source: str | Path) -> bool:
    """Whether a folder holds a MoGe-2 checkpoint: the published ``model.pt`` or the
    ``config.json`` that :meth:`MoGe2.save_pretrained` writes (nothing is loaded)."""
    folder = Path(source).expanduser()
    if (folder / OFFICIAL_FILE).is_file():
        return True
    try:
        meta = json.loads((folder / CONFIG_FILE).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and meta.get("architecture") == "moge-2"
