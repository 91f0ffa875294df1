"""Tensor and optimizer operations the bundled adapters share.

- ``make_adam`` / ``scale_for_views``: the original's Adam, and Grendel-GS's rule for a step of
  M views (MVGSConfig.views_scaling="sqrt");
- ``log_linear``: the log-linear learning-rate schedules of 3DGS, 4DGS and Scaffold-GS;
- ``swap_param``: replace one optimizer group's parameter by a tensor with other rows (densify,
  prune, reset), carrying Adam's moments along row by row;
- ``growth_cap``: the lower of several optional caps on a model's size.

Inside-box tests and ranking by score live in :mod:`mvgs_plugin.densify` (``boxes_contain``,
``top_by_score``), the argument checks in :mod:`mvgs_plugin.checks`."""

from __future__ import annotations

import math
from typing import Any, Dict, Optional

import torch
from torch import Tensor

from mvgs_plugin.checks import check_int

__all__ = ["ADAM_BETAS", "make_adam", "scale_for_views", "log_linear", "swap_param", "remap_state",
           "growth_cap", "stats_in_one_dict"]

ADAM_BETAS = (0.9, 0.999)  # torch's and the original's


def make_adam(groups, eps: float) -> torch.optim.Adam:
    """Adam as the original (lr per group, eps), with torch's fused kernel where it exists (CPU
    since torch 2.4, CUDA): the same update in one pass over all groups, 6x faster than the
    per-tensor loop at 50k Gaussians on one CPU thread (benchmarks/bench_step.py)."""
    try:
        return torch.optim.Adam(groups, lr=0.0, eps=eps, fused=True)
    except (RuntimeError, TypeError, ValueError):  # no fused kernel for this torch / device / dtype
        return torch.optim.Adam(groups, lr=0.0, eps=eps)


def scale_for_views(optimizer: torch.optim.Optimizer, lrs: Dict[str, float], views: int, eps: float) -> None:
    """Set every named group's learning rate for a step of `views` views, with Grendel-GS's
    batch rule (a batch of M images: learning rate x √M, Adam betas to the power M, eps / √M, so
    M images in one step move the parameters about as M single-image steps would); views = 1
    gives the single-view values exactly. lrs: the single-view rate of each group, by name."""
    root = math.sqrt(views)
    for group in optimizer.param_groups:
        group["lr"] = lrs[group["name"]] * root
        group["betas"] = (ADAM_BETAS[0] ** views, ADAM_BETAS[1] ** views)
        group["eps"] = eps / root


def log_linear(step: int, start: int, length: int, init: float, final: float) -> float:
    """``init`` before ``start``, ``final`` after ``start + length``, log-linear in between."""
    s = min(max((step - start) / length, 0.0), 1.0)
    return math.exp((1 - s) * math.log(init) + s * math.log(final))


def swap_param(optimizer: torch.optim.Optimizer, name: str, value: Tensor, src: Optional[Tensor],
               zero_moments: bool) -> torch.nn.Parameter:
    """Replace the parameter of the optimizer group called ``name`` (a group of one tensor) by
    a new one holding ``value``, carrying its Adam state along; returns the new parameter.

    src: [N_new] long, the old row each new row continues (-1 = new row: zero moments), or None
    when the rows are the same. Adam's ``step`` (a 0-dim tensor shared by all rows) is kept as
    it is. zero_moments: zero every row's moments (opacity reset).
    """
    group = next(g for g in optimizer.param_groups if g["name"] == name)
    old = group["params"][0]
    new = torch.nn.Parameter(value.detach().clone().contiguous())
    state = optimizer.state.pop(old, None)
    if state is not None:
        optimizer.state[new] = {key: remap_state(v, old, src, zero_moments) for key, v in state.items()}
    group["params"][0] = new
    return new


def remap_state(v: Any, old: Tensor, src: Optional[Tensor], zero: bool) -> Any:
    """One entry of a parameter's optimizer state, moved to the rows ``src`` (see swap_param)."""
    if not (isinstance(v, Tensor) and v.shape == old.shape):
        return v  # Adam's step counter, shared by all rows
    rows = v.shape[0] if src is None else len(src)
    out = v.new_zeros((rows,) + v.shape[1:])
    if zero:
        return out
    if src is None:
        return v.clone()
    cont = src >= 0
    out[cont] = v[src[cont]]
    return out


def stats_in_one_dict(cls: type, names) -> type:
    """Give an adapter class one attribute per densification statistic, each stored in the
    instance's dict ``self.stats`` (name -> tensor), so the statistics are reset, saved, summed
    across ranks and loaded as one dict while ``adapter.grad_accum`` etc. still read and write."""
    for name in names:
        setattr(cls, name, property(lambda self, n=name: self.stats[n],
                                    lambda self, value, n=name: self.stats.__setitem__(n, value),
                                    doc=f"The {name!r} entry of self.stats."))
    return cls


def growth_cap(*caps: Optional[int]) -> Optional[int]:
    """The lowest of the caps that are set (each an int >= 0), or None when none is."""
    given = [check_int("max_primitives", c, 0) for c in caps if c is not None]
    return min(given) if given else None
