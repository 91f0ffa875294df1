"""Cross-ray densification (CRD): boxes where high-loss rays of different views cross.

Per view: the window (h rows x w columns, non-overlapping tiling, last partial strips skipped)
with the largest mean loss; rays through its four corners. For every pair of views, corner k
of one view meets corner k of the other at the midpoint of the two rays' closest points; the
axis-aligned box of the four midpoints is where both views see high loss, and the adapter
densifies what lies inside. All of it is vectorised over views and pairs.

Guards (each optional, all off in the paper preset): rays only forward (both closest points in
front of their cameras), a maximum miss distance between the two rays, near-parallel pairs
skipped, boxes grown by half the pair's largest miss distance (each midpoint is only known to
within half the gap between its two rays, and four nearly coplanar midpoints would otherwise
give a box too thin to hold anything), boxes clipped to given bounds (e.g. the model's bounding
box).
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor


def best_windows(loss_maps: Tensor, window: Tuple[int, int]) -> Tensor:
    """The highest-mean-loss window of each view.

    Args:
        loss_maps: [M, H, W] per-pixel loss.
        window: (h, w); clamped to the image size.
    Returns:
        [M, 4] int64: top, left, h, w (pixels) of each view's window.
    """
    if loss_maps.dim() != 3:
        raise ValueError(f"loss_maps must be [M,H,W], got {list(loss_maps.shape)}")
    M, H, W = loss_maps.shape
    h, w = min(int(window[0]), H), min(int(window[1]), W)
    if h < 1 or w < 1:
        raise ValueError(f"window must be positive, got {window!r}")
    rows, cols = H // h, W // w
    means = loss_maps[:, : rows * h, : cols * w].reshape(M, rows, h, cols, w).mean(dim=(2, 4))  # [M, rows, cols]
    flat = means.reshape(M, -1).argmax(dim=-1)
    top, left = (flat // cols) * h, (flat % cols) * w
    size = torch.tensor([h, w], dtype=torch.int64).expand(M, 2)
    return torch.cat([top[:, None], left[:, None], size], dim=-1)


def window_corners(windows: Tensor) -> Tensor:
    """[M, 4, 2] pixel coordinates (u, v) of the window corners: the pixel edges, since pixel
    (i, j) spans [i, i+1] x [j, j+1] in K's coordinates. Order: top-left, top-right,
    bottom-left, bottom-right."""
    top, left, h, w = windows.to(torch.float64).unbind(-1)
    us = torch.stack([left, left + w, left, left + w], dim=-1)
    vs = torch.stack([top, top, top + h, top + h], dim=-1)
    return torch.stack([us, vs], dim=-1)


def closest_points(o1: Tensor, d1: Tensor, o2: Tensor, d2: Tensor):
    """Closest approach of the lines o1 + t1 d1 and o2 + t2 d2 (unit directions).

    Returns:
        t1, t2 [...]: parameters of the closest points; midpoint [..., 3]; miss [...] distance
        between the two closest points; sin2 [...] squared sine of the angle between the lines
        (0 for parallel lines, where t1, t2 are meaningless).
    """
    w0 = o1 - o2
    b = (d1 * d2).sum(-1)
    d = (d1 * w0).sum(-1)
    e = (d2 * w0).sum(-1)
    sin2 = (1.0 - b * b).clamp_min(0.0)
    denom = torch.where(sin2 > 0, sin2, torch.ones_like(sin2))
    t1 = (b * e - d) / denom
    t2 = (e - b * d) / denom
    p1 = o1 + t1[..., None] * d1
    p2 = o2 + t2[..., None] * d2
    return t1, t2, 0.5 * (p1 + p2), (p1 - p2).norm(dim=-1), sin2


def cross_ray_boxes(cameras: Sequence, windows: Tensor, *, forward_only: bool = True,
                    max_miss: Optional[float] = None, min_angle_deg: float = 0.0,
                    bounds: Optional[Tensor] = None, pad_by_miss: bool = False) -> Tuple[Tensor, Tensor]:
    """Boxes from corresponding corner rays of every pair of views.

    Args:
        cameras: M cameras (mvgs_plugin Camera, at the resolution the windows refer to).
        windows: [M, 4] from best_windows.
        forward_only: drop a pair when any corner's closest point lies behind either camera.
        max_miss: drop a pair when any corner's two rays pass further apart than this (world
            units); None = no limit.
        min_angle_deg: drop a pair when any corner's rays are closer to parallel than this.
        bounds: [2, 3] (min, max) to clip boxes to; boxes left empty are dropped.
        pad_by_miss: grow each box on every side by half the largest miss distance of its pair.
    Returns:
        boxes [B, 2, 3] float64 (min corner, max corner) and pairs [B, 2] (view indices).
    """
    M = len(cameras)
    if M < 2:
        return torch.zeros(0, 2, 3, dtype=torch.float64), torch.zeros(0, 2, dtype=torch.int64)
    corners = window_corners(windows)  # [M,4,2]
    rays = [cam.rays(corners[i]) for i, cam in enumerate(cameras)]
    origins = torch.stack([r[0] for r in rays]).to(torch.float64)  # [M,4,3]
    dirs = torch.stack([r[1] for r in rays]).to(torch.float64)
    i, j = torch.triu_indices(M, M, offset=1)
    t1, t2, mid, miss, sin2 = closest_points(origins[i], dirs[i], origins[j], dirs[j])  # [P,4]
    keep = (sin2 > math.sin(math.radians(min_angle_deg)) ** 2).all(-1) & (sin2 > 1e-12).all(-1)
    if forward_only:
        keep &= ((t1 > 0) & (t2 > 0)).all(-1)
    if max_miss is not None:
        keep &= (miss <= max_miss).all(-1)
    lo, hi = mid.amin(dim=1), mid.amax(dim=1)  # [P,3]
    if pad_by_miss:
        pad = 0.5 * miss.amax(dim=-1, keepdim=True)  # [P,1]
        lo, hi = lo - pad, hi + pad
    if bounds is not None:
        b = torch.as_tensor(bounds, dtype=torch.float64)
        lo, hi = torch.maximum(lo, b[0]), torch.minimum(hi, b[1])
        keep &= (lo <= hi).all(-1)
    boxes = torch.stack([lo, hi], dim=1)[keep]
    return boxes, torch.stack([i, j], dim=-1)[keep]


# Elements per temporary comparison block of boxes_contain (2^24 float64 = 128 MB).
_CHUNK_ELEMS = 1 << 24


def boxes_contain(points: Tensor, boxes: Tensor) -> Tensor:
    """[N] bool: which points lie strictly inside at least one box.

    Args:
        points: [N, 3] world coordinates (Gaussian means, anchor positions: the frame the
            cameras' world_to_camera maps from).
        boxes: [B, 2, 3] axis-aligned world boxes, [b, 0] the min corner and [b, 1] the max
            corner, as cross_ray_boxes returns them (DensifyContext.boxes).
    A consumer outside this package's adapters (e.g. a gsplat strategy) clones the points this
    selects. Compared in float64, in blocks of at most 2^24 elements.
    """
    N, B = points.shape[0], boxes.shape[0]
    inside = torch.zeros(N, dtype=torch.bool, device=points.device)
    if N == 0 or B == 0:
        return inside
    p = points.detach().to(torch.float64)
    lo, hi = boxes[:, 0].to(p), boxes[:, 1].to(p)  # [B, 3]
    rows = max(1, _CHUNK_ELEMS // (3 * B))
    for s in range(0, N, rows):
        q = p[s:s + rows, None, :]  # [c, 1, 3]
        inside[s:s + rows] = ((q > lo) & (q < hi)).all(dim=-1).any(dim=-1)
    return inside


def top_by_score(mask: Tensor, score: Tensor, k: int) -> Tensor:
    """Keep at most k of the True entries of mask [N]: those with the largest score [N] (ties:
    lower index first). CRD's cap on what one call clones (DensifyContext.max_new_from_boxes),
    ranked by the mean screen-space gradient."""
    idx = mask.nonzero().squeeze(1)
    if idx.numel() <= k:
        return mask
    order = torch.sort(score[idx].to(mask.device), descending=True, stable=True).indices[:k]
    out = torch.zeros_like(mask)
    out[idx[order]] = True
    return out


def check_boxes(boxes) -> Tensor:
    """A DensifyContext's boxes as a [B, 2, 3] tensor (min corner, max corner); raises on a wrong
    shape, non-finite values or a box whose min exceeds its max (naming the box)."""
    boxes = torch.as_tensor(boxes)
    if boxes.ndim != 3 or tuple(boxes.shape[1:]) != (2, 3):
        raise ValueError(f"ctx.boxes must be [B,2,3] (min, max corners), got {list(boxes.shape)}")
    if not bool(torch.isfinite(boxes).all()):
        raise ValueError("ctx.boxes must be finite")
    bad = (boxes[:, 0] > boxes[:, 1]).any(dim=-1)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"ctx.boxes[{i}] has min > max: {boxes[i].tolist()} (corners swapped?)")
    return boxes


def loss_map(render: Tensor, target: Tensor) -> Tensor:
    """[H, W] per-pixel L1 loss (mean over channels), as the released code uses."""
    return (render.detach() - target.to(render)).abs().mean(dim=-1)
