"""Tile-based compositing in plain PyTorch: the readable reference and the fallback.

Same rules as csrc/rasterize.cpp (docs/design.md, "Image formation"); gradients come from autograd.
The sequential per-pixel loop becomes cumulative products over each tile's depth-sorted list:
a Gaussian contributes when the transmittance including it stays >= 1e-4 (it is monotone, so that
is exactly "stop before the one that would take it below"). Runs on any device torch supports.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


def bin_tiles(rects: Tensor, order: Tensor, tiles_x: int, tiles_y: int):
    """Per-(camera, tile) lists of Gaussians in depth order.

    Args:
        rects: [C, N, 4] int32 tile ranges (x0, x1, y0, y1), half-open; order: [C, N] depth order.
    Returns:
        offsets [C * tiles + 1] int64 and ids [total] int32 (list of (camera, tile) i is
        ids[offsets[i]:offsets[i+1]]).
    """
    C, N = order.shape
    n_tiles = tiles_x * tiles_y
    device = order.device
    r = torch.gather(rects.long(), 1, order[..., None].expand(C, N, 4))  # in depth order
    w, h = r[..., 1] - r[..., 0], r[..., 3] - r[..., 2]
    counts = (w * h).reshape(-1)  # [C*N]
    gauss = order.reshape(-1).repeat_interleave(counts)
    cam = torch.arange(C, device=device).repeat_interleave(N).repeat_interleave(counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(int(counts.sum()), device=device) - first.repeat_interleave(counts)
    w_rep = w.reshape(-1).repeat_interleave(counts)
    tx = r[..., 0].reshape(-1).repeat_interleave(counts) + local % w_rep.clamp_min(1)
    ty = r[..., 2].reshape(-1).repeat_interleave(counts) + local // w_rep.clamp_min(1)
    key = cam * n_tiles + ty * tiles_x + tx
    key, perm = torch.sort(key, stable=True)  # stable: keeps depth order within a tile
    offsets = torch.zeros(C * n_tiles + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(torch.bincount(key, minlength=C * n_tiles), 0)
    return offsets, gauss[perm].to(torch.int32)


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    backgrounds: Tensor,
    offsets: Tensor,
    ids: Tensor,
    width: int,
    height: int,
    tile: int,
    max_pairs: int = 1 << 22,
    stats: Optional[dict] = None,
):
    """Alpha-composites every (camera, tile) list.

    Args:
        means2d: [C,N,2]; conics: [C,N,3]; opacities: [C,N]; colors: [C,N,D]; backgrounds: [C,D];
        offsets, ids: from bin_tiles; max_pairs: pixel-Gaussian pairs evaluated per chunk;
        stats: a dict to fill with what was blended (benchmarks/bench_step_parts.py): "counts"
        [C,H,W] Gaussians blended per pixel, "pairs" [C,N] pixels each Gaussian is blended at,
        "weight" [C,N] its blend weight alpha * T summed over them (not differentiable).
    Returns:
        colour [C,H,W,D] and alpha [C,H,W,1].
    """
    C, N, D = colors.shape
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    n_tiles = tiles_x * tiles_y
    device, dtype = colors.device, colors.dtype
    counts = offsets[1:] - offsets[:-1]  # [C*tiles]
    busy = torch.nonzero(counts).squeeze(-1)
    busy = busy[torch.argsort(counts[busy])]  # similar lengths share a chunk: little padding

    iy, ix = torch.meshgrid(*(torch.arange(tile, device=device),) * 2, indexing="ij")
    iy, ix = iy.reshape(-1), ix.reshape(-1)  # pixel offsets within a tile, [P]
    pix_xy = torch.stack([ix, iy], dim=-1).to(dtype) + 0.5  # pixel centres within a tile
    P = tile * tile

    flat_m, flat_q = means2d.reshape(C * N, 2), conics.reshape(C * N, 3)
    flat_o, flat_c = opacities.reshape(C * N), colors.reshape(C * N, D)
    out_rows, out_col, out_trans, out_count = [], [], [], []
    if stats is not None:
        pairs = torch.zeros(C * N, device=device, dtype=dtype)
        weight = torch.zeros(C * N, device=device, dtype=dtype)
    # Chunks of tiles whose padded pair count stays under max_pairs (counts ascend along busy).
    sorted_counts = counts[busy].tolist()
    chunks, start = [], 0
    for end in range(1, len(sorted_counts) + 1):
        if end - start > 1 and (end - start) * P * sorted_counts[end - 1] > max_pairs:
            chunks.append((start, end - 1))
            start = end - 1
    if start < len(sorted_counts):
        chunks.append((start, len(sorted_counts)))
    for start, end in chunks:
        chunk = busy[start:end]
        kmax = sorted_counts[end - 1]

        slot = offsets[chunk, None] + torch.arange(kmax, device=device)  # [B,K]
        present = slot < offsets[chunk + 1, None]
        cam = torch.div(chunk, n_tiles, rounding_mode="floor")
        g = cam[:, None] * N + ids[slot.clamp_max(ids.numel() - 1)].long()  # [B,K]
        t = chunk % n_tiles
        origin = torch.stack([t % tiles_x, torch.div(t, tiles_x, rounding_mode="floor")], -1) * tile
        xy = origin[:, None, :].to(dtype) + pix_xy  # [B,P,2] pixel centres

        d = flat_m[g][:, None, :, :] - xy[:, :, None, :]  # [B,P,K,2]
        q = flat_q[g][:, None]  # [B,1,K,3]
        sigma = 0.5 * (q[..., 0] * d[..., 0] ** 2 + q[..., 2] * d[..., 1] ** 2) + q[..., 1] * d[..., 0] * d[..., 1]
        alpha = torch.clamp_max(flat_o[g][:, None] * torch.exp(-sigma.clamp_min(0)), ALPHA_MAX)
        keep = present[:, None] & (sigma >= 0) & (alpha >= ALPHA_MIN)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            keep = keep & (torch.cumprod(1 - alpha, dim=-1) >= T_MIN)
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        trans_incl = torch.cumprod(1 - alpha, dim=-1)  # [B,P,K]
        trans = torch.cat([torch.ones_like(trans_incl[..., :1]), trans_incl[..., :-1]], dim=-1)
        weights = alpha * trans
        col = torch.einsum("bpk,bkd->bpd", weights, flat_c[g])
        out_col.append(col.reshape(-1, D))
        out_trans.append(trans_incl[..., -1].reshape(-1))
        if stats is not None:
            with torch.no_grad():
                out_count.append(keep.sum(-1).reshape(-1).to(dtype))
                # a tile's pixels past the image's right or bottom edge are not part of it
                inside = ((xy[..., 0] < width) & (xy[..., 1] < height))[..., None]  # [B,P,1]
                pairs.index_add_(0, g.reshape(-1), (keep & inside).sum(1).reshape(-1).to(dtype))
                weight.index_add_(0, g.reshape(-1), (weights * inside).sum(1).reshape(-1))
        # Flat index of each tile pixel in a [C, TY*T, TX*T] canvas.
        canvas_w = tiles_x * tile
        rows = (cam[:, None] * (tiles_y * tile) + origin[:, None, 1] + iy) * canvas_w
        out_rows.append((rows + origin[:, None, 0] + ix).reshape(-1))

    if not out_rows:
        # Nothing visible: an empty contribution still links the output to every input, so
        # backward works (with zero gradients) as it does when something is visible.
        empty = flat_m[:0, :1] + flat_q[:0, :1] + flat_o[:0, None]  # [0,1]
        out_col, out_trans, out_rows = [flat_c[:0] + empty], [empty[:, 0]], [torch.zeros(0, dtype=torch.long, device=device)]
    canvas = C * tiles_y * tile * tiles_x * tile
    idx = torch.cat(out_rows)
    col = torch.zeros(canvas, D, device=device, dtype=dtype).index_copy(0, idx, torch.cat(out_col))
    trans = torch.ones(canvas, device=device, dtype=dtype).index_copy(0, idx, torch.cat(out_trans))
    col = col.reshape(C, tiles_y * tile, tiles_x * tile, D)[:, :height, :width]
    trans = trans.reshape(C, tiles_y * tile, tiles_x * tile, 1)[:, :height, :width]
    if stats is not None:
        counts = torch.zeros(canvas, device=device, dtype=dtype)
        if out_count:
            counts = counts.index_copy(0, idx, torch.cat(out_count))
        stats.update(counts=counts.reshape(C, tiles_y * tile, tiles_x * tile)[:, :height, :width],
                     pairs=pairs.reshape(C, N), weight=weight.reshape(C, N))
    return col + trans * backgrounds[:, None, None, :], 1 - trans
