"""Depth Anything 3 (DA3-Small, DA3-Base: Apache-2.0 weights): multi-view depth and cameras from RGB.

An own implementation of the any-view network of ByteDance-Seed/Depth-Anything-3
(``src/depth_anything_3/model/{da3,dualdpt,cam_dec,cam_enc}.py``, ``dinov2/``; configs
``da3-small.yaml``, ``da3-base.yaml``) whose module and parameter names are the published
checkpoint's keys: ``model.safetensors`` of ``depth-anything/DA3-SMALL`` / ``DA3-BASE`` loads
without renaming (the keys start with ``model.``, the attribute of their hub wrapper).

Network: a DINOv2 ViT/14 (no registers) whose blocks 0-3 attend within each view; from block
4 on, qk-norm and RoPE-2D are on, even blocks attend within a view and odd ones across all
views, and the [cls] token is replaced by a learned camera token (one for the reference view,
one shared by the others). With three or more views a reference view is chosen from the
[cls] tokens ("saddle_balanced") and moved first; outputs come back in input order. Blocks
5, 7, 9, 11 (their within-view features concatenated with the normalised cross-view ones)
feed a DPT head for depth and confidence; the last one's camera token feeds a small MLP for
the camera (translation, quaternion, field of view).

Depth is up to scale (not metric); poses are in the reference view's frame at that scale.
Not run: the ray branch of the head (``*_aux``: DA3's alternative pose path) and the camera
encoder (``cam_enc``: conditioning on known poses); their weights load and are kept.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from ...core.atomic import atomic_write, atomic_write_json
from ...core.rotations import quat_to_rotmat
from .checkpoints import CONFIG_FILE, WEIGHTS_FILE, check_state, resolve
from .config import PATCH_SIZE
from .encoder import PatchEmbed
from .layers import Block

#: name -> (ViT width, heads, DPT features, DPT stage channels), from configs/da3-*.yaml
PRESETS = {
    "da3-small": (384, 6, 64, (48, 96, 192, 384)),
    "da3-base": (768, 12, 128, (96, 192, 384, 768)),
}
DEPTH, ALT_START, OUT_LAYERS = 12, 4, (5, 7, 9, 11)  # alt_start = qknorm_start = rope_start = 4
POS_GRID = 37  # the learned position grid: 518 / 14
#: Checkpoint names of the one LayerNorm DualDPT's four aux levels share -> the name it is saved
#: under: the published files hold it once, under level 0 (safetensors' ``save_model`` drops
#: tied tensors), so the loader fills the other three from it.
TIED = {f"model.head.scratch.output_conv2_aux.{level}.2.{p}": f"model.head.scratch.output_conv2_aux.0.2.{p}"
        for level in (1, 2, 3) for p in ("weight", "bias")}  # fmt: skip
#: DA3's default inference size is a longest side of 504 pixels
DA3_MAX_PIXELS = 504 * 504


@dataclass(frozen=True)
class DA3Config:
    name: str = "da3-small"

    def __post_init__(self):
        if self.name not in PRESETS:
            raise ValueError(f"DA3Config: name must be one of {sorted(PRESETS)} (the Apache-2.0 models), "
                             f"got {self.name!r}")  # fmt: skip

    def to_dict(self) -> dict:
        """What identifies the model, with the licence of its published weights."""
        return {"architecture": "depth-anything-3", "name": self.name, "licence": "Apache-2.0"}


# ---------------------------------------------------------------- backbone
class ViT(nn.Module):
    """DA3's DINOv2 with camera tokens and alternating view / cross-view attention (``backbone.pretrained``)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.camera_token = nn.Parameter(torch.randn(1, 2, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + POS_GRID**2, dim))
        self.patch_embed = PatchEmbed(dim)
        self.blocks = nn.ModuleList(
            Block(
                dim,
                heads,
                4.0,
                layerscale=1.0,
                qk_norm=i >= ALT_START,
                rope_freq=100.0 if i >= ALT_START else None,
            )
            for i in range(DEPTH)
        )
        self.norm = nn.LayerNorm(dim)

    def position_embedding(self, h: int, w: int) -> torch.Tensor:
        """(1, 1 + h*w, dim): the grid resized bicubically by scale (h + 0.1) / 37, (w + 0.1) / 37."""
        if (h, w) == (POS_GRID, POS_GRID):
            return self.pos_embed
        pe = self.pos_embed.float()
        grid = pe[:, 1:].reshape(1, POS_GRID, POS_GRID, -1).permute(0, 3, 1, 2)
        scale = ((h + 0.1) / POS_GRID, (w + 0.1) / POS_GRID)
        grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", antialias=False)
        grid = grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)
        return torch.cat([pe[:, :1], grid], dim=1).to(self.pos_embed.dtype)

    def forward(self, x: torch.Tensor, views: int) -> tuple[list[torch.Tensor], torch.Tensor]:
        """x: (B*V, 3, H, W) normalised images.

        Returns four (B*V, h*w, 2*dim) patch features (blocks 5, 7, 9, 11: within-view tokens,
        normalised cross-view tokens) and the last one's (B, V, 2*dim) camera token, unnormalised.
        """
        n, _, H, W = x.shape
        B, V, h, w = n // views, views, H // PATCH_SIZE, W // PATCH_SIZE
        t = self.patch_embed(x)
        t = torch.cat([self.cls_token.expand(n, -1, -1), t], dim=1) + self.position_embedding(h, w)
        N, C = t.shape[1:]
        t = t.reshape(B, V, N, C)
        pos = _token_positions(h, w, x.device)  # (N, 2)
        local_pos, global_pos = pos[None], (pos > 0).to(pos).expand(V, -1, -1).reshape(1, V * N, 2)
        order, local, outs = None, t, []
        for i, blk in enumerate(self.blocks):
            if i == ALT_START - 1 and V >= 3:
                order = _reference_first(t[:, :, 0])
                t, local = _take(t, order), _take(local, order)
            if i == ALT_START:
                cam = torch.cat(
                    [self.camera_token[:, :1], self.camera_token[:, 1:].expand(-1, V - 1, -1)], dim=1
                )
                t = torch.cat([cam.expand(B, -1, -1)[:, :, None].to(t.dtype), t[:, :, 1:]], dim=2)
            rope = i >= ALT_START
            if i >= ALT_START and i % 2 == 1:
                t = blk(t.reshape(B, V * N, C), global_pos if rope else None).reshape(B, V, N, C)
            else:
                t = local = blk(t.reshape(B * V, N, C), local_pos if rope else None).reshape(B, V, N, C)
            if i in OUT_LAYERS:
                outs.append(torch.cat([local, t], dim=-1))
        if order is not None:
            outs = [_take(o, torch.argsort(order, dim=1)) for o in outs]
        camera = outs[-1][:, :, 0]
        feats = [
            torch.cat([o[..., :C], self.norm(o[..., C:])], dim=-1)[:, :, 1:].reshape(n, N - 1, 2 * C)
            for o in outs
        ]
        return feats, camera


