"""A built-in procedural tabletop RGB-D scene, ray-cast analytically in pure PyTorch.

The scene is the library's default data (demo command) and its ground truth at *any*
camera pose (tests, fidelity checks). World frame: Z up, metres, the table top is the plane
z = 0 and the robot workspace is the 0.8 m x 0.6 m rectangle centred on the origin.

Contents (all deterministic from the seed):

* a closed room (floor with checker tiles, four tinted walls with a height gradient and
  vertical bands, a plain ceiling), so every ray cast from inside it hits something;
* a 1.2 m x 0.9 m wooden table slab (planks and grain) with its top at z = 0;
* 5-8 objects resting on the table: z-rotated boxes, spheres and upright cylinders, each
  with its own colour and soft stripes.

Shading is Lambertian with one fixed world light and no shadows or specular terms, so a
surface point has the same colour from every viewpoint (a reconstruction can match it
exactly). ``render`` returns depth 0 (and ``BACKGROUND_RGB``) for rays that hit nothing;
this only happens for cameras outside the room.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..core.cameras import Cameras, focal_from_fov, look_at

#: Centre of the robot workspace (slightly above the table top) and its size (x, y) in metres.
WORKSPACE_CENTER = (0.0, 0.0, 0.05)
WORKSPACE_SIZE = (0.8, 0.6)
#: Table slab: centre and half extents; its top face is z = 0.
TABLE_CENTER = (0.0, 0.0, -0.025)
TABLE_HALF_SIZE = (0.6, 0.45, 0.025)
#: Room box (seen from inside): centre and half extents; the floor is at z = -0.75.
ROOM_CENTER = (0.0, 0.0, 0.5)
ROOM_HALF_SIZE = (1.6, 1.6, 1.25)
#: Unit direction towards the light (world frame) and the ambient term of the shading.
LIGHT_DIR = tuple((np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])).tolist())
AMBIENT = 0.4
#: Colour of rays that hit nothing (their depth is 0, meaning invalid).
BACKGROUND_RGB = (1.0, 1.0, 1.0)
#: Values of :meth:`TabletopScene.labels`: nothing, room, table, then object i is 3 + i.
LABEL_NONE, LABEL_ROOM, LABEL_TABLE, LABEL_FIRST_OBJECT = 0, 1, 2, 3

#: Default external cameras, in order [left, right, front]: (eye, target) in metres.
DEFAULT_VIEWS = {
    "left": ((0.30, 0.62, 0.52), WORKSPACE_CENTER),
    "right": ((0.36, -0.60, 0.48), WORKSPACE_CENTER),
    "front": ((0.62, 0.0, 0.80), (0.0, 0.0, 0.0)),
}

_PALETTE = np.array([
    [0.85, 0.15, 0.12], [0.15, 0.62, 0.22], [0.14, 0.32, 0.85], [0.95, 0.80, 0.10],
    [0.95, 0.48, 0.08], [0.55, 0.20, 0.75], [0.10, 0.72, 0.78], [0.92, 0.40, 0.65],
])
_STRIPE_AXES = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [math.sqrt(0.5), 0, math.sqrt(0.5)]])
_WALL_TINTS = torch.tensor([[0.62, 0.70, 0.80], [0.80, 0.72, 0.60], [0.66, 0.78, 0.66], [0.78, 0.68, 0.76]])
_WOOD = torch.tensor([0.66, 0.45, 0.26])
_EPS = 1e-7
_CHUNK = 1 << 16


@dataclass(frozen=True)
class SceneObject:
    """One object on the table.

    Attributes:
        kind: "box", "sphere" or "cylinder" (upright).
        center: geometric centre (x, y, z), metres.
        half_size: half extents (hx, hy, hz) in the object frame; a sphere has (r, r, r), a
            cylinder (r, r, height / 2).
        yaw: rotation about world Z in radians (object frame -> world).
        color, stripe_color: RGB albedos in [0, 1], blended by a sinusoid of period
            ``stripe_period`` (m) along ``stripe_axis`` (unit, object frame).
    """

    kind: str
    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    yaw: float
    color: tuple[float, float, float]
    stripe_color: tuple[float, float, float]
    stripe_axis: tuple[float, float, float]
    stripe_period: float

    @property
    def top(self) -> tuple[float, float, float]:
        """Centre of the top of the object (its highest point for spheres)."""
        x, y, z = self.center
        return (x, y, z + self.half_size[2])


def _yaw_matrix(yaw: float) -> torch.Tensor:
    """(3, 3) rotation about Z, object frame -> world."""
    c, s = math.cos(yaw), math.sin(yaw)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _sample_objects(seed: int) -> tuple[SceneObject, ...]:
    """5-8 non-overlapping objects inside the workspace, drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(5, 9))
    kinds = ["box", "sphere", "cylinder"] + list(rng.choice(["box", "box", "sphere", "cylinder"], count - 3))
    colors = _PALETTE[rng.permutation(len(_PALETTE))]
    placed: list[tuple[float, float, float]] = []  # (x, y, footprint radius)
    objects = []
    for kind, color in zip(kinds, colors):
        if kind == "box":
            half = (rng.uniform(0.02, 0.05), rng.uniform(0.02, 0.05), rng.uniform(0.015, 0.07))
            yaw, reach = rng.uniform(0.0, math.pi / 2), math.hypot(half[0], half[1])
        elif kind == "sphere":
            r = rng.uniform(0.025, 0.05)
            half, yaw, reach = (r, r, r), 0.0, r
        else:
            r = rng.uniform(0.02, 0.04)
            half, yaw, reach = (r, r, rng.uniform(0.04, 0.08)), 0.0, r
        xy = _place(rng, reach, placed)
        if xy is None:
            continue
        placed.append((*xy, reach))
        color = np.clip(color * rng.uniform(0.85, 1.0), 0.0, 1.0)
        stripe = color * 0.45 if rng.random() < 0.5 else 0.45 * color + 0.55
        objects.append(SceneObject(
            kind=kind,
            center=(xy[0], xy[1], half[2]),
            half_size=tuple(float(h) for h in half),
            yaw=float(yaw),
            color=tuple(color.tolist()),
            stripe_color=tuple(stripe.tolist()),
            stripe_axis=tuple(_STRIPE_AXES[rng.integers(len(_STRIPE_AXES))].tolist()),
            stripe_period=float(rng.uniform(0.02, 0.05)),
        ))
    return tuple(objects)


