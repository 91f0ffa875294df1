"""Losses and metrics against scikit-image, scipy-based hand computations and closed forms."""

import importlib.util
import math
import sys

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage.metrics import structural_similarity

from mvgs_plugin import losses, metrics

C1, C2 = 0.01 ** 2, 0.03 ** 2


def skimage_ssim(a, b):
    return structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=-1)


def zero_padded_ssim(a, b):
    """The original 3DGS SSIM (11-tap Gaussian, zero padding, mean of the full map), in scipy."""
    x = np.arange(11) - 5.0
    g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
    g /= g.sum()

    def blur(img):
        out = ndimage.correlate1d(img, g, axis=0, mode="constant", cval=0.0)
        return ndimage.correlate1d(out, g, axis=1, mode="constant", cval=0.0)

    maps = []
    for c in range(a.shape[2]):
        p, q = a[..., c], b[..., c]
        mp, mq = blur(p), blur(q)
        vp, vq, cov = blur(p * p) - mp ** 2, blur(q * q) - mq ** 2, blur(p * q) - mp * mq
        maps.append((2 * mp * mq + C1) * (2 * cov + C2) / ((mp ** 2 + mq ** 2 + C1) * (vp + vq + C2)))
    return float(np.mean(maps))


def structured_pair(h, w, rng):
    """A ramp + checkerboard + sinusoid image and a blurred, shifted, noisy copy."""
    jj, ii = np.mgrid[0:h, 0:w]
    ramp = ii / max(w - 1, 1)
    checker = ((ii // 4 + jj // 4) % 2).astype(float)
    wave = 0.5 + 0.5 * np.sin(ii / 3.0) * np.cos(jj / 5.0)
    a = np.stack([ramp, checker, wave], axis=-1)
    b = ndimage.gaussian_filter(a, sigma=(1.0, 1.0, 0)) * 0.9 + 0.05
    b = np.clip(b + 0.03 * rng.standard_normal(a.shape), 0, 1)
    return a, b


SIZES = [(11, 11), (16, 23), (40, 32), (64, 64)]


@pytest.mark.parametrize("h, w", SIZES)
def test_ssim_agrees_with_skimage(h, w):
    rng = np.random.default_rng(h * 100 + w)
    pairs = [(rng.random((h, w, 3)), rng.random((h, w, 3))), structured_pair(h, w, rng)]
    for a, b in pairs:
        expected = skimage_ssim(a, b)
        got64 = float(losses.ssim(torch.from_numpy(a), torch.from_numpy(b)))
        got32 = float(losses.ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()))
        assert abs(got64 - expected) < 1e-9 and abs(got32 - expected) < 1e-3
        assert abs(metrics.ssim(a, b) - expected) < 1e-12


def test_ssim_zero_padding_is_the_original_3dgs_ssim():
    rng = np.random.default_rng(1)
    for h, w in [(1, 1), (5, 7), (20, 13)]:
        a, b = structured_pair(h, w, rng)
        got = float(losses.ssim(torch.from_numpy(a), torch.from_numpy(b), padding="zero"))
        assert abs(got - zero_padded_ssim(a, b)) < 1e-9


@pytest.mark.parametrize("h,w", [(64, 48), (12, 12), (5, 7)])
def test_the_3dgs_evaluation_ssim_is_the_zero_padded_one_and_reads_higher_than_skimages(h, w):
    """metrics.ssim_3dgs against the scipy computation of 3DGS's metrics.py; on a noisy pair the
    zero-padded mean counts the border pixels skimage leaves out (and reads higher here), the
    gap larger on the smaller image."""
    rng = np.random.default_rng(h * w)
    a = rng.uniform(0.2, 0.8, (h, w, 3))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    assert metrics.ssim_3dgs(a, b) == pytest.approx(zero_padded_ssim(a, b), abs=1e-9)
    assert metrics.ssim_3dgs(torch.from_numpy(a).float(), torch.from_numpy(a).float()) == pytest.approx(1.0, abs=1e-6)
    if h >= 11 and w >= 11:
        assert metrics.ssim_3dgs(a, b) > metrics.ssim(a, b)
    with pytest.raises(ValueError, match=r"ssim_3dgs: images must be \[H,W,C\] or \[H,W\], got \[2, 2, 2, 3\]"):
        metrics.ssim_3dgs(np.zeros((2, 2, 2, 3)), np.zeros((2, 2, 2, 3)))


def test_batched_ssim_and_reduction():
    rng = np.random.default_rng(2)
    imgs = [structured_pair(16, 20, rng) for _ in range(3)]
    a = torch.from_numpy(np.stack([p[0] for p in imgs]))
    b = torch.from_numpy(np.stack([p[1] for p in imgs]))
    per = losses.ssim(a, b, reduction="none")
    assert per.shape == (3,)
    expected = [skimage_ssim(p[0], p[1]) for p in imgs]
    assert np.allclose(per.numpy(), expected, atol=1e-9)
    assert abs(float(losses.ssim(a, b)) - np.mean(expected)) < 1e-9


def test_ssim_gradient_matches_finite_differences():
    # directional derivatives (central differences, float64) against autograd's gradient
    rng = np.random.default_rng(3)
    a = torch.from_numpy(rng.random((6, 7, 3))).requires_grad_(True)
    b = torch.from_numpy(rng.random((6, 7, 3)))
    for padding in ("valid", "zero"):
        (grad,) = torch.autograd.grad(losses.ssim(a, b, padding=padding), a)
        for _ in range(3):
            v = torch.from_numpy(rng.standard_normal((6, 7, 3)))
            eps = 1e-6
            with torch.no_grad():
                fd = (losses.ssim(a + eps * v, b, padding=padding)
                      - losses.ssim(a - eps * v, b, padding=padding)) / (2 * eps)
            assert float((grad * v).sum()) == pytest.approx(float(fd), rel=1e-5, abs=1e-8)


@pytest.mark.parametrize("n", range(1, 9))
@pytest.mark.parametrize("padding", ["valid", "zero"])
def test_small_images_finite_in_range_with_finite_gradients(n, padding):
    rng = np.random.default_rng(n)
    a = torch.from_numpy(rng.random((n, n, 3))).float().requires_grad_(True)
    b = torch.from_numpy(rng.random((n, n, 3))).float()
    s = losses.ssim(a, b, padding=padding).detach()
    assert math.isfinite(float(s)) and -1.0 <= float(s) <= 1.0
    loss = losses.photometric_loss(a, b, padding=padding)
    loss.backward()
    assert bool(torch.isfinite(a.grad).all()) and float(a.grad.abs().sum()) > 0
    assert float(losses.ssim(b, b, padding=padding)) == pytest.approx(1.0, abs=1e-6)
    # the evaluation metric applies the same small-window rule as the valid-padding loss
    if padding == "valid":
        assert metrics.ssim(a.detach().double(), b.double()) == pytest.approx(
            float(losses.ssim(a.detach().double(), b.double())), abs=1e-9)


@pytest.mark.parametrize("n", [1, 3, 8, 16])
def test_constant_images_have_the_closed_form_luminance_ssim(n):
    c1, c2 = 0.2, 0.7  # zero variances: SSIM = (2 c1 c2 + C1) / (c1^2 + c2^2 + C1)
    a, b = np.full((n, n, 3), c1), np.full((n, n, 3), c2)
    expected = (2 * c1 * c2 + C1) / (c1 ** 2 + c2 ** 2 + C1)
    assert float(losses.ssim(torch.from_numpy(a), torch.from_numpy(b))) == pytest.approx(expected, abs=1e-9)
    assert metrics.ssim(a, b) == pytest.approx(expected, abs=1e-9)
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    zero_map = float(losses.ssim(torch.from_numpy(a).float(), torch.from_numpy(a).float(), padding="zero"))
    assert zero_map == pytest.approx(1.0, abs=1e-5)


def test_l1_dssim_and_photometric_loss_hand_formula():
    rng = np.random.default_rng(4)
    a, b = structured_pair(24, 18, rng)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    l1 = np.abs(a - b).mean()
    assert float(losses.l1_loss(ta, tb)) == pytest.approx(l1, abs=1e-12)
    assert float(losses.dssim_loss(ta, tb)) == pytest.approx((1 - skimage_ssim(a, b)) / 2, abs=1e-9)
    assert float(losses.dssim_loss(ta, ta)) == pytest.approx(0.0, abs=1e-12)
    # default: the original 3DGS loss, 0.8 L1 + 0.2 (1 - zero-padded SSIM)
    assert float(losses.photometric_loss(ta, tb)) == pytest.approx(
        0.8 * l1 + 0.2 * (1 - zero_padded_ssim(a, b)), abs=1e-9)
    assert float(losses.photometric_loss(ta, tb, lambda_dssim=0.5, ssim_term="dssim", padding="valid")) \
        == pytest.approx(0.5 * l1 + 0.5 * (1 - skimage_ssim(a, b)) / 2, abs=1e-9)
    with pytest.raises(ValueError, match="lambda_dssim"):
        losses.photometric_loss(ta, tb, lambda_dssim=1.5)
    with pytest.raises(ValueError, match=r"same shape, got \[24, 18, 3\] and \[24, 17, 3\]"):
        losses.l1_loss(ta, tb[:, :17])


def test_psnr_closed_form_and_edge_cases():
    rng = np.random.default_rng(5)
    a = rng.uniform(0.2, 0.8, size=(13, 9, 3))
    for delta in (0.1, 0.01, 1e-4):
        assert metrics.psnr(a + delta, a) == pytest.approx(-10 * math.log10(delta ** 2), abs=1e-6)
    assert metrics.psnr(a, a) == float("inf")
    assert metrics.psnr(torch.zeros(1, 1, 3), torch.zeros(1, 1, 3)) == float("inf")
    assert metrics.psnr(torch.zeros(1, 1, 3), torch.ones(1, 1, 3)) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="same shape"):
        metrics.psnr(a, a[:5])
    with pytest.raises(ValueError, match="NaN"):
        metrics.psnr(np.full((2, 2, 3), np.nan), np.zeros((2, 2, 3)))


