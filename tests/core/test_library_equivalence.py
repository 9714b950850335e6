"""The library calls that replaced hand-written code give the results of that code.

Each ``old_*`` function below is the former hand-written implementation, kept verbatim as the
reference. The PLY reference is a file written (and read back) by the former writer and reader:
``tests/assets/gaussians_3dgs.ply`` and ``tests/assets/gaussians_3dgs.safetensors``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw
from safetensors.torch import load_file

from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.core.images import save_grid, to_uint8
from gensplat_transforms.core.metrics import ssim, ssim_map
from gensplat_transforms.core.rotations import normalize_quat, quat_to_rotmat, rotmat_to_quat
from gensplat_transforms.geometry.model.frames import quat_mul
from gensplat_transforms.geometry.model.losses import LossWeights, rgb_loss
from gensplat_transforms.training import ema_model
from gensplat_transforms.views.perturbation import axis_rotation

DATA = Path(__file__).resolve().parents[1] / "assets"


# ---------------------------------------------------------------------------- SSIM
def old_ssim_map(pred, target, max_val=1.0, window=11, sigma=1.5, k1=0.01, k2=0.03):
    c, h, w = pred.shape[-3:]
    x = pred.double().reshape(-1, c, h, w)
    y = target.double().reshape(-1, c, h, w)
    t = torch.arange(window, dtype=x.dtype) - (window - 1) / 2
    g = torch.exp(-(t**2) / (2 * sigma**2))
    g = g / g.sum()
    gx, gy = g.view(1, 1, 1, -1).expand(c, 1, 1, -1), g.view(1, 1, -1, 1).expand(c, 1, -1, 1)

    def blur(v):
        return F.conv2d(F.conv2d(v, gx, groups=c), gy, groups=c)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = (k1 * max_val) ** 2, (k2 * max_val) ** 2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return s.reshape(*pred.shape[:-3], c, *s.shape[-2:])


def image_pairs(seed: int, shape=(2, 3, 40, 52)):
    """Random images, a noisy copy, a constant image and a dark low-contrast pair."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g)
    noisy = (x + 0.1 * torch.randn(shape, generator=g)).clamp(0, 1)
    flat = torch.full(shape, 0.3)
    dark = 1e-3 * torch.rand(shape, generator=g)
    return [(x, torch.rand(shape, generator=g)), (x, noisy), (x, flat), (flat, flat + 0.2), (dark, dark.flip(-1))]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_ssim_map_equals_the_old_valid_window_map(seed, dtype):
    for a, b in image_pairs(seed):
        new = ssim_map(a.to(dtype), b.to(dtype))
        assert new.dtype == torch.float64 and new.shape == (2, 3, 30, 42)
        torch.testing.assert_close(new, old_ssim_map(a.to(dtype), b.to(dtype)), rtol=0, atol=1e-12)


def test_ssim_metric_and_loss_equal_the_old_ones():
    for a, b in image_pairs(2):
        assert ssim(a, b) == pytest.approx(float(old_ssim_map(a, b).mean()), abs=1e-12)
        assert ssim(a, b, max_val=2.0, window=7) == pytest.approx(float(old_ssim_map(a, b, 2.0, 7).mean()), abs=1e-12)
        old_loss = (a - b).abs().mean() + 0.2 * (1 - old_ssim_map(a, b).mean())
        torch.testing.assert_close(rgb_loss(a, b).double(), old_loss, rtol=0, atol=1e-5)  # float32
    lead = torch.rand(2, 2, 3, 16, 16), torch.rand(2, 2, 3, 16, 16)  # extra leading dimensions
    torch.testing.assert_close(ssim_map(*lead), old_ssim_map(*lead))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_ssim_loss_of_half_precision_is_finite_and_near_float64(dtype):
    for a, b in image_pairs(3):
        loss = rgb_loss(a.to(dtype), b.to(dtype), LossWeights(l1=0.0, perceptual=1.0))
        assert torch.isfinite(loss)
        torch.testing.assert_close(loss.double(), 1 - old_ssim_map(a, b).mean(), rtol=0, atol=2e-2)


def test_ssim_loss_has_the_old_gradient():
    a, b = image_pairs(4)[1]
    new, old = a.clone().requires_grad_(True), a.double().clone().requires_grad_(True)
    rgb_loss(new, b).backward()
    ((old - b).abs().mean() + 0.2 * (1 - old_ssim_map(old, b).mean())).backward()
    torch.testing.assert_close(new.grad.double(), old.grad, rtol=1e-3, atol=1e-8)


# ---------------------------------------------------------------------------- rotations
def old_normalize_quat(q, eps=1e-8):
    m = q.detach().abs().amax(-1, keepdim=True).clamp_min(eps)
    s = q / m
    n = s.norm(dim=-1, keepdim=True)
    ident = torch.zeros_like(q)
    ident[..., 0] = 1.0
    return torch.where(m * n > eps, s / n.clamp_min(1.0), ident)


