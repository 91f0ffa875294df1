"""EWA projection of 3D Gaussians to screen-space conics, radii and tile ranges (PyTorch).

Follows docs/design.md "Image formation": the classic 3DGS rules, which gsplat's projection shares.
Everything here is plain tensor code batched over cameras, so autograd provides the gradients
from the screen-space quantities back to means, quaternions, scales and camera poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import torch
from torch import Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions w-x-y-z (normalised here).

    Args:
        quats: [N, 4], no zero rows.
    Returns:
        [N, 3, 3]
    """
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariance R S S^T R^T.

    Args:
        quats: [N, 4] w-x-y-z; scales: [N, 3] (activated).
    Returns:
        [N, 3, 3]
    """
    m = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # R @ diag(s)
    # Broadcast-and-sum instead of a batched matmul: for 3x3 blocks it is several times faster.
    return (m.unsqueeze(-2) * m.unsqueeze(-3)).sum(-1)


@dataclass
class Projection:
    """Screen-space splats for C cameras and N Gaussians (pixel units, centres at +0.5).

    means2d [C,N,2] (differentiable); conics [C,N,3] = upper triangle (a, b, c) of the inverse
    2D covariance (differentiable); depths [C,N] camera-space z (differentiable); compensation
    [C,N] = sqrt(det(cov2d) / det(cov2d + eps2d I)) for the antialiased mode (differentiable);
    radii [C,N] int32 square radius, 0 where culled; rects [C,N,4] int32 tile ranges
    x0, x1, y0, y1 (half-open, empty where culled); valid [C,N] bool.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    compensation: Tensor
    radii: Tensor
    rects: Tensor
    valid: Tensor


# Splats whose 2D determinant (pixels^4) is at or below this are culled: the conic 1/det and its
# gradient 1/det^2 would overflow float64 (a standard deviation under 1e-37 px: no pixel centre
# sees it).
DET_FLOOR = 1e-150


def project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int = 16,
    radius_clip: float = 0.0,
) -> Projection:
    """Projects N Gaussians into C pinhole cameras (OpenCV axes, world-to-camera viewmats).

    Args:
        means: [N, 3]; quats: [N, 4] w-x-y-z; scales: [N, 3]; viewmats: [C, 4, 4]; Ks: [C, 3, 3].

    The arithmetic runs in float64 whatever the inputs' dtype, and the results come back in it:
    in float32 the 2D covariance's determinant overflows for footprints beyond ~4e9 px (a scale
    of 1e10, or a focal of 1e30, was culled) and cancels for long thin needles (a conic 40 %
    off at 3000 px), and its gradients met 0 * inf = NaN. A splat whose float32 results are not
    finite (a footprint so small its conic overflows, a centre beyond float32's range) is
    culled; a huge one's conic underflows to 0, its exact limit (alpha = opacity everywhere).
    """
    if means.dtype == torch.float64:
        return _project64(means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
                          tile_size, radius_clip)
    d = lambda x: x.to(torch.float64)  # noqa: E731  (differentiable: gradients come back cast)
    p = _project64(d(means), d(quats), d(scales), d(viewmats), d(Ks), width, height, near_plane, far_plane,
                   eps2d, tile_size, radius_clip)
    return narrow(p, means.dtype)


def narrow(p: Projection, dtype: torch.dtype) -> Projection:
    """A float64 Projection in `dtype`, culling the splats whose values do not fit in it."""
    means2d, conics = p.means2d.to(dtype), p.conics.to(dtype)
    depths, comp = p.depths.to(dtype), p.compensation.to(dtype)
    fine = torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1) & torch.isfinite(comp)
    if bool(fine.all()):
        return Projection(means2d, conics, depths, comp, p.radii, p.rects, p.valid)
    valid = p.valid & fine
    zero = torch.zeros((), dtype=dtype, device=means2d.device)
    return Projection(torch.where(fine[..., None], means2d, zero), torch.where(fine[..., None], conics, zero), depths,
                      torch.where(fine, comp, zero), torch.where(valid, p.radii, torch.zeros_like(p.radii)),
                      torch.where(valid[..., None], p.rects, torch.zeros_like(p.rects)), valid)