def _place(
    rng: np.random.Generator, reach: float, placed: list, gap: float = 0.02, tries: int = 500
) -> tuple[float, float] | None:
    """Rejection-sample an (x, y) whose footprint disc stays in the workspace and clear of ``placed``."""
    hx, hy = WORKSPACE_SIZE[0] / 2 - reach, WORKSPACE_SIZE[1] / 2 - reach
    for _ in range(tries):
        x, y = float(rng.uniform(-hx, hx)), float(rng.uniform(-hy, hy))
        if all(math.hypot(x - px, y - py) >= reach + pr + gap for px, py, pr in placed):
            return x, y
    return None


# ---------------------------------------------------------------------------- intersection
def _safe(x: torch.Tensor) -> torch.Tensor:
    """Replace near-zero values by a signed tiny number so divisions stay finite."""
    return torch.where(x.abs() < 1e-12, torch.where(x < 0, -1e-12, 1e-12), x)


def _nearest(t1: torch.Tensor, t2: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """First root in front of the origin (t1 <= t2), +inf where none."""
    t = torch.where(t1 > _EPS, t1, t2)
    return torch.where(valid & (t > _EPS), t, torch.inf)


def _intersect_boxes(o, d, centers, halves, rots) -> torch.Tensor:
    """Slab method. o, d: (R, 3); centers, halves: (K, 3); rots: (K, 3, 3). Returns t (R, K).

    A ray starting inside a box (the room) hits its far side.
    """
    ol = torch.einsum("rkj,kji->rki", o[:, None] - centers, rots)
    inv = 1.0 / _safe(torch.einsum("rj,kji->rki", d, rots))
    ta, tb = (-halves - ol) * inv, (halves - ol) * inv
    t_near = torch.minimum(ta, tb).amax(-1)
    t_far = torch.maximum(ta, tb).amin(-1)
    return _nearest(t_near, t_far, t_near <= t_far)


def _intersect_spheres(o, d, centers, radii) -> torch.Tensor:
    """o, d: (R, 3); centers (K, 3); radii (K,). Returns t (R, K)."""
    oc = o[:, None] - centers
    a = (d * d).sum(-1, keepdim=True)
    b = (oc * d[:, None]).sum(-1)
    disc = b * b - a * ((oc * oc).sum(-1) - radii**2)
    sq = disc.clamp(min=0).sqrt()
    return _nearest((-b - sq) / a, (-b + sq) / a, disc >= 0)


def _intersect_cylinders(o, d, centers, radii, half_heights) -> torch.Tensor:
    """Upright capped cylinders. o, d: (R, 3); centers (K, 3); radii, half_heights (K,). Returns t (R, K)."""
    oc = o[:, None] - centers
    dx, dy, dz = (d[:, None, i] for i in range(3))
    a = (dx * dx + dy * dy).clamp(min=1e-18)
    b = oc[..., 0] * dx + oc[..., 1] * dy
    disc = b * b - a * (oc[..., 0] ** 2 + oc[..., 1] ** 2 - radii**2)
    sq = disc.clamp(min=0).sqrt()
    candidates = []
    for t in ((-b - sq) / a, (-b + sq) / a):
        inside = (oc[..., 2] + t * dz).abs() <= half_heights
        candidates.append(torch.where((disc >= 0) & inside & (t > _EPS), t, torch.inf))
    for sign in (-1.0, 1.0):
        t = (sign * half_heights - oc[..., 2]) / _safe(dz)
        x, y = oc[..., 0] + t * dx, oc[..., 1] + t * dy
        candidates.append(torch.where((x * x + y * y <= radii**2) & (t > _EPS), t, torch.inf))
    return torch.stack(candidates, -1).amin(-1)


# ---------------------------------------------------------------------------- appearance
def _box_normal(q: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Outward normal of the box face nearest to local points q (R, 3): normal (R, 3), face (R,).

    face = 2 * axis + (1 if the face is on the positive side else 0).
    """
    axis = (q.abs() / half).argmax(-1)
    positive = q.gather(-1, axis[:, None])[:, 0] > 0
    normal = torch.nn.functional.one_hot(axis, 3).to(q.dtype)
    normal = torch.where(positive[:, None], normal, -normal)
    return normal, 2 * axis + positive.long()


def _room_albedo(p: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
    """(R, 3) albedo of room points p (R, 3): checker floor, tinted banded walls, plain ceiling."""
    lo = ROOM_CENTER[2] - ROOM_HALF_SIZE[2]
    tile = (torch.floor(p[:, 0] / 0.25) + torch.floor(p[:, 1] / 0.25)).remainder(2)[:, None]
    floor = torch.where(tile > 0, p.new_tensor([0.55, 0.52, 0.48]), p.new_tensor([0.36, 0.34, 0.32]))
    height = ((p[:, 2] - lo) / (2 * ROOM_HALF_SIZE[2]))[:, None]
    along = torch.where(face < 2, p[:, 1], p[:, 0])[:, None]  # horizontal coordinate on the wall
    bands = 0.88 + 0.12 * torch.sin(2 * math.pi * along / 0.3)
    wall = _WALL_TINTS.to(p)[face.clamp(max=3)] * (0.7 + 0.3 * height) * bands
    ceiling = p.new_tensor([0.92, 0.92, 0.90]).expand_as(p)
    return torch.where((face == 4)[:, None], floor, torch.where((face == 5)[:, None], ceiling, wall))


def _wood_albedo(p: torch.Tensor) -> torch.Tensor:
    """(R, 3) albedo of table points p (R, 3): planks along x with per-plank tone and wavy grain."""
    plank = torch.floor(p[:, 1] / 0.09)
    tone = 0.8 + 0.2 * torch.frac((torch.sin(plank * 12.9898) * 43758.5453).abs())
    phase = 14 * p[:, 0] + 0.35 * torch.sin(2 * math.pi * (3 * p[:, 0] + 0.29 * plank)) + 0.61 * plank
    grain = 0.5 + 0.5 * torch.sin(2 * math.pi * phase)
    return _WOOD.to(p) * (tone * (0.78 + 0.22 * grain))[:, None]


def _object_surface(obj: SceneObject, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Outward normal (R, 3) and striped albedo (R, 3) of ``obj`` at world points p (R, 3)."""
    rot = _yaw_matrix(obj.yaw).to(p)
    q = (p - p.new_tensor(obj.center)) @ rot
    half = p.new_tensor(obj.half_size)
    if obj.kind == "box":
        normal, _ = _box_normal(q, half)
    elif obj.kind == "sphere":
        normal = q / q.norm(dim=-1, keepdim=True)
    else:
        radial = q[:, :2].norm(dim=-1, keepdim=True)
        on_cap = q[:, 2:].abs() / half[2] > radial / half[0]
        cap = torch.nn.functional.pad(q[:, 2:].sign(), (2, 0))
        side = torch.nn.functional.pad(q[:, :2] / radial.clamp(min=1e-12), (0, 1))
        normal = torch.where(on_cap, cap, side)
    mix = 0.5 + 0.5 * torch.sin(2 * math.pi * (q @ p.new_tensor(obj.stripe_axis)) / obj.stripe_period)
    albedo = torch.lerp(p.new_tensor(obj.color), p.new_tensor(obj.stripe_color), mix[:, None])
    return normal @ rot.T, albedo


def _shade(albedo: torch.Tensor, normal: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Lambertian colour (R, 3); the normal is turned towards the viewer (rooms are seen from inside)."""
    normal = torch.where(((normal * d).sum(-1, keepdim=True) > 0), -normal, normal)
    lambert = (normal @ normal.new_tensor(LIGHT_DIR)).clamp(min=0)[:, None]
    return albedo * (AMBIENT + (1 - AMBIENT) * lambert)


# ---------------------------------------------------------------------------- scene
class TabletopScene:
    """Procedural tabletop scene with exact analytic RGB-D rendering at any camera pose.

    Args:
        seed: draws the objects' number, kinds, sizes, poses, colours and stripes.

    Attributes:
        objects: the objects on the table; object i has label ``LABEL_FIRST_OBJECT + i``.

    Example:
        >>> scene = TabletopScene(seed=0)
        >>> rgb, depth = scene.render(default_cameras())
        >>> rgb.shape, depth.shape
        (torch.Size([3, 3, 224, 224]), torch.Size([3, 1, 224, 224]))
    """

    def __init__(self, seed: int = 0) -> None:
        self.seed = int(seed)
        self.objects = _sample_objects(self.seed)
        self._build_primitives()

    def with_objects(self, objects: tuple[SceneObject, ...]) -> TabletopScene:
        """The same room and table with other objects (e.g. moved ones, for an episode)."""
        scene = object.__new__(TabletopScene)
        scene.seed, scene.objects = self.seed, tuple(objects)
        scene._build_primitives()
        return scene

    def _build_primitives(self) -> None:
        """Stack primitive parameters per kind and remember the label of every column."""
        f64 = {"dtype": torch.float64}
        boxes = [
            (ROOM_CENTER, ROOM_HALF_SIZE, 0.0, LABEL_ROOM),
            (TABLE_CENTER, TABLE_HALF_SIZE, 0.0, LABEL_TABLE),
        ]
        spheres, cylinders = [], []
        for i, obj in enumerate(self.objects):
            entry = (obj.center, obj.half_size, obj.yaw, LABEL_FIRST_OBJECT + i)
            {"box": boxes, "sphere": spheres, "cylinder": cylinders}[obj.kind].append(entry)
        self._boxes = (
            torch.tensor([b[0] for b in boxes], **f64),
            torch.tensor([b[1] for b in boxes], **f64),
            torch.stack([_yaw_matrix(b[2]) for b in boxes]),
        )
        self._spheres = (torch.tensor([s[0] for s in spheres], **f64).reshape(-1, 3),
                         torch.tensor([s[1][0] for s in spheres], **f64))
        self._cylinders = (torch.tensor([c[0] for c in cylinders], **f64).reshape(-1, 3),
                           torch.tensor([c[1][0] for c in cylinders], **f64),
                           torch.tensor([c[1][2] for c in cylinders], **f64))
        self._column_labels = torch.tensor([e[3] for e in boxes + spheres + cylinders])

    # ------------------------------------------------------------------ public API
    def render(self, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
        """Ray-cast every pixel centre.

        Returns:
            rgb: (B, 3, H, W) float32 in [0, 1].
            depth: (B, 1, H, W) float32 camera-frame z in metres; 0 where the ray hit nothing.
        """
        rgb, depth, _ = self._render(cameras)
        return rgb, depth

    def labels(self, cameras: Cameras) -> torch.Tensor:
        """(B, 1, H, W) int64 id of the surface seen at each pixel (see ``LABEL_*``)."""
        return self._render(cameras)[2]

    def cast_rays(
        self, origins: torch.Tensor, directions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Closest hits of rays (R, 3) (directions need not be unit).

        Returns:
            t: (R,) float64 ray parameter of the hit (``origins + t * directions``), inf on a miss.
            rgb: (R, 3) float64 shaded colour (``BACKGROUND_RGB`` on a miss).
            label: (R,) int64 surface id (``LABEL_NONE`` on a miss).
        """
        o, d = origins.to(torch.float64), directions.to(torch.float64)
        chunks = [self._cast_chunk(oc, dc) for oc, dc in zip(o.split(_CHUNK), d.split(_CHUNK))]
        return tuple(torch.cat(parts) for parts in zip(*chunks))

    # ------------------------------------------------------------------ internals
    def _render(self, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """rgb (B, 3, H, W), depth (B, 1, H, W) and labels (B, 1, H, W) of every pixel centre."""
        o, d = _camera_rays(cameras)
        t, rgb, label = self.cast_rays(o.reshape(-1, 3), d.reshape(-1, 3))
        b, h, w = len(cameras), cameras.height, cameras.width
        depth = torch.where(torch.isfinite(t), t, 0.0)  # directions have camera z = 1, so t is depth
        rgb = rgb.reshape(b, h, w, 3).permute(0, 3, 1, 2).clamp(0, 1).float().contiguous()
        return rgb, depth.reshape(b, 1, h, w).float(), label.reshape(b, 1, h, w)

    def _cast_chunk(self, o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """:meth:`cast_rays` for one chunk of float64 rays o, d (R, 3)."""
        dev = o.device
        t_all = torch.cat([
            _intersect_boxes(o, d, *(x.to(dev) for x in self._boxes)),
            _intersect_spheres(o, d, *(x.to(dev) for x in self._spheres)),
            _intersect_cylinders(o, d, *(x.to(dev) for x in self._cylinders)),
        ], 1)
        t, column = t_all.min(1)
        hit = torch.isfinite(t)
        label = torch.where(hit, self._column_labels.to(dev)[column], LABEL_NONE)
        rgb = o.new_tensor(BACKGROUND_RGB).repeat(len(o), 1)
        p = o + torch.where(hit, t, 0.0)[:, None] * d
        for value in label[hit].unique().tolist():
            mask = label == value
            normal, albedo = self._surface(value, p[mask])
            rgb[mask] = _shade(albedo, normal, d[mask])
        return t, rgb, label

    def _surface(self, label: int, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Outward normal (R, 3) and albedo (R, 3) of surface ``label`` at points p (R, 3)."""
        if label == LABEL_ROOM:
            normal, face = _box_normal(p - p.new_tensor(ROOM_CENTER), p.new_tensor(ROOM_HALF_SIZE))
            return normal, _room_albedo(p, face)
        if label == LABEL_TABLE:
            normal, _ = _box_normal(p - p.new_tensor(TABLE_CENTER), p.new_tensor(TABLE_HALF_SIZE))
            return normal, _wood_albedo(p)
        return _object_surface(self.objects[label - LABEL_FIRST_OBJECT], p)


def _camera_rays(cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays through every pixel centre: origins and directions, each (B, H*W, 3) float64.

    Directions have camera-frame z = 1, so the ray parameter of a hit is its depth.
    """
    K = cameras.K.to(torch.float64)
    c2w = cameras.c2w.to(torch.float64)
    uv = cameras.pixel_centers().to(torch.float64)
    x = (uv[:, 0] - K[:, None, 0, 2]) / K[:, None, 0, 0]
    y = (uv[:, 1] - K[:, None, 1, 2]) / K[:, None, 1, 1]
    d = torch.stack([x, y, torch.ones_like(x)], -1) @ c2w[:, :3, :3].transpose(1, 2)
    return c2w[:, None, :3, 3].expand_as(d), d


def default_cameras(width: int = 224, height: int = 224, fov_deg: float = 60.0) -> Cameras:
    """The three default external cameras, in order [left, right, front] (see ``DEFAULT_VIEWS``).

    Left (+y, the robot's left when it stands at -x facing +x) and right (-y) stand beside
    the table, about 0.85 m from its centre and 0.5 m above it, DROID-style; both look at
    ``WORKSPACE_CENTER``, so their pivot (``pivot_point``) is there. Front looks down at the
    table centre from across it, about 1 m away. ``fov_deg`` is the vertical field
    of view; pixels are square and the principal point is the image centre.
    """
    c2w = torch.stack([look_at(eye, target) for eye, target in DEFAULT_VIEWS.values()])
    f = focal_from_fov(fov_deg, height)
    return Cameras.from_intrinsics(f, f, width / 2, height / 2, c2w, width, height)
