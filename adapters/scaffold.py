"""Scaffold-GS (Lu et al., CVPR 2024) as an MVGS adapter: anchors that decode neural Gaussians.

Model (one row per anchor a; k = n_offsets children per anchor; F = feat_dim):

    anchors   [A, 3]      voxel centres of the scene points, fixed (not trained)
    features  [A, F]      per-anchor feature
    offsets   [A, k, 3]   child offsets, in units of exp(scaling[:, :3])
    scaling   [A, 6]      log scales: [:3] scale the offsets, [3:] bound the child scales

For a camera with centre c, every anchor that passes the visibility prefilter is decoded:

    d = |a - c|, v = (a - c) / d,  x = [feature, v] (+ [d] with use_distance)
    opacity [k] = tanh(MLP_o(x))       children with opacity <= 0 are not rendered
    colour  [k, 3] = sigmoid(MLP_c(x))
    cov [k, 7] = MLP_s(x): scale = exp(scaling[3:]) * sigmoid(cov[:3]), quat = normalise(cov[3:])
    position = a + offsets * exp(scaling[:3])

and the children are rasterised with precomputed colours. Growing adds anchors in empty grid
cells where children show large screen-space gradients (3 grid levels), pruning removes anchors
whose children stay transparent; see :meth:`ScaffoldAdapter.densify`.

MVGS fit (each choice is documented where it is implemented):
- statistics are gathered per rendered view (one visit per view), and the visit thresholds of the
  original (``check_interval * success_threshold`` with check_interval = its update interval of
  100 one-view steps) are fractions of the views folded in since the last densification call, so M
  views per step do not reach them M times faster (:meth:`ScaffoldAdapter.visit_thresholds`);
- the densify context's threshold (lowered by MVAD) is the β of growing;
- cross-ray boxes add anchors: every child strictly inside a box seeds an anchor in its finest
  grid cell when that cell is empty (there is nothing to clone).

Deviations from the released code: no appearance embedding and no feature bank (both optional
there); anchors are never trained (the original's anchor learning rate is 0); voxel_size=None
takes the median kNN *distance* of the points (the original takes the median mean *squared*
distance as a length); growing visits every level (the original skips levels 1 and 2 when level 0
added nothing); the volume regulariser counts once per step (protocol), on the first chunk's views
(so next to M photometric terms it weighs 1/M of the original's one-view step). Like the original,
there is no opacity reset (reset_opacity is a no-op) and no size pruning (ctx.prune_large is
ignored); the controller's densification clock decides when growing runs (the original starts
statistics at step 500 and growing at 1500).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mvgs_plugin.camera import Camera, stack_cameras
from mvgs_plugin.checks import check_float, check_int
from mvgs_plugin.data.init import random_init_points
from mvgs_plugin.densify import boxes_contain, check_boxes
from mvgs_plugin.io import save_atomic
from mvgs_plugin.protocol import DensifyContext, DensifyReport, RenderResult
from mvgs_plugin.reference_renderer import rasterization

from .gs3d import SH_C0, keep_scores_of
from .knn import knn_mean_sq_dist, spacing_log_scale
from .ops import growth_cap, log_linear, make_adam, scale_for_views, stats_in_one_dict, swap_param
from .ply import write_gaussian_ply

LOG = logging.getLogger("mvgs_plugin")

__all__ = ["ScaffoldConfig", "ScaffoldAdapter", "ScaffoldMLPs", "voxelize", "decode_children",
           "new_cells", "ANCHOR_GROUPS", "MLP_NAMES"]

ANCHOR_GROUPS = ("features", "offsets", "scaling")  # optimizer groups with one row per anchor
MLP_NAMES = ("mlp_opacity", "mlp_color", "mlp_cov")
STAT_NAMES = ("offset_grad_accum", "offset_denom", "opacity_accum", "anchor_denom", "views_seen")
_STATE_FORMAT = "mvgs-scaffold/1"
_RUNTIME_FIELDS = ("rasterize", "rasterize_kwargs")
_NEAR = 0.01


@dataclass
class ScaffoldConfig:
    """Hyper-parameters (defaults: the released Scaffold-GS's, but for voxel_size; docs/scaffold.md
    lists where this adapter differs).

    Model: voxel_size (None = the median over the scene's own points, PointCloud.own, of their
        RMS distance to their 3 nearest neighbours),
        feat_dim (32), n_offsets k (10), use_distance (feed |a - c| to the three MLPs; off in the
        original's defaults), offset_init_std (0 = the original's zero offsets; > 0 draws
        N(0, std^2) offsets, which lets a fresh model grow, e.g. in conformance tests), prefilter
        (decode only anchors passing the frustum test), seed (MLP init, growing draws),
        random_init (points drawn for a scene without a point cloud, where the cameras look as
        mvgs_plugin.data.init.random_init_points places them, before voxelisation; the
        graphdeco-based Scaffold-GS starts such scenes from random points too).
    Learning rates (Adam, eps adam_eps; "init -> final" decay log-linearly over lr_max_steps):
        offsets 0.01 -> 1e-4 times the scene extent, features 0.0075, scaling 0.007, MLPs opacity
        0.002 -> 2e-5, colour 0.008 -> 5e-5, covariance 0.004 -> 0.004.
    Growing / pruning: growth_levels (3), update_init_factor (16) and update_hierarchy_factor (4):
        level i uses cells of voxel_size * (update_init_factor // update_hierarchy_factor^i) and
        threshold β * (update_hierarchy_factor // 2)^i; a candidate child survives the random draw
        with probability 1 - 0.5^(i+1) (the original keeps rand > 0.5^(i+1)); success_threshold
        (0.8) sets the visit thresholds; min_opacity (0.005) the pruning; max_anchors caps growth.
    scale_reg_weight: weight of the mean volume (product of the 3 scales) of the decoded
        children (0.01).
    """

    voxel_size: Optional[float] = None
    feat_dim: int = 32
    n_offsets: int = 10
    use_distance: bool = False
    offset_init_std: float = 0.0
    prefilter: bool = True
    seed: int = 0
    random_init: int = 10_000
    lr_offsets_init: float = 0.01
    lr_offsets_final: float = 1e-4
    lr_features: float = 0.0075
    lr_scaling: float = 0.007
    lr_mlp_opacity_init: float = 0.002
    lr_mlp_opacity_final: float = 2e-5
    lr_mlp_color_init: float = 0.008
    lr_mlp_color_final: float = 5e-5
    lr_mlp_cov_init: float = 0.004
    lr_mlp_cov_final: float = 0.004
    lr_max_steps: int = 30_000
    adam_eps: float = 1e-15
    growth_levels: int = 3
    update_init_factor: int = 16
    update_hierarchy_factor: int = 4
    success_threshold: float = 0.8
    min_opacity: float = 0.005
    max_anchors: Optional[int] = None
    scale_reg_weight: float = 0.01
    rasterize: Callable[..., Any] = rasterization
    rasterize_kwargs: Dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.voxel_size is not None:
            check_float("voxel_size", self.voxel_size, positive=True)
        for name in ("feat_dim", "n_offsets", "lr_max_steps", "growth_levels", "update_hierarchy_factor", "random_init"):
            check_int(name, getattr(self, name), 1)
        check_int("seed", self.seed, 0)
        check_int("update_init_factor", self.update_init_factor,
                   self.update_hierarchy_factor ** (self.growth_levels - 1))  # coarsest..finest >= 1 voxel
        if self.max_anchors is not None:
            check_int("max_anchors", self.max_anchors, 0)
        for name in ("lr_offsets_init", "lr_offsets_final", "lr_mlp_opacity_init", "lr_mlp_opacity_final",
                     "lr_mlp_color_init", "lr_mlp_color_final", "lr_mlp_cov_init", "lr_mlp_cov_final",
                     "adam_eps"):
            check_float(name, getattr(self, name), positive=True)
        for name in ("offset_init_std", "lr_features", "lr_scaling", "min_opacity", "scale_reg_weight"):
            check_float(name, getattr(self, name))
        s = check_float("success_threshold", self.success_threshold, positive=True)
        if s > 1:
            raise ValueError(f"success_threshold must be in (0, 1], got {s}")
        if not callable(self.rasterize):
            raise ValueError(f"rasterize must be callable, got {self.rasterize!r}")
        if not isinstance(self.rasterize_kwargs, dict):
            raise ValueError(f"rasterize_kwargs must be a dict, got {self.rasterize_kwargs!r}")

    def saved_values(self) -> Dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in _RUNTIME_FIELDS}

    @classmethod
    def for_run(cls, run, **fields) -> "ScaffoldConfig":
        """The config whose learning-rate decays follow the run's clock (run.clock_length of an
        MVGSConfig) instead of the original's 30k steps, as examples/train_scaffold.py builds it.
        fields: any other ScaffoldConfig field."""
        return cls(lr_max_steps=int(run.clock_length), **fields)

    def cell_size(self, voxel_size: float, level: int) -> float:
        """Grid cell edge of growing level ``level`` (0 = coarsest)."""
        return voxel_size * (self.update_init_factor // self.update_hierarchy_factor ** level)

    def level_threshold(self, beta: float, level: int) -> float:
        return beta * (self.update_hierarchy_factor // 2) ** level


class ScaffoldMLPs(torch.nn.Module):
    """The three decoders: in = feat_dim + 3 (+ 1 with distance); k = n_offsets.
    opacity: Lin(in, F) ReLU Lin(F, k) Tanh; colour: ... Lin(F, 3k) Sigmoid; cov: ... Lin(F, 7k)."""

    def __init__(self, feat_dim: int, n_offsets: int, use_distance: bool):
        super().__init__()
        d_in, F, k = feat_dim + 3 + int(use_distance), feat_dim, n_offsets
        lin = torch.nn.Linear
        self.mlp_opacity = torch.nn.Sequential(lin(d_in, F), torch.nn.ReLU(), lin(F, k), torch.nn.Tanh())
        self.mlp_color = torch.nn.Sequential(lin(d_in, F), torch.nn.ReLU(), lin(F, 3 * k), torch.nn.Sigmoid())
        self.mlp_cov = torch.nn.Sequential(lin(d_in, F), torch.nn.ReLU(), lin(F, 7 * k))


def voxelize(points: Tensor, voxel_size: float) -> Tensor:
    """[A, 3] unique voxel centres round(p / v) * v of points [P, 3] (sorted lexicographically)."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [P,3], got {list(points.shape)}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError("points has non-finite values")
    cells = torch.unique(torch.round(points.double() / voxel_size).long(), dim=0)
    return cells.double() * voxel_size


def decode_children(anchors: Tensor, features: Tensor, offsets: Tensor, scaling: Tensor,
                    mlps: ScaffoldMLPs, center: Tensor, use_distance: bool) -> Dict[str, Tensor]:
    """Neural Gaussians of anchors [n, 3] for a camera centre [3], vectorised.

    Returns means [n*k, 3], opacities [n*k] (tanh, may be <= 0), colors [n*k, 3], scales [n*k, 3],
    quats [n*k, 4] (normalised); child j of anchor i is row i*k + j.
    """
    n, k = offsets.shape[0], offsets.shape[1]
    rel = anchors - center.to(anchors)
    dist = rel.norm(dim=1, keepdim=True)
    view = rel / dist.clamp_min(1e-12)
    x = torch.cat([features, view] + ([dist] if use_distance else []), dim=1)
    s = torch.exp(scaling)
    cov = mlps.mlp_cov(x).reshape(n * k, 7)
    s_rep = s.repeat_interleave(k, dim=0)  # [n*k, 6]
    return {
        "means": (anchors[:, None, :] + offsets * s[:, None, :3]).reshape(n * k, 3),
        "opacities": mlps.mlp_opacity(x).reshape(n * k),
        "colors": mlps.mlp_color(x).reshape(n * k, 3),
        "scales": s_rep[:, 3:] * torch.sigmoid(cov[:, :3]),
        "quats": torch.nn.functional.normalize(cov[:, 3:], dim=1),
    }


def new_cells(points: Tensor, occupied: Tensor, cell: float) -> Tuple[Tensor, Tensor]:
    """Grid cells (edge ``cell``, centres at integer multiples) that hold some of points [P, 3]
    but none of occupied [A, 3]. Returns cell coordinates [Q, 3] long and, for every point, the
    index of its cell in that list or -1 when its cell is occupied."""
    pc = torch.round(points.double() / cell).long()
    uniq, inv = torch.unique(pc, dim=0, return_inverse=True)
    oc = torch.round(occupied.double() / cell).long()
    both = torch.cat([oc, uniq])
    _, inv_all = torch.unique(both, dim=0, return_inverse=True)
    taken = torch.zeros(int(inv_all.max()) + 1 if len(inv_all) else 0, dtype=torch.bool, device=points.device)
    taken[inv_all[:len(oc)]] = True
    free = ~taken[inv_all[len(oc):]]
    remap = torch.full((len(uniq),), -1, dtype=torch.long, device=points.device)
    remap[free] = torch.arange(int(free.sum()), device=points.device)
    return uniq[free], remap[inv]


class ScaffoldAdapter:
    """Scaffold-GS anchors + MLPs + Adam + anchor growing/pruning, driven by the MVGS controller.

    Construct with :meth:`from_scene` or from tensors (anchors [A,3], features [A,F], offsets
    [A,k,3], scaling [A,6] log). Primitives are anchors: positions() and num_primitives() count
    anchors; each view decodes its own set of neural Gaussians (:meth:`decode`).
    """

    # Adam-state surgery shared with the 3DGS adapter: one parameter per anchor group, rows
    # remapped (kept rows carry their moments, new rows start at zero); MLP groups untouched.

    def __init__(self, anchors: Tensor, features: Tensor, offsets: Tensor, scaling: Tensor,
                 scene_extent: float, voxel_size: float, config: Optional[ScaffoldConfig] = None) -> None:
        self.config = ScaffoldConfig() if config is None else config
        if not isinstance(self.config, ScaffoldConfig):
            raise ValueError(f"config must be a ScaffoldConfig, got {type(self.config).__name__}")
        self.scene_extent = check_float("scene_extent", scene_extent, positive=True)
        self.voxel_size = check_float("voxel_size", voxel_size, positive=True)
        self._generator = torch.Generator().manual_seed(self.config.seed)
        self._step = 0
        # True while every anchor's scaling is from_scene's spacing rule (no optimizer step yet): a
        # cut then re-sizes the kept anchors by the spacing of the kept ones (see densify)
        self.sized_by_spacing = False
        self._views = 1  # views per step the optimizer is scaled for (set_views_per_step)
        self._reg_cameras: List[Camera] = []
        with torch.random.fork_rng():
            torch.manual_seed(self.config.seed)
            self.mlps = ScaffoldMLPs(self.config.feat_dim, self.config.n_offsets, self.config.use_distance)
        if isinstance(features, Tensor) and features.is_floating_point():
            # the MLPs compute in the dtype, and on the device, of the anchor rows
            self.mlps.to(device=features.device, dtype=features.dtype)
        self._build(anchors, {"features": features, "offsets": offsets, "scaling": scaling})

    # ---- construction ----------------------------------------------------------------------
    def _check_rows(self, anchors: Tensor, rows: Dict[str, Tensor]) -> None:
        if not isinstance(anchors, Tensor) or anchors.ndim != 2 or anchors.shape[1] != 3:
            raise ValueError(f"anchors must be a [A,3] tensor, got {getattr(anchors, 'shape', anchors)!r}")
        a, c = anchors.shape[0], self.config
        shapes = {"features": (a, c.feat_dim), "offsets": (a, c.n_offsets, 3), "scaling": (a, 6)}
        for name, shape in shapes.items():
            t = rows[name]
            if not isinstance(t, Tensor) or tuple(t.shape) != shape:
                got = list(t.shape) if isinstance(t, Tensor) else repr(t)
                raise ValueError(f"{name} must be {list(shape)} (A={a} from anchors, feat_dim, n_offsets), got {got}")
        for name, t in [("anchors", anchors)] + list(rows.items()):
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} has non-finite values")

    def _build(self, anchors: Tensor, rows: Dict[str, Tensor]) -> None:
        """(Re)create the anchor parameters, a fresh optimizer and zero statistics."""
        self._check_rows(anchors, rows)
        ref = next(self.mlps.parameters())  # the anchors live where, and as, the MLPs compute
        self.anchors = anchors.detach().to(ref).clone().contiguous()
        self.params: Dict[str, torch.nn.Parameter] = {
            n: torch.nn.Parameter(rows[n].detach().to(ref).clone().contiguous()) for n in ANCHOR_GROUPS}
        lrs = self._lrs(self._step)
        groups = [{"params": [self.params[n]], "lr": lrs[n], "name": n} for n in ANCHOR_GROUPS]
        groups += [{"params": list(getattr(self.mlps, n).parameters()), "lr": lrs[n], "name": n} for n in MLP_NAMES]
        self.optimizer = make_adam(groups, self.config.adam_eps)
        self._reset_all_stats()

    def _reset_all_stats(self) -> None:
        a, k, ref = self.num_primitives(), self.config.n_offsets, self.anchors
        shapes = {"offset_grad_accum": (a, k), "offset_denom": (a, k), "opacity_accum": (a,), "anchor_denom": (a,),
                  "views_seen": ()}
        self.stats: Dict[str, Tensor] = {name: torch.zeros(shapes[name], dtype=ref.dtype, device=ref.device)
                                         for name in STAT_NAMES}

    @classmethod
    def from_scene(cls, scene, config: Optional[ScaffoldConfig] = None, dtype: torch.dtype = torch.float32,
                   device: Optional[torch.device | str] = None) -> "ScaffoldAdapter":
        """Anchors = unique voxel centres of scene.points (without points: of config.random_init
        points where the cameras look, drawn with config.seed); features 0; offsets 0 (or
        N(0, offset_init_std^2)); scaling log(sqrt(mean squared distance to the 3 nearest other
        anchors)) repeated 6 times (floored at 1e-7 before the root, as 3DGS). device: where the
        anchors and MLPs live (default: the CPU); made on the CPU, then moved, so a seed gives
        the same model on any device."""
        config = ScaffoldConfig() if config is None else config
        points = getattr(scene, "points", None)
        if points is None or len(points) == 0:
            gen = torch.Generator().manual_seed(config.seed + 1)
            xyz, _, description = random_init_points(scene, config.random_init, gen)
            LOG.info("Scaffold-GS anchors from %s", description)
        else:
            xyz = points.xyz.to(torch.float64)
        voxel = config.voxel_size
        if voxel is None:
            # the scene's own points' spacing: the far background shell (load_scene's
            # background_points) is sparse and, on a scene with few points, most of the points
            own = xyz if points is None or len(points) - points.shell < 4 else points.own.to(torch.float64)
            voxel = float(knn_mean_sq_dist(own, k=3).sqrt().median()) if len(own) > 1 else 0.0
            if not voxel > 0:
                raise ValueError(f"voxel_size=None needs points at distinct positions to take the voxel from their "
                                 f"spacing (median distance to the nearest points is 0, {len(own)} points); give "
                                 f"ScaffoldConfig.voxel_size (--voxel-size)")
        anchors = voxelize(xyz, voxel)
        a, k = anchors.shape[0], config.n_offsets
        scaling = spacing_log_scale(anchors)[:, None].repeat(1, 6)
        gen = torch.Generator().manual_seed(config.seed)
        offsets = torch.randn(a, k, 3, generator=gen, dtype=torch.float64) * config.offset_init_std
        features = torch.zeros(a, config.feat_dim, dtype=torch.float64)
        t = lambda x: x.to(device=device, dtype=dtype)  # noqa: E731
        model = cls(t(anchors), t(features), t(offsets), t(scaling), scene.extent, voxel, config)
        model.sized_by_spacing = True
        return model

    # ---- views of the model --------------------------------------------------------------
    def positions(self) -> Tensor:
        """[A, 3] anchor positions."""
        return self.anchors

    def num_primitives(self) -> int:
        return int(self.anchors.shape[0])

    def visible_anchors(self, camera: Camera) -> Tensor:
        """[A] bool: the frustum prefilter. An anchor passes when the ball around it that holds
        its children's 3-sigma ellipsoids (radius: largest child offset + 3 * its largest child
        scale bound) meets the view's pyramid, the image widened by 15% on each side, past the
        near plane: its signed distance to each of the pyramid's four side planes (through the
        camera centre) is at least minus the radius. Exact for the ball, so no child it drops
        reaches the widened image; a ball's projection is not the disc f * radius / depth off the
        axis (it stretches there), which an earlier test assumed and so dropped visible anchors
        just outside the image."""
        if not self.config.prefilter:
            return torch.ones(self.num_primitives(), dtype=torch.bool, device=self.anchors.device)
        with torch.no_grad():
            s = torch.exp(self.params["scaling"].detach())
            reach = (self.params["offsets"].detach() * s[:, None, :3]).norm(dim=-1).amax(dim=1) \
                + 3 * s[:, 3:].amax(dim=1)
            w2c = camera.world_to_camera.to(self.anchors)
            p = self.anchors @ w2c[:3, :3].T + w2c[:3, 3]
            x, y, z = p.unbind(-1)
            W, H = camera.width, camera.height
            keep = z + reach > _NEAR
            # the widened image's edges as slopes x/z, y/z; a side plane's inward signed distance
            for q, c, f, size in ((x, camera.cx, camera.fx, W), (y, camera.cy, camera.fy, H)):
                a0, a1 = (-0.15 * size - float(c)) / float(f), (1.15 * size - float(c)) / float(f)
                keep &= (q - a0 * z) / math.sqrt(1.0 + a0 * a0) >= -reach
                keep &= (a1 * z - q) / math.sqrt(1.0 + a1 * a1) >= -reach
            return keep

    def decode(self, camera: Camera, anchor_mask: Optional[Tensor] = None) -> Tuple[Tensor, Dict[str, Tensor]]:
        """Decode the children of the anchors in anchor_mask [A] (default: the prefilter) for
        ``camera``. Returns the anchor indices [n] and decode_children()'s dict."""
        mask = self.visible_anchors(camera) if anchor_mask is None else anchor_mask
        idx = mask.nonzero().squeeze(1)
        p = self.params
        children = decode_children(self.anchors[idx], p["features"][idx], p["offsets"][idx], p["scaling"][idx],
                                   self.mlps, camera.center, self.config.use_distance)
        return idx, children

    # ---- schedule ------------------------------------------------------------------------
    def _lrs(self, step: int) -> Dict[str, float]:
        c, L = self.config, self.config.lr_max_steps
        return {
            "offsets": log_linear(step, 0, L, c.lr_offsets_init * self.scene_extent,
                                   c.lr_offsets_final * self.scene_extent),
            "features": c.lr_features, "scaling": c.lr_scaling,
            "mlp_opacity": log_linear(step, 0, L, c.lr_mlp_opacity_init, c.lr_mlp_opacity_final),
            "mlp_color": log_linear(step, 0, L, c.lr_mlp_color_init, c.lr_mlp_color_final),
            "mlp_cov": log_linear(step, 0, L, c.lr_mlp_cov_init, c.lr_mlp_cov_final),
        }

    def clock_mismatch(self, clock: int) -> Optional[Tuple[str, int, str]]:
        """ClockedAdapter: the learning-rate decays span config.lr_max_steps."""
        steps = self.config.lr_max_steps
        return None if steps == clock else ("lr_max_steps: its learning rates will not decay as planned", steps,
                                            "ScaffoldConfig.for_run(config)")

    def set_step(self, step: int) -> None:
        """Learning rates for ``step`` (pure functions of it)."""
        self._step = check_int("step", step, 0)
        scale_for_views(self.optimizer, self._lrs(step), self._views, self.config.adam_eps)

    def set_views_per_step(self, views: int) -> None:
        """Scale the optimizer for steps of `views` views from the next set_step on (Grendel-GS's
        rule, see adapters.ops.scale_for_views)."""
        self._views = check_int("views", views, 1)

    def learning_rates(self) -> Dict[str, float]:
        return {g["name"]: g["lr"] for g in self.optimizer.param_groups}

    # ---- rendering, regulariser, statistics ------------------------------------------------
    def render(self, cameras: Sequence[Camera], backgrounds: Tensor) -> RenderResult:
        """Render C cameras of one size; each decodes its own neural Gaussians (one rasterizer
        call per view). aux: one record per view (anchor indices, kept-child mask, decoded
        opacities, the rasterizer's meta with means2d retaining its gradient)."""
        cams = list(cameras)
        if not cams:
            raise ValueError("render needs at least one camera, got 0")
        sizes = sorted({(c.width, c.height) for c in cams})
        if len(sizes) != 1:
            raise ValueError(f"all cameras of a chunk must have one size, got (width, height) {sizes}")
        width, height = sizes[0]
        ref = self.anchors
        bg = torch.as_tensor(backgrounds).to(device=ref.device, dtype=ref.dtype)
        if tuple(bg.shape) != (len(cams), 3):
            raise ValueError(f"backgrounds must be [C,3] with C={len(cams)}, got {list(bg.shape)}")
        images, alphas, records = [], [], []
        for i, cam in enumerate(cams):
            idx, ch = self.decode(cam)
            keep = ch["opacities"].detach() > 0
            viewmats, Ks = stack_cameras([cam], dtype=ref.dtype, device=ref.device)
            img, alpha, meta = self.config.rasterize(
                ch["means"][keep], ch["quats"][keep], ch["scales"][keep], ch["opacities"][keep], ch["colors"][keep],
                viewmats, Ks, width, height, sh_degree=None, packed=False, backgrounds=bg[i:i + 1],
                **self.config.rasterize_kwargs)
            if meta["means2d"].requires_grad:
                meta["means2d"].retain_grad()
            images.append(img)
            alphas.append(alpha)
            records.append({"anchors": idx, "keep": keep, "opacities": ch["opacities"].detach(), "meta": meta,
                            "num_anchors": self.num_primitives()})
        if torch.is_grad_enabled():
            self._reg_cameras = cams
        return RenderResult(images=torch.cat(images), alphas=torch.cat(alphas), aux=records)

    def regularization(self, step: int) -> Optional[Tensor]:
        """scale_reg_weight * mean volume (product of the 3 scales) of the rendered children of the
        last rendered chunk (the controller calls this once per step, after the first chunk).
        The children are decoded again, so the term has its own graph. None before any render."""
        cams, self._reg_cameras = self._reg_cameras, []
        if not cams or self.config.scale_reg_weight == 0:
            return None
        vols = []
        for cam in cams:
            _, ch = self.decode(cam)
            keep = ch["opacities"].detach() > 0
            vols.append(ch["scales"][keep].prod(dim=1))
        vol = torch.cat(vols)
        if vol.numel() == 0:
            return None
        return self.config.scale_reg_weight * vol.mean()

    def accumulate_stats(self, result: RenderResult) -> None:
        """Per rendered view (one visit each), after its backward:
        - every rendered child (opacity > 0, radius > 0): offset_grad_accum += |d loss / d means2d|
          in NDC units (pixel gradient times W/2, H/2, as the original CUDA code), offset_denom += 1;
        - every anchor that passed the prefilter: opacity_accum += sum of its children's opacities
          clamped at 0, anchor_denom += 1;
        - views_seen += 1 (the visit thresholds are fractions of it)."""
        records = result.aux
        if not isinstance(records, list) or not all(isinstance(r, dict) and "meta" in r for r in records):
            raise ValueError("accumulate_stats needs the RenderResult returned by this adapter's render()")
        k = self.config.n_offsets
        for rec in records:
            if rec["num_anchors"] != self.num_primitives():
                raise ValueError(f"the render had {rec['num_anchors']} anchors but the model now has "
                                 f"{self.num_primitives()} (densified in between?)")
            meta, idx, keep = rec["meta"], rec["anchors"], rec["keep"]
            grad = meta["means2d"].grad
            if grad is None and int(keep.sum()) > 0:
                raise RuntimeError("means2d has no gradient: call backward on a loss of this render "
                                   "before accumulate_stats")
            child_ids = (idx[:, None] * k + torch.arange(k, device=idx.device)).reshape(-1)[keep]
            if child_ids.numel():
                radii = meta["radii"][0]  # [N, 2] (gsplat >= 1.5, ours) or [N] (older gsplat)
                visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
                ndc = grad[0].detach() * grad.new_tensor([meta["width"] / 2.0, meta["height"] / 2.0])
                norms = ndc.norm(dim=-1).to(self.offset_grad_accum.dtype)
                ids = child_ids[visible]
                self.offset_grad_accum.view(-1).index_add_(0, ids, norms[visible])
                self.offset_denom.view(-1).index_add_(0, ids, torch.ones_like(norms[visible]))
            op = rec["opacities"].clamp_min(0).reshape(-1, k).sum(dim=1).to(self.opacity_accum.dtype)
            self.opacity_accum.index_add_(0, idx, op)
            self.anchor_denom.index_add_(0, idx, torch.ones_like(op))
            self.views_seen += 1

    # ---- distributed training (mvgs_plugin.protocol.DistributedAdapter) -------------------
    def statistics(self) -> Dict[str, Tuple[Tensor, str]]:
        """All five statistics add up over disjoint sets of views."""
        return {name: (self.stats[name], "sum") for name in STAT_NAMES}

    def load_statistics(self, stats: Dict[str, Tensor]) -> None:
        if set(stats) != set(STAT_NAMES):
            raise ValueError(f"statistics must be exactly {list(STAT_NAMES)}, got {sorted(stats)}")
        for name in STAT_NAMES:
            want = tuple(self.stats[name].shape)
            if tuple(torch.as_tensor(stats[name]).shape) != want:
                got = list(torch.as_tensor(stats[name]).shape)
                raise ValueError(f"statistics[{name!r}] must be {list(want)}, got {got}")
        for name in STAT_NAMES:
            self.stats[name] = torch.as_tensor(stats[name]).to(self.anchors).clone()

    def gradient_parameters(self) -> Dict[str, Tensor]:
        out: Dict[str, Tensor] = dict(self.params)
        for name in MLP_NAMES:
            for pname, p in getattr(self.mlps, name).named_parameters():
                out[f"{name}.{pname}"] = p
        return out

    def named_gradients(self) -> Dict[str, Optional[Tensor]]:
        return {name: p.grad for name, p in self.gradient_parameters().items()}

    def optimizer_step(self) -> None:
        self.sized_by_spacing = False
        self.optimizer.step()

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def reset_opacity(self) -> None:
        """No-op: Scaffold-GS decodes opacities from features and has no opacity reset."""

    # ---- growing and pruning ---------------------------------------------------------------
    def visit_thresholds(self) -> Tuple[float, float]:
        """(child, anchor) visit counts above which growing and pruning judge a row: the
        original's check_interval * success_threshold * 0.5 and check_interval * success_threshold
        with check_interval = the views folded in since the last densification call (the
        original's 100 = its update interval of one-view steps)."""
        views = float(self.views_seen)
        return self.config.success_threshold * 0.5 * views, self.config.success_threshold * views

    def mean_grads(self) -> Tensor:
        """[A, k] mean NDC gradient per visit of every child (0 where never visited)."""
        return torch.where(self.offset_denom > 0, self.offset_grad_accum / self.offset_denom.clamp_min(1),
                           torch.zeros_like(self.offset_grad_accum))

    def child_positions(self) -> Tensor:
        """[A, k, 3] child positions (view-independent: anchor + offsets * exp(scaling[:3]))."""
        s = torch.exp(self.params["scaling"].detach()[:, None, :3])
        return self.anchors[:, None, :] + self.params["offsets"].detach() * s

    def densify(self, ctx: DensifyContext) -> DensifyReport:
        """Grow (boxes, then 3 grid levels) and prune anchors, then reset the judged statistics.

        With g [A, k] the mean child gradients, β = ctx.grad_threshold, (t_c, t_a) =
        visit_thresholds(), children judged = offset_denom > t_c:
          0. boxes (CRD): every child strictly inside a ctx.boxes box seeds its finest cell
             (edge voxel_size) when no anchor holds it; with ctx.max_new_from_boxes, the cells whose
             best child has the largest g;
          i = 0..growth_levels-1 (coarse to fine, cell edge config.cell_size): judged children with
             g >= β * 2^i that survive a draw with probability 1 - 0.5^(i+1) seed their cell at
             that level when no anchor (old or added earlier in this call) holds it;
          a new anchor sits at the cell centre, with feature = the element-wise max of its seeds'
          anchors' features, zero offsets, scaling log(cell edge) x 6; the cap (the lower of
          config.max_anchors and ctx.max_primitives) bounds the count after the call (later
          candidates dropped);
          prune: old anchors with anchor_denom > t_a and opacity_accum < min_opacity *
          anchor_denom; when the survivors alone exceed the cap, the ones with the lowest
          keep_scores(ctx.scene_center) go too (nothing grows then; before the first optimizer
          step, sized_by_spacing, the kept anchors' scaling is re-set to their spacing,
          knn.spacing_log_scale, as from_scene sets it).
        Statistics: judged children and judged anchors restart from 0; new rows start at 0;
        views_seen restarts. Adam moments follow their rows (new rows 0); the MLPs' state is left
        alone. The anchor rows are new tensors without gradients (as in 3DGS densification).
        """
        try:
            beta = float(ctx.grad_threshold)
        except (TypeError, ValueError):
            beta = math.nan
        if isinstance(ctx.grad_threshold, bool) or not beta >= 0:
            raise ValueError(f"ctx.grad_threshold must be a number >= 0 (inf allowed), got {ctx.grad_threshold!r}")
        a0, k = self.num_primitives(), self.config.n_offsets
        g = self.mean_grads().reshape(-1)
        t_child, t_anchor = self.visit_thresholds()
        judged = self.offset_denom.reshape(-1) > t_child
        xyz = self.child_positions().reshape(-1, 3)
        feats = self.params["features"].detach().repeat_interleave(k, dim=0)  # [A*k, F]
        cap = growth_cap(self.config.max_anchors, ctx.max_primitives)
        prune = (self.anchor_denom > t_anchor) & (self.opacity_accum < self.config.min_opacity * self.anchor_denom)
        shed = torch.zeros_like(prune)
        if cap is not None and a0 - int(prune.sum()) > cap:  # shrink to the cap: the lowest keep scores go
            score = torch.where(prune, torch.full_like(self.opacity_accum, math.inf), self.keep_scores(ctx.scene_center))
            shed[torch.sort(score, stable=True).indices[:a0 - int(prune.sum()) - cap]] = True
            prune = prune | shed
        budget = math.inf if cap is None else max(0, cap - (a0 - int(prune.sum())))
        added: List[Tuple[Tensor, Tensor, float]] = []  # (centres [Q,3], features [Q,F], cell edge)
        occupied = self.anchors
        box_new = 0
        if ctx.boxes is not None:
            sel = boxes_contain(xyz, check_boxes(ctx.boxes))
            box_cap = ctx.max_new_from_boxes
            box_cap = None if box_cap is None else check_int("max_new_from_boxes", box_cap, 0)
            cells, f = self._seed(xyz, feats, g, sel, occupied, self.voxel_size, box_cap, budget)
            box_new, budget = len(cells), budget - len(cells)
            added.append((cells, f, self.voxel_size))
            occupied = torch.cat([occupied, cells])
        per_level = []
        for i in range(self.config.growth_levels):
            cand = judged & (g >= self.config.level_threshold(beta, i))
            draw = torch.rand(cand.shape, generator=self._generator, dtype=torch.float64).to(cand.device)
            cand &= draw > 0.5 ** (i + 1)
            size = self.config.cell_size(self.voxel_size, i)
            cells, f = self._seed(xyz, feats, g, cand, occupied, size, None, budget)
            per_level.append(len(cells))
            budget -= len(cells)
            added.append((cells, f, size))
            occupied = torch.cat([occupied, cells])
        anchor_judged = self.anchor_denom > t_anchor
        self._apply(added, prune, judged.reshape(a0, k), anchor_judged)
        if self.sized_by_spacing and bool(shed.any()):  # a cut before training: sized as if voxelised from the kept
            scaling = spacing_log_scale(self.anchors)[:, None].repeat(1, 6)
            self.params["scaling"] = swap_param(self.optimizer, "scaling", scaling.to(self.params["scaling"]), None,
                                                zero_moments=False)
        n_new = sum(len(c) for c, _, _ in added)
        return DensifyReport(before=a0, after=self.num_primitives(), pruned=int(prune.sum()), from_boxes=box_new,
                             extra={"grad_threshold": beta, "grown": n_new - box_new, "grown_per_level": per_level,
                                    "visit_thresholds": (t_child, t_anchor), "shed_to_cap": int(shed.sum()),
                                    "cap": cap})

    def keep_scores(self, center: Optional[Tensor] = None) -> Tensor:
        """[A] the order in which anchors are kept when the model must shrink to a cap (largest
        kept): the opacity their children showed summed over the views since the last
        densification (opacity_accum), so an anchor that shows in many views outranks one seen in
        a single view. Before any view was folded in, gs3d.even_cut_order of the anchors with
        `center` (the scene's; densify passes DensifyContext.scene_center): the anchors inside and
        beyond the far line each keep their share, spread over their extent."""
        return keep_scores_of(torch.ones_like(self.opacity_accum), self.opacity_accum, self.anchors, center)

    def _seed(self, xyz: Tensor, feats: Tensor, g: Tensor, sel: Tensor, occupied: Tensor, size: float,
              cap: Optional[int], budget: float) -> Tuple[Tensor, Tensor]:
        """New anchors in the free cells (edge ``size``) of the selected children: centres [Q, 3]
        and features [Q, F] (max over the seeds' features). With cap / budget, the cells whose best
        seed has the largest g are kept."""
        F = feats.shape[1]
        idx = sel.nonzero().squeeze(1)
        empty = (self.anchors.new_zeros(0, 3), feats.new_zeros(0, F))
        if idx.numel() == 0:
            return empty
        cells, which = new_cells(xyz[idx], occupied, size)
        ok = which >= 0
        idx, which = idx[ok], which[ok]
        q = cells.shape[0]
        if q == 0:
            return empty
        index = which[:, None].expand(-1, F)
        f = feats.new_zeros(q, F).scatter_reduce(0, index, feats[idx], reduce="amax", include_self=False)
        limit = min(q, budget if cap is None else min(cap, budget))
        if limit < q:
            best = g.new_full((q,), -math.inf).scatter_reduce(0, which, g[idx], reduce="amax", include_self=True)
            order = torch.sort(best, descending=True, stable=True).indices[:int(limit)]
            cells, f = cells[order], f[order]
        return cells.to(self.anchors.dtype) * size, f

    def _apply(self, added, prune: Tensor, judged_children: Tensor, judged_anchors: Tensor) -> None:
        """Append the new anchors, drop the pruned ones, carry Adam state and statistics."""
        keep = ~prune
        dev, dtype = self.anchors.device, self.anchors.dtype
        centres = torch.cat([c for c, _, _ in added]) if added else self.anchors.new_zeros(0, 3)
        n_new, k = centres.shape[0], self.config.n_offsets
        new_rows = {
            "features": torch.cat([f for _, f, _ in added]) if added
            else self.params["features"].new_zeros(0, self.config.feat_dim),
            "offsets": self.params["offsets"].new_zeros(n_new, k, 3),
            "scaling": torch.cat([torch.full((len(c), 6), math.log(s), dtype=dtype, device=dev) for c, _, s in added])
            if added else self.params["scaling"].new_zeros(0, 6),
        }
        src = torch.cat([torch.arange(self.num_primitives(), device=dev)[keep],
                         torch.full((n_new,), -1, dtype=torch.long, device=dev)])
        for name in ANCHOR_GROUPS:
            value = torch.cat([self.params[name].detach()[keep], new_rows[name].to(dtype)])
            self.params[name] = swap_param(self.optimizer, name, value, src, zero_moments=False)
        self.anchors = torch.cat([self.anchors[keep], centres.to(dtype)]).contiguous()
        zc = lambda t, m: torch.where(m, torch.zeros_like(t), t)  # noqa: E731
        pad = lambda t: torch.cat([t[keep], t.new_zeros((n_new,) + t.shape[1:])])  # noqa: E731
        self.offset_grad_accum = pad(zc(self.offset_grad_accum, judged_children))
        self.offset_denom = pad(zc(self.offset_denom, judged_children))
        self.opacity_accum = pad(zc(self.opacity_accum, judged_anchors))
        self.anchor_denom = pad(zc(self.anchor_denom, judged_anchors))
        self.views_seen = torch.zeros_like(self.views_seen)

    # ---- persistence -----------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        """Anchors, anchor parameters, MLPs, Adam state, statistics, step, voxel size, scene
        extent, config values and generator state (the native anchor checkpoint)."""
        return {
            "format": _STATE_FORMAT,
            "anchors": self.anchors.clone(),
            "params": {k: p.detach().clone() for k, p in self.params.items()},
            "mlps": copy.deepcopy(self.mlps.state_dict()),
            "optimizer": copy.deepcopy(self.optimizer.state_dict()),
            "stats": {name: self.stats[name].clone() for name in STAT_NAMES},
            "step": self._step, "voxel_size": self.voxel_size, "scene_extent": self.scene_extent,
            "config": self.config.saved_values(),
            "generator": self._generator.get_state(),
        }

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        """Restore a state_dict() whatever the current anchor count; the saved config replaces
        this one's (except the rasterize function and its options)."""
        for key in ("format", "anchors", "params", "mlps", "optimizer", "stats", "step", "voxel_size",
                    "scene_extent", "config", "generator"):
            if key not in state:
                raise ValueError(f"state has no {key!r} entry; not a ScaffoldAdapter state_dict")
        if state["format"] != _STATE_FORMAT:
            raise ValueError(f"state format {state['format']!r} is not {_STATE_FORMAT!r}")
        unknown = set(state["config"]) - set(ScaffoldConfig().saved_values())
        if unknown:
            raise ValueError(f"state config has unknown fields {sorted(unknown)}")
        config = dataclasses.replace(self.config, **state["config"])
        a = state["anchors"].shape[0]
        for name in STAT_NAMES:
            want = (a, config.n_offsets) if name.startswith("offset") else (a,) if name != "views_seen" else ()
            if tuple(state["stats"][name].shape) != want:
                raise ValueError(f"stats[{name!r}] must be {list(want)}, got {list(state['stats'][name].shape)}")
        self.config = config
        self.voxel_size, self.scene_extent = float(state["voxel_size"]), float(state["scene_extent"])
        self._step = int(state["step"])
        self.sized_by_spacing = False
        ref = next(self.mlps.parameters())
        self.mlps = ScaffoldMLPs(config.feat_dim, config.n_offsets, config.use_distance).to(device=ref.device,
                                                                                              dtype=ref.dtype)
        self.mlps.load_state_dict(state["mlps"])
        self._build(state["anchors"], state["params"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.load_statistics(state["stats"])
        self._generator.set_state(state["generator"])

    def save_anchors(self, path: str) -> None:
        """Write the native anchor checkpoint (state_dict()) to ``path``, atomically."""
        save_atomic(self.state_dict(), path)

    @torch.no_grad()
    def export(self, path: str, camera: Optional[Camera] = None) -> None:
        """Write the neural Gaussians decoded for ``camera`` (prefiltered anchors, opacity > 0) as a
        standard 3DGS PLY of SH degree 0 (DC = (colour - 0.5) / SH_C0, so any viewer shows the
        decoded colour; logit opacity, log scale), atomically."""
        if not isinstance(camera, Camera):
            raise ValueError(f"Scaffold-GS decodes its Gaussians per view: export needs a Camera, got {camera!r}")
        _, ch = self.decode(camera)
        keep = ch["opacities"] > 0
        op = ch["opacities"][keep].clamp(1e-6, 1 - 1e-6)
        rgb = ch["colors"][keep]
        n = rgb.shape[0]
        write_gaussian_ply(Path(path), ch["means"][keep], ((rgb - 0.5) / SH_C0)[:, None, :], rgb.new_zeros(n, 0, 3),
                           torch.logit(op), torch.log(ch["scales"][keep].clamp_min(1e-30)), ch["quats"][keep])

    def __repr__(self) -> str:
        return (f"ScaffoldAdapter(anchors={self.num_primitives()}, k={self.config.n_offsets}, "
                f"voxel={self.voxel_size:.4g}, step={self._step})")


stats_in_one_dict(ScaffoldAdapter, STAT_NAMES)