def old_quat_to_rotmat(q):
    w, x, y, z = old_normalize_quat(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def old_rotmat_to_quat(R):
    m = R.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    case = torch.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1).argmax(-1)
    q = torch.empty(m.shape[0], 4, dtype=R.dtype)
    s0 = (1 + tr).clamp_min(1e-12).sqrt() * 2
    s1 = (1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2]).clamp_min(1e-12).sqrt() * 2
    s2 = (1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2]).clamp_min(1e-12).sqrt() * 2
    s3 = (1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]).clamp_min(1e-12).sqrt() * 2
    branches = [
        torch.stack([s0 / 4, (m[:, 2, 1] - m[:, 1, 2]) / s0, (m[:, 0, 2] - m[:, 2, 0]) / s0, (m[:, 1, 0] - m[:, 0, 1]) / s0], -1),
        torch.stack([(m[:, 2, 1] - m[:, 1, 2]) / s1, s1 / 4, (m[:, 0, 1] + m[:, 1, 0]) / s1, (m[:, 0, 2] + m[:, 2, 0]) / s1], -1),
        torch.stack([(m[:, 0, 2] - m[:, 2, 0]) / s2, (m[:, 0, 1] + m[:, 1, 0]) / s2, s2 / 4, (m[:, 1, 2] + m[:, 2, 1]) / s2], -1),
        torch.stack([(m[:, 1, 0] - m[:, 0, 1]) / s3, (m[:, 0, 2] + m[:, 2, 0]) / s3, (m[:, 1, 2] + m[:, 2, 1]) / s3, s3 / 4], -1),
    ]  # fmt: skip
    for i, b in enumerate(branches):
        q[case == i] = b[case == i]
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    return old_normalize_quat(q).reshape(*R.shape[:-2], 4)


def old_quat_mul(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)  # fmt: skip


def hard_quaternions(dtype) -> torch.Tensor:
    """(N, 4): random, zero, tiny, huge, single-axis half turns and near-identity quaternions."""
    big = 1e300 if dtype == torch.float64 else 1e37
    special = torch.tensor([
        [0.0, 0, 0, 0], [5e-9, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 1, 1, 0],
        [1, 1e-9, 0, 0], [-1, 0, 1e-7, 0], [big, big / 3, -big / 7, 0], [1e-7, 2e-7, 0, -3e-7],
        [1e-4, 1, 1, 1], [0, 0.6, -0.8, 1e-9],
    ], dtype=torch.float64).to(dtype)  # fmt: skip
    return torch.cat([special, torch.randn(4000, 4, generator=torch.Generator().manual_seed(5), dtype=dtype)])


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_rotations_equal_the_old_conversions(dtype, tol):
    q = hard_quaternions(dtype)
    R = quat_to_rotmat(q)
    assert R.dtype == dtype and torch.isfinite(R).all()
    torch.testing.assert_close(R, old_quat_to_rotmat(q), rtol=0, atol=tol)
    q2 = rotmat_to_quat(R)
    assert (q2[:, 0] >= 0).all()
    # equal up to q ~ -q where w is 0 (the old and new branches may pick either sign then)
    dots = (q2 * old_rotmat_to_quat(R)).sum(-1)
    torch.testing.assert_close(dots.abs(), torch.ones_like(dots), rtol=0, atol=tol)
    torch.testing.assert_close(q2[dots > 0], old_rotmat_to_quat(R)[dots > 0], rtol=0, atol=10 * tol)
    torch.testing.assert_close(quat_to_rotmat(q2), R, rtol=0, atol=10 * tol)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_rotations_are_finite_and_near_float32(dtype):
    q = hard_quaternions(torch.float32)[:-3990]
    q = q[q.abs().amax(-1) < 1e4]  # huge values overflow half precision by themselves
    R = quat_to_rotmat(q.to(dtype))
    assert R.dtype == dtype and torch.isfinite(R).all()
    torch.testing.assert_close(R.float(), old_quat_to_rotmat(q.to(dtype).float()), rtol=0, atol=2e-2)
    assert torch.isfinite(rotmat_to_quat(R)).all()


