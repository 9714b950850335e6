"""Batched pinhole cameras in the OpenCV convention.

Conventions used everywhere in the library:

* camera frame: x right, y down, +z forward (the viewing direction);
* extrinsics are camera-to-world 4x4 matrices (``c2w``), metres;
* intrinsics are in pixels; continuous image coordinates put the *centre* of pixel
  ``(row i, column j)`` at ``(u, v) = (j + 0.5, i + 0.5)``, so a principal point at the
  image centre is ``(W / 2, H / 2)`` (the MuJoCo / gsplat convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .checked import tensors_state

# OpenGL / nerfstudio / MuJoCo cameras look along -z with y up: flip y and z.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
#: largest accepted |R^T R - I| entry, |det R - 1| and bottom-row error of a c2w (float32
#: round-off of composed poses stays far below; a scale, shear or mirror is far above); poses
#: in a coarser dtype get :func:`rigid_tolerance`
RIGID_TOLERANCE = 1e-3
_K_TOLERANCE = 1e-6  # on K's fixed entries: skew, K[1, 0], K[2, :2] (0) and K[2, 2] (1)
#: largest accepted focal length in pixels: a field of view of about a nanoradian on a
#: 1000-pixel image; the renderers' float32 projection overflows near 1e20 px (an empty image)
FOCAL_MAX_PX = 1e12


def _check_intrinsics(K: np.ndarray) -> None:
    """Raise ``ValueError`` unless every (3, 3) of K (float64) is [[fx, 0, cx], [0, fy, cy],
    [0, 0, 1]] with 0 < fx, fy <= :data:`FOCAL_MAX_PX`."""
    focal = K[:, [0, 1], [0, 1]]
    bad = ~((focal > 0) & (focal <= FOCAL_MAX_PX)).all(-1)
    if bad.any():
        i = int(bad.nonzero()[0][0])
        raise ValueError(f"Cameras.K: focal lengths must be > 0 and at most {FOCAL_MAX_PX:g} px, got fx, fy = "
                         f"{focal[i].tolist()} (camera {i})")
    fixed = K[:, [0, 1, 2, 2, 2], [1, 0, 0, 1, 2]] - np.array([0.0, 0.0, 0.0, 0.0, 1.0])
    bad = (np.abs(fixed) > _K_TOLERANCE).any(-1)
    if bad.any():
        i = int(bad.nonzero()[0][0])
        raise ValueError(
            f"Cameras.K: must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew, K[2, 2] = 1), "
            f"got {K[i].tolist()} (camera {i})"
        )


def rigid_tolerance(dtype: torch.dtype) -> float:
    """The rigidity tolerance of poses held in ``dtype``: :data:`RIGID_TOLERANCE`, or 8
    epsilons of a dtype coarser than float32 (float16 rounds a rotation by up to ~1e-3)."""
    return max(RIGID_TOLERANCE, 8 * torch.finfo(dtype).eps) if dtype.is_floating_point else RIGID_TOLERANCE


def _check_rigid(T: np.ndarray, tolerance: float) -> None:
    """Raise ``ValueError`` unless every (4, 4) of c2w (float64) is a rigid transform within
    ``tolerance``: bottom row [0, 0, 0, 1], rotation orthonormal with determinant +1."""
    bad = ~(np.abs(T[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])) <= tolerance).all(-1)
    if bad.any():
        i = int(bad.nonzero()[0][0])
        raise ValueError(f"Cameras.c2w: bottom row must be [0, 0, 0, 1], got {T[i, 3].tolist()} (camera {i})")
    R = T[:, :3, :3]
    error = np.maximum(np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max((1, 2), initial=0.0),
                       np.abs(np.linalg.det(R) - 1))  # fmt: skip
    bad = ~(error <= tolerance)
    if bad.any():
        i = int(bad.nonzero()[0][0])
        raise ValueError(
            f"Cameras.c2w: rotation is not orthonormal with det +1 (max error {float(error[i]):.3g} > "
            f"{tolerance:g}, camera {i}): a camera-to-world matrix has no scale, shear or mirroring"
        )


@dataclass
class Cameras:
    """A batch of B pinhole cameras that share one image size.

    Attributes:
        K: (B, 3, 3) pixel intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], fx, fy > 0.
        c2w: (B, 4, 4) rigid camera-to-world transforms, OpenCV convention.
        width, height: image size in pixels.

    Construction raises ``ValueError`` naming the field for anything that is not such a
    camera: wrong shapes, NaN or Inf, focal lengths <= 0 or above :data:`FOCAL_MAX_PX`, skew
    or K[2, 2] != 1 (beyond 1e-6), a c2w rotation that is not orthonormal with determinant +1 (beyond
    ``RIGID_TOLERANCE``, 8 epsilons for float16 and bfloat16 poses: no scale, shear or
    mirroring), a c2w bottom row other than [0, 0, 0, 1] (same tolerance). Cameras the
    library derives from checked ones (indexing, ``Perturbation.move``) are not checked
    again, unless a tensor of the cameras they come from was replaced or changed in place
    through torch since its check (its version counter moved; writes through ``.data`` or a
    NumPy view go unseen there).

    Example:
        >>> c2w = look_at(eye=(1.0, 0.0, 0.5), target=(0.0, 0.0, 0.0))
        >>> cameras = Cameras.from_intrinsics(40.0, 40.0, 32.0, 24.0, c2w, width=64, height=48)
        >>> uv, z = cameras.project(torch.zeros(1, 3, dtype=torch.float64))  # the world origin
        >>> uv  # is seen at the principal point
        tensor([[[32., 24.]]], dtype=torch.float64)
    """

    K: torch.Tensor
    c2w: torch.Tensor
    width: int
    height: int
    #: what the last passed check saw (see ``_derive``)
    _checked: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.K.ndim == 2:
            self.K = self.K[None]
        if self.c2w.ndim == 2:
            self.c2w = self.c2w[None]
        if tuple(self.K.shape[1:]) != (3, 3) or tuple(self.c2w.shape[1:]) != (4, 4):
            raise ValueError(
                f"Cameras: K must be (B,3,3) and c2w (B,4,4), got {tuple(self.K.shape)} "
                f"and {tuple(self.c2w.shape)}"
            )
        if self.K.shape[0] != self.c2w.shape[0]:
            raise ValueError(f"Cameras: {self.K.shape[0]} intrinsics but {self.c2w.shape[0]} poses")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Cameras: image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        # a few 3x3 and 4x4 matrices: checked in NumPy, many times faster than in torch
        K, c2w = (t.detach().to("cpu", torch.float64).numpy() for t in (self.K, self.c2w))
        for name, values in (("K", K), ("c2w", c2w)):
            if not np.isfinite(values).all():
                raise ValueError(f"Cameras.{name}: contains NaN or Inf")
        _check_intrinsics(K)
        _check_rigid(c2w, rigid_tolerance(self.c2w.dtype))
        self._checked = self._state()

    def _state(self) -> tuple | None:
        """What a passed check saw: the image size and :func:`.checked.tensors_state` of K and
        c2w (None for inference-mode tensors: cameras derived from them are checked in full)."""
        state = tensors_state((self.K, self.c2w))
        return None if state is None else (self.width, self.height, *state)

    def _derive(self, K: torch.Tensor, c2w: torch.Tensor) -> Cameras:
        """Cameras of this image size from (B, 3, 3) K and (B, 4, 4) c2w that the library
        derived from this object's tensors such that they pass the checks when these did (a
        selection; a rigid motion of the poses, whose result is still checked to be finite).
        Constructed without the checks while this object's tensors are what its check saw,
        else with them."""
        if self._checked is None or self._checked != self._state():
            return Cameras(K, c2w, self.width, self.height)
        if not torch.isfinite(c2w).all():
            raise ValueError("Cameras.c2w: contains NaN or Inf")
        derived = object.__new__(Cameras)  # no __init__: no __post_init__ checks
        derived.K, derived.c2w, derived.width, derived.height = K, c2w, self.width, self.height
        derived._checked = derived._state()
        return derived

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_intrinsics(
        cls,
        fx: float | torch.Tensor,
        fy: float | torch.Tensor,
        cx: float | torch.Tensor,
        cy: float | torch.Tensor,
        c2w: torch.Tensor,
        width: int,
        height: int,
    ) -> Cameras:
        """Build from focal lengths and principal points (scalars or (B,) tensors)."""
        c2w = c2w if c2w.ndim == 3 else c2w[None]
        b = c2w.shape[0]

        def col(x):
            return torch.as_tensor(x, dtype=c2w.dtype, device=c2w.device).expand(b)

        K = torch.zeros(b, 3, 3, dtype=c2w.dtype, device=c2w.device)
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2] = col(fx), col(fy), col(cx), col(cy)
        K[:, 2, 2] = 1.0
        return cls(K, c2w, width, height)

    @classmethod
    def from_opengl(cls, K: torch.Tensor, c2w_gl: torch.Tensor, width: int, height: int) -> Cameras:
        """From OpenGL / nerfstudio / Blender camera-to-world (x right, y up, looks along -z)."""
        return cls(K, opengl_to_opencv(c2w_gl), width, height)

    from_nerfstudio = from_opengl

    @classmethod
    def from_mujoco(
        cls,
        cam_xpos: torch.Tensor,
        cam_xmat: torch.Tensor,
        fovy_deg: float | torch.Tensor,
        width: int,
        height: int,
    ) -> Cameras:
        """From MuJoCo ``data.cam_xpos`` (B,3) and ``data.cam_xmat`` (B,9) or (B,3,3).

        MuJoCo's ``fovy`` is the vertical field of view: f = (H / 2) / tan(fovy / 2),
        square pixels, principal point at the image centre.
        """
        xpos = torch.as_tensor(cam_xpos, dtype=torch.float64).reshape(-1, 3)
        xmat = torch.as_tensor(cam_xmat, dtype=torch.float64).reshape(-1, 3, 3)
        c2w_gl = torch.eye(4, dtype=torch.float64).repeat(xpos.shape[0], 1, 1)
        c2w_gl[:, :3, :3], c2w_gl[:, :3, 3] = xmat, xpos
        fovy = torch.as_tensor(fovy_deg, dtype=torch.float64)
        f = (height / 2) / torch.tan(torch.deg2rad(fovy) / 2)
        return cls.from_intrinsics(f, f, width / 2, height / 2, opengl_to_opencv(c2w_gl), width, height)

    # ------------------------------------------------------------------ properties
    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, idx) -> Cameras:
        if isinstance(idx, int):
            if not -len(self) <= idx < len(self):
                raise IndexError(f"Cameras index {idx} out of range for {len(self)} cameras")
            idx = slice(idx % len(self), idx % len(self) + 1)
        return self._derive(self.K[idx], self.c2w[idx])

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def dtype(self) -> torch.dtype:
        return self.c2w.dtype

    @property
    def centers(self) -> torch.Tensor:
        """(B, 3) camera centres in world coordinates."""
        return self.c2w[:, :3, 3]

    @property
    def forward(self) -> torch.Tensor:
        """(B, 3) unit viewing directions (+z of the camera) in world coordinates."""
        return self.c2w[:, :3, 2]

    def w2c(self) -> torch.Tensor:
        """(B, 4, 4) world-to-camera transforms (rigid inverse, differentiable)."""
        return rigid_inverse(self.c2w)

    def to(self, device=None, dtype=None) -> Cameras:
        return Cameras(self.K.to(device, dtype), self.c2w.to(device, dtype), self.width, self.height)

    def with_c2w(self, c2w: torch.Tensor) -> Cameras:
        """Same intrinsics and size, new poses: (B, 4, 4), or (4, 4); one camera's intrinsics are
        shared by any number of poses."""
        c2w = c2w if c2w.ndim == 3 else c2w[None]
        K = self.K.expand(c2w.shape[0], 3, 3) if len(self) == 1 else self.K
        return Cameras(K, c2w, self.width, self.height)

    @staticmethod
    def cat(cameras: list[Cameras]) -> Cameras:
        sizes = {(c.width, c.height) for c in cameras}
        if len(sizes) != 1:
            raise ValueError(f"Cameras.cat: all cameras must share one image size, got {sorted(sizes)}")
        w, h = sizes.pop()
        return Cameras(torch.cat([c.K for c in cameras]), torch.cat([c.c2w for c in cameras]), w, h)

    # ------------------------------------------------------------------ geometry
    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points into every camera.

        Args:
            points: (B, N, 3) or (N, 3) world points.
        Returns:
            uv: (B, N, 2) continuous pixel coordinates (pixel centres at +0.5);
            depth: (B, N) camera-frame z. Points with z <= 0 get meaningless (mirrored) uv;
            the caller must mask them with ``depth > 0``.
        """
        pts = points if points.ndim == 3 else points[None].expand(len(self), -1, -1)
        w2c = self.w2c().to(pts.dtype)
        cam = pts @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3]
        z = cam[..., 2]
        zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
        K = self.K.to(pts.dtype)
        u = K[:, None, 0, 0] * cam[..., 0] / zs + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * cam[..., 1] / zs + K[:, None, 1, 2]
        return torch.stack([u, v], -1), z

    def unproject(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Lift pixels to world points.

        Args:
            uv: (B, N, 2) continuous pixel coordinates.
            depth: (B, N) camera-frame z (metric depth, not ray length).
        Returns:
            (B, N, 3) world points.
        """
        K = self.K.to(uv.dtype)
        x = (uv[..., 0] - K[:, None, 0, 2]) / K[:, None, 0, 0] * depth
        y = (uv[..., 1] - K[:, None, 1, 2]) / K[:, None, 1, 1] * depth
        cam = torch.stack([x, y, depth], -1)
        c2w = self.c2w.to(uv.dtype)
        return cam @ c2w[:, :3, :3].transpose(1, 2) + c2w[:, None, :3, 3]

    def pixel_centers(self) -> torch.Tensor:
        """(H*W, 2) continuous coordinates of every pixel centre, row-major."""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=self.dtype, device=self.device) + 0.5,
            torch.arange(self.width, dtype=self.dtype, device=self.device) + 0.5,
            indexing="ij",
        )
        return torch.stack([u.reshape(-1), v.reshape(-1)], -1)

    # ------------------------------------------------------------------ image ops
    def resize(self, width: int, height: int) -> Cameras:
        """Intrinsics for the image resized to ``width x height`` (pixel-area scaling)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.clone()
        K[:, 0] *= sx
        K[:, 1] *= sy
        return Cameras(K, self.c2w, width, height)

    def crop(self, left: int, top: int, width: int, height: int) -> Cameras:
        """Intrinsics for the sub-image ``[top:top+height, left:left+width]``."""
        if left < 0 or top < 0 or left + width > self.width or top + height > self.height:
            raise ValueError(
                f"Cameras.crop: window ({left},{top},{width},{height}) leaves the "
                f"{self.width}x{self.height} image"
            )
        K = self.K.clone()
        K[:, 0, 2] -= left
        K[:, 1, 2] -= top
        return Cameras(K, self.c2w, width, height)

    def fov_deg(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Horizontal and vertical fields of view in degrees, each (B,)."""
        fovx = 2 * torch.atan(self.width / (2 * self.K[:, 0, 0]))
        fovy = 2 * torch.atan(self.height / (2 * self.K[:, 1, 1]))
        return torch.rad2deg(fovx), torch.rad2deg(fovy)


def rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 4, 4) rigid transforms via R^T (differentiable, no matrix solve)."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def opengl_to_opencv(c2w_gl: torch.Tensor) -> torch.Tensor:
    """Convert (..., 4, 4) OpenGL camera-to-world to OpenCV: R_cv = R_gl diag(1,-1,-1)."""
    return c2w_gl @ _GL_TO_CV.to(c2w_gl)


opencv_to_opengl = opengl_to_opencv  # the flip is its own inverse


def look_at(eye, target, up=(0.0, 0.0, 1.0), dtype=torch.float64) -> torch.Tensor:
    """OpenCV camera-to-world (4, 4) at ``eye`` looking at ``target`` with world ``up``.

    Example:
        >>> look_at(eye=(1.0, 0.0, 0.0), target=(0.0, 0.0, 0.0))[:3, 2]  # +z, the viewing axis
        tensor([-1.,  0.,  0.], dtype=torch.float64)
    """
    eye = torch.as_tensor(eye, dtype=dtype)
    target = torch.as_tensor(target, dtype=dtype)
    up = torch.as_tensor(up, dtype=dtype)
    z = target - eye
    if z.norm() < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'")
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    c2w = torch.eye(4, dtype=dtype)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def focal_from_fov(fov_deg: float, size: int) -> float:
    """Focal length in pixels for a field of view across ``size`` pixels."""
    return (size / 2) / math.tan(math.radians(fov_deg) / 2)


def _closest(c2w_a: torch.Tensor, c2w_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest points (..., 3) on the optical axes of (..., 4, 4) poses, and |d1 x d2|^2 (...)
    (the points are not finite where it is 0: parallel axes)."""
    o1, d1 = c2w_a[..., :3, 3], c2w_a[..., :3, 2] / c2w_a[..., :3, 2].norm(dim=-1, keepdim=True)
    o2, d2 = c2w_b[..., :3, 3], c2w_b[..., :3, 2] / c2w_b[..., :3, 2].norm(dim=-1, keepdim=True)
    w = o1 - o2
    b = (d1 * d2).sum(-1)
    denom = 1.0 - b * b  # |d1 x d2|^2 for unit directions
    d, e = (d1 * w).sum(-1), (d2 * w).sum(-1)
    s = (b * e - d) / denom
    t = (e - b * d) / denom
    return o1 + s[..., None] * d1, o2 + t[..., None] * d2, denom


def pivot_point(c2w_a: torch.Tensor, c2w_b: torch.Tensor, parallel_tol: float = 1e-6) -> torch.Tensor:
    """(..., 3) pivot of (..., 4, 4) camera pairs: midpoint of the shortest segment between
    two cameras' optical axes.

    Falls back to the midpoint of the camera centres when the axes are (near) parallel.

    Example: two cameras looking at the origin
        >>> from gensplat_transforms import look_at
        >>> pivot = pivot_point(look_at((1.0, 0.5, 0.5), (0, 0, 0)), look_at((1.0, -0.5, 0.5), (0, 0, 0)))
        >>> torch.allclose(pivot, torch.zeros(3, dtype=torch.float64))
        True
    """
    pa, pb, denom = _closest(c2w_a, c2w_b)
    parallel = (denom < parallel_tol)[..., None]
    return torch.where(parallel, 0.5 * (c2w_a[..., :3, 3] + c2w_b[..., :3, 3]), 0.5 * (pa + pb))