class Backbone(nn.Module):
    """DA3's ``DinoV2`` wrapper: only holds the ViT as ``pretrained``."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.pretrained = ViT(dim, heads)


def _token_positions(h: int, w: int, device) -> torch.Tensor:
    """(1 + h*w, 2) RoPE (row, column) positions: 0 for the camera token, 1-based for patches."""
    rows, cols = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    patches = torch.stack([rows, cols], dim=-1).reshape(-1, 2) + 1
    return torch.cat([torch.zeros(1, 2, dtype=patches.dtype, device=device), patches])


def _reference_first(cls: torch.Tensor) -> torch.Tensor:
    """(B, V) view order with the "saddle_balanced" reference view first, the others in order.

    cls: (B, V, C) [cls] tokens. The reference is the view whose mean cosine similarity to the
    others, token norm and token variance are together closest to the middle of their ranges.
    """
    B, V, _ = cls.shape
    unit = cls / cls.norm(dim=-1, keepdim=True)
    sim = (unit @ unit.transpose(1, 2) - torch.eye(V, device=cls.device)).sum(-1) / (V - 1)

    def spread(m):
        lo, hi = m.min(dim=1, keepdim=True).values, m.max(dim=1, keepdim=True).values
        return ((m - lo) / (hi - lo + 1e-8) - 0.5).abs()

    ref = (spread(sim) + spread(cls.norm(dim=-1)) + spread(unit.var(dim=-1))).argmin(dim=1)  # (B,)
    idx = torch.arange(V, device=cls.device).expand(B, -1)
    order = torch.where((idx > 0) & (idx <= ref[:, None]), idx - 1, idx)
    order[:, 0] = ref
    return order


def _take(x: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """x: (B, V, ...) reordered along V by order (B, V)."""
    return x[torch.arange(x.shape[0], device=x.device)[:, None], order]


# ---------------------------------------------------------------- depth head (DualDPT)
class ResidualConvUnit(nn.Module):
    def __init__(self, features: int):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, 1, 1)
        self.conv2 = nn.Conv2d(features, features, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """(x + unit1(skip)) -> unit2 -> bilinear resize (align corners; default 2x) -> 1x1 conv."""

    def __init__(self, features: int, has_residual: bool = True):
        super().__init__()
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)
        self.out_conv = nn.Conv2d(features, features, 1)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None, size=None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        size = size or (2 * x.shape[-2], 2 * x.shape[-1])
        return self.out_conv(F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=True))


def _aux_out1(c: int) -> nn.Sequential:
    return nn.Sequential(
        *(nn.Conv2d(a, b, 3, 1, 1) for a, b in [(c, c // 2), (c // 2, c)] * 2 + [(c, c // 2)])
    )


class Permute(nn.Module):
    def __init__(self, *dims: int):
        super().__init__()
        self.dims = dims

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.permute(*self.dims)


class DualDPT(nn.Module):
    """DPT over four token stages -> depth (exp) and confidence (exp + 1) at full resolution.

    The ``*_aux`` modules (the ray branch, 7 channels at 8x the patch grid) are built for the
    checkpoint's keys but not run: the camera comes from ``cam_dec``, as in DA3's default.
    """

    def __init__(self, dim_in: int, features: int, out_channels: tuple[int, ...]):
        super().__init__()
        c = out_channels
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, oc, 1) for oc in c)
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(c[0], c[0], 4, 4), nn.ConvTranspose2d(c[1], c[1], 2, 2), nn.Identity(),
            nn.Conv2d(c[3], c[3], 3, 2, 1),
        ])  # fmt: skip
        s = self.scratch = nn.Module()
        for i, oc in enumerate(c, start=1):
            setattr(s, f"layer{i}_rn", nn.Conv2d(oc, features, 3, 1, 1, bias=False))
        for suffix in ("", "_aux"):
            for i in range(1, 5):
                setattr(s, f"refinenet{i}{suffix}", FusionBlock(features, has_residual=i < 4))
        s.output_conv1 = nn.Conv2d(features, features // 2, 3, 1, 1)
        s.output_conv2 = nn.Sequential(nn.Conv2d(features // 2, 32, 3, 1, 1), nn.ReLU(), nn.Conv2d(32, 2, 1))
        s.output_conv1_aux = nn.ModuleList(_aux_out1(features) for _ in range(4))
        norm = nn.LayerNorm(32)  # one LayerNorm for the four levels, as in DA3 (see TIED)
        s.output_conv2_aux = nn.ModuleList(
            nn.Sequential(nn.Conv2d(features // 2, 32, 3, 1, 1), Permute(0, 2, 3, 1), norm,
                          Permute(0, 3, 1, 2), nn.ReLU(), nn.Conv2d(32, 7, 1))
            for _ in range(4)
        )  # fmt: skip

    def forward(self, feats: list[torch.Tensor], h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        """feats: four (N, h*w, dim_in) -> depth (N, 14h, 14w) and confidence (N, 14h, 14w), >= 1."""
        H, W = h * PATCH_SIZE, w * PATCH_SIZE
        s, levels = self.scratch, []
        for i, f in enumerate(feats):
            x = self.norm(f).transpose(1, 2).reshape(f.shape[0], -1, h, w)
            x = _add_uv_embedding(self.projects[i](x), W / H)
            levels.append(getattr(s, f"layer{i + 1}_rn")(self.resize_layers[i](x)))
        l1, l2, l3, l4 = levels
        x = s.refinenet4(l4, size=l3.shape[2:])
        x = s.refinenet3(x, l3, size=l2.shape[2:])
        x = s.refinenet2(x, l2, size=l1.shape[2:])
        x = s.output_conv1(s.refinenet1(x, l1))
        x = F.interpolate(x, size=(H, W), mode="bilinear", align_corners=True)
        out = s.output_conv2(_add_uv_embedding(x, W / H))
        return torch.exp(out[:, 0]), torch.exp(out[:, 1]) + 1


def _add_uv_embedding(x: torch.Tensor, aspect: float) -> torch.Tensor:
    """x (N, C, h, w) + 0.1 * sin-cos embedding (frequencies 100^(-k/(C/4))) of the pixel-centre
    UV grid, which spans the image diagonal-normalised (u in +-aspect/diag, v in +-1/diag)."""
    C, h, w = x.shape[1:]
    diag = (aspect**2 + 1) ** 0.5
    u = torch.linspace(-1, 1, w, device=x.device) * (aspect / diag) * (w - 1) / w
    v = torch.linspace(-1, 1, h, device=x.device) * (1 / diag) * (h - 1) / h
    omega = 100.0 ** -(torch.arange(C // 4, device=x.device, dtype=torch.float32) / (C // 4))

    def sincos(p):  # (n,) -> (n, C/2)
        a = p[:, None] * omega
        return torch.cat([a.sin(), a.cos()], dim=-1)

    emb = torch.cat([sincos(u)[None].expand(h, -1, -1), sincos(v)[:, None].expand(-1, w, -1)], dim=-1)
    return x + 0.1 * emb.permute(2, 0, 1).to(x.dtype)


# ---------------------------------------------------------------- cameras
class CameraDec(nn.Module):
    """Camera token (N, dim_in) -> pose encoding (N, 9): translation, quaternion x-y-z-w, fov (h, w)."""

    def __init__(self, dim_in: int):
        super().__init__()
        self.backbone = nn.Sequential(
            nn.Linear(dim_in, dim_in), nn.ReLU(), nn.Linear(dim_in, dim_in), nn.ReLU()
        )
        self.fc_t = nn.Linear(dim_in, 3)
        self.fc_qvec = nn.Linear(dim_in, 4)
        self.fc_fov = nn.Sequential(nn.Linear(dim_in, 2), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.backbone(x)
        return torch.cat([self.fc_t(x), self.fc_qvec(x), self.fc_fov(x)], dim=-1)


class PoseBranch(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.fc1 = nn.Linear(9, dim // 2)
        self.fc2 = nn.Linear(dim // 2, dim)


class CameraEnc(nn.Module):
    """DA3's encoder of known cameras into camera tokens; its weights are kept, it is not run."""

    def __init__(self, dim: int):
        super().__init__()
        self.trunk = nn.Sequential(*(Block(dim, 16, 4.0, layerscale=0.01) for _ in range(4)))
        self.token_norm = nn.LayerNorm(dim)
        self.trunk_norm = nn.LayerNorm(dim)
        self.pose_branch = PoseBranch(dim)


