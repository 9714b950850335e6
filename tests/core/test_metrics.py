"""Image metrics: PSNR and SSIM against values derived by hand."""

import math

import pytest
import torch

from gensplat_transforms.core.metrics import psnr, ssim, ssim_map

C1, C2 = 0.01**2, 0.03**2


def _image(seed: int, shape=(2, 3, 32, 40)) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    smooth = torch.nn.functional.avg_pool2d(torch.rand(shape, generator=g), 5, 1, 2)
    return smooth.clamp(0, 1)


def test_psnr_of_a_constant_error():
    x = torch.full((3, 8, 8), 0.5)
    assert psnr(x + 0.1, x) == pytest.approx(20.0)
    assert psnr(x, x) == math.inf


def test_ssim_of_identical_images_is_one():
    x = _image(0)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    assert ssim_map(x, x).shape == (2, 3, 22, 30)  # valid windows only


def test_noise_lowers_ssim_monotonically():
    x = _image(1)
    g = torch.Generator().manual_seed(2)
    noise = torch.randn(x.shape, generator=g)
    scores = [ssim((x + s * noise).clamp(0, 1), x) for s in (0.01, 0.05, 0.2)]
    assert 1.0 > scores[0] > scores[1] > scores[2]
    assert ssim(x, (x + 0.05 * noise).clamp(0, 1)) == pytest.approx(scores[1])  # symmetric


def test_constant_shift_of_a_constant_image():
    # x = a and y = a + c everywhere: both variances and the covariance vanish, so the
    # contrast-structure factor is C2 / C2 = 1 and SSIM is the luminance term alone:
    # (2 a (a + c) + C1) / (a^2 + (a + c)^2 + C1).
    a, c = 0.2, 0.1
    x = torch.full((3, 16, 16), a, dtype=torch.float64)
    expected = (2 * a * (a + c) + C1) / (a**2 + (a + c) ** 2 + C1)
    assert ssim(x + c, x) == pytest.approx(expected, rel=1e-9)  # 0.92314...


def test_one_window_against_direct_weighted_statistics():
    x, y = _image(3, (1, 1, 20, 20)), _image(4, (1, 1, 20, 20))
    i, j = 4, 7  # window centred on pixel (i + 5, j + 5)
    t = torch.arange(11, dtype=torch.float64) - 5
    w = torch.exp(-(t[:, None] ** 2 + t[None] ** 2) / (2 * 1.5**2))
    w /= w.sum()
    px, py = x[0, 0, i : i + 11, j : j + 11].double(), y[0, 0, i : i + 11, j : j + 11].double()
    mx, my = (w * px).sum(), (w * py).sum()
    vx, vy = (w * (px - mx) ** 2).sum(), (w * (py - my) ** 2).sum()
    cxy = (w * (px - mx) * (py - my)).sum()
    expected = (2 * mx * my + C1) * (2 * cxy + C2) / ((mx**2 + my**2 + C1) * (vx + vy + C2))
    assert float(ssim_map(x, y)[0, 0, i, j]) == pytest.approx(float(expected), rel=1e-9)


def test_masked_ssim_averages_the_selected_window_centres():
    x, y = _image(5), _image(6)
    full = torch.ones(2, 1, 32, 40, dtype=torch.bool)
    assert ssim(x, y, full) == pytest.approx(ssim(x, y))
    half = full.clone()
    half[..., 20:] = False  # window centres in columns 5..19, i.e. map columns 0..14
    assert ssim(x, y, half) == pytest.approx(float(ssim_map(x, y)[..., :15].mean()))
    with pytest.raises(ValueError, match="no window"):
        ssim(x, y, torch.zeros_like(full))


def test_ssim_rejects_bad_shapes():
    with pytest.raises(ValueError, match="one shape"):
        ssim(torch.zeros(3, 16, 16), torch.zeros(3, 16, 17))
    with pytest.raises(ValueError, match="smaller"):
        ssim(torch.zeros(3, 8, 8), torch.zeros(3, 8, 8))
