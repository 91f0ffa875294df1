"""4D Gaussian Splatting (Wu et al., CVPR 2024) as an MVGS adapter.

One set of canonical 3D Gaussians (exactly the 3DGS adapter's parameters, optimizer groups,
densification and PLY layout: :class:`GS4DAdapter` subclasses :class:`GS3DAdapter`) plus a
deformation field that moves them to a time t:

    u = 2 (x - lo) / (hi - lo) - 1 per axis (box [lo, hi] fixed from the initial points),
    τ = 2 t - 1                                            q = (u_x, u_y, u_z, τ) in [-1, 1]^4
    f_s(q) = ∏_{(a,b) in 6 pairs} bilinear(P_{s,ab}, (q_a, q_b))      [F] per scale s
    h = W_0 [f_1, ..., f_S] + b_0                                     concatenated over scales
    Δx, Δ log s, Δq = head_x(h), head_s(h), head_q(h)                 head = ReLU-Lin-ReLU-Lin
    means(t) = means + Δx, log scales(t) = log scales + Δ log s, quats(t) = quats + Δq

(the offsets are added before activation; opacities and colours are not deformed, as in the
original's defaults). The six planes P_ab of a scale are the coordinate pairs of (x, y, z, t):
xy, xz, xt, yz, yt, zt; scale s multiplies the spatial resolution (not the temporal one), and
bilinear lookups clamp at the border (the original's ``grid_sample(padding_mode="border")``).
Planes are initialised uniform in [0.1, 0.5], the time planes to 1 (so a fresh field does not
depend on t), linear layers Xavier-uniform with zero biases.

Training (``set_step``): steps 1..coarse_steps are the coarse stage (the field is off: a static
3DGS fit of the canonical Gaussians); later steps the fine stage (the field is on, its Adam groups
"planes" and "mlp" decay log-linearly over fine_steps, both times the scene extent, and the
regularisers of :meth:`regularization` are added once per step).

Deviations from the released 4DGS code, each a config field or stated here:
- ``zero_init_heads`` (default True): the last layer of every head starts at zero, so the fine
  stage starts exactly from the coarse result (the original's random heads jolt every Gaussian
  by a random offset at the hand-over).
- time enters the planes as 2t - 1, the full time axis (the original feeds t in [0, 1] into a
  [-1, 1] grid, using half of its time resolution). The time regularisers keep the original's
  weights, so per unit of time they act differently: node spacing halves, which makes the
  second-difference smoother 12-16x weaker for the same motion (its squared difference
  goes with spacing^4; the released configs pick the time resolution from the frame count with
  the half axis in mind), and |1 - P| about twice as strong (the original's mean counts the unused
  half). Not measured apart from the runs of docs/gs4d.md.
- one continuous step clock: the original runs coarse and fine as two trainings that recreate
  the optimizer and restart the means' learning-rate decay and the densification clock.
- the plane TV is K-Planes' (squared first differences along both axes of the space planes); the
  original code applies its second-difference smoother there too.

MVGS: every view of a chunk renders at its own ``Camera.time`` (views of one time share one
rasterizer call); densification statistics are gathered per view on the deformed Gaussians and
fold into the canonical rows they came from (one visit per view). Cross-ray boxes are found by
the controller in world space from views at different times; in the fine stage a canonical
Gaussian counts as inside a box when its *deformed* position at any of the triggering step's
view times is inside (see :meth:`GS4DAdapter.box_selection`), and its clone shares its
canonical position and so its whole trajectory.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mvgs_plugin.camera import Camera
from mvgs_plugin.checks import check_float, check_int
from mvgs_plugin.data.init import init_region, random_init_points
from mvgs_plugin.data.scene import PointCloud
from mvgs_plugin.densify import boxes_contain, top_by_score
from mvgs_plugin.io import save_atomic
from mvgs_plugin.protocol import DensifyContext, DensifyReport, RenderResult

from .gs3d import GS3DAdapter, GS3DConfig
from .ops import log_linear, make_adam, scale_for_views

# points drawn where the cameras look to size a deformation box when the initial points span nothing
_REGION_SAMPLES = 4096

LOG = logging.getLogger("mvgs_plugin")

__all__ = ["GS4DConfig", "GS4DAdapter", "HexPlaneField", "PLANES", "SPACE_PLANES", "TIME_PLANES"]

PLANES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))  # xy xz xt yz yt zt of (x, y, z, t)
SPACE_PLANES = (0, 1, 3)
TIME_PLANES = (2, 4, 5)
_STATE_FORMAT = "mvgs-gs4d/1"
_DEFORMATION_FORMAT = "mvgs-gs4d-deformation/1"
_FIELD_SHAPE_KEYS = ("resolution", "multires", "features", "width")


@dataclass
class GS4DConfig:
    """Hyper-parameters of the 4DGS model (defaults: the original 4DGS on D-NeRF).

    canonical: the canonical Gaussians' GS3DConfig (learning rates, densification, SH, ...).
    coarse_steps, fine_steps: length of the static coarse stage and of the deformation stage
        (original D-NeRF: 3000 and 20000); set_step(s) is coarse while s <= coarse_steps.
    Field:
        resolution: (x, y, z, t) plane resolution at scale 1 (original: 64, 64, 64, 25).
        multires: spatial resolution multipliers, one feature block per entry (original D-NeRF:
            (1, 2)).
        features: channels per plane (original 32); width: hidden width of the MLP (64).
        bounds: ((x0, y0, z0), (x1, y1, z1)) box mapped to [-1, 1]^3; None = the bounding box of
            the initial Gaussians, each side widened to at least min_bounds_fraction of the
            longest (a flat initial cloud, e.g. ground points only, still gets a 3D box); from_scene
            leaves out the far background shell (PointCloud.shell), whose Gaussians then look up
            the box's border.
        zero_init_heads: start the field at exactly zero offset (see the module docstring).
    Learning rates (Adam, log-linear decay over fine_steps, times the scene extent):
        lr_planes_init / lr_planes_final (1.6e-3 -> 1.6e-5), lr_mlp_init / lr_mlp_final
        (1.6e-4 -> 1.6e-6): the D-NeRF configs' (4DGaussians' generic defaults end 10x higher).
    Regularisers (fine stage, once per step): plane_tv_weight (1e-4) on the space planes,
        time_smoothness_weight (1e-2) on the time planes' second difference along t,
        l1_time_planes_weight (1e-4) on |1 - P| of the time planes.
    Densification caps of the original: growth_cap (360000): no clone/split/box growth once the
        model has this many Gaussians (None = no cap); prune_min_count (200000): the prune rules
        act only when the model (after growth) has more Gaussians than this (0 = always, as 3DGS).
    Initialisation (from_scene): init_random_points extra points uniform in init_box
        (((x0, y0, z0), (x1, y1, z1)); None = the scene's own points' bounding box (not the
        background shell's) widened to a cube,
        or without points where the cameras look, as mvgs_plugin.data.init.random_init_points
        places them: the cube scene.center ± scene.extent around the scene, photo-consistent
        points in the frusta of a forward-facing rig), colours uniform in [0, 1]; for scenes
        whose point cloud misses the moving objects (4DGS draws 2000 random points in
        [-1.3, 1.3]^3 for D-NeRF).
    """

    canonical: GS3DConfig = field(default_factory=GS3DConfig)
    coarse_steps: int = 3_000
    fine_steps: int = 20_000
    resolution: Tuple[int, int, int, int] = (64, 64, 64, 25)
    multires: Tuple[int, ...] = (1, 2)
    features: int = 32
    width: int = 64
    bounds: Optional[Tuple[Tuple[float, float, float], Tuple[float, float, float]]] = None
    min_bounds_fraction: float = 0.05
    zero_init_heads: bool = True
    lr_planes_init: float = 1.6e-3
    lr_planes_final: float = 1.6e-5
    lr_mlp_init: float = 1.6e-4
    lr_mlp_final: float = 1.6e-6
    plane_tv_weight: float = 1e-4
    time_smoothness_weight: float = 1e-2
    l1_time_planes_weight: float = 1e-4
    growth_cap: Optional[int] = 360_000
    prune_min_count: int = 200_000
    init_random_points: int = 0
    init_box: Optional[Tuple[Tuple[float, float, float], Tuple[float, float, float]]] = None

    def __post_init__(self) -> None:
        if not isinstance(self.canonical, GS3DConfig):
            raise ValueError(f"canonical must be a GS3DConfig, got {type(self.canonical).__name__}")
        check_int("coarse_steps", self.coarse_steps, 0)
        check_int("fine_steps", self.fine_steps, 1)
        self.resolution = tuple(self.resolution)
        if len(self.resolution) != 4:
            raise ValueError(f"resolution must be (x, y, z, t), got {self.resolution!r}")
        for r in self.resolution:
            check_int("resolution entries", r, 2)
        self.multires = tuple(self.multires)
        if not self.multires:
            raise ValueError("multires must name at least one scale, got ()")
        for m in self.multires:
            check_int("multires entries", m, 1)
        check_int("features", self.features, 1)
        check_int("width", self.width, 1)
        check_int("prune_min_count", self.prune_min_count, 0)
        check_int("init_random_points", self.init_random_points, 0)
        if self.growth_cap is not None:
            check_int("growth_cap", self.growth_cap, 0)
        for name in ("lr_planes_init", "lr_planes_final", "lr_mlp_init", "lr_mlp_final"):
            check_float(name, getattr(self, name), positive=True)
        for name in ("plane_tv_weight", "time_smoothness_weight", "l1_time_planes_weight"):
            check_float(name, getattr(self, name))
        v = check_float("min_bounds_fraction", self.min_bounds_fraction, positive=True)
        if v > 1:
            raise ValueError(f"min_bounds_fraction must be in (0, 1], got {v}")
        for name in ("bounds", "init_box"):
            if getattr(self, name) is not None:
                setattr(self, name, _check_box(name, getattr(self, name)))

    @property
    def total_steps(self) -> int:
        return self.coarse_steps + self.fine_steps

    @classmethod
    def for_run(cls, run, coarse_fraction: float = 3000 / 23000, canonical: Optional[GS3DConfig] = None,
                **fields) -> "GS4DConfig":
        """The config whose schedules follow the run's clock, as examples/train_4dgs.py builds it:
        the canonical Gaussians' GS3DConfig.for_run(run) (or `canonical`), and the coarse (static)
        stage the original's share of it, 3000 of 23000 steps, then the deformation field.
        fields: any other GS4DConfig field. Without it a short run keeps the field off (the
        default coarse stage is 3000 steps)."""
        clock = int(run.clock_length)
        if not 0 <= coarse_fraction < 1:
            raise ValueError(f"coarse_fraction must be in [0, 1), got {coarse_fraction!r}")
        coarse = min(clock - 1, round(coarse_fraction * clock))
        return cls(canonical=GS3DConfig.for_run(run) if canonical is None else canonical, coarse_steps=coarse,
                   fine_steps=clock - coarse, **fields)

    def saved_values(self) -> Dict[str, Any]:
        """The fields a checkpoint carries (the canonical config travels with the 3DGS state)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "canonical"}


