"""Pixel-aligned Gaussians from calibrated RGB-D views.

Each valid pixel becomes one Gaussian at its back-projected surface point. Its shape is the
pixel's own footprint on the surface: with a and b the 3D steps to the neighbouring pixels
along u and v, the covariance is

    Sigma = k^2 (a a^T + b b^T) + (t k min(|a|, |b|))^2 n n^T,   n = a x b / |a x b|

so in the source camera every splat projects to an isotropic blob of about k pixels
(the 0.3 px^2 rasterizer dilation comes on top), while seen from a moved camera it stays a
disc lying *in the surface*, which is what keeps novel views hole-free: camera-facing discs
would turn edge-on and open cracks as soon as the camera rotates. ``t`` makes the discs
thin. Neighbour steps are one-sided (the shorter of forward/backward), so a disc never
bridges a depth edge; where even the shorter step is more than ``max_stretch`` times the
fronto-parallel footprint z/f (a grazing surface or an occlusion boundary), that axis
falls back to the fronto-parallel footprint. Splats on the nearer side of a depth edge are
shrunk across it (``edge_scale``) so silhouettes do not bleed onto the background; the splats
behind the edge keep their size (they fill the view that opens beside a silhouette when the
camera moves), and so do splats beside pixels without depth.

The discs are drawn sharp: a small rasterizer dilation (``dilation``, 0.04 px^2 instead of
the 0.3 learnt Gaussians are trained with) and saturated alpha (``saturation``: alpha =
min(0.99, 2 exp(-q/2)) for opaque discs), so each disc covers its pixel fully and falls off
within a fraction of a pixel: at the source pose every pixel shows its own colour, and a
moved camera still sees a closed surface. Where two cameras saw one surface, the discs of the
camera whose view is closest to the rendered one are composited in front
(``view_preference``, :meth:`.views.Reconstruction.seen_from`), instead of a depth-noise
coin toss between the two. The footprint is small (k = 0.3 px), so fine real texture stays
as sharp as the image; a moved camera sees partly covered pixels between such discs, which
hole filling blends with their surroundings and, where holes are not filled, ``cover``
shows in the discs' own colour. These settings, and the disc shape itself, say how discs are
drawn from the depth a cache stores, not what it stores, so they are not part of the
reconstructor's identity.

Sharp discs suit exact depth. On a depth sensor's noisy depth, neighbouring discs lie at
scattered depths, and a moved camera sees the cracks and colour speckle between them. Where
the depth is rough (``soften_noise``; :func:`depth_roughness`: the part of inverse depth's
second difference that changes sign at random over 5x5 pixels, in pixel footprints z/f, is
above ``ROUGH_START``), the discs turn into plain Gaussians, fully at ``ROUGH_FULL``: their
own saturation falls to 1 (the reconstruction's ``render_options["saturation"]`` is then one
number per disc) and their footprint in the surface widens by the plain render's dilation
(``PLAIN_DILATION`` minus ``dilation`` px^2, in source pixels). Planes at any tilt and curved
surfaces read 0, and depth edges (a step beyond ``ROUGH_EDGE`` footprints) are not counted,
so exact depth keeps its sharp discs: on the built-in simulation the mean blend is 0.97 on
its simulated RealSense depth (``gensplat_sim.sensor``) and 0.02 on exact depth (small steps).
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F

from ..core.cameras import Cameras
from ..core.config_flags import flag, real_number, whole_number
from ..core.gaussians import Gaussians
from ..core.rotations import rotmat_to_quat
from ..core.scenes import Scenes
from ..core.sh import num_sh_bases, rgb_to_sh_dc
from ..core.views import source_rays
from . import discs_fast
from .base import DepthReconstructor, Reconstruction, Views, valid_depth
from .depth_fill import fill_depth
from .discs_fast import surface_discs


@dataclass
class RGBDConfig:
    """Settings of :class:`RGBDReconstructor`.

    Attributes:
        sigma_px: splat standard deviation in source pixels (k above).
        thickness: disc thickness relative to its in-plane size (t above).
        max_stretch: longest in-surface step, in units of the fronto-parallel footprint.
        edge_scale: splats on the nearer side of a depth edge shrink to this fraction
            across it, so that foreground splats do not overhang the background.
        opacity: opacity of every splat.
        sh_degree: SH degree of the output (only the DC term is non-zero).
        max_depth: ignore pixels farther than this (metres); None keeps all.
        stride: keep every ``stride``-th pixel in u and v (density 1/stride^2); the splat
            size grows with the stride so the surface stays covered.
        fill_depth_px: pixels without depth within this many pixels of depth get the
            farthest depth around them before the discs are built (:mod:`.depth_fill`: a
            depth sensor's holes, whose colours the image has); 0 fills none. Stored depth
            stays as measured.
        dilation: px^2 the rasterizer adds to each disc's 2D covariance (``render``'s).
        saturation: alpha gain of the discs (``render``'s; 1: plain Gaussians).
        view_preference: how far behind, as a fraction of their distance, discs from a
            camera whose view differs from the rendered one by more than about 16 deg are
            drawn (:func:`.views.preferred_means`; depth rendered where only such a camera
            saw the surface is that much too far); 0 composites all views alike.
        soften_noise: discs on rough depth (a sensor's noise) are drawn as plain Gaussians
            (module docstring); False keeps every disc sharp.
        cover: a pixel the discs cover to at least this alpha shows their colour alone
            (``render``'s; where holes are not filled: the cracks between small discs seen
            from a moved camera); 1 leaves every pixel as composited.
    """

    sigma_px: float = 0.3
    thickness: float = 0.1
    max_stretch: float = 4.0
    edge_scale: float = 0.5
    opacity: float = 1.0
    sh_degree: int = 0
    max_depth: float | None = None
    stride: int = 1
    fill_depth_px: int = field(default=0, metadata=flag(
        "rgbd: give pixels without depth within PIXELS of measured depth the farthest depth around them before "
        "the discs are built, for a depth sensor's holes (e.g. 8; 0: none)", flag="--fill-depth", metavar="PIXELS"))
    dilation: float = 0.04
    saturation: float = 2.0
    view_preference: float = 0.03
    soften_noise: bool = True
    cover: float = 0.1

    def __post_init__(self) -> None:
        checks = {  # field: (valid, what it must be)
            "sigma_px": (real_number(self.sigma_px) and self.sigma_px > 0, "a number > 0 (pixels)"),
            "thickness": (real_number(self.thickness) and self.thickness >= 0, "a number >= 0"),
            "max_stretch": (real_number(self.max_stretch) and self.max_stretch >= 1, "a number >= 1"),
            "edge_scale": (real_number(self.edge_scale) and 0 < self.edge_scale <= 1, "a number in (0, 1]"),
            "opacity": (real_number(self.opacity) and 0 <= self.opacity <= 1, "a number in [0, 1]"),
            "sh_degree": (whole_number(self.sh_degree) and self.sh_degree >= 0, "a whole number >= 0"),
            "max_depth": (self.max_depth is None or real_number(self.max_depth) and self.max_depth >= 0,
                          "None or a number >= 0 (metres; 0 keeps no pixel)"),
            "stride": (whole_number(self.stride) and self.stride >= 1, "a whole number >= 1"),
            "fill_depth_px": (whole_number(self.fill_depth_px) and self.fill_depth_px >= 0, "a whole number >= 0 (pixels)"),
            "dilation": (real_number(self.dilation) and self.dilation > 0, "a number > 0 (px^2)"),
            "saturation": (real_number(self.saturation) and self.saturation >= 1, "a number >= 1"),
            "view_preference": (real_number(self.view_preference) and 0 <= self.view_preference <= 1, "a number in [0, 1]"),
            "cover": (real_number(self.cover) and 0 < self.cover <= 1, "a number in (0, 1]"),
            "soften_noise": (isinstance(self.soften_noise, bool), "True or False"),  # not a truthy "false" from a file
        }  # fmt: skip
        for name, (valid, what) in checks.items():
            if not valid:
                raise ValueError(f"RGBDConfig.{name} must be {what}, got {getattr(self, name)!r}")


class RGBDReconstructor(DepthReconstructor):
    """Calibrated RGB + metric depth -> one Gaussian per valid pixel (see module docstring).

    ``fast=True`` (default) builds the discs with the compiled twin in :mod:`.discs_fast`
    (not differentiable); ``fast=False`` with the PyTorch rule below. Both give the same
    Gaussians (to float32 round-off) and the same :meth:`identity`.

    Example:
        >>> from gensplat_transforms.data.scenes import TabletopScene, default_cameras
        >>> cameras = default_cameras(16, 16)[:2]
        >>> images, depths = TabletopScene(seed=0).render(cameras)
        >>> result = RGBDReconstructor().reconstruct(Views(images, cameras, depths))
        >>> len(result.gaussians)  # one per pixel with depth
        512
    """

    name = "rgbd"
    given_depth = True

    def __init__(self, config: RGBDConfig | None = None, fast: bool = True, **overrides) -> None:
        self.cfg = RGBDConfig(**{**asdict(config or RGBDConfig()), **overrides})
        self.fast = fast

    def config(self) -> dict:
        config = disc_identity(self.cfg)
        if not config["fill_depth_px"]:  # unset: identities as before
            del config["fill_depth_px"]
        return config

    def render_style(self, saturation: torch.Tensor | None = None) -> dict:
        """What a :class:`~.views.Reconstruction` of these discs carries for rendering: with
        the discs' own ``saturation`` (N,) where some were softened (:func:`own_saturation`),
        else the configured one."""
        saturation = self.cfg.saturation if saturation is None else saturation
        options = {"dilation": self.cfg.dilation, "saturation": saturation, "cover": self.cfg.cover}
        return {"render_options": options, "view_preference": self.cfg.view_preference}

    def predict_depth(self, views: Views) -> Views:
        """The given depth, 0 where invalid (see :func:`.base.valid_depth`) or beyond
        ``max_depth``."""
        _require_depth(views)
        return Views(views.images, views.cameras, self.clean_depth(views.depths))

    def clean_depth(self, depths: torch.Tensor) -> torch.Tensor:
        """``depths`` (any shape) as float32, 0 where invalid or beyond ``max_depth``."""
        z = depths.float()
        valid = valid_depth(z)
        if self.cfg.max_depth is not None:
            valid &= z <= self.cfg.max_depth
        return torch.where(valid, z, torch.zeros_like(z))

    def disc_depth(self, depths: torch.Tensor) -> torch.Tensor:
        """The depth the discs are built from: :meth:`clean_depth` with its small holes
        filled (``fill_depth_px``; a fill put behind ``max_depth`` is dropped again)."""
        clean = self.clean_depth(depths)
        return self.clean_depth(fill_depth(clean, self.cfg.fill_depth_px)) if self.cfg.fill_depth_px else clean

    def assemble(self, views: Views) -> Reconstruction:
        _require_depth(views)
        depths, cfg = self.disc_depth(views.depths), self.cfg
        if self.fast:  # all views in one compiled pass, into one set of arrays
            means, quats, scales, dc, pixel_ids = surface_discs(
                depths[:, 0], views.images, views.cameras.K, views.cameras.c2w, cfg.stride, cfg.sigma_px,
                cfg.thickness, cfg.max_stretch, cfg.edge_scale,
            )  # fmt: skip
            saturation = None
            if cfg.soften_noise:
                saturation = discs_fast.soften_discs(  # scales changed in place
                    depths[:, 0], views.cameras.K, pixel_ids, scales, ROUGH_EDGE, ROUGH_WINDOW, ROUGH_START,
                    ROUGH_FULL, _grow(cfg), cfg.saturation)  # fmt: skip
        else:
            means, quats, scales, dc, saturation, keep = dense_discs(
                depths[:, 0], views.images, views.cameras.K.float(), views.cameras.c2w.float(), cfg)  # fmt: skip
            means, quats, scales, dc, saturation = (t[keep] for t in (means, quats, scales, dc, saturation))
            pixel_ids = grid_pixel_ids(*depths.shape[-2:], cfg.stride, len(views))[keep]
            saturation = own_saturation(saturation, cfg)
        n = means.shape[0]
        sh = dc[:, None]  # DC only; higher degrees are zero
        if cfg.sh_degree > 0:
            sh = torch.cat([sh, dc.new_zeros(n, num_sh_bases(cfg.sh_degree) - 1, 3)], 1)
        # the compiled builder's output is finite for any depth and finite images (Views checks
        # them): valid by construction, so the per-sample scan is skipped
        g = Gaussians(means, quats, scales, torch.full((n,), cfg.opacity), sh, validate=not self.fast)
        return Reconstruction(g.mark_checked() if self.fast else g, views.cameras, pixel_ids,
                              **self.render_style(saturation))  # fmt: skip


    def scenes(self, depths: torch.Tensor, images: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor,
               compiled: bool = False) -> Scenes:  # fmt: skip
        """M timesteps of V views each, as :meth:`assemble` makes one, as M :class:`Scenes`
        (the batch mode's): discs by the PyTorch rule (:func:`dense_discs`, in float32;
        ``compiled``: by :func:`compiled_discs`) on every view's pixel grid, padded where a
        pixel has no depth.

        Args:
            depths: (M, V, h, w) depth as stored (cleaned here, :meth:`disc_depth`);
            images: (M, V, 3, h, w) float in [0, 1]; K (M, V, 3, 3), c2w (M, V, 4, 4).
        """
        f32, cfg = torch.float32, self.cfg
        rule = compiled_discs if compiled else dense_discs
        means, quats, scales, dc, saturation, keep = (t.flatten(1, 2) for t in rule(
            self.disc_depth(depths), images, K.to(f32), c2w.to(f32), cfg))  # fmt: skip
        M, N = keep.shape
        sh = dc[:, :, None]
        if cfg.sh_degree > 0:
            sh = torch.cat([sh, sh.new_zeros(M, N, num_sh_bases(cfg.sh_degree) - 1, 3)], 2)
        rays = None
        if cfg.view_preference:  # each disc's camera centre, its view's n discs in a row
            origins = c2w[..., :3, 3].to(means).repeat_interleave(N // K.shape[1], 1)
            rays = source_rays(means, origins)
        sources = Cameras(K.flatten(0, 1), c2w.flatten(0, 1), depths.shape[-1], depths.shape[-2])
        return Scenes(means, quats, scales, torch.full_like(saturation, cfg.opacity), sh, keep, saturation, sources,
                      rays, cfg.view_preference, {"dilation": cfg.dilation, "cover": cfg.cover})  # fmt: skip

#: RGBDConfig fields that shape only what is drawn, not what a cache stores (not part of its identity)
RENDER_FIELDS = ("dilation", "saturation", "view_preference", "soften_noise", "cover")
#: the disc shape: how workers build discs from the depth a cache stores, not what it stores.
#: A cache's identity lists these fields at these fixed values whatever the configured ones
#: (the identity's format: caches keyed by them stay valid).
SHAPE_IDENTITY = {"sigma_px": 0.4, "thickness": 0.1, "max_stretch": 4.0, "edge_scale": 0.25, "opacity": 1.0,
                  "sh_degree": 0, "stride": 1}  # fmt: skip

#: ``soften_noise``: roughness (in pixel footprints) at which discs start turning into plain
#: Gaussians, and at which they are plain; second differences beyond ``ROUGH_EDGE`` are depth
#: edges, not noise; the mean is taken over ``ROUGH_WINDOW`` x ``ROUGH_WINDOW`` pixels
ROUGH_START, ROUGH_FULL, ROUGH_EDGE, ROUGH_WINDOW = 0.2, 0.4, 4.0, 5
#: the rasterizer dilation (px^2) of plain Gaussians, which rough discs are drawn with
PLAIN_DILATION = 0.3


def depth_roughness(z: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(M, H, W) roughness of (M, H, W) depth (0: none) seen with intrinsics K (M, 3, 3): how
    far depth leaves the chord of its neighbours at random, in pixel footprints z/f. With
    d = (w(-1) - 2 w + w(+1)) z f / 2 along u and along v (w = 1/z: a plane's d is 0), over
    ``ROUGH_WINDOW`` x ``ROUGH_WINDOW`` pixels: (sum |d| - |sum d_u| - |sum d_v|) / count, so a
    curved surface, whose d keeps its sign, reads near 0, and noise, whose d does not, reads
    about its mean |d|. Steps beyond ``ROUGH_EDGE`` and pixels without both neighbours are left
    out; a window with nothing counted reads 0."""
    valid = z > 0
    w = torch.where(valid, 1 / z.clamp_min(torch.finfo(z.dtype).tiny), 0.0)
    planes = torch.zeros(len(z), 4, *z.shape[1:], dtype=z.dtype, device=z.device)  # sum |d|, sum d_u, d_v, count
    for plane, dim, f in ((1, 2, K[:, 0, 0]), (2, 1, K[:, 1, 1])):
        n = z.shape[dim]
        if n < 3:
            continue
        inner = (slice(None), *(slice(1, n - 1) if d == dim else slice(None) for d in (1, 2)))
        d = (w.narrow(dim, 0, n - 2) + w.narrow(dim, 2, n - 2) - 2 * w[inner]) * z[inner] * (0.5 * f).to(z).reshape(-1, 1, 1)
        ok = valid.narrow(dim, 0, n - 2) & valid.narrow(dim, 2, n - 2) & valid[inner] & (d.abs() < ROUGH_EDGE)
        d = torch.where(ok, d, 0.0)
        planes[(slice(None), 0, *inner[1:])] += d.abs()
        planes[(slice(None), plane, *inner[1:])] += d
        planes[(slice(None), 3, *inner[1:])] += ok.to(z.dtype)
    r = ROUGH_WINDOW // 2
    sums = F.avg_pool2d(F.avg_pool2d(planes, (1, ROUGH_WINDOW), 1, (0, r)), (ROUGH_WINDOW, 1), 1, (r, 0))
    noise = (sums[:, 0] - sums[:, 1].abs() - sums[:, 2].abs()).clamp_min(0)
    return torch.where(sums[:, 3] > 0, noise / sums[:, 3].clamp_min(1e-12), 0.0)


def rough_blend(z: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For (M, H, W) depth and (M, 3, 3) intrinsics: how plain each pixel's disc is drawn,
    (M, H, W) in [0, 1] (0 below ``ROUGH_START``, 1 from ``ROUGH_FULL``), and its footprint
    z / fx (M, H, W) in metres."""
    blend = ((depth_roughness(z, K) - ROUGH_START) / (ROUGH_FULL - ROUGH_START)).clamp(0, 1)
    return blend, z / K[:, 0, 0].to(z).reshape(-1, 1, 1)


def own_saturation(saturation: torch.Tensor, cfg: RGBDConfig) -> torch.Tensor | None:
    """The discs' saturations (N,) where some differ from ``cfg.saturation`` (softened), else None."""
    return saturation if bool((saturation != cfg.saturation).any()) else None


def _grow(cfg: RGBDConfig) -> float:
    """px^2 a fully rough disc's footprint gains: up to the plain render's dilation."""
    return max(PLAIN_DILATION - cfg.dilation, 0.0)


def soften(scales: torch.Tensor, blend: torch.Tensor, footprint: torch.Tensor,
           cfg: RGBDConfig) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Scales (..., 3) and saturations (...) of discs drawn ``blend`` (...) of the way to plain
    Gaussians: in-plane variances plus blend (PLAIN_DILATION - dilation) footprint^2 (the
    thickness kept), saturation from ``cfg.saturation`` (blend 0) down to 1 (blend 1)."""
    grow = blend * (_grow(cfg) * footprint.square())
    in_plane = (scales[..., :2].square() + grow[..., None]).sqrt()
    return torch.cat([in_plane, scales[..., 2:]], -1), cfg.saturation - blend * (cfg.saturation - 1)


def disc_identity(cfg: RGBDConfig) -> dict:
    """The settings of ``cfg`` that a cache's identity covers: all but ``RENDER_FIELDS``, the
    shape at ``SHAPE_IDENTITY``."""
    return {**{k: v for k, v in asdict(cfg).items() if k not in RENDER_FIELDS}, **SHAPE_IDENTITY}


def grid_pixel_ids(height: int, width: int, stride: int, views: int) -> torch.Tensor:
    """(V, n) pixel ids ``v * H * W + row * W + col`` of the n pixels on the stride grid of each
    of V views, row-major (the order of :func:`dense_discs`)."""
    sel = slice(stride // 2, None, stride)
    grid = torch.arange(height * width).reshape(height, width)[sel, sel].reshape(-1)
    return grid + torch.arange(views)[:, None] * (height * width)


def dense_discs(z: torch.Tensor, images: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, cfg: RGBDConfig):
    """The PyTorch rule for every pixel on the stride grid of any number of views at once.

    Args:
        z: (..., H, W) cleaned depth (0 = no disc); images: (..., 3, H, W) in [0, 1];
        K: (..., 3, 3); c2w: (..., 4, 4); all of one float dtype, which the rule computes in.
    Returns:
        means (..., n, 3), quats (..., n, 4), scales (..., n, 3), SH DC (..., n, 3), each
        disc's saturation (..., n) (:func:`soften`) and keep (..., n) bool (the pixel has depth), for
        the n pixels on the stride grid, row-major. Pixels without depth get finite
        placeholder values (identity rotation, zero scales).
    """
    lead, (H, W) = z.shape[:-2], z.shape[-2:]
    z, images = z.reshape(-1, H, W), images.reshape(-1, 3, H, W)
    K, c2w = K.reshape(-1, 1, 1, 3, 3), c2w.reshape(-1, 1, 1, 4, 4)
    valid = z > 0
    v, u = torch.meshgrid(torch.arange(H, dtype=z.dtype, device=z.device) + 0.5,
                          torch.arange(W, dtype=z.dtype, device=z.device) + 0.5, indexing="ij")  # fmt: skip
    cam = torch.stack([(u - K[..., 0, 2]) / K[..., 0, 0] * z, (v - K[..., 1, 2]) / K[..., 1, 1] * z, z], -1)
    R = c2w[..., :3, :3]
    pts = (cam[..., None, :] * R).sum(-1) + c2w[..., :3, 3]  # (M, H, W, 3): R cam + t, no batched matmul
    a = _surface_step(pts, valid, z / K[..., 0, 0], R[..., :, 0], cfg.max_stretch, cfg.edge_scale, dim=2)
    b = _surface_step(pts, valid, z / K[..., 1, 1], R[..., :, 1], cfg.max_stretch, cfg.edge_scale, dim=1)

    s = cfg.stride
    sel = (slice(None), slice(s // 2, None, s), slice(s // 2, None, s))
    keep = valid[sel].flatten(1)
    a, b = a[sel].flatten(1, 2) * s, b[sel].flatten(1, 2) * s
    means = pts[sel].flatten(1, 2)
    rgb = images.permute(0, 2, 3, 1)[sel].flatten(1, 2)
    quats, scales = _disc_shape(a.reshape(-1, 3), b.reshape(-1, 3), cfg.sigma_px, cfg.thickness)
    quats = torch.where(keep.reshape(-1, 1), quats, quats.new_tensor([1.0, 0, 0, 0]))
    scales = torch.where(keep.reshape(-1, 1), scales, 0.0)
    n = keep.shape[1]
    saturation = torch.full_like(scales[:, 0], cfg.saturation)
    if cfg.soften_noise:
        blend, footprint = (t[sel].reshape(-1) for t in rough_blend(z, K.reshape(-1, 3, 3)))
        scales, saturation = soften(scales, blend, footprint, cfg)
    return (means.reshape(*lead, n, 3), quats.reshape(*lead, n, 4), scales.reshape(*lead, n, 3),
            rgb_to_sh_dc(rgb).reshape(*lead, n, 3), saturation.reshape(*lead, n), keep.reshape(*lead, n))  # fmt: skip


def _require_depth(views: Views) -> None:
    if views.cameras is None or views.depths is None:
        missing = [n for n in ("cameras", "depths") if getattr(views, n) is None]
        raise ValueError(f"RGBDReconstructor needs calibrated cameras and depth; missing: {missing}")


def _disc_shape(a: torch.Tensor, b: torch.Tensor, k: float, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Quaternions (N, 4) and scales (N, 3) of the covariance in the module docstring.

    Closed form (no eigen-solver): n = a x b is an exact eigenvector (eigenvalue
    (t k min(|a|, |b|))^2); the in-plane 2x2 block is diagonalised by one angle.
    """
    n = torch.linalg.cross(a, b)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)
    la = a.norm(dim=-1).clamp_min(1e-20)
    e1 = a / la[:, None]
    e2 = torch.linalg.cross(n, e1)
    b1, b2 = (b * e1).sum(-1), (b * e2).sum(-1)
    g11, g12, g22 = la**2 + b1**2, b1 * b2, b2**2  # (aa^T + bb^T) in the (e1, e2) basis
    phi = 0.5 * torch.atan2(2 * g12, g11 - g22)
    mid, rad = 0.5 * (g11 + g22), torch.sqrt((0.5 * (g11 - g22)) ** 2 + g12**2)
    c, s = torch.cos(phi)[:, None], torch.sin(phi)[:, None]
    R = torch.stack([c * e1 + s * e2, c * e2 - s * e1, n], -1)  # columns; det = +1
    thick = t * k * torch.minimum(la, b.norm(dim=-1))
    scales = torch.stack([k * (mid + rad).sqrt(), k * (mid - rad).clamp_min(0).sqrt(), thick], -1)
    return rotmat_to_quat(R), scales


def _surface_step(pts, valid, footprint, axis, max_stretch, edge_scale, dim):
    """(H, W, 3) step to the neighbouring pixel along ``dim`` (1: u, 0: v) on the surface.

    Takes the shorter of the forward and backward differences among valid neighbours;
    falls back to the fronto-parallel footprint ``footprint * axis`` where there is none
    or it is longer than ``max_stretch`` footprints. On the nearer side of a depth edge (a
    difference longer than that to a farther neighbour) the step is scaled by ``edge_scale``.
    """
    n = pts.shape[dim]
    both = valid.narrow(dim, 1, n - 1) & valid.narrow(dim, 0, n - 1)
    diff = pts.narrow(dim, 1, n - 1) - pts.narrow(dim, 0, n - 1)
    first, second = footprint.narrow(dim, 0, n - 1), footprint.narrow(dim, 1, n - 1)  # z / f: nearer is smaller
    jump = both & (diff.norm(dim=-1) > max_stretch * first)
    diff = torch.where(both[..., None], diff, torch.full_like(diff, float("inf")))
    fwd = torch.full_like(pts, float("inf"))
    bwd = torch.full_like(pts, float("inf"))
    fwd.narrow(dim, 0, n - 1).copy_(diff)
    bwd.narrow(dim, 1, n - 1).copy_(diff)
    step = torch.where((fwd.norm(dim=-1) <= bwd.norm(dim=-1))[..., None], fwd, bwd)
    ok = step.norm(dim=-1) <= max_stretch * footprint
    step = torch.where(ok[..., None], step, footprint[..., None] * axis)
    edge = torch.zeros_like(valid)
    edge.narrow(dim, 0, n - 1).logical_or_(jump & (first < second))
    edge.narrow(dim, 1, n - 1).logical_or_(jump & (second < first))
    return torch.where(edge[..., None], step * edge_scale, step)


_COMPILED: dict = {}  # the disc rule compiled by torch.compile, made once per process


def compiled_discs(*args):
    """:func:`dense_discs` compiled by ``torch.compile`` (dynamic shapes: one compilation for
    any number of timesteps; fused kernels on CUDA); where compiling fails (no compiler, an
    unsupported device), a warning and the plain rule from then on."""
    if "rule" not in _COMPILED:
        _COMPILED["rule"] = torch.compile(dense_discs, dynamic=True)
    if _COMPILED["rule"] is not dense_discs:
        try:
            return _COMPILED["rule"](*args)
        except Exception as e:  # noqa: BLE001 - any compiler failure: the plain rule still works
            warnings.warn(f"torch.compile of the disc rule failed ({type(e).__name__}: {e}); using the plain rule",
                          RuntimeWarning, stacklevel=3)  # fmt: skip
            _COMPILED["rule"] = dense_discs
    return dense_discs(*args)
