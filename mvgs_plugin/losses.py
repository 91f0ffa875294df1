"""Differentiable photometric losses: L1, SSIM / D-SSIM, and the 3DGS training loss.

Images are [H, W, C] or [B, H, W, C] (C = 3 for RGB; any C >= 1 works), values in [0, 1].

SSIM uses a Gaussian window (11 x 11, sigma = 1.5), C1 = 0.01^2, C2 = 0.03^2 and population
(biased) local variances, as Wang et al. 2004, the original 3DGS and scikit-image with
``gaussian_weights=True, use_sample_covariance=False``. Two border treatments:

* ``padding="valid"`` (default): the SSIM map is evaluated only where the whole window lies
  inside the image and averaged there. This is what scikit-image reports (it filters with
  reflection and then crops the border), so the training SSIM and the evaluation SSIM agree.
  An image smaller than the window gets a smaller window: the largest odd size w <= min(H, W)
  with sigma = 1.5 * w / 11 (same shape, shrunk); a 1 x 1 image then compares only the means.
  :func:`mvgs_plugin.metrics.ssim` applies the same rule, so the two still agree.
* ``padding="zero"``: the map is evaluated at every pixel with the input zero-padded by 5, the
  window is never shrunk; this is exactly the original 3DGS training SSIM.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

__all__ = ["l1_loss", "ssim", "dssim_loss", "photometric_loss", "ssim_window"]

WINDOW = 11
SIGMA = 1.5
C1 = 0.01 ** 2
C2 = 0.03 ** 2


def ssim_window(height: int, width: int, padding: str = "valid") -> tuple[int, float]:
    """(window size, sigma) used for an image of this size; see the module docstring."""
    if padding == "zero":
        return WINDOW, SIGMA
    w = min(WINDOW, height, width)
    w = w if w % 2 == 1 else w - 1
    return w, SIGMA * w / WINDOW


def _check_pair(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"images must have the same shape, got {list(a.shape)} and {list(b.shape)}")
    if a.ndim not in (3, 4) or a.shape[-1] < 1 or a.shape[-2] < 1 or a.shape[-3] < 1:
        raise ValueError(f"images must be [H,W,C] or [B,H,W,C] and non-empty, got {list(a.shape)}")


def l1_loss(render: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over all elements -> scalar."""
    _check_pair(render, gt)
    return (render - gt).abs().mean()


def _gaussian_1d(size: int, sigma: float, dtype: torch.dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype=dtype, device=device)


def _blur(x: torch.Tensor, g: torch.Tensor, pad: int) -> torch.Tensor:
    """Separable Gaussian filter of [B, K, H, W] per channel (rows, then columns)."""
    k = x.shape[1]
    size = g.numel()
    x = F.conv2d(x, g.view(1, 1, size, 1).expand(k, 1, size, 1), padding=(pad, 0), groups=k)
    return F.conv2d(x, g.view(1, 1, 1, size).expand(k, 1, 1, size), padding=(0, pad), groups=k)


def ssim(img1: torch.Tensor, img2: torch.Tensor, padding: Literal["valid", "zero"] = "valid",
         reduction: Literal["mean", "none"] = "mean") -> torch.Tensor:
    """Structural similarity, differentiable in both inputs.

    Args:
        img1, img2: [H, W, C] or [B, H, W, C].
        padding: "valid" (scikit-image's value) or "zero" (the original 3DGS's); see module doc.
        reduction: "mean" -> scalar; "none" -> [B] per image (scalar for unbatched input).
    Returns:
        SSIM in [-1, 1] (1 for identical images), in the inputs' dtype.
    """
    _check_pair(img1, img2)
    if padding not in ("valid", "zero"):
        raise ValueError(f"padding must be 'valid' or 'zero', got {padding!r}")
    if reduction not in ("mean", "none"):
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    batched = img1.ndim == 4
    x = (img1 if batched else img1[None]).movedim(-1, 1)  # [B, C, H, W]
    y = (img2 if batched else img2[None]).movedim(-1, 1)
    c = x.shape[1]
    size, sigma = ssim_window(x.shape[2], x.shape[3], padding)
    g = _gaussian_1d(size, sigma, x.dtype, x.device)
    # one filter call for all five local moments
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), g,
                  pad=size // 2 if padding == "zero" else 0)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(c, dim=1)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    # C1, C2 > 0 keep both denominators positive even when a variance rounds slightly negative
    num = (2 * mu_x * mu_y + C1) * (2 * cov + C2)
    den = (mu_x * mu_x + mu_y * mu_y + C1) * (var_x + var_y + C2)
    per_image = (num / den).flatten(1).mean(dim=1)  # [B]
    if reduction == "mean":
        return per_image.mean()
    return per_image if batched else per_image[0]


def dssim_loss(img1: torch.Tensor, img2: torch.Tensor,
               padding: Literal["valid", "zero"] = "valid") -> torch.Tensor:
    """Structural dissimilarity (1 - SSIM) / 2, in [0, 1] -> scalar."""
    return (1.0 - ssim(img1, img2, padding=padding)) / 2.0


def photometric_loss(render: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2,
                     ssim_term: Literal["1-ssim", "dssim"] = "1-ssim",
                     padding: Literal["valid", "zero"] = "zero") -> torch.Tensor:
    """The 3DGS training loss (1 - lambda) * L1 + lambda * S -> scalar.

    The defaults reproduce the original 3DGS code exactly: S = 1 - SSIM and zero-padded SSIM.
    Note the paper writes the term as "D-SSIM" but the released code uses 1 - SSIM, i.e. twice
    (1 - SSIM) / 2; the difference changes the gradient magnitudes that densification compares
    with its threshold, so the default follows the code. ``ssim_term="dssim"`` uses
    (1 - SSIM) / 2 instead; ``padding="valid"`` uses the evaluation SSIM.
    """
    lam = float(lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lambda_dssim must be in [0,1], got {lambda_dssim}")
    if ssim_term not in ("1-ssim", "dssim"):
        raise ValueError(f"ssim_term must be '1-ssim' or 'dssim', got {ssim_term!r}")
    s = 1.0 - ssim(render, gt, padding=padding)
    if ssim_term == "dssim":
        s = s / 2.0
    return (1.0 - lam) * l1_loss(render, gt) + lam * s
