"""Exact k-nearest-neighbour distances for point clouds of 100k+ points on the CPU.

The adapters size their initial Gaussians (3DGS, 4DGS) and anchors (Scaffold-GS) by the mean
squared distance of every point to its three nearest others, as the original code does with a
CUDA kNN. A brute-force search is O(P^2); this one bounds each point's search box with a
space-filling curve first (see knn_mean_sq_dist), so it stays exact and fast without a GPU."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from mvgs_plugin.checks import check_int

__all__ = ["knn_mean_sq_dist", "spacing_log_scale"]

_CHUNK_ELEMS = 1 << 24  # distance-matrix entries per block


def knn_mean_sq_dist(points: Tensor, k: int = 3, chunk: int = 256, window: int = 8) -> Tensor:
    """Mean squared distance of every point to its k nearest *other* points (exact).

    Args:
        points: [P, 3].
        chunk: queries per block; window: curve neighbours per side for the first bound (>= k).
    Returns:
        [P] float64. With P <= k the mean is over the P - 1 others; a lone point gets 0.

    Brute force is O(P^2) (minutes for the 100k-300k points of a COLMAP scene), so:
    1. sort the points along a Z-order curve; the distances to the ``window`` curve neighbours
       on each side bound every point's k-th neighbour distance from above;
    2. for each block of ``chunk`` consecutive points, the true neighbours of its points lie in
       the block's bounding box grown by its largest bound: search only the points in that box.
    The result is exact whatever the distribution; only the speed depends on it.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [P,3], got {list(points.shape)}")
    check_int("window", window, max(k, 1))
    P = points.shape[0]
    out = torch.zeros(P, dtype=torch.float64, device=points.device)
    kk = min(k, P - 1)
    if kk <= 0:
        return out
    x = points.detach().to(torch.float64)
    x = x - x.mean(dim=0)  # ranks below use |a|^2 + |b|^2 - 2ab: keep magnitudes small
    order = _morton_order(x)
    xs = x[order]
    bound = _curve_bound(xs, kk, window).sqrt() * (1 + 1e-9) + 1e-12  # [P], margin for rounding
    positions = torch.arange(P, device=x.device)
    sorted_out = torch.empty(P, dtype=torch.float64, device=x.device)
    for s in range(0, P, chunk):
        q = xs[s:s + chunk]
        r = bound[s:s + chunk].max()
        lo, hi = q.min(dim=0).values - r, q.max(dim=0).values + r
        cand = ((xs >= lo) & (xs <= hi)).all(dim=1).nonzero().squeeze(1)
        sorted_out[s:s + chunk] = _block_knn(q, positions[s:s + chunk], xs[cand], cand, kk)
    out[order] = sorted_out
    return out


def _morton_order(x: Tensor) -> Tensor:
    """[P] permutation sorting points [P, 3] along a Z-order curve (10 bits per axis)."""
    lo = x.min(dim=0).values
    span = float((x.max(dim=0).values - lo).max())
    q = ((x - lo) * (1023.0 / max(span, 1e-300))).long().clamp(0, 1023)
    code = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return torch.argsort(code, stable=True)


def _curve_bound(xs: Tensor, k: int, window: int) -> Tensor:
    """[P] k-th smallest squared distance from each point of xs [P, 3] to its ``window``
    predecessors and successors in the array: an upper bound of its k-th neighbour distance."""
    P = xs.shape[0]
    d = torch.full((P, 2 * window), math.inf, dtype=xs.dtype, device=xs.device)
    for o in range(1, min(window, P - 1) + 1):
        pair = ((xs[o:] - xs[:-o]) ** 2).sum(dim=1)  # between i and i + o
        d[:-o, 2 * o - 2] = pair
        d[o:, 2 * o - 1] = pair
    return d.topk(k, dim=1, largest=False).values[:, -1]


def _block_knn(q: Tensor, q_idx: Tensor, c: Tensor, c_idx: Tensor, k: int) -> Tensor:
    """[Q] mean squared distance of queries q [Q, 3] to their k nearest candidates c [M, 3],
    skipping the candidate with the query's own index (q_idx [Q], c_idx [M])."""
    out = torch.empty(q.shape[0], dtype=q.dtype, device=q.device)
    rows = max(1, _CHUNK_ELEMS // (4 * max(1, c.shape[0])))
    centre = q.mean(dim=0)
    cc = c - centre
    csq = (cc * cc).sum(dim=1)
    for s in range(0, q.shape[0], rows):
        qc = q[s:s + rows] - centre
        d2 = torch.addmm(csq[None, :], qc, cc.T, alpha=-2.0) + (qc * qc).sum(dim=1, keepdim=True)
        d2[q_idx[s:s + rows, None] == c_idx[None, :]] = math.inf  # not its own neighbour
        idx = d2.topk(k, dim=1, largest=False).indices  # ranked by the expansion ...
        exact = ((q[s:s + rows, None, :] - c[idx]) ** 2).sum(dim=-1)  # ... measured exactly
        out[s:s + rows] = exact.mean(dim=1)
    return out


def spacing_log_scale(points: Tensor, chunk: int = 256) -> Tensor:
    """[P] float64 log of the root mean squared distance of every point to its three nearest
    others (floored at 1e-7 before the root): the size 3DGS gives a Gaussian initialised at a
    point, and Scaffold-GS an anchor, so neighbours just overlap."""
    return torch.log(knn_mean_sq_dist(points, k=3, chunk=chunk).clamp_min(1e-7).sqrt())
