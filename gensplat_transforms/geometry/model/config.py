"""Sizes of the GenSplat model: ``full`` loads the official Pi3 checkpoint, ``small`` runs on a CPU."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

PATCH_SIZE = 14  # ViT/14: input height and width must be multiples of this
MAX_DEPTH, MAX_WIDTH = 256, 1 << 14  # beyond any real model: a config.json asking for more is refused


def check_max_pixels(owner: str, max_pixels: int | None) -> None:
    """Raise ValueError naming ``owner`` unless ``max_pixels`` is None or an integer of at
    least one patch (a cap on the pixels per view a model sees)."""
    if max_pixels is not None and (type(max_pixels) is not int or max_pixels < PATCH_SIZE**2):
        raise ValueError(f"{owner}: max_pixels must be an integer >= {PATCH_SIZE**2} (one patch), got {max_pixels!r}")


@dataclass(frozen=True)
class ModelConfig:
    """Architecture hyper-parameters. The defaults are the full (Pi3-compatible) size.

    Attributes:
        dim: token width of the encoder and the main decoder (Pi3 has no projection between them).
        mlp_ratio: MLP hidden width / token width, in every transformer block.
        enc_depth, enc_heads: DINOv2 encoder blocks and attention heads.
        enc_registers: DINOv2 register tokens (dropped from the encoder output).
        enc_pos_grid: side of the learned position-embedding grid (37 = 518 / 14 for DINOv2);
            other patch grids interpolate it bicubically.
        enc_layerscale: LayerScale initial value in the encoder.
        dec_depth, dec_heads: main decoder blocks (even: within a frame, odd: across frames).
        dec_registers: register tokens shared by every frame (Pi3's ``register_token``).
        dec_layerscale: LayerScale initial value in the main decoder.
        rope_freq: RoPE-2D base frequency.
        head_dim, head_depth, head_heads: the point / confidence / camera decoders.
        head_out_dim: output width of the point and confidence decoders.
        camera_dim: output width of the camera decoder, width of the camera head.
        gs_taps: four main-decoder block indices whose outputs feed the Gaussian head.
        gs_features: DPT feature channels of the Gaussian head.
        gs_rgb_features: channels of the shallow full-resolution RGB features.
        sh_degree: spherical-harmonics degree of the predicted colour (0..4).
    """

    dim: int = 1024
    mlp_ratio: float = 4.0
    enc_depth: int = 24
    enc_heads: int = 16
    enc_registers: int = 4
    enc_pos_grid: int = 37
    enc_layerscale: float = 1.0
    dec_depth: int = 36
    dec_heads: int = 16
    dec_registers: int = 5
    dec_layerscale: float = 0.01
    rope_freq: float = 100.0
    head_dim: int = 1024
    head_depth: int = 5
    head_heads: int = 16
    head_out_dim: int = 1024
    camera_dim: int = 512
    gs_taps: tuple[int, ...] = (11, 19, 27, 35)
    gs_features: int = 256
    gs_rgb_features: int = 32
    sh_degree: int = 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "gs_taps", tuple(int(t) for t in self.gs_taps))
        sizes = ("dim", "enc_depth", "enc_heads", "enc_pos_grid", "dec_heads", "head_dim", "head_depth",
                 "head_heads", "head_out_dim", "camera_dim", "gs_features", "gs_rgb_features")  # fmt: skip
        bad = [n for n in (*sizes, "mlp_ratio") if getattr(self, n) <= 0] + [
            n for n in ("enc_registers", "dec_registers") if getattr(self, n) < 0
        ]
        if bad:
            raise ValueError(f"ModelConfig: {bad} must be positive (registers: >= 0)")
        huge = [f"{n}={getattr(self, n)}" for n in (*sizes, "dec_depth", "enc_registers", "dec_registers", "mlp_ratio")
                if getattr(self, n) > (MAX_DEPTH if n.endswith("depth") else MAX_WIDTH)]  # fmt: skip
        if huge:
            raise ValueError(f"ModelConfig: sizes beyond any real model: {huge} (depths at most {MAX_DEPTH}, "
                             f"others at most {MAX_WIDTH})")  # fmt: skip
        taps = self.gs_taps
        checks = {
            "dim divisible by the heads": self.dim % self.enc_heads == self.dim % self.dec_heads == 0,
            "head_dim divisible by head_heads": self.head_dim % self.head_heads == 0,
            "RoPE head widths (dim / dec_heads, head_dim / head_heads) divisible by 4":
                (self.dim // self.dec_heads) % 4 == (self.head_dim // self.head_heads) % 4 == 0,
            "dec_depth even (frame/global pairs)": self.dec_depth >= 2 and self.dec_depth % 2 == 0,
            "gs_taps: 4 distinct indices below dec_depth":
                len(set(taps)) == len(taps) == 4 and all(0 <= t < self.dec_depth for t in taps),
            "sh_degree in 0..4": 0 <= self.sh_degree <= 4,
        }  # fmt: skip
        failed = [k for k, ok in checks.items() if not ok]
        if failed:
            raise ValueError(f"ModelConfig: need {'; '.join(failed)}")

    @classmethod
    def full(cls) -> ModelConfig:
        """Pi3 size (ViT-L encoder, 36 decoder blocks, about 0.96 B parameters + Gaussian head)."""
        return cls()

    @classmethod
    def small(cls) -> ModelConfig:
        """CPU size: the same architecture, 128 wide, 4 + 4 blocks, 16 x 16 position grid (224 px)."""
        return cls(
            dim=128, enc_depth=4, enc_heads=4, enc_pos_grid=16, dec_depth=4, dec_heads=4,
            head_dim=128, head_depth=2, head_heads=4, head_out_dim=128, camera_dim=128,
            gs_taps=(0, 1, 2, 3), gs_features=48, gs_rgb_features=16, sh_degree=1,
        )  # fmt: skip

    def to_dict(self) -> dict:
        d = asdict(self)
        d["gs_taps"] = list(self.gs_taps)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        """The config of :meth:`to_dict`'s ``d``; ``ValueError`` names unknown fields and values of the wrong type."""
        if not isinstance(d, dict):
            raise ValueError(f"ModelConfig: expected an object of fields, got {type(d).__name__}")  # noqa: TRY004
        types = {f.name: f.type for f in fields(cls)}
        unknown = sorted(set(d) - set(types))
        if unknown:
            raise ValueError(f"ModelConfig: unknown fields {unknown}")
        wrong = [f"{k}={v!r} (expected {types[k]})" for k, v in d.items() if not _is(v, types[k])]
        if wrong:
            raise ValueError(f"ModelConfig: wrong field types: {', '.join(wrong)}")
        return cls(**d)


def _is(value, kind: str) -> bool:
    """Whether a JSON ``value`` fits a field annotated ``kind`` (int, float or tuple[int, ...])."""
    if kind == "int":
        return type(value) is int
    if kind == "float":
        return type(value) in (int, float) and math.isfinite(value)
    return isinstance(value, (list, tuple)) and all(type(t) is int for t in value)