class DA3Net(nn.Module):
    """DA3's ``DepthAnything3Net``: ``backbone``, ``head``, ``cam_dec``, ``cam_enc``."""

    def __init__(self, name: str):
        super().__init__()
        dim, heads, features, out_channels = PRESETS[name]
        self.backbone = Backbone(dim, heads)
        self.head = DualDPT(2 * dim, features, out_channels)
        self.cam_dec = CameraDec(2 * dim)
        self.cam_enc = CameraEnc(dim)


# ---------------------------------------------------------------- the model
class DepthAnything3(nn.Module):
    """DA3-Small / DA3-Base: images -> per-view depth (up to scale), confidence, cameras.

    ``model`` holds the network under the published checkpoint's key names. Example:
        >>> m = DepthAnything3(DA3Config("da3-small")).eval()
        >>> out = m(torch.rand(1, 2, 3, 28, 42))
        >>> out["depth"].shape, out["camera_poses"].shape, out["intrinsics"].shape
        (torch.Size([1, 2, 28, 42]), torch.Size([1, 2, 4, 4]), torch.Size([1, 2, 3, 3]))
    """

    max_pixels = DA3_MAX_PIXELS

    def __init__(self, config: DA3Config | None = None):
        super().__init__()
        self.config = config or DA3Config()
        self.model = DA3Net(self.config.name)
        mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
        self.register_buffer("image_mean", mean.view(1, 3, 1, 1), persistent=False)
        self.register_buffer("image_std", std.view(1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        """
        Args:
            images: (B, V, 3, H, W) in [0, 1]; H and W multiples of 14.
        Returns:
            depth: (B, V, H, W) > 0, up to one scale shared by the views and the translations.
            depth_conf: (B, V, H, W) >= 1 (DA3's confidence); conf: (B, V, H, W) its logit,
                log(depth_conf - 1), so sigmoid(conf) = 1 - 1 / depth_conf.
            camera_poses: (B, V, 4, 4) camera-to-world, OpenCV axes, the reference view's frame.
            intrinsics: (B, V, 3, 3) pinhole, principal point at the image centre.
            local_points: (B, V, H, W, 3) camera-frame points: pixel centres unprojected to depth.
        The head and the camera decoder run in float32 even under autocast.
        """
        if (
            images.ndim != 5
            or images.shape[2] != 3
            or images.shape[-1] % PATCH_SIZE
            or images.shape[-2] % PATCH_SIZE
        ):
            raise ValueError(f"DepthAnything3: images must be (B, V, 3, H, W), H and W multiples of {PATCH_SIZE}, "
                             f"got {tuple(images.shape)}")  # fmt: skip
        B, V, _, H, W = images.shape
        x = ((images - self.image_mean) / self.image_std).reshape(B * V, 3, H, W)
        feats, camera = self.model.backbone.pretrained(x, V)
        with torch.autocast(images.device.type, enabled=False):
            depth, conf = self.model.head([f.float() for f in feats], H // PATCH_SIZE, W // PATCH_SIZE)
            c2w, K = pose_encoding_to_cameras(self.model.cam_dec(camera.float()), H, W)
            local = unproject(depth, K.reshape(B * V, 3, 3))

        def per_view(t):
            return t.reshape(B, V, *t.shape[1:])

        return {
            "depth": per_view(depth), "depth_conf": per_view(conf), "conf": per_view(torch.log(conf - 1)),
            "camera_poses": c2w, "intrinsics": K, "local_points": per_view(local),
        }  # fmt: skip

    # ------------------------------------------------------------------ checkpoints
    def save_pretrained(self, directory: str | Path) -> Path:
        """Write the published layout: ``config.json`` (``{"model_name": ...}``) and ``model.safetensors``
        (the shared LayerNorm once, as the hub's files hold it: :data:`TIED`)."""
        directory = Path(directory)
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items() if k not in TIED}
        atomic_write(directory / WEIGHTS_FILE, lambda tmp: save_file(state, tmp))
        atomic_write_json(directory / CONFIG_FILE, {"model_name": self.config.name})
        return directory

    @classmethod
    def from_pretrained(cls, source: str | Path, device: str | torch.device = "cpu") -> DepthAnything3:
        """Load a DA3-Small / DA3-Base checkpoint: a directory with the published ``config.json``
        and ``model.safetensors``, or a hub id such as ``depth-anything/DA3-SMALL`` (needs
        huggingface_hub). Every key must be present with its shape, but for the tied names of
        :data:`TIED`, filled from the tensor they alias. Returns the model in eval mode."""
        path = resolve(source)
        config_file, weights_file = path / CONFIG_FILE, path / WEIGHTS_FILE
        for f in (config_file, weights_file):
            if not f.is_file():
                raise FileNotFoundError(
                    f"{f}: missing (a DA3 checkpoint has {CONFIG_FILE} and {WEIGHTS_FILE})"
                )
        model = cls(DA3Config(_model_name(config_file)))
        try:
            state = load_file(str(weights_file))
        except (SafetensorError, OSError) as e:
            raise ValueError(f"{weights_file}: not a readable safetensors file ({e})") from None
        for name, alias in TIED.items():
            if name not in state and alias in state:
                state[name] = state[alias]
            elif name in state and alias in state and not torch.equal(state[name], state[alias]):
                raise ValueError(f"{weights_file}: {name} differs from {alias}; DA3 shares one LayerNorm there")
        check_state(model, state, weights_file, model.config.name)
        model.load_state_dict(state)
        return model.to(device).eval()


def _model_name(config_file: Path) -> str:
    try:
        meta = json.loads(config_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{config_file}: not valid JSON ({e})") from None
    name = meta.get("model_name") if isinstance(meta, dict) else None
    if name not in PRESETS:
        raise ValueError(f"{config_file}: model_name {name!r} is not one of {sorted(PRESETS)} (the DA3 models with "
                         "Apache-2.0 weights; the larger ones are CC BY-NC and not supported)")  # fmt: skip
    return name


def is_da3_checkpoint(source: str | Path) -> bool:
    """Whether a checkpoint directory / hub id holds a Depth Anything 3 model (its config names one)."""
    try:
        meta = json.loads((resolve(source) / CONFIG_FILE).read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return False
    return isinstance(meta, dict) and str(meta.get("model_name", "")).startswith("da3")


def pose_encoding_to_cameras(enc: torch.Tensor, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, V, 9) pose encodings -> (B, V, 4, 4) camera-to-world and (B, V, 3, 3) intrinsics.

    Translation, quaternion x-y-z-w (normalised here), vertical and horizontal field of view:
    f = (size / 2) / tan(fov / 2), principal point at the image centre.
    """
    R = quat_to_rotmat(enc[..., [6, 3, 4, 5]])
    c2w = torch.zeros(*enc.shape[:-1], 4, 4, device=enc.device, dtype=enc.dtype)
    c2w[..., :3, :3], c2w[..., :3, 3], c2w[..., 3, 3] = R, enc[..., :3], 1.0
    fy = (H / 2) / torch.tan(enc[..., 7] / 2).clamp_min(1e-6)
    fx = (W / 2) / torch.tan(enc[..., 8] / 2).clamp_min(1e-6)
    K = torch.zeros_like(c2w[..., :3, :3])
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2], K[..., 2, 2] = fx, fy, W / 2, H / 2, 1.0
    return c2w, K


def unproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """depth (N, H, W), intrinsics (N, 3, 3) -> (N, H, W, 3) camera-frame points at the pixel centres."""
    H, W = depth.shape[1:]
    v, u = torch.meshgrid(torch.arange(H, device=depth.device) + 0.5, torch.arange(W, device=depth.device) + 0.5,
                          indexing="ij")  # fmt: skip
    x = (u - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]
    y = (v - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]
    return torch.stack([x * depth, y * depth, depth], dim=-1)
