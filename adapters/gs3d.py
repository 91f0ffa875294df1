"""The original 3D Gaussian Splatting model (Kerbl et al. 2023) as an MVGS adapter.

Parameters are stored raw and activated on use, as the original code does:

    means      [N, 3]        world positions
    sh0        [N, 1, 3]     SH DC coefficient (colour = SH + 0.5)
    shN        [N, K', 3]    higher SH bands, K' = (d+1)^2 - 1 for the maximum degree d
    scales     [N, 3]        log scales        (scale = exp)
    quats      [N, 4]        w-x-y-z rotations (normalised by the renderer)
    opacities  [N]           logit opacities   (opacity = sigmoid)

One ``torch.optim.Adam`` holds one parameter group per attribute, named as above. Rendering
goes through ``config.rasterize`` (the reference CPU rasterizer by default; ``gsplat.rasterization``
has the same call shape). Densification follows the original ``densify_and_prune`` (clone small,
split large, prune transparent / oversized) with MVGS's cross-ray boxes in front of it.

Differences from the original 3DGS code are listed in :class:`GS3DConfig` and in the docstrings
of the methods concerned; each is a config field.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mvgs_plugin.camera import Camera, stack_cameras
from mvgs_plugin.checks import check_float, check_int
from mvgs_plugin.data.init import is_forward_facing, random_init_points
from mvgs_plugin.densify import boxes_contain, check_boxes, top_by_score
from mvgs_plugin.protocol import DensifyContext, DensifyReport, RenderResult
from mvgs_plugin.reference_renderer import rasterization
from mvgs_plugin.reference_renderer._validate import max_scale
from mvgs_plugin.reference_renderer.projection import clamp_bounds, quat_to_rotmat

from .knn import knn_mean_sq_dist, spacing_log_scale
from .ops import growth_cap, make_adam, scale_for_views, stats_in_one_dict, swap_param
from .ply import read_gaussian_ply, write_gaussian_ply

__all__ = ["GS3DConfig", "GS3DAdapter", "knn_mean_sq_dist", "SH_C0", "PARAM_NAMES", "STAT_NAMES"]

SH_C0 = 0.28209479177387814  # the degree-0 real SH basis constant, 1 / (2 sqrt(pi))
PARAM_NAMES = ("means", "sh0", "shN", "scales", "quats", "opacities")
# The densification statistics and how two ranks' values combine (see statistics()).
STAT_NAMES = {"grad_accum": "sum", "denom": "sum", "max_radii2D": "max", "grad_sq_accum": "sum",
              "coverage_accum": "sum", "blend_weight_accum": "sum", "blend_pixels_accum": "sum"}
# Statistics a checkpoint of an earlier release may lack (they start from zero when it is loaded).
_LATER_STATS = ("grad_sq_accum", "coverage_accum", "blend_weight_accum", "blend_pixels_accum")
_STATE_FORMAT = "mvgs-gs3d/1"
# Config fields tied to the running process (a function, backend options): never saved or loaded.
_RUNTIME_FIELDS = ("rasterize", "rasterize_kwargs")
# Elements per temporary distance matrix in kNN and box tests (2^24 float64 = 128 MB).
LOG = logging.getLogger("mvgs_plugin")
# After an optimizer step a log-scale above the log of the largest scale the renderer takes in
# the parameters' dtype (max_log_scale: 37.45 in float32, whose covariance squares the scale), or
# a mean farther than this many scene extents from the model's median position, means a
# diverging run: at 1e4 extents a Gaussian's parallax between the training cameras is below
# 1e-4 rad while float32 spacing there is ~1e-3 extent.
def max_log_scale(dtype: torch.dtype) -> float:
    return math.log(max_scale(dtype))


MAX_LOG_SCALE = max_log_scale(torch.float32)
MAX_MEAN_EXTENTS = 1e4
# GS3DConfig.opacity_reset_scope "inside": resets leave the Gaussians at least this fraction of
# far_distance (the initial model's farthest mean) from the scene centre; with the examples'
# background shell at twice the rig's radius, that is beyond 1.5 rig radii: the far background
FAR_RESET_FRACTION = 0.75
OPACITY_RESET_SCOPES = ("all", "inside")
# GS3DConfig.world_size_rule: the size prune's limit, the same everywhere or growing with distance
WORLD_SIZE_RULES = ("extent", "distance")
# GS3DConfig.budget_growth_order: how growth candidates are ordered when a Gaussian budget binds
BUDGET_GROWTH_ORDERS = ("auto", "inside-first", "score")
# GS3DConfig.means_lr_rule: how a mean's Adam step scales with its distance from the scene centre
MEANS_LR_RULES = ("auto", "extent", "distance", "disparity")


@dataclass
class GS3DConfig:
    """Hyper-parameters of the 3DGS model (defaults: the original 3DGS, see docs/method.md §5).

    Initialisation:
        sh_degree: maximum SH degree (0..3).
        sh_degree_interval: the active degree is min(sh_degree, step // interval).
        init_opacity: opacity of every initial Gaussian.
        random_init: number of points drawn when the scene has no point cloud, where the
            cameras look (mvgs_plugin.data.init.init_region: the cube scene.center ± extent for
            rigs around the scene, the training frusta for forward-facing and one-sided rigs,
            half of each for rigs that look outwards; logged to the
            "mvgs_plugin" logger), colours uniform in [0, 1]. The original 3DGS draws 100k
            points in [-1.3, 1.3]^3 for NeRF-synthetic (with near-grey colours); 10k suits the
            CPU renderer.
        random_init_half_size: None (init_region decides), or the half size of a cube about
            scene.center to use instead.
        seed: seeds the adapter's own generator (random init, split samples); its state is part
            of state_dict(), so a resumed run draws the same samples.
    Learning rates (Adam, eps = adam_eps):
        lr_means_init, lr_means_final: times the scene extent; log-linear decay over
            position_lr_max_steps steps, then constant (the original's delay multiplier is
            inactive with its default lr_delay_steps = 0 and is not implemented).
        means_lr_rule: how a mean's Adam step scales with its distance d from the scene centre
            (the adapter's scene_center; Scene.center for from_scene), with f = max(extent, d) /
            extent (1 within the extent). "extent" is 3DGS's rule: the same step everywhere.
            "distance": the whole step times f, so a step turns a Gaussian by about the same
            angle as seen from the rig wherever it lies. "disparity": across the line of sight
            from the centre times f, along it times f^2, so steps are uniform in angle and in
            1/d, as depth is known from a small baseline: a forward-facing capture's cameras
            stand close together (3DGS's extent is their spread), its content lies 4x to 18x
            that away on the generated rigs, and its depth errors grow as d^2. "auto" (default):
            from_scene resolves it to "disparity" on a forward-facing rig
            (mvgs_plugin.data.init.is_forward_facing) and to "extent" elsewhere (on a 360-degree
            rig only the far background lies beyond the extent); without a scene it is
            "extent", as is every rule without a scene_center. Measured in
            docs/equal_compute_log.md ("A step size for far content").
        lr_sh0, lr_shN, lr_opacities, lr_scales, lr_quats: constant.
    Densification (original constants):
        percent_dense: clone if max scale <= percent_dense * extent, else split.
        split_samples: children per split Gaussian; their scale is divided by 0.8 * split_samples.
        min_opacity: prune below this opacity.
        max_world_size: with ctx.prune_large, prune max scale > max_world_size * extent.
        world_size_rule: "distance" (default) keeps the limit max_world_size * extent within the
            extent of the scene centre (ctx.scene_center) and beyond lets it grow with the
            distance d from the centre, max_world_size * max(extent, d): a fixed angle as seen
            from the rig, so the far background (sky, horizon, a background shell at twice the
            rig's radius, the far wall of a forward-facing capture) keeps the large Gaussians a
            camera sees as small. "extent" is 3DGS's rule (the same limit everywhere), which
            prunes them. Without ctx.scene_center "distance" is the extent rule. Measured in
            docs/equal_compute_log.md ("A size rule for the far background").
        max_screen_size: with ctx.prune_large, prune max screen radius (pixels) above this.
            Default None: the released 3DGS code zeroes its radius statistic before testing it,
            so this rule never fires there (the authors kept it so to preserve their results,
            graphdeco-inria/gaussian-splatting#123); 20.0 turns on the rule the paper describes.
        opacity_reset_value: reset_opacity() caps opacities at this value.
        opacity_reset_scope: "all" (3DGS: every Gaussian) or "inside": a reset leaves the
            Gaussians at FAR_RESET_FRACTION (3/4) of far_distance or more from the scene centre as
            they are (with the examples' background shell at twice the rig's radius: the far
            background beyond 1.5 rig radii). A reset is there to remove floaters in front of
            the cameras; on a 360-degree rig most of the far background is seen by one training
            view, gets a gradient on one step in V, and does not come back in time from a reset
            before the next: the test views that see it between the training views get holes.
            Without a scene_center (or an initial model) it is "all". Default "inside" since
            2026-11-28: with it the baseline no longer falls from 2k to 3k to 10k steps on any
            generated scene. Measured in docs/equal_compute_log.md ("Resets that spare the far
            background", and "... made the default").
        budget_growth_order: the order in which growth candidates take the room a Gaussian
            budget leaves (config.max_gaussians or DensifyContext.max_primitives, when the
            candidates outnumber it). "score": by densify_scores(ctx.rank_by) alone.
            "inside-first": every candidate nearer the scene centre than the far line
            (FAR_RESET_FRACTION of far_distance, opacity_reset_scope's line) before any beyond
            it, each group by score; without a scene_center it is "score". Under a quarter of
            the baseline's count on a 360-degree rig, "score" gave half the budget to the far
            background (10-30 % of a view's pixels): its many evenly seen, textured Gaussians
            outscore the object's detail. "auto" (default): from_scene resolves it to
            "inside-first" on a rig that surrounds the scene and to "score" on a forward-facing
            one (is_forward_facing), where the far part is the scene's own back wall, seen in
            every view; an adapter built without from_scene keeps "auto", which orders by score.
            Measured in docs/equal_compute_log.md ("A budget that grows the object first").
        max_gaussians: cap on the number of Gaussians growth may reach (None = no cap).
    Rendering:
        rasterize: a function with gsplat's ``rasterization`` call shape.
        rasterize_kwargs: extra keyword arguments for it (e.g. ``{"backend": "torch"}``).
        beside_cull: 0 (default, off: 3DGS's and gsplat's image formation) or k > 0: a Gaussian
            is not drawn in a view (opacity 0 and radius 0 there, so no gradient and no visit)
            when its centre lies outside the frustum widened as the renderer clamps its Jacobian
            (0.3 tan(fov / 2) beyond each image edge) at a camera depth below k x its largest
            scale: beside the camera and larger than its distance, where the splat's linearisation
            smears it over the frame (:func:`beside_camera`). Measured in docs/equal_compute.md
            ("Where the quarter loses at 10k").
        knn_chunk: query points per block of the initial kNN search (see knn_mean_sq_dist).
    """

    sh_degree: int = 3
    sh_degree_interval: int = 1000
    init_opacity: float = 0.1
    random_init: int = 10_000
    random_init_half_size: Optional[float] = None
    seed: int = 0
    lr_means_init: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    position_lr_max_steps: int = 30_000
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    lr_opacities: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    adam_eps: float = 1e-15
    percent_dense: float = 0.01
    split_samples: int = 2
    min_opacity: float = 0.005
    max_world_size: float = 0.1
    world_size_rule: str = "distance"
    means_lr_rule: str = "auto"
    max_screen_size: Optional[float] = None
    opacity_reset_value: float = 0.01
    opacity_reset_scope: str = "inside"
    budget_growth_order: str = "auto"
    max_gaussians: Optional[int] = None
    rasterize: Callable[..., Any] = rasterization
    rasterize_kwargs: Dict[str, Any] = field(default_factory=dict)
    beside_cull: float = 0.0
    knn_chunk: int = 256

    def __post_init__(self) -> None:
        check_int("sh_degree", self.sh_degree, 0, 3)
        for name in ("sh_degree_interval", "position_lr_max_steps", "knn_chunk", "split_samples"):
            check_int(name, getattr(self, name), 1)
        check_int("random_init", self.random_init, 1)
        check_int("seed", self.seed, 0)
        if self.max_gaussians is not None:
            check_int("max_gaussians", self.max_gaussians, 0)
        for name in ("lr_means_init", "lr_means_final", "adam_eps", "percent_dense", "max_world_size"):
            check_float(name, getattr(self, name), positive=True)
        for name in ("lr_sh0", "lr_shN", "lr_opacities", "lr_scales", "lr_quats", "min_opacity", "beside_cull"):
            check_float(name, getattr(self, name))
        for name in ("init_opacity", "opacity_reset_value"):
            v = check_float(name, getattr(self, name), positive=True)
            if v >= 1:
                raise ValueError(f"{name} must be in (0, 1), got {v}")
        for name in ("random_init_half_size", "max_screen_size"):
            if getattr(self, name) is not None:
                check_float(name, getattr(self, name), positive=True)
        if self.world_size_rule not in WORLD_SIZE_RULES:
            raise ValueError(f"world_size_rule must be 'extent' or 'distance', got {self.world_size_rule!r}")
        if self.opacity_reset_scope not in OPACITY_RESET_SCOPES:
            raise ValueError(f"opacity_reset_scope must be one of {', '.join(map(repr, OPACITY_RESET_SCOPES))}, "
                             f"got {self.opacity_reset_scope!r}")
        if self.budget_growth_order not in BUDGET_GROWTH_ORDERS:
            raise ValueError(f"budget_growth_order must be one of {', '.join(map(repr, BUDGET_GROWTH_ORDERS))}, "
                             f"got {self.budget_growth_order!r}")
        if self.means_lr_rule not in MEANS_LR_RULES:
            raise ValueError(f"means_lr_rule must be one of {', '.join(map(repr, MEANS_LR_RULES))}, "
                             f"got {self.means_lr_rule!r}")
        if not callable(self.rasterize):
            raise ValueError(f"rasterize must be callable, got {self.rasterize!r}")
        if not isinstance(self.rasterize_kwargs, dict):
            raise ValueError(f"rasterize_kwargs must be a dict, got {self.rasterize_kwargs!r}")

    def saved_values(self) -> Dict[str, Any]:
        """The fields a checkpoint carries (everything but the runtime ones)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in _RUNTIME_FIELDS}

    @classmethod
    def for_run(cls, run, **fields) -> "GS3DConfig":
        """The config whose own schedules follow the run's clock, as the examples build it: the
        means' learning-rate decay over run.clock_length (an MVGSConfig's: its steps, or its work
        on a budget) instead of 30k steps, and the SH degree raised every 1000 / 30k of it.
        fields: any other GS3DConfig field. Without it a 3000-step run of the controller keeps
        the means' rate near its start and stays at SH degree 2."""
        clock = int(run.clock_length)
        return cls(position_lr_max_steps=clock, sh_degree_interval=max(1, round(1000 * clock / 30_000)), **fields)



def beside_camera(means: Tensor, scales: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
                  k: float) -> Tensor:
    """[C, N] True where Gaussian n stands beside camera c (GS3DConfig.beside_cull): its centre,
    in front of the camera, is outside the image widened by 0.3 tan(fov / 2) on each side (the
    bound at which the reference renderer, as 3DGS and gsplat, clamps the Jacobian of the
    projection) and nearer than k x its largest activated scale. means [N, 3], scales [N, 3]
    activated, viewmats [C, 4, 4] world-to-camera, Ks [C, 3, 3]."""
    R, t = viewmats[:, None, :3, :3], viewmats[:, None, :3, 3]
    p = (R * means.to(viewmats.dtype)[None, :, None, :]).sum(-1) + t  # [C, N, 3]
    x, y, z = p.unbind(-1)
    zs = torch.where(z > 0, z, torch.ones_like(z))
    x_lo, x_hi, y_lo, y_hi = clamp_bounds(Ks, width, height)
    u, v = x / zs, y / zs
    outside = (u < x_lo) | (u > x_hi) | (v < y_lo) | (v > y_hi)
    return (z > 0) & outside & (z < k * scales.to(viewmats.dtype).amax(-1)[None])


def consistency_of(grad_sum: Tensor, grad_sq_sum: Tensor, visits: Tensor) -> Tensor:
    """(sum g)^2 / (visits sum g^2) per row, clamped to 1 (see GS3DAdapter.consistency): 0 where
    nothing was pulled, 1 where a gradient was summed without its squares."""
    num = grad_sum.square()
    den = visits * grad_sq_sum
    ratio = torch.where(den > 0, num / den.clamp_min(torch.finfo(den.dtype).tiny), torch.zeros_like(num))
    return torch.where((grad_sq_sum <= 0) & (grad_sum > 0), torch.ones_like(ratio), ratio.clamp(max=1.0))


def farthest_distance(means: Tensor, center: Optional[Tensor]) -> Optional[float]:
    """far_distance: the largest distance of `means` [N, 3] from `center` [3] (float64, taken on
    the CPU); None without a centre or rows. Its FAR_RESET_FRACTION is the far line."""
    if center is None or not len(means):
        return None
    return float(torch.linalg.vector_norm(means.detach().double().cpu() - center, dim=1).max())


def world_size_limit(means: Tensor, extent: float, center: Optional[Tensor], rule: str,
                     max_world_size: float) -> Tensor:
    """[N] the largest scale a size prune keeps for each row of `means`: max_world_size x extent
    (world_size_rule "extent", or no centre), or with "distance" x max(extent, d), d the row's
    distance from `center` (a fixed angle as seen from the rig beyond the extent)."""
    if rule == "distance" and center is not None:
        d = torch.linalg.vector_norm(means.detach() - torch.as_tensor(center).to(means), dim=1)
        return max_world_size * torch.clamp_min(d, extent)
    return torch.full((means.shape[0],), max_world_size * extent, dtype=means.dtype, device=means.device)


def beyond_far_line(means: Tensor, center: Optional[Tensor], far_distance: Optional[float]) -> Optional[Tensor]:
    """bool per row of `means`: at least FAR_RESET_FRACTION * far_distance from `center` (the far
    background of a rig round the scene); None without a centre or far_distance."""
    if center is None or far_distance is None:
        return None
    d = torch.linalg.vector_norm(means.detach() - center.to(means), dim=1)
    return d >= FAR_RESET_FRACTION * far_distance


def far_last(order: Tensor, far: Tensor) -> Tensor:
    """`order` (row indices) with the rows `far` marks after all others, each group in its order
    (budget_growth_order "inside-first": a stable sort by tier)."""
    return order[torch.sort(far[order].to(torch.uint8), stable=True).indices]


def growth_that_fits(score: Tensor, cost: Tensor, room: int, far: Optional[Tensor] = None) -> Tensor:
    """[K] bool over K growth candidates: the ones a Gaussian budget lets grow. Ranked by `score`
    [K] (largest first, ties in the given order; with `far` [K] bool, the ones it marks after all
    others: budget_growth_order "inside-first"), the longest prefix whose `cost` [K] (the rows each
    adds: a clone 1, a split its samples - 1) sums to at most `room`. The ranking GS3DAdapter,
    GS4DAdapter and MVGSStrategy apply, and a hand-written loop can (examples/graphdeco_loop)."""
    order = torch.sort(score, descending=True, stable=True).indices
    if far is not None:
        order = far_last(order, far)
    fits = torch.zeros(len(score), dtype=torch.bool, device=score.device)
    fits[order] = torch.cumsum(cost[order], 0) <= room
    return fits


SPREAD_LEVELS = 21  # spread_order's grid levels: 2^21 cells a side, a cell's code fits 63 bits


def spread_order(positions: Tensor) -> Tensor:
    """[N] scores in (0, 1] whose descending order lists `positions` [N, 3] coarse to fine, so
    that every prefix is spread over space: on grids of 2^j cells a side over the points'
    bounding cube (j = 0 .. SPREAD_LEVELS - 1), each occupied cell has one representative, its
    point with the smallest key of a uniform draw (generator seed 0); a point's level is the
    coarsest grid it represents (the grids nest, so it represents every finer one too), and its
    score (SPREAD_LEVELS - level + 1 - key) / (SPREAD_LEVELS + 1). The first K of the order hold
    one point of every occupied cell of the finest grid with at most K occupied cells: where
    points crowd, the cut thins them; a point alone in its region stays. Points at one
    position share the last level. Computed in float64 on the CPU."""
    p = positions.detach().double().cpu()
    n = p.shape[0]
    key = torch.rand(n, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    level = torch.full((n,), SPREAD_LEVELS, dtype=torch.long)
    if n:
        lo = p.min(dim=0).values
        span = max(float((p.max(dim=0).values - lo).max()), 1e-300)
        unplaced = torch.ones(n, dtype=torch.bool)
        for j in range(SPREAD_LEVELS):
            c = ((p - lo) / span * 2 ** j).floor().long().clamp(0, 2 ** j - 1)
            _, cell = torch.unique((c[:, 0] << (2 * j)) | (c[:, 1] << j) | c[:, 2], return_inverse=True)
            first = torch.full((int(cell.max()) + 1,), math.inf, dtype=torch.float64)
            first = first.scatter_reduce(0, cell, key, reduce="amin")
            rep = key == first[cell]
            level[rep & unplaced] = j
            unplaced &= ~rep
            if not bool(unplaced.any()):
                break
    return ((SPREAD_LEVELS - level).double() + 1.0 - key) / (SPREAD_LEVELS + 1)


def even_cut_order(positions: Tensor, center: Optional[Tensor] = None) -> Tensor:
    """[N] scores in (0, 1] for a cut before any view (largest kept): within each of two groups,
    the rows beyond the far line (FAR_RESET_FRACTION of these positions' own farthest distance
    from `center`) and the others, the group's own spread_order as 1 - rank / group size. So a cut keeps
    each group's share of the rows (the scene's points are spread as its views' pixels are; a
    far background shell's few points cover a large area and would take a world-space spread's
    first places) and, within each, a subset spread over its extent. Without a center: one
    group, spread_order."""
    p = positions.detach().double().cpu()
    center = _check_center(center)
    far = beyond_far_line(p, center, farthest_distance(p, center))
    if far is None:
        return spread_order(p)
    out = torch.empty(len(p), dtype=torch.float64)
    for g in (far, ~far):
        idx = g.nonzero().squeeze(1)
        rank = torch.empty(len(idx), dtype=torch.float64)
        rank[torch.sort(spread_order(p[idx]), descending=True, stable=True).indices] = torch.arange(
            len(idx), dtype=torch.float64)
        out[idx] = 1.0 - rank / len(idx)  # an empty group assigns nothing
    return out


def keep_scores_of(opacity: Tensor, coverage: Tensor, positions: Tensor, center: Optional[Tensor]) -> Tensor:
    """opacity x coverage (a Gaussian's summed footprint over the window's views), or, when no
    view was folded in (coverage all 0), opacity x even_cut_order(positions, center): a cut
    before any view keeps the object's and the far background's shares, each spread over its
    extent."""
    if bool((coverage > 0).any()):
        return opacity * coverage.to(opacity)
    return opacity * even_cut_order(positions, center).to(opacity)


def rasterizer_reports_blend(rasterize) -> bool:
    """Whether a rasterizer with gsplat's call shape takes the reference renderer's
    ``blend_stats`` keyword (meta "blend_weight" / "blend_pixels"): a parameter of that name in
    its signature (a **kwargs catch-all does not count: gsplat's would pass it to nothing)."""
    try:
        return "blend_stats" in inspect.signature(rasterize).parameters
    except (TypeError, ValueError):  # a builtin or C function without a signature
        return False


def faint_rows(weight: Tensor, pixels: Tensor, seen: Tensor, share: float) -> Tensor:
    """[N] bool: the faintest Gaussians (MVGSConfig.prune_faint, DensifyContext.faint_share).
    weight [N]: blend weight (alpha x T) summed over some views; pixels [N]: the pixels it was
    blended at there; seen [N] bool: the rows those views judged (others are never chosen).
    Among the seen rows, in order of weight per blended pixel (0 where never blended; ties by
    row), the longest prefix whose summed weight is at most `share` of all the weight. Nothing
    when no weight was blended."""
    out = torch.zeros(weight.shape, dtype=torch.bool, device=weight.device)
    w = weight.detach().to(torch.float64)
    total = float(w.sum())
    if share <= 0 or not total > 0:
        return out
    rows = seen.nonzero().squeeze(1)
    per_pixel = torch.where(pixels[rows] > 0, w[rows] / pixels[rows].to(w).clamp_min(1), torch.zeros_like(w[rows]))
    order = rows[torch.sort(per_pixel, stable=True).indices]
    count = int(torch.searchsorted(torch.cumsum(w[order], 0), share * total, right=True))
    out[order[:count]] = True
    return out


def _check_center(center) -> Optional[Tensor]:
    """A scene centre as a [3] float64 tensor (None stays None), or ValueError naming it."""
    if center is None:
        return None
    c = torch.as_tensor(center).detach().to(dtype=torch.float64, device="cpu").reshape(-1)
    if c.numel() != 3 or not bool(torch.isfinite(c).all()):
        raise ValueError(f"scene_center must be 3 finite numbers, got {center!r}")
    return c.clone()


def _n_rest(degree: int) -> int:
    return (degree + 1) ** 2 - 1


class GS3DAdapter:
    """3DGS parameters + Adam + densification, driven by the MVGS controller.

    Construct with :meth:`from_scene`, :meth:`from_tensors` or :meth:`from_ply`; the
    constructor itself takes the raw (pre-activation) tensors listed in the module docstring.

    Attributes:
        params: dict name -> nn.Parameter (replaced, not resized, when N changes).
        optimizer: the Adam optimizer, one group per name in PARAM_NAMES.
        stats: the [N] densification statistics by name, STAT_NAMES (see accumulate_stats); each is
            also an attribute (``adapter.grad_accum``).
        scene_extent: the scene scale of the learning rate of the means.
        scene_center: [3] float64 centre the means' step rule measures distances from
            (config.means_lr_rule), or None (then every Gaussian gets the extent rule).
        active_sh_degree: SH degree rendered now.
    """

    def __init__(self, means: Tensor, sh0: Tensor, shN: Tensor, scales: Tensor, quats: Tensor,
                 opacities: Tensor, scene_extent: float, config: Optional[GS3DConfig] = None,
                 active_sh_degree: int = 0, *, scene_center: Optional[Tensor] = None) -> None:
        self.config = GS3DConfig() if config is None else config
        if not isinstance(self.config, GS3DConfig):
            raise ValueError(f"config must be a GS3DConfig, got {type(self.config).__name__}")
        self.scene_extent = check_float("scene_extent", scene_extent, positive=True)
        self.scene_center = _check_center(scene_center)
        # the initial model's farthest mean from the centre: the step rules' factor stops growing there,
        # and 3/4 of it is where opacity_reset_scope "inside"'s far background begins
        self.far_distance: Optional[float] = farthest_distance(means, self.scene_center)
        raw = dict(means=means, sh0=sh0, shN=shN, scales=scales, quats=quats, opacities=opacities)
        self._check_raw(raw)
        self._generator = torch.Generator().manual_seed(self.config.seed)
        self._step = 0
        self._views = 1  # views per step the optimizer is scaled for (set_views_per_step)
        self._mean_reference: Optional[Tensor] = None  # see optimizer_step
        # True while every scale is from_scene's spacing rule (no optimizer step yet): a cut then
        # re-sizes the kept Gaussians by the spacing of the kept points (see densify)
        self.sized_by_spacing = False
        # whether render asks the rasterizer for blend statistics (collect_blend_stats)
        self.blend_stats = False
        self.active_sh_degree = check_int("active_sh_degree", active_sh_degree, 0,
                                           self.config.sh_degree)
        self._build(raw)

    # ---- construction ----------------------------------------------------------------------
    def _check_raw(self, raw: Dict[str, Tensor]) -> None:
        means = raw["means"]
        if not isinstance(means, Tensor) or means.ndim != 2 or means.shape[1] != 3:
            raise ValueError(f"means must be a [N,3] tensor, got {getattr(means, 'shape', means)!r}")
        if not means.is_floating_point():
            raise ValueError(f"means must be floating point, got {means.dtype}")
        n, k = means.shape[0], _n_rest(self.config.sh_degree)
        shapes = {"sh0": (n, 1, 3), "shN": (n, k, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,)}
        for name, shape in shapes.items():
            t = raw[name]
            if not isinstance(t, Tensor) or tuple(t.shape) != shape:
                got = list(t.shape) if isinstance(t, Tensor) else repr(t)
                hint = f" (sh_degree={self.config.sh_degree})" if name == "shN" else ""
                raise ValueError(f"{name} must be {list(shape)}{hint} with N={n} from means, got {got}")
        for name, t in raw.items():
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} has non-finite values")

    def _build(self, raw: Dict[str, Tensor]) -> None:
        """(Re)create parameters, a fresh optimizer and zero statistics from raw tensors."""
        ref = raw["means"]
        self.params: Dict[str, torch.nn.Parameter] = {
            name: torch.nn.Parameter(raw[name].detach().to(ref).clone().contiguous())
            for name in PARAM_NAMES
        }
        lrs = self._base_lrs()
        groups = [{"params": [self.params[n]], "lr": lrs[n], "name": n} for n in PARAM_NAMES]
        self.optimizer = make_adam(groups, self.config.adam_eps)
        self._reset_stats()

    def _base_lrs(self) -> Dict[str, float]:
        c = self.config
        return {"means": self.means_lr(self._step), "sh0": c.lr_sh0, "shN": c.lr_shN,
                "scales": c.lr_scales, "quats": c.lr_quats, "opacities": c.lr_opacities}

    def _reset_stats(self) -> None:
        n, ref = self.num_primitives(), self.params["means"]
        self.stats: Dict[str, Tensor] = {name: torch.zeros(n, dtype=ref.dtype, device=ref.device) for name in STAT_NAMES}

    @classmethod
    def from_tensors(cls, means: Tensor, *, scales: Tensor, opacities: Tensor, scene_extent: float,
                     rgb: Optional[Tensor] = None, sh: Optional[Tensor] = None,
                     quats: Optional[Tensor] = None, config: Optional[GS3DConfig] = None,
                     dtype: Optional[torch.dtype] = None, scene_center: Optional[Tensor] = None) -> "GS3DAdapter":
        """Build from activated values (the docs/design.md conventions).

        Args:
            means: [N, 3]. scales: [N, 3] > 0. opacities: [N] in (0, 1).
            rgb: [N, 3] colours (SH DC = (rgb - 0.5) / SH_C0, higher bands 0), or
            sh: [N, (d+1)^2, 3] SH coefficients, d <= config.sh_degree (missing bands are 0).
            quats: [N, 4] w-x-y-z (default identity).
            dtype: of the parameters (default: that of means).
            scene_center: [3], the centre config.means_lr_rule measures from (None: the extent rule).
        """
        config = GS3DConfig() if config is None else config
        means = torch.as_tensor(means).detach()
        if means.ndim != 2 or means.shape[1] != 3:
            raise ValueError(f"means must be [N,3], got {list(means.shape)}")
        dtype = (means.dtype if means.is_floating_point() else torch.float32) if dtype is None else dtype
        means = means.to(dtype)
        n = means.shape[0]
        t = lambda x: torch.as_tensor(x).detach().to(device=means.device, dtype=dtype)  # noqa: E731
        if (rgb is None) == (sh is None):
            raise ValueError("give exactly one of rgb [N,3] or sh [N,K,3]")
        if rgb is not None:
            rgb = t(rgb)
            if tuple(rgb.shape) != (n, 3):
                raise ValueError(f"rgb must be [N,3] with N={n}, got {list(rgb.shape)}")
            sh = torch.cat([((rgb - 0.5) / SH_C0)[:, None, :],
                            torch.zeros(n, _n_rest(config.sh_degree), 3, dtype=dtype, device=means.device)], 1)
        sh0, shN = cls._split_sh(t(sh), n, config.sh_degree)
        scales, opacities = t(scales), t(opacities)
        if scales.numel() and not bool((scales > 0).all()):
            raise ValueError(f"scales must be > 0 (activated), got min {float(scales.min())}")
        if opacities.numel() and not bool(((opacities > 0) & (opacities < 1)).all()):
            raise ValueError(f"opacities must be in (0, 1) (activated), got range "
                             f"[{float(opacities.min())}, {float(opacities.max())}]")
        if quats is None:
            quats = torch.zeros(n, 4, dtype=dtype, device=means.device)
            quats[:, 0] = 1.0
        return cls(means, sh0, shN, torch.log(scales), t(quats), torch.logit(opacities),
                   scene_extent, config, scene_center=scene_center)

    @staticmethod
    def _split_sh(sh: Tensor, n: int, degree: int) -> Tuple[Tensor, Tensor]:
        """[N, K, 3] SH -> sh0 [N, 1, 3] and shN [N, (degree+1)^2 - 1, 3], zero-padding bands."""
        k_max = (degree + 1) ** 2
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"sh must be [N,(d+1)^2,3] with N={n}, got {list(sh.shape)}")
        if sh.shape[1] > k_max:
            raise ValueError(f"sh has {sh.shape[1]} coefficients per channel, more than "
                             f"config.sh_degree={degree} holds ({k_max})")
        pad = torch.zeros(n, k_max - sh.shape[1], 3, dtype=sh.dtype, device=sh.device)
        full = torch.cat([sh, pad], dim=1)
        return full[:, :1].clone(), full[:, 1:].clone()

    @classmethod
    def from_scene(cls, scene, config: Optional[GS3DConfig] = None, dtype: torch.dtype = torch.float32,
                   device: Optional[torch.device | str] = None, points=None) -> "GS3DAdapter":
        """Initialise from ``scene.points`` (or ``points``, a PointCloud given in their place) as
        the original 3DGS, or randomly without points.

        config.means_lr_rule and config.budget_growth_order "auto" are resolved here for the
        scene's rig (see GS3DConfig).
        SH DC from the point colours, higher bands 0; isotropic scales sqrt(mean squared distance
        to the 3 nearest other points), floored at 1e-7 before the square root; identity
        rotations; opacity config.init_opacity. Without points: config.random_init points where the
        cameras look (see GS3DConfig.random_init), colours uniform in [0, 1] (drawn from a
        generator seeded with config.seed).
        """
        config = GS3DConfig() if config is None else config
        if "auto" in (config.means_lr_rule, config.budget_growth_order):  # the rig decides (GS3DConfig)
            forward = getattr(scene, "center", None) is not None and is_forward_facing(scene.train_cameras)
            if config.means_lr_rule == "auto":  # no centre, no rule
                config = dataclasses.replace(config, means_lr_rule="disparity" if forward else "extent")
            if config.budget_growth_order == "auto":
                config = dataclasses.replace(config, budget_growth_order="score" if forward else "inside-first")
        points = getattr(scene, "points", None) if points is None else points
        if points is None or len(points) == 0:
            xyz, rgb = cls._random_points(scene, config)
        else:
            xyz, rgb = points.xyz.to(torch.float64), points.rgb.to(torch.float64)
        xyz, rgb = xyz.to(device), rgb.to(device)
        log_scale = spacing_log_scale(xyz, chunk=config.knn_chunk)[:, None].repeat(1, 3)
        n = xyz.shape[0]
        quats = torch.zeros(n, 4, dtype=torch.float64, device=xyz.device)
        quats[:, 0] = 1.0
        sh0 = ((rgb - 0.5) / SH_C0)[:, None, :]
        shN = torch.zeros(n, _n_rest(config.sh_degree), 3, dtype=torch.float64, device=xyz.device)
        opac = torch.full((n,), math.log(config.init_opacity / (1 - config.init_opacity)),
                          dtype=torch.float64, device=xyz.device)
        t = lambda x: x.to(dtype)  # noqa: E731
        model = cls(t(xyz), t(sh0), t(shN), t(log_scale), t(quats), t(opac), scene.extent, config,
                    scene_center=getattr(scene, "center", None))
        model.sized_by_spacing = True
        return model

    @staticmethod
    def _random_points(scene, config: GS3DConfig) -> Tuple[Tensor, Tensor]:
        gen = torch.Generator().manual_seed(config.seed)
        xyz, rgb, description = random_init_points(scene, config.random_init, gen, config.random_init_half_size)
        LOG.info("%s", description)
        return xyz, rgb

    @classmethod
    def from_ply(cls, path, scene_extent: float, config: Optional[GS3DConfig] = None,
                 dtype: torch.dtype = torch.float32, device: Optional[torch.device | str] = None,
                 scene_center: Optional[Tensor] = None) -> "GS3DAdapter":
        """Load a 3DGS PLY (ours or another tool's). Without a config the file's SH degree is the
        maximum; a config with a higher degree gets zero higher bands, a lower one is an error.
        The active SH degree starts at the file's degree (the model is trained); set_step()
        recomputes it from the step. scene_center: as for from_tensors."""
        g = read_gaussian_ply(path)
        d = g.sh_degree
        config = GS3DConfig(sh_degree=d) if config is None else config
        if config.sh_degree < d:
            raise ValueError(f"{path} holds SH degree {d} but config.sh_degree={config.sh_degree}; "
                             f"raise config.sh_degree (bands would be dropped)")
        sh0, shN = cls._split_sh(torch.cat([g.sh0, g.shN], 1), g.means.shape[0], config.sh_degree)
        t = lambda x: x.to(device=device, dtype=dtype)  # noqa: E731
        return cls(t(g.means), t(sh0), t(shN), t(g.scales), t(g.quats), t(g.opacities), scene_extent,
                   config, active_sh_degree=d, scene_center=scene_center)

    # ---- activated views -----------------------------------------------------------------
    def get_scales(self) -> Tensor:
        """[N, 3] activated scales."""
        return torch.exp(self.params["scales"])

    def get_opacities(self) -> Tensor:
        """[N] activated opacities."""
        return torch.sigmoid(self.params["opacities"])

    def positions(self) -> Tensor:
        """[N, 3] Gaussian centres (detached)."""
        return self.params["means"].detach()

    def num_primitives(self) -> int:
        return int(self.params["means"].shape[0])

    # ---- schedule -----------------------------------------------------------------------
    def means_lr(self, step: int) -> float:
        """Learning rate of the means at ``step``: log-linear from lr_means_init * extent at
        step 0 to lr_means_final * extent at position_lr_max_steps, constant after."""
        c = self.config
        t = min(max(step / c.position_lr_max_steps, 0.0), 1.0)
        lo, hi = math.log(c.lr_means_init * self.scene_extent), math.log(c.lr_means_final * self.scene_extent)
        return math.exp((1.0 - t) * lo + t * hi)

    def set_views_per_step(self, views: int) -> None:
        """Scale the optimizer for steps of `views` views from the next set_step on (Grendel-GS's
        rule, see scale_for_views; MVGSConfig.views_scaling="sqrt" calls it every step)."""
        self._views = check_int("views", views, 1)

    def set_step(self, step: int) -> None:
        """Learning rates (the means' decay, times √M for M-view steps, see set_views_per_step)
        and the active SH degree for ``step``: pure functions of the step, so a resumed run
        continues exactly."""
        self._step = check_int("step", step, 0)
        scale_for_views(self.optimizer, self._base_lrs(), self._views, self.config.adam_eps)
        self.active_sh_degree = min(self.config.sh_degree, step // self.config.sh_degree_interval)

    def learning_rates(self) -> Dict[str, float]:
        """Current learning rate of every group, by name."""
        return {g["name"]: g["lr"] for g in self.optimizer.param_groups}

    # ---- rendering and statistics -------------------------------------------------------
    def render(self, cameras: Sequence[Camera], backgrounds: Tensor) -> RenderResult:
        """Render C cameras of one size.

        Args:
            cameras: C >= 1 cameras, all of one width and height.
            backgrounds: [C, 3].
        Returns:
            RenderResult with images [C, H, W, 3], alphas [C, H, W, 1] and the rasterizer's meta
            dict as aux (its means2d retains its gradient for accumulate_stats).
        """
        return self.render_raw(self.params, cameras, backgrounds)

    def render_raw(self, raw: Dict[str, Tensor], cameras: Sequence[Camera], backgrounds: Tensor) -> RenderResult:
        """Render C cameras of one size from the given raw (pre-activation) attributes instead of
        self.params: same names and shapes as self.params (e.g. deformed copies of them, as the
        4DGS adapter renders). Activation, rasterizer call and the returned record are those of
        :meth:`render`, which is ``render_raw(self.params, ...)``."""
        cams = list(cameras)
        if not cams:
            raise ValueError("render needs at least one camera, got 0")
        sizes = sorted({(c.width, c.height) for c in cams})
        if len(sizes) != 1:
            raise ValueError(f"all cameras of a chunk must have one size, got (width, height) "
                             f"{sizes} for uids {[c.uid for c in cams]}")
        width, height = sizes[0]
        p = raw
        ref = p["means"]
        viewmats, Ks = stack_cameras(cams, dtype=ref.dtype, device=ref.device)
        bg = torch.as_tensor(backgrounds).to(device=ref.device, dtype=ref.dtype)
        if tuple(bg.shape) != (len(cams), 3):
            raise ValueError(f"backgrounds must be [C,3] with C={len(cams)}, got {list(bg.shape)}")
        colors = torch.cat([p["sh0"], p["shN"]], dim=1)  # [N, K, 3]
        scales, opacities = torch.exp(p["scales"]), torch.sigmoid(p["opacities"])
        drawn = None
        kwargs = dict(self.config.rasterize_kwargs)
        if self.blend_stats:
            kwargs["blend_stats"] = True
        if self.config.beside_cull > 0:
            drawn = ~beside_camera(p["means"].detach(), scales.detach(), viewmats, Ks, width, height,
                                   self.config.beside_cull)
            opacities = opacities.reshape(1, -1) * drawn.to(opacities.dtype)  # [C, N]
        images, alphas, meta = self.config.rasterize(
            p["means"], p["quats"], scales, opacities, colors,
            viewmats, Ks, width, height, sh_degree=self.active_sh_degree, packed=False,
            backgrounds=bg, **kwargs,
        )
        if drawn is not None:  # not drawn: not visited either (accumulate_stats reads radii)
            radii = meta["radii"]
            meta["radii"] = torch.where(drawn.reshape(drawn.shape + (1,) * (radii.dim() - 2)), radii,
                                        torch.zeros_like(radii))
        if meta["means2d"].requires_grad:  # not under torch.no_grad()
            meta["means2d"].retain_grad()
        return RenderResult(images=images, alphas=alphas, aux=meta)

    def regularization(self, step: int) -> Optional[Tensor]:
        return None

    def accumulate_stats(self, result: RenderResult) -> None:
        """Fold a rendered chunk's screen-space statistics in (call after its backward).

        For every camera c of the chunk and every Gaussian visible in it (radius > 0):
        grad_accum += |d loss / d means2d[c]| measured in NDC, i.e. the pixel-space gradient
        scaled by (W/2, H/2) as the original CUDA code reports it (so 2e-4 keeps its meaning);
        denom += 1 (each view is one visit, so a chunk of C views adds up to C);
        max_radii2D = max(max_radii2D, radius in pixels);
        grad_sq_accum += the same NDC norm squared (for the consistency of densify_scores);
        coverage_accum += pi radius^2 / (W H), the share of the view its footprint covers (for
        keep_scores);
        blend_weight_accum, blend_pixels_accum += the blend weight and blended pixels the renderer
        reported (meta "blend_weight", "blend_pixels"; after collect_blend_stats(), for faint_rows).

        gsplat's DefaultStrategy additionally multiplies the gradient by the number of cameras
        of the render call, because its loss averages over them; here the controller's loss is
        a sum of per-view losses, so no such factor applies.
        """
        meta = result.aux
        if not isinstance(meta, dict) or "means2d" not in meta or "radii" not in meta:
            raise ValueError("accumulate_stats needs the RenderResult returned by this adapter's render()")
        means2d = meta["means2d"]
        grad = means2d.grad
        if grad is None:
            raise RuntimeError("means2d has no gradient: call backward on a loss of this render "
                               "before accumulate_stats")
        n = self.num_primitives()
        if grad.shape[-2] != n:
            raise ValueError(f"the render has {grad.shape[-2]} Gaussians but the model now has {n} "
                             f"(densified in between?)")
        radii = meta["radii"]  # [C, N, 2] (gsplat >= 1.5, ours) or [C, N] (older gsplat)
        if radii.dim() == 3:
            visible, radius = (radii > 0).all(dim=-1), radii.max(dim=-1).values
        else:
            visible, radius = radii > 0, radii
        ndc = grad.detach() * grad.new_tensor([meta["width"] / 2.0, meta["height"] / 2.0])
        norms = ndc.norm(dim=-1).to(self.grad_accum.dtype)  # [C, N]
        vis = visible.to(self.grad_accum.dtype)
        self.grad_accum += (norms * vis).sum(dim=0)
        self.grad_sq_accum += (norms.square() * vis).sum(dim=0)
        self.denom += vis.sum(dim=0)
        area = math.pi * radius.to(self.grad_accum.dtype).square() / float(meta["width"] * meta["height"])
        self.coverage_accum += (area * vis).sum(dim=0)
        if "blend_weight" in meta:
            self.blend_weight_accum += meta["blend_weight"].detach().to(self.grad_accum).sum(dim=0)
            self.blend_pixels_accum += meta["blend_pixels"].detach().to(self.grad_accum).sum(dim=0)
        elif self.blend_stats:
            raise ValueError("collect_blend_stats() asked for the blend weights of every view (MVGSConfig.prune_faint), "
                             "but config.rasterize returned no meta['blend_weight'] (the reference renderer reports "
                             "them with blend_stats=True)")
        radius = torch.where(visible, radius.to(self.max_radii2D.dtype), torch.zeros_like(self.max_radii2D))
        self.max_radii2D = torch.maximum(self.max_radii2D, radius.max(dim=0).values)

    def collect_blend_stats(self) -> bool:
        """From now on, ask the rasterizer for each view's blend statistics (its ``blend_stats``
        keyword) and fold them into blend_weight_accum / blend_pixels_accum, for the cut of the
        faintest Gaussians (DensifyContext.faint_share; the controller calls this when
        MVGSConfig.prune_faint is set). Off by default: it costs a few percent of the forward pass.
        Returns whether it will: False, and nothing changes, when config.rasterize takes no
        ``blend_stats`` keyword (gsplat's own rasterization, for one: only the reference renderer
        reports them)."""
        if not rasterizer_reports_blend(self.config.rasterize):
            return False
        self.blend_stats = True
        return True

    # ---- distributed training (mvgs_plugin.protocol.DistributedAdapter) -------------------
    def gradient_parameters(self) -> Dict[str, Tensor]:
        """The parameters by group name (the names of named_gradients())."""
        return dict(self.params)

    def statistics(self) -> Dict[str, Tuple[Tensor, str]]:
        """grad_accum, grad_sq_accum, coverage_accum, blend_weight_accum, blend_pixels_accum and
        denom [N] add up over disjoint sets of views; max_radii2D [N] is a maximum."""
        return {name: (self.stats[name], STAT_NAMES[name]) for name in STAT_NAMES}

    def load_statistics(self, stats: Dict[str, Tensor]) -> None:
        """Replace every statistic of STAT_NAMES by [N] tensors (cast to the model's dtype)."""
        names = tuple(STAT_NAMES)
        if set(stats) != set(names):
            raise ValueError(f"statistics must be exactly {list(names)}, got {sorted(stats)}")
        n, ref = self.num_primitives(), self.params["means"]
        for name in names:
            t = torch.as_tensor(stats[name])
            if tuple(t.shape) != (n,):
                raise ValueError(f"statistics[{name!r}] must be [{n}], got {list(t.shape)}")
        for name in names:
            self.stats[name] = torch.as_tensor(stats[name]).to(device=ref.device, dtype=ref.dtype).clone()

    def mean_grads(self) -> Tensor:
        """[N] accumulated NDC gradient norm per visit (0 where never visible)."""
        return torch.where(self.denom > 0, self.grad_accum / self.denom.clamp_min(1),
                           torch.zeros_like(self.grad_accum))

    def consistency(self) -> Tensor:
        """[N] in [1/n, 1]: how evenly a Gaussian's screen-space gradient is shared by the n views
        that saw it since the last densification, (sum g)^2 / (n sum g^2) over its visits (1: the
        same gradient in every view; 1/n: one view holds it all; 0 where never visible or never
        pulled). The views may come from one step (M views) or from the window's one-view steps.
        Statistics without squares (set by hand, or loaded from a release before grad_sq_accum)
        count as consistent (1)."""
        return consistency_of(self.grad_accum, self.grad_sq_accum, self.denom)

    def densify_scores(self, rank_by: str = "consistency") -> Tensor:
        """[N] the order in which growth candidates are kept under a cap (largest first):
        "gradient" is 3DGS's mean gradient per visit; "consistency" (default) multiplies it by
        consistency(), so error that every view sees is densified before error one view alone
        reports (FastGS's multi-view consistency idea, scored here from the statistics every
        step already collects)."""
        if rank_by == "gradient":
            return self.mean_grads()
        if rank_by == "consistency":
            return self.mean_grads() * self.consistency()
        raise ValueError(f"rank_by must be 'gradient' or 'consistency', got {rank_by!r}")

    def keep_scores(self) -> Tensor:
        """[N] the order in which Gaussians are kept when the model must shrink to a cap (largest
        kept): opacity times the footprint summed over the views since the last densification
        (coverage_accum, shares of each view), so a Gaussian that covers much of many views
        outranks one seen in a single view or nearly transparent. Before any view was folded in
        (all coverage 0) no view says which Gaussian helps: opacity times
        even_cut_order(means, scene_center), so a cut keeps the object's and the far background's
        shares of the points, each spread over its extent (a seeded random subset kept the shares
        but left holes where the draw thinned; docs/equal_compute_log.md, "A first cut spread over
        the model")."""
        return keep_scores_of(self.get_opacities().detach(), self.coverage_accum, self.params["means"], self.scene_center)

    # ---- densification -------------------------------------------------------------------
    def densify(self, ctx: DensifyContext) -> DensifyReport:
        """The original 3DGS densify_and_prune, with MVGS cross-ray boxes before it.

        With g = mean NDC gradient per visit, β = ctx.grad_threshold, E = ctx.scene_extent,
        all selections made on the Gaussians present before the call:
          1. boxes: every Gaussian strictly inside any of ctx.boxes is cloned once (no gradient
             or size test); with ctx.max_new_from_boxes, the ones with the largest g;
          2. clone: g >= β and max scale <= percent_dense * E -> an exact copy;
          3. split: g >= β and max scale > percent_dense * E -> split_samples children at
             mean + R (s ⊙ n), n ~ N(0, I), scale s / (0.8 * split_samples), other attributes
             copied; the parent is removed;
          4. prune (all rows, new ones included): opacity < min_opacity and, with
             ctx.prune_large, max scale > max_world_size * E (config.world_size_rule "distance":
             max_world_size * max(E, distance from ctx.scene_center)) or (when
             config.max_screen_size is set) max screen radius > max_screen_size;
          5. with ctx.faint_share S: faint_rows over the window's blend statistics (the rows
             some view saw with the least blend weight per blended pixel, carrying at most S of
             all the weight; they are not grown from either), counted in extra["faint"].
        With a cap (the lower of config.max_gaussians and ctx.max_primitives) the count after the
        call never exceeds it: the rows step 4 prunes are not grown from; when the survivors
        alone exceed the cap, the ones with the lowest keep_scores() are removed down to it (and
        nothing grows; before the first optimizer step, sized_by_spacing, the kept rows' scales
        are re-set to the spacing of the kept means, knn.spacing_log_scale, as from_scene sizes
        them); otherwise, when the candidates' growth exceeds the room left, up to
        floor(ctx.swap_share x cap) of the lowest keep_scores() among the other rows are removed
        to make more room (the swap: _swap_out), and the candidates of 1-3 are ranked by
        densify_scores(ctx.rank_by) together (with config.budget_growth_order "inside-first",
        those inside the far line before those beyond it) and the best whose growth fits the
        room are kept (each adds 1, a split adds samples - 1).
        New rows start with zero statistics, a zero radius and zero Adam moments; surviving rows
        keep theirs. As in the original, the parameters are new tensors without gradients, so an
        optimizer step right after densify leaves them unchanged for that step. The statistics
        are reset to zero.

        Report: cloned / split / from_boxes count the selected Gaussians (a split adds
        split_samples - 1 net); pruned counts every row removed but split parents (rule prunes,
        new rows included, rows shed to the cap, also in extra["shed_to_cap"], and rows swapped
        out, in extra["swapped"]); so after =
        before + from_boxes + cloned + split * (split_samples - 1) - pruned.
        """
        try:
            beta = float(ctx.grad_threshold)
        except (TypeError, ValueError):
            beta = math.nan
        if isinstance(ctx.grad_threshold, bool) or not beta >= 0:
            # +inf is allowed: no gradient-driven growth (boxes and pruning still run)
            raise ValueError(f"ctx.grad_threshold must be a number >= 0 (inf allowed), "
                             f"got {ctx.grad_threshold!r}")
        extent = check_float("scene_extent", ctx.scene_extent, positive=True)
        n0 = self.num_primitives()
        g = self.mean_grads()
        score = self.densify_scores(ctx.rank_by)
        max_scale = self.get_scales().detach().max(dim=1).values
        small = max_scale <= self.config.percent_dense * extent
        box_sel, dropped_box_cap = self.box_selection(ctx, g)
        # the faintest rows (ctx.faint_share) go and are not grown from
        faint = faint_rows(self.blend_weight_accum, self.blend_pixels_accum, self.denom > 0, float(ctx.faint_share))
        if ctx.faint_share > 0 and not float(self.blend_weight_accum.sum()) > 0:
            raise ValueError(f"ctx.faint_share={ctx.faint_share} needs blend statistics, and none were folded in since "
                             "the last call: call collect_blend_stats() before the views are rendered")
        box_sel = box_sel & ~faint
        clone_sel = (g >= beta) & small & ~faint
        split_sel = (g >= beta) & ~small & ~faint
        cap = growth_cap(self.config.max_gaussians, ctx.max_primitives)
        shed = torch.zeros(n0, dtype=torch.bool, device=g.device)
        swapped = torch.zeros_like(shed)
        dropped_cap = 0
        if cap is not None:
            gone = self.prune_mask({k: v.detach() for k, v in self.params.items()}, self.max_radii2D, extent,
                                   ctx.prune_large, ctx.scene_center) | faint
            excess = n0 - int(gone.sum()) - cap
            if excess > 0:  # shrink to the cap: the lowest keep scores go
                keep_score = torch.where(gone, torch.full_like(g, math.inf), self.keep_scores().to(g))
                shed[torch.sort(keep_score, stable=True).indices[:excess]] = True
                gone = gone | shed
            box_sel, clone_sel, split_sel = box_sel & ~gone, clone_sel & ~gone, split_sel & ~gone
            room = max(0, cap - (n0 - int(gone.sum())))
            if excess <= 0:  # a model that had to shrink to the cap swaps nothing
                swapped = self._swap_out(box_sel, clone_sel, split_sel, gone, room, cap, ctx.swap_share)
                shed, gone, room = shed | swapped, gone | swapped, room + int(swapped.sum())
            box_sel, clone_sel, split_sel, dropped_cap = self._cap_growth(box_sel, clone_sel, split_sel, score, room)

        new_rows = self._new_rows(box_sel, clone_sel, split_sel)
        n_new = new_rows["means"].shape[0]
        all_rows = {k: torch.cat([self.params[k].detach(), new_rows[k]]) for k in PARAM_NAMES}
        radii = torch.cat([self.max_radii2D, self.max_radii2D.new_zeros(n_new)])
        prune = self.prune_mask(all_rows, radii, extent, ctx.prune_large, ctx.scene_center) | torch.cat(
            [shed | faint, shed.new_zeros(n_new)])
        parents = torch.cat([split_sel, split_sel.new_zeros(n_new)])
        keep = ~(prune | parents)
        if cap is not None and int(keep.sum()) > cap:  # a subclass's prune rule kept more: the newest rows go
            kept_new = keep.nonzero().squeeze(1)
            kept_new = kept_new[kept_new >= n0]
            over = int(keep.sum()) - cap
            prune[kept_new[len(kept_new) - over:]] = True
            keep = ~(prune | parents)
        src = torch.cat([torch.arange(n0, device=keep.device),
                         torch.full((n_new,), -1, dtype=torch.long, device=keep.device)])
        rows = {k: v[keep] for k, v in all_rows.items()}
        if self.sized_by_spacing and bool(shed.any()):  # a cut before training: sized as if built from the kept points
            rows["scales"] = spacing_log_scale(rows["means"], self.config.knn_chunk)[:, None].repeat(1, 3).to(
                rows["scales"])
        self._replace(rows, src[keep])
        self._reset_stats()
        return DensifyReport(
            before=n0, after=self.num_primitives(), cloned=int(clone_sel.sum()),
            split=int(split_sel.sum()), pruned=int((prune & ~parents).sum()),
            from_boxes=int(box_sel.sum()),
            extra={"grad_threshold": beta, "split_children": int(split_sel.sum()) * self.config.split_samples,
                   "dropped_by_box_cap": dropped_box_cap, "dropped_by_max_gaussians": dropped_cap,
                   "shed_to_cap": int((shed & ~swapped).sum()), "swapped": int(swapped.sum()), "cap": cap,
                   "faint": int(faint.sum())},
        )

    # ---- densification hooks: what a subclass may override (GS4DAdapter tests the boxes at the
    # views' times and prunes with the 4DGS rules) -------------------------------------------
    def box_selection(self, ctx: DensifyContext, g: Tensor) -> Tuple[Tensor, int]:
        """[N] bool: Gaussians strictly inside a CRD box, capped by ctx.max_new_from_boxes (the
        largest mean gradients kept); and how many the cap dropped."""
        n = self.num_primitives()
        none = torch.zeros(n, dtype=torch.bool, device=g.device)
        if ctx.boxes is None:
            return none, 0
        boxes = check_boxes(ctx.boxes)
        sel = boxes_contain(self.params["means"], boxes.to(g.device))
        total = int(sel.sum())
        if ctx.max_new_from_boxes is not None:
            sel = top_by_score(sel, g, check_int("max_new_from_boxes", ctx.max_new_from_boxes, 0))
        return sel, total - int(sel.sum())

    def _swap_out(self, box_sel: Tensor, clone_sel: Tensor, split_sel: Tensor, gone: Tensor, room: int, cap: int,
                  share: float) -> Tensor:
        """[N] bool: the rows a call at a binding cap removes so that more candidates can grow
        (DensifyContext.swap_share): the lowest keep_scores() among the rows that are neither
        candidates nor already gone, as many as the candidates' growth exceeds the room (a box
        clone or clone grows 1, a split split_samples - 1) and at most floor(share x cap)."""
        out = torch.zeros_like(gone)
        growth = int(box_sel.sum()) + int(clone_sel.sum()) + int(split_sel.sum()) * (self.config.split_samples - 1)
        want = min(growth - room, math.floor(float(share) * cap))
        if want <= 0:
            return out
        eligible = ~(gone | box_sel | clone_sel | split_sel)
        score = torch.where(eligible, self.keep_scores().to(torch.float64), torch.full_like(gone, math.inf, dtype=torch.float64))
        order = torch.sort(score, stable=True).indices[:min(want, int(eligible.sum()))]
        out[order] = True
        return out

    def _cap_growth(self, box_sel: Tensor, clone_sel: Tensor, split_sel: Tensor, score: Tensor, room: int):
        """Rank all growth candidates by `score` (largest first, ties in row order; with
        config.budget_growth_order "inside-first", those beyond the far line after all others)
        and keep the longest prefix whose net growth fits `room` (a box clone or clone adds 1, a
        split adds split_samples - 1). Returns the three masks and how many candidates fell."""
        masks = [box_sel, clone_sel, split_sel]
        costs = [1, 1, self.config.split_samples - 1]
        idx = [m.nonzero().squeeze(1) for m in masks]
        ranked = torch.cat([score[i] for i in idx])
        cost = torch.cat([torch.full((len(i),), c, dtype=torch.long, device=score.device)
                          for i, c in zip(idx, costs)])
        # the order matters only when some candidates must fall: only then, and only for them, the far line
        far = (self._beyond_far_line(torch.cat(idx)) if self.config.budget_growth_order == "inside-first"
               and int(cost.sum()) > room else None)
        fits = growth_that_fits(ranked, cost, room, far)
        out, start = [], 0
        for m, i in zip(masks, idx):
            kept = torch.zeros_like(m)
            kept[i[fits[start:start + len(i)]]] = True
            out.append(kept)
            start += len(i)
        return out[0], out[1], out[2], int((~fits).sum())

    def _new_rows(self, box_sel: Tensor, clone_sel: Tensor, split_sel: Tensor) -> Dict[str, Tensor]:
        """Raw attributes of the rows to append: box clones, clones, then split children."""
        p = {k: v.detach() for k, v in self.params.items()}
        parts = [{k: v[box_sel] for k, v in p.items()}, {k: v[clone_sel] for k, v in p.items()},
                 self._split_children(split_sel)]
        return {k: torch.cat([part[k] for part in parts]) for k in PARAM_NAMES}

    def _split_children(self, sel: Tensor) -> Dict[str, Tensor]:
        """split_samples children per selected Gaussian: positions mean + R (s ⊙ n), n ~ N(0, I);
        scales s / (0.8 * split_samples); other attributes copied. Rows ordered sample-major."""
        k = self.config.split_samples
        p = {name: v.detach()[sel] for name, v in self.params.items()}
        s = torch.exp(p["scales"]).repeat(k, 1)  # [k*M, 3]
        n = torch.randn(s.shape, generator=self._generator, dtype=torch.float64).to(s)
        R = quat_to_rotmat(p["quats"]).repeat(k, 1, 1)  # [k*M, 3, 3]
        out = {name: v.repeat(k, *([1] * (v.ndim - 1))) for name, v in p.items()}
        out["means"] = out["means"] + (R @ (s * n).unsqueeze(-1)).squeeze(-1)
        out["scales"] = torch.log(s / (0.8 * k))
        return out

    def prune_mask(self, rows: Dict[str, Tensor], radii: Tensor, extent: float, prune_large: bool,
                   center: Optional[Tensor] = None) -> Tensor:
        """[rows] bool: the rows (raw attributes after growth) densify() removes: opacity below
        config.min_opacity, and with prune_large world size above config.max_world_size x extent
        (world_size_rule "distance" with a center [3]: x max(extent, distance from center)) or
        screen radius above config.max_screen_size."""
        c = self.config
        prune = torch.sigmoid(rows["opacities"]) < c.min_opacity
        if prune_large:
            size = torch.exp(rows["scales"]).max(dim=1).values
            prune |= size > world_size_limit(rows["means"], extent, center, c.world_size_rule, c.max_world_size)
            if c.max_screen_size is not None:
                prune |= radii > c.max_screen_size
        return prune

    def _replace(self, values: Dict[str, Tensor], src: Tensor) -> None:
        """Swap in new tensors for every group; src [N_new] long gives the old row each new row
        continues (-1 = new row)."""
        for name in PARAM_NAMES:
            self._swap_group(name, values[name], src, zero_moments=False)

    def _swap_group(self, name: str, value: Tensor, src: Optional[Tensor], zero_moments: bool) -> None:
        """Replace one group's parameter, its Adam state carried along (ops.swap_param)."""
        self.params[name] = swap_param(self.optimizer, name, value, src, zero_moments)

    def reset_opacity(self) -> None:
        """Cap the opacities at config.opacity_reset_value (0.01) and zero the opacity group's
        Adam moments, as the original. Like the original, the opacity tensor is replaced, so its
        current gradient is dropped (the other groups keep theirs). With
        config.opacity_reset_scope "inside" (the default) the far background (_far_reset_mask)
        keeps its opacities; "all" caps every one, as the original."""
        v = self.config.opacity_reset_value
        opacities = self.params["opacities"].detach()
        capped = torch.clamp_max(opacities, math.log(v / (1.0 - v)))
        spared = self._far_reset_mask()
        if spared is not None:
            capped = torch.where(spared, opacities, capped)
        self._swap_group("opacities", capped, None, zero_moments=True)

    def _far_reset_mask(self) -> Optional[Tensor]:
        """[N] bool: the Gaussians a reset leaves alone (config.opacity_reset_scope "inside":
        at least FAR_RESET_FRACTION * far_distance from scene_center), or None when a reset
        caps every one ("all", or no scene_center / far_distance)."""
        return None if self.config.opacity_reset_scope == "all" else self._beyond_far_line()

    def _beyond_far_line(self, rows: Optional[Tensor] = None) -> Optional[Tensor]:
        """bool per Gaussian (of `rows`, default all): at least FAR_RESET_FRACTION * far_distance
        from scene_center (the far background of a rig round the scene); None without a centre
        or an initial model."""
        means = self.params["means"].detach()
        return beyond_far_line(means if rows is None else means[rows], self.scene_center, self.far_distance)

    # ---- optimisation ---------------------------------------------------------------------
    def named_gradients(self) -> Dict[str, Optional[Tensor]]:
        return {name: p.grad for name, p in self.params.items()}

    def clock_mismatch(self, clock: int) -> Optional[Tuple[str, int, str]]:
        """ClockedAdapter: the means' learning-rate decay spans config.position_lr_max_steps."""
        steps = self.config.position_lr_max_steps
        return None if steps == clock else ("position_lr_max_steps: its means' learning rate will not decay as "
                                            "planned", steps, "GS3DConfig.for_run(config)")

    def optimizer_step(self) -> None:
        """Adam on every group (with config.means_lr_rule "distance" or "disparity" and a
        scene_center, the means' Adam move is applied with the rule's per-row factors,
        means_step_scale, in one addition, so a move far below float32's spacing at the mean is
        not rounded away before it is scaled), then a check of what
        the renderer will take: a scale it refuses (log-scale > max_log_scale(dtype)) or a mean
        beyond MAX_MEAN_EXTENTS scene extents raises FloatingPointError naming the group (a
        diverging learning rate)."""
        self.sized_by_spacing = False
        means = self.params["means"]
        rule = self._means_rule() if means.grad is not None else None
        if rule is None:
            self.optimizer.step()
        else:  # Adam's step is per group, the rule's per row: the moments move, the means by the rule
            group = next(g for g in self.optimizer.param_groups if g["name"] == "means")
            lr, group["lr"] = group["lr"], 0.0
            try:
                self.optimizer.step()  # every group; the means' moments and step count, not the means
            finally:
                group["lr"] = lr
            with torch.no_grad():
                means.add_(self._ruled_move(group, lr, *rule))  # one rounding, however small the move
        with torch.no_grad():
            top = float(self.params["scales"].max()) if self.params["scales"].numel() else 0.0
            limit = max_log_scale(self.params["scales"].dtype)
            if top > limit:  # NaN passes here: the controller's finiteness check names it
                raise FloatingPointError(f"group 'scales': a log-scale reached {top:.4g} (> {limit:.4g}, scale "
                                         f"{math.exp(min(top, 700)):.3g}, beyond what the renderer takes in "
                                         f"{self.params['scales'].dtype}); the learning rate diverges")
            means = self.params["means"]
            if means.numel():
                if self._mean_reference is None:  # the model's median at its first step here (not saved)
                    self._mean_reference = means.median(dim=0).values.clone()
                far = float((means - self._mean_reference).abs().max())
                if far > MAX_MEAN_EXTENTS * self.scene_extent:
                    raise FloatingPointError(
                        f"group 'means': a mean moved {far:.4g} from the model's median, beyond {MAX_MEAN_EXTENTS:g} "
                        f"scene extents ({self.scene_extent:.4g}); the learning rate diverges")

    def _ruled_move(self, group, lr: float, out: Tensor, scale: Tensor) -> Tensor:
        """Adam's move of the means (torch's formula, from the moments this step left: lr / (1 -
        b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps), negated) times the rule's factors (out, scale:
        see _means_rule)."""
        state = self.optimizer.state[self.params["means"]]
        t = float(state["step"])
        b1, b2 = group["betas"]
        m, v = state["exp_avg"], state["exp_avg_sq"]
        move = m / (v.sqrt() / math.sqrt(1.0 - b2 ** t) + group["eps"]) * (-lr / (1.0 - b1 ** t))
        if self.config.means_lr_rule == "disparity":  # the part along the line of sight once more: uniform in 1/d
            move = move + out * ((move * out).sum(dim=1, keepdim=True) * (scale[:, None] - 1.0))
        return move * scale[:, None]

    def _means_rule(self) -> Optional[Tuple[Tensor, Tensor]]:
        """None when config.means_lr_rule leaves Adam's step as it is ("extent", or no
        scene_center), else ([N, 3] unit directions from scene_center, [N] factors f; see
        means_step_scale), from one pass over the means."""
        if self.config.means_lr_rule in ("extent", "auto") or self.scene_center is None:
            return None
        means = self.params["means"].detach()
        offset = means - self.scene_center.to(means)
        d = torch.linalg.vector_norm(offset, dim=1, keepdim=True)
        far = max(self.scene_extent, self.far_distance if self.far_distance is not None else math.inf)
        return offset / d.clamp_min(1e-30), d[:, 0].clamp(self.scene_extent, far) / self.scene_extent

    def means_step_scale(self) -> Optional[Tensor]:
        """[N] the factor config.means_lr_rule puts on each mean's Adam step, f = max(extent, d) /
        extent with d the distance from scene_center ("distance": the whole step; "disparity":
        the step across the line of sight from the centre, and f^2 along it), or None (no factor:
        the "extent" rule, or no scene_center). d is clamped to the initial model's farthest
        distance (far_distance): beyond the content it started with, no Gaussian speeds up, so a
        Gaussian pushed outward keeps a bounded step instead of one that grows with its distance."""
        rule = self._means_rule()
        return None if rule is None else rule[1]

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    # ---- persistence -----------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        """A self-contained copy: parameters, Adam state, statistics, step, SH degree, scene
        extent, config values (not the rasterize function) and the generator state."""
        return {
            "format": _STATE_FORMAT,
            "params": {k: p.detach().clone() for k, p in self.params.items()},
            "optimizer": copy.deepcopy(self.optimizer.state_dict()),
            "stats": {name: t.clone() for name, t in self.stats.items()},
            "step": self._step,
            "active_sh_degree": self.active_sh_degree,
            "scene_extent": self.scene_extent,
            "scene_center": None if self.scene_center is None else self.scene_center.clone(),
            "far_distance": self.far_distance,
            "config": self.config.saved_values(),
            "generator": self._generator.get_state(),
            "blend_stats": self.blend_stats,  # collect_blend_stats() was called: a resumed run goes on collecting
        }

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        """Restore a state_dict(), whatever the current number of Gaussians. Parameters keep
        this adapter's dtype and device; the saved config values replace the current ones except
        rasterize and rasterize_kwargs."""
        for key in ("format", "params", "optimizer", "stats", "step", "active_sh_degree",
                    "scene_extent", "config", "generator"):
            if key not in state:
                raise ValueError(f"state has no {key!r} entry; not a GS3DAdapter state_dict")
        if state["format"] != _STATE_FORMAT:
            raise ValueError(f"state format {state['format']!r} is not {_STATE_FORMAT!r}")
        unknown = set(state["config"]) - set(GS3DConfig().saved_values())
        if unknown:
            raise ValueError(f"state config has unknown fields {sorted(unknown)}")
        ref = self.params["means"]
        # an earlier release moved every mean by 3DGS's rule, reset every opacity and grew by score
        saved = {"means_lr_rule": "extent", "opacity_reset_scope": "all", "budget_growth_order": "score", **state["config"]}
        config = dataclasses.replace(self.config, **saved)
        raw = {k: state["params"][k].to(device=ref.device, dtype=ref.dtype) for k in PARAM_NAMES}
        old_config, self.config = self.config, config
        try:
            self._check_raw(raw)
        except ValueError:
            self.config = old_config
            raise
        n = raw["means"].shape[0]
        stats = {k: torch.zeros(n) for k in _LATER_STATS if k not in state["stats"]}  # an earlier release's
        stats.update(state["stats"])
        for key in STAT_NAMES:
            if key not in stats:
                self.config = old_config
                raise ValueError(f"state has no statistic {key!r}; not a GS3DAdapter state_dict")
            if tuple(stats[key].shape) != (n,):
                self.config = old_config
                raise ValueError(f"stats[{key!r}] must be [{n}], got {list(stats[key].shape)}")
        self.scene_extent = float(state["scene_extent"])
        if "scene_center" in state:  # an earlier release's state has none: the current centre stays
            self.scene_center = _check_center(state["scene_center"])
        if "far_distance" in state:
            self.far_distance = None if state["far_distance"] is None else float(state["far_distance"])
        self._step = int(state["step"])
        self._mean_reference = None
        self.sized_by_spacing = False
        self.active_sh_degree = int(state["active_sh_degree"])
        self._build(raw)
        self.optimizer.load_state_dict(state["optimizer"])
        for key in STAT_NAMES:
            self.stats[key] = stats[key].to(device=ref.device, dtype=ref.dtype).clone()
        self._generator.set_state(state["generator"])
        if state.get("blend_stats", False):  # absent before the cut of the faintest Gaussians
            self.collect_blend_stats()

    def export(self, path: str, camera: Optional[Camera] = None) -> None:
        """Write the standard 3DGS PLY (raw values; see adapters/ply.py), atomically. ``camera``
        is unused: 3DGS Gaussians do not depend on the view."""
        p = {k: v.detach() for k, v in self.params.items()}
        write_gaussian_ply(Path(path), p["means"], p["sh0"], p["shN"], p["opacities"], p["scales"],
                           p["quats"])

    def __repr__(self) -> str:
        return (f"GS3DAdapter(N={self.num_primitives()}, sh_degree={self.active_sh_degree}/"
                f"{self.config.sh_degree}, extent={self.scene_extent:.4g}, step={self._step})")


stats_in_one_dict(GS3DAdapter, STAT_NAMES)
