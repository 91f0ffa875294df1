"""Real spherical harmonics up to degree 3, in the basis and sign convention of the original 3DGS
(so SH coefficients move between it, gsplat and this renderer unchanged)."""

from __future__ import annotations

import torch
from torch import Tensor

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Basis functions at unit directions.

    Args:
        degree: 0..3.
        dirs: [..., 3] unit vectors.
    Returns:
        [..., (degree+1)^2]
    """
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"sh_degree must be 0, 1, 2 or 3, got {degree!r}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            _C2[0] * x * y,
            _C2[1] * y * z,
            _C2[2] * (2 * zz - xx - yy),
            _C2[3] * x * z,
            _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _C3[0] * y * (3 * xx - yy),
            _C3[1] * x * y * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH value sum_k coeffs[k] * Y_k(dir) (no +0.5 offset, no clamp).

    Args:
        degree: 0..3; only the first (degree+1)^2 coefficients are used.
        coeffs: [..., K, 3] with K >= (degree+1)^2.
        dirs: [..., 3] unit view directions (broadcast against coeffs' leading dims).
    Returns:
        [..., 3]
    """
    n = (degree + 1) ** 2
    basis = sh_basis(degree, dirs)  # [..., n]
    return torch.matmul(basis.unsqueeze(-2), coeffs[..., :n, :]).squeeze(-2)


def sh_to_rgb(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Colour as the original 3DGS forms it: SH value + 0.5, clamped at 0 from below."""
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)