def _check_box(name: str, box) -> Tuple[Tuple[float, ...], Tuple[float, ...]]:
    try:
        t = torch.as_tensor(box, dtype=torch.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be ((x0, y0, z0), (x1, y1, z1)), got {box!r}") from None
    if tuple(t.shape) != (2, 3) or not bool(torch.isfinite(t).all()) or not bool((t[0] < t[1]).all()):
        raise ValueError(f"{name} must be ((x0, y0, z0), (x1, y1, z1)) finite with min < max, got {box!r}")
    return tuple(map(tuple, t.tolist()))


def bounds_from_points(points: Tensor, min_fraction: float) -> Tensor:
    """[2, 3] float64 box of points [N, 3]; sides shorter than min_fraction x the longest are
    widened about their centre. Raises when the points do not span any length."""
    if points.ndim != 2 or points.shape[0] == 0:
        raise ValueError(f"the deformation box needs initial points, got {list(points.shape)}; "
                         f"give GS4DConfig.bounds")
    p = points.detach().to(torch.float64)
    lo, hi = p.min(dim=0).values, p.max(dim=0).values
    longest = float((hi - lo).max())
    if not longest > 0:
        raise ValueError(f"the initial points span no volume (all at {lo.tolist()}); give GS4DConfig.bounds")
    pad = ((min_fraction * longest - (hi - lo)) / 2).clamp_min(0)
    return torch.stack([lo - pad, hi + pad])


class HexPlaneField(torch.nn.Module):
    """The deformation field: multi-resolution HexPlane features -> MLP -> offsets.

    forward(means [N, 3], t) -> (Δmeans [N, 3], Δlog-scales [N, 3], Δquats [N, 4]), t a float
    in [0, 1]. ``planes[6 * k + p]`` is plane PLANES[p] of scale multires[k], shaped
    [1, F, R_b, R_a] for the pair (a, b): the lookup's first coordinate runs along the last axis
    (``grid_sample``'s convention), so a time plane's time axis is dim -2.
    """

    def __init__(self, bounds: Tensor, resolution: Sequence[int], multires: Sequence[int], features: int,
                 width: int, zero_init_heads: bool = True, generator: Optional[torch.Generator] = None,
                 dtype: torch.dtype = torch.float32, device=None) -> None:
        super().__init__()
        self.register_buffer("bounds", torch.as_tensor(bounds).to(dtype=dtype, device=device).clone())
        self.multires = tuple(multires)
        planes = []
        for m in self.multires:
            res = [r * m for r in resolution[:3]] + [resolution[3]]
            for a, b in PLANES:
                shape = (1, features, res[b], res[a])
                if b == 3:  # time planes start at 1: the product of features ignores t at first
                    plane = torch.ones(shape, dtype=torch.float64)
                else:
                    plane = 0.1 + 0.4 * torch.rand(shape, generator=generator, dtype=torch.float64)
                planes.append(torch.nn.Parameter(plane.to(dtype=dtype, device=device)))
        self.planes = torch.nn.ParameterList(planes)
        self.trunk = torch.nn.Linear(features * len(self.multires), width)
        self.heads = torch.nn.ModuleDict({
            name: torch.nn.Sequential(torch.nn.ReLU(), torch.nn.Linear(width, width), torch.nn.ReLU(),
                                      torch.nn.Linear(width, out))
            for name, out in (("means", 3), ("scales", 3), ("quats", 4))
        })
        for lin in [self.trunk] + [h[i] for h in self.heads.values() for i in (1, 3)]:
            _xavier(lin.weight, generator)
            torch.nn.init.zeros_(lin.bias)
        if zero_init_heads:
            for h in self.heads.values():
                torch.nn.init.zeros_(h[3].weight)
        self.to(dtype=dtype, device=device)

    def mlp_parameters(self) -> List[torch.nn.Parameter]:
        return list(self.trunk.parameters()) + list(self.heads.parameters())

    def normalize(self, xyz: Tensor, t: float) -> Tensor:
        """[N, 4] lookup coordinates in [-1, 1] (space may fall outside: lookups clamp)."""
        lo, hi = self.bounds[0], self.bounds[1]
        u = (xyz - lo) * (2.0 / (hi - lo)) - 1.0
        tau = torch.full_like(u[:, :1], 2.0 * float(t) - 1.0)
        return torch.cat([u, tau], dim=1)

    def features(self, xyz: Tensor, t: float) -> Tensor:
        """[N, F * S] plane features, multiplied over the six planes, concatenated over scales."""
        q = self.normalize(xyz, t)
        n = q.shape[0]
        out = []
        for k in range(len(self.multires)):
            f = None
            for p, (a, b) in enumerate(PLANES):
                grid = q[:, [a, b]].view(1, 1, n, 2)
                v = torch.nn.functional.grid_sample(self.planes[6 * k + p], grid, mode="bilinear",
                                                    padding_mode="border", align_corners=True)
                v = v[0, :, 0, :].T  # [N, F]
                f = v if f is None else f * v
            out.append(f)
        return torch.cat(out, dim=1)

    def forward(self, xyz: Tensor, t: float) -> Tuple[Tensor, Tensor, Tensor]:
        h = self.trunk(self.features(xyz, t))
        return self.heads["means"](h), self.heads["scales"](h), self.heads["quats"](h)

    def regularizers(self) -> Dict[str, Tensor]:
        """Unweighted plane regularisers, summed over scales:
        tv: mean squared first difference along both axes of every space plane (K-Planes TV);
        time_smoothness: mean squared second difference along t of every time plane;
        l1_time: mean |1 - P| of every time plane (1 = no change with time)."""
        zero = self.planes[0].new_zeros(())
        tv, smooth, l1 = zero, zero, zero
        for k in range(len(self.multires)):
            for p in SPACE_PLANES:
                g = self.planes[6 * k + p]
                tv = tv + (g[..., 1:, :] - g[..., :-1, :]).square().mean() \
                    + (g[..., :, 1:] - g[..., :, :-1]).square().mean()
            for p in TIME_PLANES:
                g = self.planes[6 * k + p]
                if g.shape[-2] >= 3:
                    smooth = smooth + (g[..., 2:, :] - 2 * g[..., 1:-1, :] + g[..., :-2, :]).square().mean()
                l1 = l1 + (1.0 - g).abs().mean()
        return {"tv": tv, "time_smoothness": smooth, "l1_time": l1}


def _xavier(w: Tensor, generator: Optional[torch.Generator]) -> None:
    """Xavier-uniform (gain 1) from our own generator, so the field is seeded by the config."""
    fan_out, fan_in = w.shape
    a = math.sqrt(6.0 / (fan_in + fan_out))
    with torch.no_grad():
        w.copy_((2 * torch.rand(w.shape, generator=generator, dtype=torch.float64) - 1) * a)


def _check_time(cam: Camera) -> float:
    if cam.time is None:
        raise ValueError(f"camera {cam.name!r} (uid {cam.uid}) has no time; the 4DGS deformation "
                         f"needs Camera.time in [0, 1]")
    return float(cam.time)


class GS4DAdapter(GS3DAdapter):
    """Canonical 3DGS Gaussians (inherited: parameters, Adam groups, densification, PLY) plus a
    HexPlane deformation field with its own Adam (groups "planes" and "mlp").

    Construct with :meth:`from_scene` or :meth:`from_canonical` (any GS3DAdapter, e.g. a trained
    static model); the constructor takes the raw canonical tensors like GS3DAdapter's, and a
    GS4DConfig (a plain GS3DConfig is taken as GS4DConfig(canonical=it), so the inherited
    ``from_tensors`` / ``from_ply`` build a 4DGS model with the default field).

    Attributes (besides GS3DAdapter's):
        gs4d_config: the whole GS4DConfig (field, schedules, caps); canonical_config: its
        ``canonical`` GS3DConfig, the settings of the canonical Gaussians (the inherited code reads
        it as ``config``); field: the HexPlaneField; field_optimizer: its Adam.
    """

    @property
    def canonical_config(self) -> GS3DConfig:
        """The canonical Gaussians' GS3DConfig (``gs4d_config.canonical``; ``config`` to the
        inherited GS3DAdapter code)."""
        return self.config

    @property
    def config4d(self) -> GS4DConfig:
        """Deprecated name of gs4d_config (kept until the next release)."""
        warnings.warn("GS4DAdapter.config4d is deprecated; use gs4d_config", DeprecationWarning, stacklevel=2)
        return self.gs4d_config

    def __init__(self, means: Tensor, sh0: Tensor, shN: Tensor, scales: Tensor, quats: Tensor,
                 opacities: Tensor, scene_extent: float, config=None, active_sh_degree: int = 0, *,
                 scene_center: Optional[Tensor] = None) -> None:
        config = self._as_gs4d_config(config)
        self.gs4d_config = config
        super().__init__(means, sh0, shN, scales, quats, opacities, scene_extent, config.canonical,
                         active_sh_degree, scene_center=scene_center)
        bounds = (torch.tensor(config.bounds, dtype=torch.float64) if config.bounds is not None
                  else bounds_from_points(self.params["means"], config.min_bounds_fraction))
        self._build_field(bounds)

    def _build_field(self, bounds: Tensor) -> None:
        c, ref = self.gs4d_config, self.params["means"]
        gen = torch.Generator().manual_seed(self.config.seed + 1)
        self.field = HexPlaneField(bounds, c.resolution, c.multires, c.features, c.width, c.zero_init_heads,
                                   gen, dtype=ref.dtype, device=ref.device)
        groups = [{"params": list(self.field.planes), "lr": 0.0, "name": "planes"},
                  {"params": self.field.mlp_parameters(), "lr": 0.0, "name": "mlp"}]
        self.field_optimizer = make_adam(groups, self.config.adam_eps)
        self._set_field_lrs(self._step)

    # ---- construction ----------------------------------------------------------------------
    @classmethod
    def from_canonical(cls, canonical: GS3DAdapter, config: Optional[GS4DConfig] = None) -> "GS4DAdapter":
        """A 4DGS model whose canonical Gaussians are a copy of a GS3DAdapter's (its config's
        canonical part replaced by that adapter's config)."""
        config = GS4DConfig() if config is None else config
        config = dataclasses.replace(config, canonical=canonical.config)
        p = {k: v.detach() for k, v in canonical.params.items()}
        model = cls(p["means"], p["sh0"], p["shN"], p["scales"], p["quats"], p["opacities"],
                    canonical.scene_extent, config, canonical.active_sh_degree, scene_center=canonical.scene_center)
        model.sized_by_spacing = canonical.sized_by_spacing
        return model

    @staticmethod
    def _as_gs4d_config(config) -> GS4DConfig:
        """None, a GS3DConfig (the canonical Gaussians' settings) or a GS4DConfig, as __init__
        takes them, made a GS4DConfig."""
        if config is None or isinstance(config, GS3DConfig):
            return GS4DConfig() if config is None else GS4DConfig(canonical=config)
        if not isinstance(config, GS4DConfig):
            raise ValueError(f"config must be a GS4DConfig, got {type(config).__name__}")
        return config

    @classmethod
    def from_tensors(cls, means: Tensor, *, config=None, **kwargs) -> "GS4DAdapter":
        """GS3DAdapter.from_tensors's canonical Gaussians (its arguments; SH bands as
        config.canonical asks) with a fresh deformation field (`config`: a GS4DConfig, or a
        GS3DConfig for the canonical Gaussians)."""
        config = cls._as_gs4d_config(config)
        return cls.from_canonical(GS3DAdapter.from_tensors(means, config=config.canonical, **kwargs), config)

    @classmethod
    def from_ply(cls, path, scene_extent: float, config=None, dtype: torch.dtype = torch.float32,
                 device=None, scene_center: Optional[Tensor] = None) -> "GS4DAdapter":
        """Canonical Gaussians loaded as GS3DAdapter.from_ply loads them (without a config, the
        file's SH degree) with a fresh deformation field (`config`: a GS4DConfig, or a
        GS3DConfig for the canonical Gaussians)."""
        given = config
        config = cls._as_gs4d_config(config)
        base = GS3DAdapter.from_ply(path, scene_extent, None if given is None else config.canonical, dtype, device,
                                    scene_center)
        return cls.from_canonical(base, config)

    @classmethod
    def from_scene(cls, scene, config: Optional[GS4DConfig] = None, dtype: torch.dtype = torch.float32,
                   device=None) -> "GS4DAdapter":
        """Canonical Gaussians initialised as GS3DAdapter.from_scene does, from the scene's points
        plus config.init_random_points random ones (see GS4DConfig)."""
        config = GS4DConfig() if config is None else config
        if not isinstance(config, GS4DConfig):
            raise ValueError(f"config must be a GS4DConfig, got {type(config).__name__}")
        points = cls._with_random_points(scene, config) if config.init_random_points else None
        base = GS3DAdapter.from_scene(scene, config.canonical, dtype, device, points=points)
        if config.bounds is None:
            pts = points if points is not None else getattr(scene, "points", None)
            config = cls._deformation_box(config, scene, pts, base.params["means"].detach().double())
        return cls.from_canonical(base, config)

    @staticmethod
    def _deformation_box(config: GS4DConfig, scene, pts, means: Tensor) -> GS4DConfig:
        """config with the deformation box the initial model asks for (config.bounds None):
        - the box of the scene's own points when it has a far background shell (static, at twice
          the rig's radius, it would spread the planes' cells over empty space; its Gaussians fall
          outside the box, where lookups clamp to the border), else of every initial Gaussian
          (config unchanged: from_canonical takes that box); own points that span nothing keep
          the box of every Gaussian;
        - along an axis where those points are flat (thinner than min_bounds_fraction x their
          longest side: a ground-only point file) the box spans the region where the cameras
          look, with a warning: a slab would have every Gaussian above the ground read the planes
          at its top face, so motion could not vary with height;
        - points that span nothing at all (one point, a repeated one): the region's box, with a
          warning."""
        def span(x: Tensor) -> Tensor:
            return x.max(0).values - x.min(0).values if len(x) else torch.zeros(3, dtype=torch.float64)

        own = pts.own.double() if pts is not None and pts.shell else None
        shell_box = own is not None and float(span(own).max()) > 0
        cloud = own if shell_box else means
        extent = span(cloud)
        longest = float(extent.max())
        flat = extent < config.min_bounds_fraction * longest if longest > 0 else torch.ones(3, dtype=torch.bool)
        if not bool(flat.any()):
            if not shell_box:
                return config
            return dataclasses.replace(config, bounds=tuple(map(tuple, bounds_from_points(own, config.min_bounds_fraction).tolist())))
        region = init_region(scene.train_cameras, scene.center, float(scene.extent))
        samples = region.sample(_REGION_SAMPLES, torch.Generator().manual_seed(config.canonical.seed + 3))
        if longest > 0:
            box = bounds_from_points(cloud, config.min_bounds_fraction)
            box[0] = torch.where(flat, torch.minimum(box[0], samples.min(0).values), box[0])
            box[1] = torch.where(flat, torch.maximum(box[1], samples.max(0).values), box[1])
            said = (f"the initial points are flat along {''.join(a for a, f in zip('xyz', flat.tolist()) if f)} "
                    f"({[round(v, 3) for v in extent.tolist()]} across): the deformation box spans the region where "
                    f"the cameras look along it ({region.description})")
        else:
            box = bounds_from_points(torch.cat([samples, cloud]), config.min_bounds_fraction)
            said = (f"the {len(cloud)} initial point(s) span no volume (all at {cloud[0].tolist() if len(cloud) else '-'}): "
                    f"the deformation box is where the cameras look instead ({region.description})")
        warnings.warn(f"{said}: {[round(v, 3) for v in box[0].tolist()]} to {[round(v, 3) for v in box[1].tolist()]}; "
                      "GS4DConfig.bounds sets it", stacklevel=3)
        return dataclasses.replace(config, bounds=tuple(map(tuple, box.tolist())))

    @staticmethod
    def _with_random_points(scene, config: GS4DConfig) -> PointCloud:
        """The scene's points with config.init_random_points added after its own ones (the
        background shell stays last, counted as such)."""
        pts = getattr(scene, "points", None)
        if pts is None:
            pts = PointCloud(torch.zeros(0, 3), torch.zeros(0, 3))
        own = len(pts) - pts.shell
        gen = torch.Generator().manual_seed(config.canonical.seed + 2)
        if config.init_box is None and own == 0:
            # no points of the scene's own: where the cameras look (the 3DGS cube around the scene,
            # the frusta of a forward rig)
            new_xyz, new_rgb, description = random_init_points(scene, config.init_random_points, gen)
            LOG.info("4DGS extra points: %s", description)
        else:
            if config.init_box is not None:
                box = torch.tensor(config.init_box, dtype=torch.float64)
            else:  # the scene's own points' box widened to a cube (the shell left out)
                lo, hi = pts.own.double().min(0).values, pts.own.double().max(0).values
                half = float((hi - lo).max()) / 2
                if not half > 0:
                    raise ValueError("init_random_points: the scene points span no volume; give init_box "
                                     "(--init-box)")
                c = (lo + hi) / 2
                box = torch.stack([c - half, c + half])
            u = torch.rand(config.init_random_points, 3, generator=gen, dtype=torch.float64)
            new_xyz = box[0] + u * (box[1] - box[0])
            new_rgb = torch.rand(config.init_random_points, 3, generator=gen, dtype=torch.float64)
        xyz = torch.cat([pts.xyz[:own], new_xyz.to(pts.xyz.dtype), pts.xyz[own:]])
        rgb = torch.cat([pts.rgb[:own], new_rgb.to(pts.rgb.dtype), pts.rgb[own:]])
        return PointCloud(xyz, rgb, shell=pts.shell)

    # ---- schedule -----------------------------------------------------------------------
    def clock_mismatch(self, clock: int) -> Optional[Tuple[str, int, str]]:
        """ClockedAdapter: the coarse and fine stages span coarse_steps + fine_steps (then the
        canonical Gaussians' schedules, as GS3DAdapter's)."""
        c = self.gs4d_config
        if c.total_steps != clock:
            return (f"coarse_steps + fine_steps ({c.coarse_steps} + {c.fine_steps}): its deformation field starts at "
                    f"step {c.coarse_steps}", c.total_steps, "GS4DConfig.for_run(config)")
        return super().clock_mismatch(clock)

    @property
    def deformation_active(self) -> bool:
        """Whether the current step is in the fine stage (the field moves the Gaussians)."""
        return self._step > self.gs4d_config.coarse_steps

    def field_lrs(self, step: int) -> Dict[str, float]:
        """Learning rates of "planes" and "mlp" at ``step``: log-linear over the fine stage (held
        at the initial rates during the coarse stage), times the scene extent."""
        c, e = self.gs4d_config, self.scene_extent
        return {"planes": e * log_linear(step, c.coarse_steps, c.fine_steps, c.lr_planes_init, c.lr_planes_final),
                "mlp": e * log_linear(step, c.coarse_steps, c.fine_steps, c.lr_mlp_init, c.lr_mlp_final)}

    def _set_field_lrs(self, step: int) -> None:
        scale_for_views(self.field_optimizer, self.field_lrs(step), self._views, self.config.adam_eps)

    def set_step(self, step: int) -> None:
        """The 3DGS schedules, the field's learning rates and the stage (coarse or fine)."""
        super().set_step(step)
        self._set_field_lrs(step)

    def learning_rates(self) -> Dict[str, float]:
        return {**super().learning_rates(), **{g["name"]: g["lr"] for g in self.field_optimizer.param_groups}}

    # ---- deformation and rendering ----------------------------------------------------------
    def deformed(self, t: float, force: bool = False) -> Dict[str, Tensor]:
        """Raw (pre-activation) attributes at time t, keyed like self.params: the canonical ones
        in the coarse stage (unless ``force``), else with the field's offsets added to means,
        log-scales and quaternions. Differentiable w.r.t. the canonical parameters and the field."""
        p = dict(self.params)
        if not (force or self.deformation_active):
            return p
        t = check_float("t", t)
        if t > 1:
            raise ValueError(f"t must be in [0, 1], got {t}")
        dx, ds, dq = self.field(p["means"], t)
        p["means"], p["scales"], p["quats"] = p["means"] + dx, p["scales"] + ds, p["quats"] + dq
        return p

    def render(self, cameras: Sequence[Camera], backgrounds: Tensor) -> RenderResult:
        """Render C cameras of one size, each at its own time (cameras sharing a time share one
        rasterizer call). Coarse stage: the canonical Gaussians for every camera (time unused).

        Returns images [C, H, W, 3], alphas [C, H, W, 1] and as aux the list of the rasterizer
        calls' meta dicts with the positions in the chunk they cover (for accumulate_stats).
        """
        cams = list(cameras)
        if not self.deformation_active or not cams:
            result = super().render(cams, backgrounds)
            result.aux = [(list(range(len(cams))), result.aux)]
            return result
        sizes = sorted({(c.width, c.height) for c in cams})
        if len(sizes) != 1:
            raise ValueError(f"all cameras of a chunk must have one size, got (width, height) "
                             f"{sizes} for uids {[c.uid for c in cams]}")
        groups: Dict[float, List[int]] = {}
        for i, cam in enumerate(cams):
            groups.setdefault(_check_time(cam), []).append(i)
        bg = torch.as_tensor(backgrounds)
        if tuple(bg.shape) != (len(cams), 3):
            raise ValueError(f"backgrounds must be [C,3] with C={len(cams)}, got {list(bg.shape)}")
        images: List[Optional[Tensor]] = [None] * len(cams)
        alphas: List[Optional[Tensor]] = [None] * len(cams)
        aux = []
        for t, idx in groups.items():
            res = self.render_raw(self.deformed(t), [cams[i] for i in idx], bg[idx])
            for k, i in enumerate(idx):
                images[i], alphas[i] = res.images[k], res.alphas[k]
            aux.append((idx, res.aux))
        return RenderResult(images=torch.stack(images), alphas=torch.stack(alphas), aux=aux)

    def accumulate_stats(self, result: RenderResult) -> None:
        """GS3DAdapter's statistics, per rasterizer call of the chunk: the screen-space gradient of
        every view's deformed Gaussians folds into the canonical rows (one visit per view)."""
        if not isinstance(result.aux, list):
            raise ValueError("accumulate_stats needs the RenderResult returned by this adapter's render()")
        for _, meta in result.aux:
            super().accumulate_stats(RenderResult(images=result.images, aux=meta))

    def regularization(self, step: int) -> Optional[Tensor]:
        """Fine stage: plane_tv_weight * TV(space planes) + time_smoothness_weight * smoothness(time
        planes) + l1_time_planes_weight * |1 - time planes| (HexPlaneField.regularizers); None in
        the coarse stage."""
        if step <= self.gs4d_config.coarse_steps:
            return None
        c, r = self.gs4d_config, self.field.regularizers()
        return (c.plane_tv_weight * r["tv"] + c.time_smoothness_weight * r["time_smoothness"]
                + c.l1_time_planes_weight * r["l1_time"])

    # ---- densification ----------------------------------------------------------------------
    def densify(self, ctx: DensifyContext) -> DensifyReport:
        """GS3DAdapter.densify with the original 4DGS caps: no growth (gradient or boxes) once
        the model holds growth_cap Gaussians; prune rules only above prune_min_count (see
        prune_mask)."""
        capped = self.gs4d_config.growth_cap is not None and self.num_primitives() >= self.gs4d_config.growth_cap
        if capped:
            ctx = dataclasses.replace(ctx, grad_threshold=math.inf, boxes=None)
        report = super().densify(ctx)
        report.extra["growth_capped"] = capped
        return report

    def prune_mask(self, rows: Dict[str, Tensor], radii: Tensor, extent: float, prune_large: bool,
                   center: Optional[Tensor] = None) -> Tensor:
        if rows["means"].shape[0] <= self.gs4d_config.prune_min_count:
            return torch.zeros(rows["means"].shape[0], dtype=torch.bool, device=rows["means"].device)
        return super().prune_mask(rows, radii, extent, prune_large, center)

    def box_selection(self, ctx: DensifyContext, g: Tensor) -> Tuple[Tensor, int]:
        """Cross-ray boxes for moving content. The boxes come from rays of views taken at
        different times, so they are approximate where content moves between those times; a
        canonical Gaussian is selected when its deformed position at any time of the step's views
        (ctx.cameras) is strictly inside any box. Coarse stage or no times: the 3DGS rule on the
        canonical positions. The cap keeps the largest mean gradients."""
        times = sorted({c.time for c in ctx.cameras if c.time is not None})
        if ctx.boxes is None or not self.deformation_active or not times:
            return super().box_selection(ctx, g)
        boxes = torch.as_tensor(ctx.boxes)
        if boxes.ndim != 3 or tuple(boxes.shape[1:]) != (2, 3) or not bool(torch.isfinite(boxes).all()) \
                or bool((boxes[:, 0] > boxes[:, 1]).any()):
            raise ValueError(f"ctx.boxes must be finite [B,2,3] (min, max corners), got {boxes.tolist()}")
        sel = torch.zeros(self.num_primitives(), dtype=torch.bool, device=g.device)
        with torch.no_grad():
            for t in times:
                sel |= boxes_contain(self.deformed(t)["means"], boxes.to(g.device))
        total = int(sel.sum())
        if ctx.max_new_from_boxes is not None:
            sel = top_by_score(sel, g, check_int("max_new_from_boxes", ctx.max_new_from_boxes, 0))
        return sel, total - int(sel.sum())

    # ---- optimisation -----------------------------------------------------------------------
    def _field_named(self) -> Dict[str, torch.nn.Parameter]:
        return {f"deformation.{k}": v for k, v in self.field.named_parameters()}

    def named_gradients(self) -> Dict[str, Optional[Tensor]]:
        return {**super().named_gradients(), **{k: v.grad for k, v in self._field_named().items()}}

    def gradient_parameters(self) -> Dict[str, Tensor]:
        """Every trainable tensor, by the names of named_gradients() (canonical and field)."""
        return {**dict(self.params), **self._field_named()}

    def optimizer_step(self) -> None:
        super().optimizer_step()
        self.field_optimizer.step()  # no-op in the coarse stage: the field has no gradients

    def zero_grad(self) -> None:
        super().zero_grad()
        self.field_optimizer.zero_grad(set_to_none=True)

    # ---- persistence ------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        """GS3DAdapter's state (canonical Gaussians, their Adam, statistics, step) plus the field,
        its Adam and the GS4DConfig values."""
        return {
            "format": _STATE_FORMAT,
            "canonical": super().state_dict(),
            "field": {k: v.detach().clone() for k, v in self.field.state_dict().items()},
            "field_optimizer": copy.deepcopy(self.field_optimizer.state_dict()),
            "config4d": self.gs4d_config.saved_values(),
        }

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        """Restore a state_dict() (any number of Gaussians; the field's shape comes from the
        saved config)."""
        for key in ("format", "canonical", "field", "field_optimizer", "config4d"):
            if key not in state:
                raise ValueError(f"state has no {key!r} entry; not a GS4DAdapter state_dict")
        if state["format"] != _STATE_FORMAT:
            raise ValueError(f"state format {state['format']!r} is not {_STATE_FORMAT!r}")
        unknown = set(state["config4d"]) - set(GS4DConfig().saved_values())
        if unknown:
            raise ValueError(f"state config4d has unknown fields {sorted(unknown)}")
        super().load_state_dict(state["canonical"])
        self.gs4d_config = dataclasses.replace(self.gs4d_config, canonical=self.config, **state["config4d"])
        self._build_field(state["field"]["bounds"])
        self.field.load_state_dict(state["field"])
        self.field_optimizer.load_state_dict(state["field_optimizer"])
        self._set_field_lrs(self._step)

    def export(self, path: str, camera: Optional[Camera] = None) -> None:
        """Without a camera: the canonical Gaussians as a standard 3DGS PLY. With one: the
        Gaussians baked at camera.time (export_at_time)."""
        if camera is None:
            super().export(path)
        else:
            self.export_at_time(path, _check_time(camera))

    def export_at_time(self, path: str, t: float) -> None:
        """The Gaussians deformed to time t (field applied whatever the stage), as a standard 3DGS
        PLY with raw values (log scales, unnormalised quaternions): any 3DGS viewer shows the
        scene at t, and GS3DAdapter.from_ply renders it as this model renders t."""
        from .ply import write_gaussian_ply

        with torch.no_grad():
            p = self.deformed(t, force=True)
        write_gaussian_ply(Path(path), p["means"], p["sh0"], p["shN"], p["opacities"], p["scales"], p["quats"])

    def save_deformation(self, path: str) -> None:
        """The deformation field alone (weights, box, shape, and whether it moves the Gaussians:
        the fine stage), written atomically; with the canonical PLY it is the whole trained model."""
        c = self.gs4d_config
        weights = {k: v.detach().cpu().clone() for k, v in self.field.state_dict().items()}
        data = {"format": _DEFORMATION_FORMAT, "field": weights, "active": bool(self.deformation_active),
                **{k: getattr(c, k) for k in _FIELD_SHAPE_KEYS}}
        save_atomic(data, path)

    def load_deformation(self, path: str) -> None:
        """Load a save_deformation() file into this model (its field shape must match). A field
        saved in the fine stage (every trained model's: the field moves the Gaussians) puts this
        model in the fine stage too, whatever its step (set_step(coarse_steps + 1) when it is
        before it), so a model rebuilt from its two files renders each time as the trained one
        did; a file written before the stage was recorded counts as fine."""
        data = torch.load(path, weights_only=True, map_location="cpu")  # copied onto the field's device below
        if not isinstance(data, dict) or data.get("format") != _DEFORMATION_FORMAT:
            raise ValueError(f"{path} is not a {_DEFORMATION_FORMAT} file")
        for k in _FIELD_SHAPE_KEYS:
            mine, theirs = getattr(self.gs4d_config, k), data[k]
            if (tuple(mine) if isinstance(mine, (tuple, list)) else mine) != \
                    (tuple(theirs) if isinstance(theirs, (tuple, list)) else theirs):
                raise ValueError(f"{path}: field {k} is {theirs!r}, this model has {mine!r}")
        self._build_field(data["field"]["bounds"])
        self.field.load_state_dict(data["field"])
        if data.get("active", True) and not self.deformation_active:
            self.set_step(self.gs4d_config.coarse_steps + 1)

    def __repr__(self) -> str:
        stage = "fine" if self.deformation_active else "coarse"
        return (f"GS4DAdapter(N={self.num_primitives()}, {stage} stage, step={self._step}, "
                f"planes={len(self.field.planes)}, extent={self.scene_extent:.4g})")
