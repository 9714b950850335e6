"""A container for N 3D Gaussians, with safetensors and 3DGS-PLY input/output."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyListProperty, PlyParseError
from safetensors.torch import load_file, save_file

from .checked import tensors_state
from .sh import MAX_DEGREE, num_sh_bases, sh_degree_from_bases

FORMAT_NAME = "gensplat-gaussians"
FORMAT_VERSION = 1
_FIELDS = ("means", "quats", "scales", "opacities", "sh")


@dataclass
class Gaussians:
    """N Gaussians in world coordinates (metres).

    Attributes:
        means: (N, 3) centres.
        quats: (N, 4) orientations, w-x-y-z; need not be normalised (zero = identity).
        scales: (N, 3) standard deviations along the rotated axes, >= 0.
        opacities: (N,) in [0, 1].
        sh: (N, K, 3) spherical-harmonic colour coefficients, K = (degree+1)^2, degree <= 4.

    Construction validates shapes and finiteness and raises ``ValueError`` naming the
    offending field. Pass ``validate=False`` only for tensors already checked.

    Example:
        >>> g = Gaussians(means=torch.zeros(2, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(2, 1),
        ...               scales=torch.full((2, 3), 0.05), opacities=torch.ones(2), sh=torch.zeros(2, 1, 3))
        >>> len(g), g.sh_degree
        (2, 0)
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    validate: bool = True
    #: what the last passed check saw (see ``check``)
    _checked: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.validate:
            self.check()

    def _fingerprint(self) -> tuple | None:
        """What a passed check saw (see :func:`.checked.tensors_state`)."""
        return tensors_state(self.tensors().values())

    def mark_checked(self) -> Gaussians:
        """Record the tensors as valid without scanning them: only for values valid by
        construction (e.g. decoded from a checksummed cache)."""
        self._checked = self._fingerprint()
        return self

    def check(self, force: bool = False) -> Gaussians:
        """Raise ``ValueError`` naming the first invalid field: shapes, dtypes, NaN or Inf,
        opacities outside [0, 1], negative scales.

        A check that passed is remembered until a tensor is replaced or changed in place
        through torch (its version counter moves), so calling ``check()`` again does not
        rescan unchanged tensors. Writes through ``.data`` or a NumPy view do not move the
        version counter: ``force=True`` rescans regardless (``render`` always passes it).
        """
        if not force and self._checked is not None and self._checked == self._fingerprint():
            return self
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"Gaussians.means: expected shape (N, 3), got {tuple(self.means.shape)}")
        n = self.means.shape[0]
        expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, shape in expected.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise ValueError(f"Gaussians.{name}: expected shape {shape}, got {tuple(t.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh: expected shape ({n}, K, 3), got {tuple(self.sh.shape)}")
        try:
            sh_degree_from_bases(self.sh.shape[1])
        except ValueError as e:
            raise ValueError(f"Gaussians.sh: {e}") from None
        lo = {}
        for name in _FIELDS:
            t = getattr(self, name)
            if not t.is_floating_point():
                raise ValueError(f"Gaussians.{name}: expected a floating-point tensor, got {t.dtype}")
            if n == 0:
                continue
            # min/max propagate NaN and expose Inf: one fast pass instead of isfinite
            lo[name], hi = (float(v) for v in torch.aminmax(t.detach()))
            if not (math.isfinite(lo[name]) and math.isfinite(hi)):
                bad = int((~torch.isfinite(t)).reshape(n, -1).any(-1).sum())
                raise ValueError(f"Gaussians.{name}: {bad} Gaussian(s) have NaN or Inf values")
            if name == "opacities" and (lo[name] < 0 or hi > 1):
                raise ValueError("Gaussians.opacities: opacities must lie in [0, 1]")
        if lo.get("scales", 0.0) < 0:
            raise ValueError("Gaussians.scales: scales must be >= 0")
        return self.mark_checked()

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def tensors(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in _FIELDS}

    def _new(self, **tensors) -> Gaussians:
        return Gaussians(**tensors, validate=False)

    def to(self, device=None, dtype=None) -> Gaussians:
        return self._new(**{k: v.to(device, dtype) for k, v in self.tensors().items()})

    def __getitem__(self, index) -> Gaussians:
        """Select Gaussians with a boolean mask, index tensor or slice (an int keeps one)."""
        if isinstance(index, int):
            if not -len(self) <= index < len(self):
                raise IndexError(f"Gaussians index {index} out of range for {len(self)} Gaussians")
            index = slice(index % len(self), index % len(self) + 1)
        return self._new(**{k: v[index] for k, v in self.tensors().items()})

    def with_sh_degree(self, degree: int) -> Gaussians:
        """Truncate or zero-pad the SH coefficients to ``degree``."""
        if not 0 <= degree <= MAX_DEGREE:
            raise ValueError(f"Gaussians.with_sh_degree: degree must be in 0..{MAX_DEGREE}, got {degree}")
        k, have = num_sh_bases(degree), self.sh.shape[1]
        sh = (
            self.sh[:, :k]
            if k <= have
            else torch.cat([self.sh, self.sh.new_zeros(len(self), k - have, 3)], 1)
        )
        return self._new(**{**self.tensors(), "sh": sh})

    @staticmethod
    def cat(items: list[Gaussians]) -> Gaussians:
        """Concatenate; SH is zero-padded to the highest degree present."""
        if not items:
            raise ValueError("Gaussians.cat: nothing to concatenate")
        degree = max(g.sh_degree for g in items)
        checked = all(g._checked is not None and g._checked == g._fingerprint() for g in items)
        items = [g.with_sh_degree(degree) for g in items]
        out = Gaussians(**{k: torch.cat([getattr(g, k) for g in items]) for k in _FIELDS}, validate=False)
        return out.mark_checked() if checked else out

    @staticmethod
    def empty(sh_degree: int = 0, dtype=torch.float32, device=None) -> Gaussians:
        def z(*shape):
            return torch.zeros(*shape, dtype=dtype, device=device)

        return Gaussians(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, num_sh_bases(sh_degree), 3))

    def prune(self, min_opacity: float = 1 / 255) -> Gaussians:
        """Drop Gaussians whose opacity is below ``min_opacity`` (they can never reach the
        renderer's alpha threshold when ``min_opacity`` is 1/255)."""
        return self[self.opacities >= min_opacity]

    # ------------------------------------------------------------------ safetensors
    def save(self, path: str | Path, metadata: dict[str, str] | None = None) -> None:
        """Write a safetensors file with a format name/version header (atomic).

        ``metadata`` values must be strings; its ``format`` / ``format_version`` keys are
        ignored (the file's own format header always wins, so the file stays loadable)."""
        path = Path(path)
        metadata = dict(metadata or {})
        for k, v in metadata.items():
            if not isinstance(k, str) or not isinstance(v, str):
                raise TypeError(f"Gaussians.save: metadata keys and values must be str, got {k!r}: {v!r}")
        meta = {**metadata, "format": FORMAT_NAME, "format_version": str(FORMAT_VERSION)}
        tmp = path.with_name(f".{path.name}.tmp")
        save_file(
            {k: v.detach().contiguous().cpu() for k, v in self.tensors().items()}, str(tmp), metadata=meta
        )
        tmp.replace(path)

    @staticmethod
    def load(path: str | Path, device="cpu") -> tuple[Gaussians, dict[str, str]]:
        """Read a file written by :meth:`save`; returns the Gaussians and the metadata."""
        from safetensors import safe_open

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such Gaussians file")
        try:
            with safe_open(str(path), "pt") as f:
                meta = f.metadata() or {}
        except Exception as e:  # safetensors raises its own error types
            raise ValueError(f"{path}: not a readable safetensors file ({e})") from e
        if meta.get("format") != FORMAT_NAME:
            raise ValueError(f"{path}: not a Gaussians file (format={meta.get('format')!r})")
        if meta.get("format_version") != str(FORMAT_VERSION):
            raise ValueError(
                f"{path}: Gaussians format version {meta.get('format_version')} is not the "
                f"supported version {FORMAT_VERSION}"
            )
        try:
            tensors = load_file(str(path), device=str(device))
        except Exception as e:
            raise ValueError(f"{path}: could not read the tensors ({e})") from e
        missing = [k for k in _FIELDS if k not in tensors]
        if missing:
            raise ValueError(f"{path}: missing tensors {missing}")
        try:
            return Gaussians(**{k: tensors[k] for k in _FIELDS}), meta
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None

    # ------------------------------------------------------------------ PLY (3DGS layout)
    def to_ply(self, path: str | Path) -> None:
        """Write the standard 3DGS binary PLY (x y z nx ny nz f_dc_* f_rest_* opacity
        scale_* rot_*) with plyfile: opacity as a logit, scales as logs, rotation w-x-y-z,
        f_rest channel-major. Opens in common splat viewers."""
        n = len(self)
        eps = 1e-7
        op = self.opacities.detach().double().clamp(eps, 1 - eps)
        cols = {
            "x": self.means[:, 0], "y": self.means[:, 1], "z": self.means[:, 2],
            "nx": torch.zeros(n), "ny": torch.zeros(n), "nz": torch.zeros(n),
        }  # fmt: skip
        for c in range(3):
            cols[f"f_dc_{c}"] = self.sh[:, 0, c]
        rest = self.sh[:, 1:].transpose(1, 2).reshape(n, -1)  # (N, 3*(K-1)) channel-major
        for i in range(rest.shape[1]):
            cols[f"f_rest_{i}"] = rest[:, i]
        cols["opacity"] = torch.log(op / (1 - op))
        log_s = torch.log(self.scales.detach().double().clamp_min(1e-30))
        for i in range(3):
            cols[f"scale_{i}"] = log_s[:, i]
        for i in range(4):
            cols[f"rot_{i}"] = self.quats[:, i]
        arr = np.empty(n, dtype=[(name, "<f4") for name in cols])
        for name, v in cols.items():
            arr[name] = v.detach().cpu().double().numpy()
        PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(path))

    @staticmethod
    def from_ply(path: str | Path) -> Gaussians:
        """Read a 3DGS PLY (binary or ASCII; scalar vertex properties of any PLY type) with plyfile.

        A malformed file raises ``ValueError`` naming the file and the problem."""
        try:
            _check_ply_rows(path, longer=False)
            ply = PlyData.read(str(path), mmap=False)
        except (PlyParseError, ValueError) as e:  # numpy's ValueError: e.g. a repeated property
            raise ValueError(f"{path}: not a readable PLY file ({e})") from None
        if not ply.elements or ply.elements[0].name != "vertex":
            raise ValueError(f"{path}: PLY must start with a 'vertex' element, got {[e.name for e in ply.elements]}")
        vertex = ply["vertex"]
        lists = [p.name for p in vertex.properties if isinstance(p, PlyListProperty)]
        if lists:
            raise ValueError(f"{path}: unsupported PLY vertex list properties {lists}")
        names = {p.name for p in vertex.properties}
        need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
        need += [f"rot_{i}" for i in range(4)]
        missing = [p for p in need if p not in names]
        if missing:
            raise ValueError(f"{path}: PLY lacks 3DGS properties {missing}")
        n = vertex.count

        def col(*ps):
            return torch.from_numpy(np.stack([vertex[p].astype(np.float32) for p in ps], -1))

        n_rest = sum(1 for p in names if p.startswith("f_rest_"))
        k = 1 + n_rest // 3
        try:
            if n_rest % 3:
                raise ValueError(f"{n_rest} f_rest properties is not a multiple of 3")
            sh_degree_from_bases(k)
            missing = [f"f_rest_{i}" for i in range(n_rest) if f"f_rest_{i}" not in names]
            if missing:
                raise ValueError(f"f_rest properties are not numbered 0..{n_rest - 1}: missing {missing}")
        except ValueError as e:
            raise ValueError(f"{path}: bad 3DGS SH layout: {e}") from None
        try:
            _check_ply_rows(path, longer=True)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None]
        if n_rest:
            rest = col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k - 1).transpose(1, 2)
            sh = torch.cat([dc, rest], 1)
        else:
            sh = dc
        try:
            return Gaussians(
                means=col("x", "y", "z"),
                quats=col("rot_0", "rot_1", "rot_2", "rot_3"),
                scales=torch.exp(col("scale_0", "scale_1", "scale_2")),
                opacities=torch.sigmoid(col("opacity")[:, 0]),
                sh=sh.contiguous(),
            )
        except ValueError as e:  # e.g. NaN values, or log-scales whose exp overflows
            raise ValueError(f"{path}: {e}") from None


def _check_ply_rows(path: str | Path, longer: bool) -> None:
    """Raise ValueError when the body of a PLY file holds fewer rows than its header declares
    (checked before reading: a count of 1e11 would not fit in memory) or, with ``longer``, more
    (plyfile would drop them)."""
    with open(path, "rb") as f:
        header = PlyData._parse_header(f)
        if header.text:
            found, unit = sum(1 for line in f if line.strip()), "rows"
        else:
            found, unit = os.fstat(f.fileno()).st_size - f.tell(), "bytes"

    def row(element) -> int:  # bytes of a binary row; the least when it has lists (their lengths alone)
        props = element.properties
        return sum(np.dtype(p.len_dtype if isinstance(p, PlyListProperty) else p.val_dtype).itemsize for p in props)

    claimed = sum(e.count * (1 if header.text else row(e)) for e in header.elements)
    exact = header.text or not any(isinstance(p, PlyListProperty) for e in header.elements for p in e.properties)
    if found < claimed or (longer and found > claimed and exact):
        counts = ", ".join(f"{e.count} {e.name}" for e in header.elements)
        raise ValueError(f"the header declares {counts} ({claimed} {unit}) but the body has {found} {unit}")