@pytest.mark.parametrize("n", range(1, 9))
def test_metric_ssim_small_images(n):
    rng = np.random.default_rng(10 + n)
    a, b = rng.random((n, n + 1, 3)), rng.random((n, n + 1, 3))
    v = metrics.ssim(a, b)
    assert math.isfinite(v) and -1.0 <= v <= 1.0
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert metrics.psnr(a, b) > 0


def test_lpips_is_explicitly_unavailable_without_the_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "lpips", None)  # makes "import lpips" fail
    assert metrics.lpips_available() is False
    with pytest.warns(UserWarning, match="LPIPS unavailable"):
        assert metrics.lpips(np.zeros((16, 16, 3)), np.ones((16, 16, 3))) is None


def test_lpips_matches_what_is_installed():
    a = np.random.default_rng(6).random((64, 64, 3))
    installed = all(importlib.util.find_spec(m) is not None for m in ("lpips", "torchvision"))
    if not installed:
        assert metrics.lpips_available() is False
    if metrics.lpips_available():
        assert metrics.lpips(a, a) == pytest.approx(0.0, abs=1e-6)
        assert metrics.lpips(a, 1.0 - a) > 0.05
    else:
        with pytest.warns(UserWarning, match="LPIPS unavailable"):
            assert metrics.lpips(a, a) is None
