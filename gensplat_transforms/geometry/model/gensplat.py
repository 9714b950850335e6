"""The feed-forward GenSplat model: uncalibrated views in, cameras, point maps and Gaussians out.

Pi3's architecture (its state-dict keys, unchanged) plus a DPT Gaussian head under
``gaussian_head.``. Poses live in a frame the model chooses from the set of views, not from
their order: there is no reference view, and permuting the input views permutes every output.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from safetensors.torch import save_file
from torch import nn

from ...core.atomic import atomic_write, atomic_write_json
from ...core.gaussians import Gaussians
from ...core.rotations import rotmat_to_quat
from ...core.sh import rgb_to_sh_dc
from .checkpoints import (
    CONFIG_FILE,
    FORMAT_NAME,
    FORMAT_VERSION,
    WEIGHTS_FILE,
    check_pi3_file,
    load_pi3_weights,
    read_config,
    read_weights,
    resolve,
)
from .config import PATCH_SIZE, ModelConfig, check_max_pixels
from .decoder import Decoder, token_positions
from .encoder import Encoder
from .frames import quat_mul, sh_rotation
from .gaussian_head import GaussianHead
from .heads import CameraHead, HeadDecoder, PixelHead

#: the most pixels per view Pi3's own image loaders feed it (its ``PIXEL_LIMIT``)
PI3_MAX_PIXELS = 255_000


class GenSplatModel(nn.Module):
    """Pi3 geometry (encoder, equivariant decoder, point / confidence / camera heads) + Gaussian head.

    ``max_pixels``: the most pixels per view the checkpoint was trained to see (its
    ``config.json``'s ``max_pixels``; ``PI3_MAX_PIXELS`` for a Pi3 checkpoint), None where
    unknown. The geometry reconstructor shrinks its input to it: the depth of a model run on
    many more pixels than it was trained at can be far worse (``benchmarks/geometry_resolution.py``).
    """

    max_pixels: int | None = None

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = cfg = config
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)
        self.register_token = nn.Parameter(torch.zeros(1, 1, cfg.dec_registers, cfg.dim))

        self.point_decoder = HeadDecoder(2 * cfg.dim, cfg.head_out_dim, cfg)
        self.point_head = PixelHead(cfg.head_out_dim, 3)
        self.conf_decoder = HeadDecoder(2 * cfg.dim, cfg.head_out_dim, cfg)
        self.conf_head = PixelHead(cfg.head_out_dim, 1)
        self.camera_decoder = HeadDecoder(2 * cfg.dim, cfg.camera_dim, cfg)
        self.camera_head = CameraHead(cfg.camera_dim)
        self.register_buffer("image_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("image_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))
        self.gaussian_head = GaussianHead(cfg.dim, cfg.gs_features, cfg.gs_rgb_features, cfg.sh_degree)
        self._init_weights()

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)
        nn.init.trunc_normal_(self.encoder.pos_embed, std=0.02)
        for p in (self.encoder.cls_token, self.encoder.register_tokens, self.register_token):
            nn.init.normal_(p, std=1e-6)

    def set_gradient_checkpointing(self, enabled: bool = True) -> None:
        """Recompute transformer-block activations in the backward pass (less memory, ~30% slower)."""
        for m in self.modules():
            if isinstance(m, Encoder | Decoder | HeadDecoder):
                m.checkpointing = enabled

    def forward(self, images: torch.Tensor, gaussians: bool = True) -> dict[str, torch.Tensor]:
        """
        Args:
            images: (B, V, 3, H, W) in [0, 1]; H and W multiples of 14.
            gaussians: run the Gaussian head; False returns the geometry alone (camera_poses,
                local_points, points, conf: what a depth cache keeps) without its cost.
        Returns:
            camera_poses: (B, V, 4, 4) camera-to-world, OpenCV axes.
            local_points: (B, V, H, W, 3) camera-frame points, z > 0.
            points: (B, V, H, W, 3) world points R P + T (the Gaussian centres).
            conf: (B, V, H, W) confidence logits (sigmoid -> [0, 1], higher is better).
            opacity: (B, V, H, W); quats: (B, V, H, W, 4) w-x-y-z, world frame;
            scales: (B, V, H, W, 3); sh: (B, V, H, W, K, 3) world frame, K = (sh_degree + 1)^2.
        The heads run in float32 even under autocast.
        """
        B, V, H, W = _check_images(images)
        h, w, r = H // PATCH_SIZE, W // PATCH_SIZE, self.config.dec_registers
        x = ((images - self.image_mean) / self.image_std).reshape(B * V, 3, H, W)
        tokens = self.encoder(x).reshape(B, V, h * w, -1)
        tokens = torch.cat([self.register_token.expand(B, V, -1, -1).to(tokens.dtype), tokens], dim=2)
        pos = token_positions(h, w, r, device=images.device)
        depth, taps = self.config.dec_depth, self.config.gs_taps
        outs = self.decoder(tokens, pos, keep={depth - 2, depth - 1, *(taps if gaussians else ())})
        hidden = torch.cat([outs[depth - 2], outs[depth - 1]], dim=-1).reshape(B * V, h * w + r, -1)
        point_tokens = self.point_decoder(hidden, pos)[:, r:]
        conf_tokens = self.conf_decoder(hidden, pos)[:, r:]
        camera_tokens = self.camera_decoder(hidden, pos)[:, r:]

        with torch.autocast(images.device.type, enabled=False):
            xy, z = self.point_head(point_tokens.float(), h, w).split([2, 1], dim=-1)
            z = torch.exp(z)
            local = torch.cat([xy * z, z], dim=-1)
            conf = self.conf_head(conf_tokens.float(), h, w)[..., 0]
            poses = self.camera_head(camera_tokens.float())
            points = torch.einsum("nij,nhwj->nhwi", poses[:, :3, :3], local) + poses[:, None, None, :3, 3]

        def per_view(t):
            return t.reshape(B, V, *t.shape[1:])

        geometry = {"camera_poses": per_view(poses), "local_points": per_view(local), "points": per_view(points),
                    "conf": per_view(conf)}  # fmt: skip
        if not gaussians:
            return geometry
        with torch.autocast(images.device.type, enabled=False):
            gs = self.gaussian_head(
                [outs[i][:, :, r:].reshape(B * V, h * w, -1).float() for i in taps], x.float(), h, w
            )
            # head outputs are in the camera frame: rotate orientations and SH colour into the world
            quats = quat_mul(rotmat_to_quat(poses[:, :3, :3])[:, None, None], gs["quats"])
            sh = gs["sh"]
            if sh.shape[-2] > 1:
                sh = torch.einsum("nkj,nhwjc->nhwkc", sh_rotation(poses[:, :3, :3], sh.shape[-2]), sh)
            rgb = images.reshape(B * V, 3, H, W).float().permute(0, 2, 3, 1)
            sh = torch.cat([sh[..., :1, :] + rgb_to_sh_dc(rgb)[..., None, :], sh[..., 1:, :]], dim=-2)
        return geometry | {"opacity": per_view(gs["opacity"]), "quats": per_view(quats),
                           "scales": per_view(gs["scales"]), "sh": per_view(sh)}  # fmt: skip

    # ------------------------------------------------------------------ checkpoints
    def save_pretrained(self, directory: str | Path) -> Path:
        """Write ``config.json`` and ``model.safetensors`` into ``directory`` (created if needed)."""
        directory = Path(directory)
        meta = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "config": self.config.to_dict()}
        if self.max_pixels is not None:
            meta["max_pixels"] = self.max_pixels
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        atomic_write(directory / WEIGHTS_FILE, lambda tmp: save_file(state, tmp, metadata={"format": FORMAT_NAME}))
        atomic_write_json(directory / CONFIG_FILE, meta)
        return directory

    @classmethod
    def from_pretrained(cls, source: str | Path, device: str | torch.device = "cpu") -> GenSplatModel:
        """Load a directory written by :meth:`save_pretrained`, or a Pi3 checkpoint directory
        (Pi3's config.json + model.safetensors: full size, Gaussian head untrained), or a hub id
        ``owner/name`` of either (needs huggingface_hub). Returns the model in eval mode."""
        path = resolve(source)
        if not (path / CONFIG_FILE).is_file() or not (path / WEIGHTS_FILE).is_file():
            raise FileNotFoundError(f"{path}: needs {CONFIG_FILE} and {WEIGHTS_FILE}")
        meta = read_config(path / CONFIG_FILE)
        if meta.get("format") == FORMAT_NAME:
            if meta.get("format_version") != FORMAT_VERSION:
                raise ValueError(
                    f"{path}: format version {meta.get('format_version')} is not {FORMAT_VERSION}"
                )
            try:
                config = ModelConfig.from_dict(meta.get("config"))
            except ValueError as e:
                raise ValueError(f"{path / CONFIG_FILE}: {e}") from None
            with torch.device("meta"):  # the shapes, checked against the file before anything is allocated
                shapes = {k: v.shape for k, v in cls(config).state_dict().items()}
            state = read_weights(path / WEIGHTS_FILE, shapes)
            model = cls(config)
            model.load_state_dict(state)
            check_max_pixels(str(path / CONFIG_FILE), meta.get("max_pixels"))
            model.max_pixels = meta.get("max_pixels")
        elif meta.get("decoder_size", "large") == "large" and meta.get("pos_type", "rope100") == "rope100":
            with torch.device("meta"):  # the shapes, checked against the file's header before 4 GB are allocated
                check_pi3_file(path / WEIGHTS_FILE, {k: v.shape for k, v in cls(ModelConfig.full()).state_dict().items()})
            model = cls(ModelConfig.full())
            model.max_pixels = PI3_MAX_PIXELS
            report = load_pi3_weights(model, path / WEIGHTS_FILE)
            warnings.warn(f"{path}: Pi3 checkpoint, {report}", stacklevel=2)
        else:
            raise ValueError(f"{path}: unsupported checkpoint config {meta}")
        return model.to(device).eval()


def to_gaussians(
    outputs: dict[str, torch.Tensor], index: int = 0, min_conf: float | None = None
) -> Gaussians:
    """One sample's pixel-aligned Gaussians from :meth:`GenSplatModel.forward` outputs.

    Args:
        outputs: the forward outputs.
        index: which batch element.
        min_conf: keep only pixels with sigmoid(conf) >= min_conf (None keeps all V*H*W).
    """
    k = outputs["sh"].shape[-2]
    g = Gaussians(
        means=outputs["points"][index].reshape(-1, 3),
        quats=outputs["quats"][index].reshape(-1, 4),
        scales=outputs["scales"][index].reshape(-1, 3),
        opacities=outputs["opacity"][index].reshape(-1),
        sh=outputs["sh"][index].reshape(-1, k, 3),
    )
    if min_conf is None:
        return g
    return g[torch.sigmoid(outputs["conf"][index]).reshape(-1) >= min_conf]


def _check_images(images: torch.Tensor) -> tuple[int, int, int, int]:
    if images.ndim != 5 or images.shape[2] != 3:
        raise ValueError(f"GenSplatModel: images must be (B, V, 3, H, W), got {tuple(images.shape)}")
    B, V, _, H, W = images.shape
    if B == 0 or V == 0 or H == 0 or W == 0 or H % PATCH_SIZE or W % PATCH_SIZE:
        raise ValueError(
            f"GenSplatModel: need B, V >= 1 and H, W positive multiples of {PATCH_SIZE}, got "
            f"B={B}, V={V}, H={H}, W={W} (resize or crop to e.g. "
            f"{max(1, round(H / PATCH_SIZE)) * PATCH_SIZE}x{max(1, round(W / PATCH_SIZE)) * PATCH_SIZE})"
        )
    if not images.is_floating_point():
        raise ValueError(f"GenSplatModel: images must be float in [0, 1], got {images.dtype}")
    return B, V, H, W
