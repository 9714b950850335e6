"""Depth as a real RGB-D camera delivers it, from the simulator's exact depth.

The defaults model an Intel RealSense D435 (active IR stereo, depth aligned to the colour
image, the camera most LeRobot setups use). :func:`sensor_depth` applies, in this order:

1. invalid pixels, decided on the exact depth: outside the sensor's range; the stereo
   occlusion shadow (surface the second imager, ``baseline`` to the right, cannot see: a band
   left of every foreground edge, ``fx * baseline * (1 / z_near - 1 / z_far)`` pixels wide);
   ``edge_px`` pixels on both sides of every depth discontinuity (flying pixels, which the
   sensor's filters remove); dark surfaces (low IR return) with probability ``dark_dropout``;
2. noise growing with the square of the distance:
   ``sigma(z) = z^2 * subpixel / (focal_px * baseline)`` (3.8 mm at 1 m with the defaults);
3. quantisation to ``quantum`` metres;
4. misregistration: the depth image shifted by ``shift_px`` against the colour image (the
   pixels it uncovers are invalid).

Where the defaults come from:

* ``subpixel`` 0.08 px, ``baseline`` 50 mm: the RMS error model and its typical subpixel
  value in Intel's "Tuning depth cameras for best performance" (Grunnet-Jepsen, Sweetser,
  Woodfill), with the D435's 50 mm baseline (D400 datasheet).
* ``focal_px`` 424: the D435 at its recommended 848x480 depth resolution,
  ``0.5 * 848 / tan(HFOV / 2)`` with HFOV 90 deg (Intel, "Subpixel linearity improvement for
  D400"). The depth noise is the sensor's in metres, whatever size the images are stored at.
  For a Kinect v1 (Khoshelham & Elberink 2012, Sensors 12(2): random error about
  1.6e-3 z^2 m, 4 cm at 5 m) use ``focal_px=580, baseline=0.075, subpixel=0.07``.
* ``depth_range`` 0.2 - 10 m: the D435 datasheet's minimum distance at 848x480 (about 28 cm
  at 1280x720, scaling with resolution) and its maximum range of about 10 m.
* ``quantum`` 1 mm: 16-bit millimetre depth, as the D400's ``z16`` stream (default depth
  unit 0.001 m) and ROS ``16UC1`` depth images (REP 118) store it.
* ``edge_px`` 1, ``edge_jump`` 3 %: flying pixels at discontinuities (Mallick, Das & Majumdar
  2014, "Characterizations of noise in Kinect depth images: a review", IEEE Sensors J.) taken
  out by the sensor's filters; one pixel each side is an assumption, and 3 % of the depth
  between neighbours keeps grazing table pixels (about 1.5 % at 224 px) off the list.
* ``dark_luminance`` 0.15, ``dark_dropout`` 0.5: holes on dark, IR-absorbing surfaces (low
  return; same review). Threshold and probability are illustrative, not fitted: on the
  simulated scene they select the black gripper and the arm's black band. Shiny surfaces
  are not modelled: colour alone cannot tell them from white matte ones.
* ``shift_px`` (1, 0): about one pixel of colour-depth misregistration from the factory
  extrinsics and the two sensors' different timing; an assumption, not a measured value.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from gensplat_transforms.geometry.base import valid_depth

#: Rec. 709 luma weights of the colour image (a proxy for the IR reflectance).
_LUMA = (0.2126, 0.7152, 0.0722)


@dataclass(frozen=True)
class SensorDepthConfig:
    """Settings of :func:`sensor_depth` (defaults: Intel RealSense D435; module docstring).

    Attributes:
        subpixel: RMS disparity error in pixels (0: no noise).
        baseline: stereo baseline in metres.
        focal_px: focal length of the depth imager, in its own pixels.
        depth_range: (min, max) measurable depth in metres.
        quantum: depth step in metres (0: no quantisation).
        occlusion: invalidate the stereo occlusion shadow.
        edge_px: pixels invalid on each side of a discontinuity (0: none).
        edge_jump: a discontinuity is a depth step between 4-neighbours above this fraction
            of the nearer depth.
        dark_luminance: colour luma (0-1) below which a surface counts as dark.
        dark_dropout: probability that a dark pixel has no depth.
        shift_px: (dx, dy) integer shift of the depth image against the colour image.
    """

    subpixel: float = 0.08
    baseline: float = 0.05
    focal_px: float = 424.0
    depth_range: tuple[float, float] = (0.2, 10.0)
    quantum: float = 0.001
    occlusion: bool = True
    edge_px: int = 1
    edge_jump: float = 0.03
    dark_luminance: float = 0.15
    dark_dropout: float = 0.5
    shift_px: tuple[int, int] = (1, 0)

    def noise_std(self, z: torch.Tensor) -> torch.Tensor:
        """Depth noise standard deviation (metres) at depth ``z`` (metres)."""
        return z.square() * (self.subpixel / (self.focal_px * self.baseline))


def _occlusion_shadow(z: torch.Tensor, valid: torch.Tensor, disparity_scale: float) -> torch.Tensor:
    """(H, W) bool: pixels the second imager (to the right) cannot see. A pixel at column u
    lands at u - d there (d = disparity_scale / z); it is hidden when a pixel to its right
    lands at or left of it."""
    u = torch.arange(z.shape[1], dtype=z.dtype)
    s = torch.where(valid, u - disparity_scale / z.clamp_min(1e-6), torch.full_like(z, float("inf")))
    right_min = torch.cummin(s.flip(1), dim=1).values.flip(1)  # min over columns >= u
    right_min = F.pad(right_min[:, 1:], (0, 1), value=float("inf"))  # min over columns > u
    return valid & (right_min <= s)


def _discontinuities(z: torch.Tensor, valid: torch.Tensor, jump: float, width: int) -> torch.Tensor:
    """(H, W) bool: pixels within ``width`` of a depth step > ``jump`` x the nearer depth."""
    edge = torch.zeros_like(valid)
    for dim in (0, 1):
        n = z.shape[dim]
        a, b = z.narrow(dim, 0, n - 1), z.narrow(dim, 1, n - 1)
        both = valid.narrow(dim, 0, n - 1) & valid.narrow(dim, 1, n - 1)
        step = both & ((a - b).abs() > jump * torch.minimum(a, b))
        edge.narrow(dim, 0, n - 1).logical_or_(step)
        edge.narrow(dim, 1, n - 1).logical_or_(step)
    return F.max_pool2d(edge[None, None].float(), 2 * width - 1, 1, width - 1)[0, 0] > 0


def _shift(z: torch.Tensor, dx: int, dy: int) -> torch.Tensor:
    """``z`` moved by (dx, dy) pixels (right, down); uncovered pixels are 0."""
    h, w = z.shape
    out = torch.zeros_like(z)
    if abs(dx) < w and abs(dy) < h:
        out[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = z[
            max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
        ]
    return out


def sensor_depth(
    depth: torch.Tensor, rgb: torch.Tensor, K: torch.Tensor, config: SensorDepthConfig,
    generator: torch.Generator,
) -> torch.Tensor:  # fmt: skip
    """The depth a real RGB-D camera would record (module docstring for the model).

    Args:
        depth: (H, W) exact metric camera-z depth; values that are not depths (0, negative,
            NaN, Inf, see :func:`~gensplat_transforms.geometry.base.valid_depth`) are
            invalid pixels.
        rgb: (3, H, W) colour image in [0, 1], registered to ``depth``.
        K: (3, 3) intrinsics of the colour camera (its fx sets the occlusion shadow width).
        config: sensor settings.
        generator: CPU random generator; the same state gives the same output.
    Returns:
        (H, W) float32 depth in metres, 0 where the sensor has none; finite and >= 0.
    """
    z = torch.nan_to_num(depth.detach().float().cpu(), nan=0.0, posinf=0.0, neginf=0.0)
    lo, hi = config.depth_range
    surface = valid_depth(z)  # what occludes and makes edges, in range or not
    valid = surface & (z >= lo) & (z <= hi)
    noise = torch.randn(z.shape, generator=generator)
    drop = torch.rand(z.shape, generator=generator)

    invalid = ~valid
    if config.occlusion:
        invalid |= _occlusion_shadow(z, surface, float(K[0, 0]) * config.baseline)
    if config.edge_px > 0:
        invalid |= _discontinuities(z, surface, config.edge_jump, config.edge_px)
    luma = torch.einsum("c,chw->hw", torch.tensor(_LUMA), rgb.detach().float().cpu())
    invalid |= (luma < config.dark_luminance) & (drop < config.dark_dropout)

    out = z + noise * config.noise_std(z)
    if config.quantum > 0:
        out = torch.round(out / config.quantum) * config.quantum
    out = torch.where(invalid | ~(out > 0) | ~torch.isfinite(out), torch.zeros_like(out), out)
    return _shift(out, *config.shift_px)