def test_quat_mul_equals_the_old_product_with_broadcasting_and_gradients():
    g = torch.Generator().manual_seed(6)
    a = torch.randn(3, 1, 1, 4, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(3, 5, 7, 4, generator=g, dtype=torch.float64, requires_grad=True)
    new = quat_mul(a, b)
    torch.testing.assert_close(new, old_quat_mul(a, b), rtol=0, atol=1e-14)
    grads = torch.autograd.grad(new.square().sum(), (a, b))
    old = torch.autograd.grad(old_quat_mul(a, b).square().sum(), (a, b))
    for n, o in zip(grads, old, strict=True):
        torch.testing.assert_close(n, o)


@pytest.mark.parametrize("axis", ["x", "y"])
@pytest.mark.parametrize("theta", [0.0, 1e-9, 3.0, -30.0, 90.0, 180.0, 271.5])
def test_axis_rotation_equals_the_old_matrix(axis, theta):
    import math

    c, s = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    old = [[1, 0, 0], [0, c, -s], [0, s, c]] if axis == "x" else [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    torch.testing.assert_close(axis_rotation(axis, theta), torch.tensor(old, dtype=torch.float64), rtol=0, atol=1e-15)


def test_normalize_quat_is_unchanged_on_hard_inputs():
    for dtype in (torch.float32, torch.float64):
        q = hard_quaternions(dtype)
        assert torch.equal(normalize_quat(q), old_normalize_quat(q))


# ---------------------------------------------------------------------------- PLY
def test_ply_reads_old_files_identically_and_writes_the_same_bytes(tmp_path):
    ref = load_file(str(DATA / "gaussians_3dgs.safetensors"))
    read = Gaussians.from_ply(DATA / "gaussians_3dgs.ply")
    for name, t in read.tensors().items():
        if name == "scales":  # exp of the stored logarithms: torch releases differ in the last bit
            torch.testing.assert_close(t, ref[f"read.{name}"], rtol=2.4e-7, atol=0)
        else:
            assert torch.equal(t, ref[f"read.{name}"]), name
    written = Gaussians(**{k[len("written.") :]: v for k, v in ref.items() if k.startswith("written.")})
    written.to_ply(tmp_path / "new.ply")
    assert (tmp_path / "new.ply").read_bytes() == (DATA / "gaussians_3dgs.ply").read_bytes()


# ---------------------------------------------------------------------------- EMA
class OldEMA:
    def __init__(self, model, decay):
        self.decay, self.updates = decay, 0
        self.shadow = {k: v.detach().float().clone() if v.is_floating_point() else v.detach().clone()
                       for k, v in model.state_dict().items()}  # fmt: skip

    @torch.no_grad()
    def update(self, model):
        self.updates += 1
        d = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for k, v in model.state_dict().items():
            if v.is_floating_point():
                self.shadow[k].lerp_(v.float(), 1 - d)
            else:
                self.shadow[k].copy_(v)


def test_ema_weights_equal_the_old_ema_after_n_updates():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.BatchNorm1d(8), torch.nn.Linear(8, 2))
    new, old = ema_model(model, 0.95), OldEMA(model, 0.95)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    for step in range(40):  # the ramp (1 + n) / (10 + n) passes the decay 0.95 at n = 161: all ramp
        model(torch.randn(16, 4)).square().mean().backward()
        opt.step()
        opt.zero_grad()
        new.update_parameters(model)
        old.update(model)
        if step in (0, 1, 39):
            state = new.module.state_dict()
            assert state.keys() == old.shadow.keys()
            for k, v in old.shadow.items():
                torch.testing.assert_close(state[k], v, rtol=0, atol=1e-7, msg=k)
    assert not torch.allclose(new.module[0].weight, model[0].weight)  # it lags behind the model


def test_ema_decay_is_capped():
    model = torch.nn.Linear(2, 2, bias=False)
    ema, old = ema_model(model, 0.5), OldEMA(model, 0.5)
    for _ in range(5):
        with torch.no_grad():
            model.weight.add_(1.0)
        ema.update_parameters(model)
        old.update(model)
    torch.testing.assert_close(ema.module.weight, old.shadow["weight"], rtol=0, atol=1e-7)


# ---------------------------------------------------------------------------- image grid
def old_save_grid(rows, path, row_labels=None, col_labels=None, pad=4):
    h, w = rows[0][0].shape[-2:]
    left = 110 if row_labels else 0
    top = 18 if col_labels else 0
    ncol = max(len(r) for r in rows)
    canvas = Image.new("RGB", (left + ncol * (w + pad) + pad, top + len(rows) * (h + pad) + pad), "white")
    draw = ImageDraw.Draw(canvas)
    for j, label in enumerate(col_labels or []):
        draw.text((left + pad + j * (w + pad), 3), label, fill="black")
    for i, row in enumerate(rows):
        y = top + pad + i * (h + pad)
        if row_labels:
            for k, line in enumerate(row_labels[i].split("\n")):
                draw.text((4, y + 4 + 12 * k), line, fill="black")
        for j, img in enumerate(row):
            canvas.paste(Image.fromarray(to_uint8(img).numpy()), (left + pad + j * (w + pad), y))
    canvas.save(path)


@pytest.mark.parametrize("labels", [False, True])
def test_save_grid_draws_the_old_pixels(tmp_path, labels):
    g = torch.Generator().manual_seed(7)
    rows = [[torch.rand(3, 20, 30, generator=g) * 1.2 - 0.1 for _ in range(n)] for n in (3, 1, 2)]
    rows[1][0] = rows[1][0].double()
    kw = {"row_labels": ["a", "two\nlines", "c"], "col_labels": ["x", "y", "z"]} if labels else {}
    save_grid(rows, tmp_path / "new.png", **kw)
    old_save_grid(rows, tmp_path / "old.png", **kw)
    new, old = (np.asarray(Image.open(tmp_path / f"{n}.png")) for n in ("new", "old"))
    assert new.shape == old.shape == ((18 if labels else 0) + 3 * 24 + 4, (110 if labels else 0) + 3 * 34 + 4, 3)
    np.testing.assert_array_equal(new, old)
