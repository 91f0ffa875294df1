"""Evaluation metrics: PSNR, SSIM (scikit-image) and LPIPS (only with real weights, offline).

Inputs are images [H, W, C] with values in [0, 1] (torch tensors or numpy arrays); results are
Python floats. Nothing is clamped: clamp renders to [0, 1] before calling, as the original 3DGS
evaluation does, if your renderer can leave that range.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .losses import ssim as _ssim_torch, ssim_window

__all__ = ["psnr", "masked_psnr", "ssim", "ssim_3dgs", "lpips", "lpips_available"]


def _as_numpy_pair(a, b, what: str) -> tuple[np.ndarray, np.ndarray]:
    a = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
    b = b.detach().cpu().numpy() if isinstance(b, torch.Tensor) else np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"{what}: images must have the same shape, got {list(a.shape)} and {list(b.shape)}")
    if a.size == 0:
        raise ValueError(f"{what}: images are empty, shape {list(a.shape)}")
    a, b = a.astype(np.float64), b.astype(np.float64)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError(f"{what}: images contain NaN or inf")
    return a, b


def psnr(img1, img2) -> float:
    """Peak signal-to-noise ratio in dB for data range 1: ``-10 log10(MSE)``.

    Any matching shapes; the MSE is taken over all elements (for a batch this is the PSNR of the
    pooled MSE, not the mean of per-image PSNRs). Identical images give ``float('inf')``.
    """
    a, b = _as_numpy_pair(img1, img2, "psnr")
    mse = float(np.mean((a - b) ** 2))
    if mse == 0.0:
        return float("inf")
    return -10.0 * math.log10(mse)


def masked_psnr(img1, img2, weights) -> float:
    """PSNR in dB over the pixels a mask keeps: ``-10 log10(MSE)`` with the MSE the weighted mean
    of the squared error, ``sum(w (a - b)^2) / (C sum(w))``, for images [H, W, C] and weights
    [H, W] or [H, W, 1] in [0, 1] (a 0/1 mask: the plain PSNR of the kept pixels). Identical kept
    pixels give ``float('inf')``; weights that keep nothing are refused."""
    a, b = _as_numpy_pair(img1, img2, "masked_psnr")
    w = np.asarray(weights.detach().cpu() if isinstance(weights, torch.Tensor) else weights, dtype=np.float64)
    if w.ndim == a.ndim - 1:
        w = w[..., None]
    if a.ndim != 3 or w.shape != a.shape[:2] + (1,):
        raise ValueError(f"masked_psnr: weights {list(w.shape)} do not fit images {list(a.shape)} "
                         "(expected [H, W] or [H, W, 1] for [H, W, C] images)")
    if not (np.isfinite(w).all() and w.min() >= 0 and w.max() <= 1):
        raise ValueError("masked_psnr: weights must be finite and in [0, 1]")
    total = float(w.sum()) * a.shape[2]
    if total == 0.0:
        raise ValueError("masked_psnr: the weights keep no pixel")
    mse = float((w * (a - b) ** 2).sum()) / total
    if mse == 0.0:
        return float("inf")
    return -10.0 * math.log10(mse)


def ssim(img1, img2) -> float:
    """SSIM as scikit-image computes it (``structural_similarity`` with
    ``gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0``, averaged
    over channels): the mean over the pixels whose whole window lies inside the image, as
    Mip-NeRF's evaluation does. The original 3DGS's evaluation zero-pads instead and averages
    every pixel (:func:`ssim_3dgs`), which reads higher on small images.

    Images [H, W, C] (or [H, W]). scikit-image refuses images smaller than its 11 x 11 window;
    for those the window shrinks to the largest odd size w <= min(H, W) with sigma = 1.5 w / 11
    (the rule :func:`mvgs_plugin.losses.ssim` uses), so a 1 x 1 image compares means only. The
    value is always finite and in [-1, 1]; identical images give 1.
    """
    from skimage.metrics import structural_similarity

    a, b = _as_numpy_pair(img1, img2, "ssim")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.ndim != 3:
        raise ValueError(f"ssim: images must be [H,W,C] or [H,W], got {list(a.shape)}")
    win, sigma = ssim_window(a.shape[0], a.shape[1])
    return float(structural_similarity(a, b, win_size=win, sigma=sigma, gaussian_weights=True,
                                       use_sample_covariance=False, data_range=1.0,
                                       channel_axis=-1))


def ssim_3dgs(img1, img2) -> float:
    """SSIM as the original 3DGS code evaluates it (its metrics.py): an 11 x 11 Gaussian window
    (sigma 1.5) over the zero-padded image, averaged over every pixel and channel; the value to
    set beside 3DGS's and MVGS's published tables. Images [H, W, C] (or [H, W]) in [0, 1]."""
    a, b = _as_numpy_pair(img1, img2, "ssim_3dgs")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.ndim != 3:
        raise ValueError(f"ssim_3dgs: images must be [H,W,C] or [H,W], got {list(a.shape)}")
    return float(_ssim_torch(torch.from_numpy(a.astype(np.float64)), torch.from_numpy(b.astype(np.float64)),
                               padding="zero"))


_LPIPS_BACKBONES = {"alex": "AlexNet_Weights", "vgg": "VGG16_Weights", "squeeze": "SqueezeNet1_1_Weights"}


def _lpips_missing(net: str) -> Optional[str]:
    """Why LPIPS with ``net`` cannot run offline, or None when it can."""
    if net not in _LPIPS_BACKBONES:
        return f"unknown LPIPS network {net!r}; choose one of {sorted(_LPIPS_BACKBONES)}"
    try:
        import lpips as lpips_pkg
        import torchvision.models as tvm
    except ImportError as err:
        return f"the 'lpips' and 'torchvision' packages are needed ({err})"
    linear = Path(lpips_pkg.__file__).parent / "weights" / "v0.1" / f"{net}.pth"
    if not linear.is_file():
        return f"LPIPS linear weights not found at {linear}"
    weights = getattr(tvm, _LPIPS_BACKBONES[net], None)
    if weights is None:
        return f"torchvision has no {_LPIPS_BACKBONES[net]} (torchvision >= 0.13 needed)"
    # torchvision downloads backbone weights on first use; we only run when they are cached,
    # so evaluation never depends on the network and never runs with random weights.
    cached = Path(torch.hub.get_dir()) / "checkpoints" / os.path.basename(weights.IMAGENET1K_V1.url)
    if not cached.is_file():
        return (f"backbone weights not cached at {cached}; download them once with "
                f"torchvision.models.{_LPIPS_BACKBONES[net]}.IMAGENET1K_V1.get_state_dict()")
    return None


def lpips_available(net: str = "vgg") -> bool:
    """True when :func:`lpips` can run with real weights without network access."""
    return _lpips_missing(net) is None


@functools.lru_cache(maxsize=None)
def _lpips_model(net: str):
    import lpips as lpips_pkg

    return lpips_pkg.LPIPS(net=net, verbose=False).eval()


def lpips(img1, img2, net: str = "vgg") -> Optional[float]:
    """LPIPS distance (v0.1, ``net`` = "vgg" as the original 3DGS evaluation, or "alex").

    Images [H, W, 3] in [0, 1]. Returns None, with a warning giving the reason, when the
    ``lpips`` package, torchvision or cached backbone weights are missing (see
    :func:`lpips_available`); it never falls back to untrained weights.
    """
    reason = _lpips_missing(net)
    if reason is not None:
        warnings.warn(f"LPIPS unavailable: {reason}", stacklevel=2)
        return None
    a, b = _as_numpy_pair(img1, img2, "lpips")
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"lpips: images must be [H,W,3], got {list(a.shape)}")
    to_tensor = lambda x: torch.from_numpy(x).float().permute(2, 0, 1)[None]  # noqa: E731
    with torch.no_grad():
        d = _lpips_model(net)(to_tensor(a), to_tensor(b), normalize=True)  # [0,1] -> [-1,1]
    return float(d.flatten()[0])
