"""Input checks for rasterization(): every error names the argument, what was expected and what
was given, and is raised before any work is done."""

from __future__ import annotations

import math
from typing import Optional, Sequence

import torch
from torch import Tensor

from mvgs_plugin.checks import check_int

FLOAT_DTYPES = (torch.float32, torch.float64)


def shape_str(t: Tensor) -> str:
    return "[" + ",".join(str(s) for s in t.shape) + "]"


def check_tensor(name: str, t, expected: Sequence[Optional[int]], expected_str: str) -> Tensor:
    """Type, shape (None = any size) and dtype of one tensor argument (finiteness: check_finite,
    after check_same, so a tensor on another device is reported as such)."""
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor of shape {expected_str}, got {type(t).__name__}")
    if t.dim() != len(expected) or any(e is not None and s != e for s, e in zip(t.shape, expected)):
        raise ValueError(f"{name} must be {expected_str}, got {shape_str(t)}")
    if t.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name} must be float32 or float64, got {t.dtype}")
    return t


def all_finite(t: Tensor) -> bool:
    """Whether every entry of t is finite. One reduction first (cheap, no mask allocated, no
    cast): a NaN or Inf anywhere makes the sum non-finite, so a finite sum clears the tensor;
    finite entries that overflow the sum fall through to the exact check."""
    t = t.detach()
    return t.numel() == 0 or bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


def check_finite(name: str, t: Tensor) -> None:
    t = t.detach()
    if all_finite(t):
        return
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(f"{name} must be finite, got {t[idx].item()} at index {list(idx)}")


def check_range(name: str, t: Tensor, lo: float, hi: float, what: str) -> None:
    t = t.detach()
    if t.numel() == 0 or (t.min().item() >= lo and t.max().item() <= hi):
        return
    idx = tuple(int(i) for i in ((t < lo) | (t > hi)).nonzero()[0])
    raise ValueError(f"{name} must be {what}, got {t[idx].item()} at index {list(idx)}")


def check_same(tensors: dict) -> None:
    """All float tensors share one dtype and one device (no silent casts or copies)."""
    items = [(k, v) for k, v in tensors.items() if v is not None]
    name0, t0 = items[0]
    for name, t in items[1:]:
        if t.dtype != t0.dtype:
            raise TypeError(f"{name} has dtype {t.dtype} but {name0} has {t0.dtype}; all must match")
        if t.device != t0.device:
            raise TypeError(f"{name} is on {t.device} but {name0} is on {t0.device}; all must match")


def check_positive_int(name: str, v) -> int:
    return check_int(name, v, 1)


def check_scalar(name: str, v, lo: float = -math.inf, lo_open: bool = False, finite: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
        raise ValueError(f"{name} must be a real number, got {v!r}")
    if finite and math.isinf(v):
        raise ValueError(f"{name} must be finite, got {v!r}")
    if (v <= lo) if lo_open else (v < lo):
        raise ValueError(f"{name} must be {'>' if lo_open else '>='} {lo}, got {v!r}")
    return float(v)


# Quaternions are normalised with this floor on the norm (projection.py, project.cpp): below it
# the division would not normalise (a wrong rotation, silently), so such rows are refused.
QUAT_NORM_FLOOR = 1e-12
# near_plane below this puts 1 / z^2 of the projection's Jacobian beyond float32 (1/1e-10^2 = 1e20
# times a focal of up to 1e18 still fits).
NEAR_PLANE_FLOOR = 1e-10


def check_quats(quats: Tensor) -> None:
    q = quats.detach()
    # One pass: the squared norm, in the model's dtype, must be in [floor^2, dtype max] (it
    # underflows below a norm of ~1e-19 in float32, which the floor refuses anyway, and overflows
    # above ~1.8e19, where the renderers' normalisation would fail).
    n2 = (q * q).sum(-1)
    bad = ~((n2 >= QUAT_NORM_FLOOR ** 2) & (n2 <= torch.finfo(q.dtype).max))
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        norm = float(torch.linalg.vector_norm(q[i].double()))
        raise ValueError(f"quats must have a norm in [{QUAT_NORM_FLOOR:g}, {math.sqrt(torch.finfo(q.dtype).max):.3g}] "
                         f"(they are normalised), got norm {norm:.3g} at row {i}: {q[i].tolist()}")


def max_scale(dtype: torch.dtype) -> float:
    """The largest scale the renderer takes in `dtype`: the 3D covariance squares the scales, and
    beyond this (with a 1e3 margin for the sums of the projection) the square overflows."""
    return math.sqrt(torch.finfo(dtype).max) / 1e3


def check_scales(scales: Tensor) -> None:
    check_range("scales", scales, 0.0, math.inf, ">= 0 (activated, not log-scales)")
    limit = max_scale(scales.dtype)
    check_range("scales", scales, 0.0, limit, f"<= {limit:.3g} (its square must fit in {scales.dtype})")


def check_viewmats(viewmats: Tensor) -> None:
    bottom = viewmats.new_tensor([0.0, 0.0, 0.0, 1.0])
    bad = (viewmats[:, 3, :].detach() - bottom).abs().amax(dim=-1) > 1e-6
    if bool(bad.any()):
        c = int(bad.nonzero()[0, 0])
        raise ValueError(f"viewmats[{c}] last row must be [0,0,0,1], got {viewmats[c, 3].tolist()}")
    rot = viewmats[:, :3, :3].detach()
    err = (rot @ rot.transpose(1, 2) - torch.eye(3, dtype=rot.dtype, device=rot.device)).abs().amax(dim=(1, 2))
    bad = err > 1e-3
    if bool(bad.any()):
        c = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"viewmats[{c}] must be a rigid world-to-camera transform (orthonormal rotation block), "
            f"got R R^T - I with max abs {err[c].item():.3g}"
        )
    det = torch.linalg.det(rot.to(torch.float64))
    bad = det < 0
    if bool(bad.any()):
        c = int(bad.nonzero()[0, 0])
        raise ValueError(f"viewmats[{c}] rotation block has det {float(det[c]):.6g}: a reflection, not a rotation "
                         "(one camera axis flipped? OpenGL cameras need y and z negated, not one of them)")


def check_Ks(Ks: Tensor) -> None:
    k = Ks.detach()
    for name, val, ok in (
        ("fx = Ks[c,0,0]", k[:, 0, 0], k[:, 0, 0] > 0),
        ("fy = Ks[c,1,1]", k[:, 1, 1], k[:, 1, 1] > 0),
        ("skew = Ks[c,0,1]", k[:, 0, 1], k[:, 0, 1] == 0),
    ):
        if not bool(ok.all()):
            c = int((~ok).nonzero()[0, 0])
            want = "0 (no skew)" if "skew" in name else "> 0"
            raise ValueError(f"{name.replace('c', str(c), 1)} must be {want}, got {val[c].item()}")
    rows = torch.stack([k[:, 1, 0], k[:, 2, 0], k[:, 2, 1], k[:, 2, 2] - 1], dim=-1).abs().amax(dim=-1)
    if bool((rows > 1e-6).any()):
        c = int((rows > 1e-6).nonzero()[0, 0])
        raise ValueError(f"Ks[{c}] must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {k[c].tolist()}")