def _project64(means: Tensor, quats: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
               near_plane: float, far_plane: float, eps2d: float, tile_size: int, radius_clip: float) -> Projection:
    """project() in the inputs' dtype (float64 from project())."""
    # Products of 3-vectors and 3x3 blocks are written as broadcast-and-sum: batched matmuls of
    # tiny matrices cost far more per element on the CPU.
    R, t = viewmats[:, None, :3, :3], viewmats[:, None, :3, 3]  # [C,1,3,3], [C,1,3]
    p = (R * means[None, :, None, :]).sum(-1) + t  # [C,N,3] camera space
    x, y, z = p.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    # Culled Gaussians still flow through the graph: give them a harmless depth so no inf/NaN is
    # formed (a NaN in an unused branch of torch.where would still poison the gradients).
    zs = torch.where(in_depth, z, torch.ones_like(z))

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C,1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    # Jacobian of the perspective map at the mean, with x/z and y/z clamped to the frustum
    # widened by 0.3 tan(fov/2) on each side: keeps splats far off-screen from exploding.
    x_lo, x_hi, y_lo, y_hi = clamp_bounds(Ks, width, height)
    x_over_z = torch.clamp(x / zs, min=x_lo, max=x_hi)
    y_over_z = torch.clamp(y / zs, min=y_lo, max=y_hi)
    # Rows of J @ R_view, J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] with x/z, y/z clamped.
    jw0 = (fx / zs)[..., None] * R[..., 0, :] - (fx * x_over_z / zs)[..., None] * R[..., 2, :]  # [C,N,3]
    jw1 = (fy / zs)[..., None] * R[..., 1, :] - (fy * y_over_z / zs)[..., None] * R[..., 2, :]
    cov3d = covariance_3d(quats, scales)[None]  # [1,N,3,3]
    s0 = (cov3d * jw0[..., None, :]).sum(-1)  # cov3d @ jw0, [C,N,3]
    s1 = (cov3d * jw1[..., None, :]).sum(-1)
    a_raw, b, c_raw = (jw0 * s0).sum(-1), (jw0 * s1).sum(-1), (jw1 * s1).sum(-1)
    a, c = a_raw + eps2d, c_raw + eps2d
    det = a * c - b * b
    ok = in_depth & (det > DET_FLOOR) & torch.isfinite(det)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)
    # The floor keeps sqrt's derivative finite for degenerate (flat) splats.
    det_raw = torch.where(ok, a_raw * c_raw - b * b, torch.zeros_like(det))
    compensation = torch.sqrt(torch.clamp_min(det_raw / det_s, 1e-12))

    means2d = torch.stack([fx * (x / zs) + cx, fy * (y / zs) + cy], dim=-1)  # x / z first, as the kernel
    depths = z

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam))
        ok = ok & torch.isfinite(radius) & (radius > radius_clip)
        radius = torch.where(ok, radius, torch.zeros_like(radius)).clamp_max(2**30)
        rects = tile_rects(means2d.detach(), radius, width, height, tile_size)
        ok = ok & (rects[..., 1] > rects[..., 0]) & (rects[..., 3] > rects[..., 2])
        rects = torch.where(ok[..., None], rects, torch.zeros_like(rects))
        radii = torch.where(ok, radius, torch.zeros_like(radius)).to(torch.int32)
    return Projection(means2d, conics, depths, compensation, radii, rects, ok)


def clamp_bounds(Ks: Tensor, width: int, height: int) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """[C, 1] each: the x/z and y/z range (low, high) the projection's Jacobian is clamped to,
    the image widened by 0.3 tan(fov/2) on each side, as 3DGS and gsplat clamp it."""
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (-(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x,
            -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)


def tile_rects(means2d: Tensor, radius: Tensor, width: int, height: int, tile: int) -> Tensor:
    """Tile ranges covered by a splat's square of half-size `radius` around its centre.

    x0 = clamp(floor((u - r) / T), 0, TX), x1 = clamp(floor((u + r + T - 1) / T), 0, TX), the
    same for y; computed in float64 so float32 inputs get the same tiles as float64 ones.

    Args:
        means2d: [..., 2]; radius: [...].
    Returns:
        [..., 4] int32 (x0, x1, y0, y1), half-open.
    """
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    u, v = means2d.double().unbind(-1)
    r = radius.double()
    # Clamp before the cast to int: far-away splats have centres beyond the int range.
    def rng(center, n):
        lo = torch.floor((center - r) / tile).clamp(0, n)
        hi = torch.floor((center + r + tile - 1) / tile).clamp(0, n)
        return lo, hi

    x0, x1 = rng(u, tiles_x)
    y0, y1 = rng(v, tiles_y)
    return torch.stack([x0, x1, y0, y1], dim=-1).to(torch.int32)
