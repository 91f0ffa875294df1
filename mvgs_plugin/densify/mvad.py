"""Multi-view augmented densification (MVAD): the gradient threshold of one densification call,
from the cameras of the step that triggered it.

Camera centres are projected onto the unit sphere about a normalisation centre; the discrepancy
of two views is the chord between their projections (0..2), plus optionally a weighted rotation
term (angle between the optical axes / pi); when the rule fires (any pair, or at least a given
fraction of the pairs, with discrepancy >= tau) the threshold is halved: beta_hat = beta/2.

Degenerate rigs are defined, not errors: fewer than two cameras, or no pair with a defined
direction, never fire; a camera exactly at the normalisation centre has no direction and takes
part in no pair; duplicated cameras form pairs with discrepancy 0.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import torch
from torch import Tensor


def pair_discrepancy(centers: Tensor, origin: Tensor, axes: Optional[Tensor] = None,
                     rotation_weight: float = 0.0) -> tuple[Tensor, Tensor]:
    """Discrepancy of every pair of views.

    Args:
        centers: [M, 3] camera centres (world).
        origin: [3] the normalisation centre.
        axes: [M, 3] unit optical axes (world), needed when rotation_weight > 0.
        rotation_weight: weight of angle(axis_i, axis_j) / pi.
    Returns:
        r [M, M] (symmetric, 0 on the diagonal) and valid [M, M] (both views have a direction
        and i != j).
    """
    offsets = centers - origin
    norms = offsets.norm(dim=-1, keepdim=True)
    has_dir = norms.squeeze(-1) > 1e-12 * max(1.0, float(centers.abs().max()) if centers.numel() else 1.0)
    dirs = offsets / norms.clamp_min(1e-300)
    r = (dirs[:, None, :] - dirs[None, :, :]).norm(dim=-1)
    if rotation_weight:
        if axes is None:
            raise ValueError("rotation_weight > 0 needs the cameras' optical axes")
        cos = (axes[:, None, :] * axes[None, :, :]).sum(-1).clamp(-1.0, 1.0)
        r = r + rotation_weight * torch.arccos(cos) / torch.pi
    m = centers.shape[0]
    valid = has_dir[:, None] & has_dir[None, :] & ~torch.eye(m, dtype=torch.bool, device=centers.device)
    return r, valid


def mvad_threshold(centers: Tensor, base_threshold: float, *, origin: Optional[Tensor] = None, tau: float = 1.0,
                   rule: Union[str, float] = "any", axes: Optional[Tensor] = None,
                   rotation_weight: float = 0.0) -> float:
    """beta_hat = beta - (beta / 2) * [rule fires].

    Args:
        centers: [M, 3] the step's camera centres.
        base_threshold: beta.
        origin: [3] normalisation centre (None: the world origin, as the released code).
        tau: discrepancy a pair needs.
        rule: "any" (released code) or a fraction in (0, 1] of the valid pairs.
    """
    if not isinstance(rule, str):
        if not 0.0 < float(rule) <= 1.0:
            raise ValueError(f"rule must be 'any' or a fraction in (0, 1], got {rule!r}")
    elif rule != "any":
        raise ValueError(f"rule must be 'any' or a fraction in (0, 1], got {rule!r}")
    centers = torch.as_tensor(centers, dtype=torch.float64)
    if centers.dim() != 2 or centers.shape[-1] != 3:
        raise ValueError(f"centers must be [M,3], got {list(centers.shape)}")
    if centers.shape[0] < 2:
        return float(base_threshold)
    origin = torch.zeros(3, dtype=torch.float64) if origin is None else torch.as_tensor(origin, dtype=torch.float64)
    axes = None if axes is None else torch.as_tensor(axes, dtype=torch.float64)
    r, valid = pair_discrepancy(centers, origin, axes, rotation_weight)
    upper = torch.triu(valid, diagonal=1)
    n_pairs = int(upper.sum())
    if n_pairs == 0:
        return float(base_threshold)
    hits = int(((r >= tau) & upper).sum())
    fires = hits > 0 if rule == "any" else hits >= float(rule) * n_pairs
    return float(base_threshold) / 2.0 if fires else float(base_threshold)


def camera_axes(cameras: Sequence) -> Tensor:
    """[M, 3] optical axes (camera +z in world coordinates) of mvgs_plugin Cameras."""
    return torch.stack([c.camera_to_world[:3, 2] for c in cameras])


def resolution_threshold(base_threshold: float, width: float, reference_width: Optional[float]) -> float:
    """β scaled to the rendered width: β × reference_width / width (β itself when
    reference_width is None).

    Why 1 / W: with the loss averaged over the W × H pixels, the pixel-space gradient of a
    Gaussian s pixels wide sums ~s² pixels of weight 1 / (W H), each ~ e / s for an error e per
    pixel, so ~ e s / (W H); the NDC factor W / 2 leaves ~ e s / (2 H). A threshold meant for
    images reference_width wide thus has to grow by reference_width / W to ask for the same
    error per pixel at width W.
    """
    if reference_width is None:
        return float(base_threshold)
    if not (0 < width < float("inf")) or not (0 < reference_width < float("inf")):
        raise ValueError(f"widths must be finite and > 0, got width={width!r}, reference_width={reference_width!r}")
    return float(base_threshold) * float(reference_width) / float(width)

