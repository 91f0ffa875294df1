"""MVGS for a gsplat-style trainer: :class:`MVGSStrategy` wraps gsplat's ``DefaultStrategy``.

gsplat's ``simple_trainer.py`` keeps its Gaussians in a ``ParameterDict`` (``splats``), one Adam
per parameter, its data in a ``Dataset`` read through a ``DataLoader``, and densifies with a
strategy object called around backward. MVGSStrategy *is* a ``DefaultStrategy`` (a subclass:
the trainer's ``isinstance`` checks and its reads of ``absgrad`` keep working) that drives the
one it wraps from an MVGS schedule. gsplat's own trainer adopts it with four added lines
(``docs/gsplat_loop.md`` shows them as a patch of gsplat 1.5.3's ``examples/simple_trainer.py``)::

    from mvgs_plugin.adapters.gsplat_strategy import MVGSStrategy
    self.cfg.strategy = MVGSStrategy(self.cfg.strategy, self.trainset, "multiview", steps=cfg.max_steps)
    trainloader = self.cfg.strategy.loader(trainloader)   # after the DataLoader(...) call
    ...
    strategy.step_post_backward(..., info=info, packed=packed, renders=colors)   # for CRD

The data stays the user's: their Dataset and DataLoader settings (workers, pinning) load the
items; the schedule picks which (``batch_sampler()``, indices per step, plain torch) and
``at_level`` brings a loaded batch to the step's pyramid level (images resampled as the
package's pyramid, intrinsics scaled). ``loader(trainloader)`` does both, so the loop body does
not change. ``batches()`` serves the package's own loader (a :class:`~mvgs_plugin.data.Scene`).

What reaches the wrapped strategy, and how:

- **M views per step.** One render call of the step's M cameras gives one ``info``; the
  strategy's statistics count every view. **Keep gsplat's mean over the batch**: its
  ``x n_cameras`` then makes each view's statistic exactly its single-view gradient (tested
  against one render per view). Under Adam a constant factor on the loss changes the update
  only through eps, so the mean trains as the paper's sum does.
- **Chunks.** A step's views may be rendered and backpropagated in chunks (memory): weight a
  chunk's mean loss by ``len(chunk) / M`` (``chunks()`` gives the slices and weights). The
  parameter gradients are then the unchunked step's, and the wrapper hands the strategy
  ``n_cameras = M`` for each chunk, so the statistics are the unchunked step's too (both tested).
  Call ``step_post_backward`` once per chunk; the step ends when its M views are reported.
- **Either hook order.** ``step_post_backward`` may come after the optimizer step (gsplat's
  order) or before it: a refine or opacity reset due while gradients are unused is deferred to
  the start of the next step (its batch), so no gradient is dropped and the model is the same
  in both orders (tested). gsplat's own DefaultStrategy refines at once in the second order and
  loses that step's update.
- **The pyramid.** A batch's cameras are the stage's scaled cameras (the x row of K times W'/W,
  the y row times H'/H) and its images the matching targets; the strategy normalises gradients
  by the batch's own width and height.
- **One clock.** The strategy's step-valued fields (``refine_start_iter``, ``refine_stop_iter``,
  ``refine_every``, ``reset_every``, ``refine_scale2d_stop_iter``, ``pause_refine_after_reset``)
  are read once, as the user set them for a run of ``steps`` single-view steps, and become the
  schedule's densification window, interval, opacity-reset period and size-pruning start
  (keeping their fraction of the run when the schedule's clock counts work). From then on the
  schedule alone decides when statistics are collected, when the strategy refines and when
  opacities are reset; the loop's ``step`` only labels log lines. The schedule counts steps
  from 1 (as graphdeco's trainer does) where gsplat's loop counts from 0, so a refine or reset
  comes one optimizer step before DefaultStrategy's would.
- **MVAD.** The strategy's ``grow_grad2d`` is β (with ``clock="config"``, the config's own β,
  with a warning when they differ); each refine runs with the schedule's threshold
  for that step (β scaled to the image width when the preset says so, halved when the step's
  cameras are far apart). The width-scaled presets (default, multiview, compact) read β as meant
  for 800-px images: β × 800 / W at W-px views; a β tuned for your full width W_full keeps its
  meaning with ``grad_threshold_width=W_full`` in the config, and ``None`` uses it as given.
- **CRD.** With ``renders=`` given to ``step_post_backward``, the step's per-view loss maps give
  cross-ray boxes; before the strategy refines, every Gaussian inside a box (at most
  ``crd_max_new`` of the count, largest mean gradient first) is copied with gsplat's
  ``ops.duplicate``, the copies starting with empty statistics. Without ``renders`` the rule is
  skipped with one warning.
- **The far background (optional, off by default).** ``world_size_rule="distance"`` lets the
  size prune's limit grow with a row's distance from the rig's centre (prune_scale3d x
  max(scene_scale, d)) and ``opacity_reset_scope="inside"`` leaves the rows beyond the far line
  out of opacity resets: the package trainer's rules, which keep a far background (a shell of
  points round the rig, sky) that gsplat's rules remove or cap (docs/gsplat_loop.md).
- **Mistakes said once.** A step whose gradient reaches only some of the views rendered
  together (a loss on ``colors[0]``), or reaches one batch position far more than the others
  over many steps (an SSIM term on ``colors[0]`` beside an L1 on all), gets one warning; with
  ``verbose`` the refine lines carry the loop's step.

How the wrapped strategy is driven: never through its private methods. Each call runs the
strategy's own ``step_post_backward`` on a shallow copy whose clock fields are set so that its
own conditions give the schedule's decision: statistics only, or (with an ``info`` that adds no
statistics) grow and prune with the step's threshold and the size-pruning rule of the current
clock. Opacity resets use gsplat's ``ops.reset_opa`` with the strategy's value (2 x
``prune_opa``). Note: gsplat 1.5.3's DefaultStrategy never resets opacities itself (its
condition ``step % reset_every == 0 & step > 0`` is always false; fixed upstream after 1.5.3),
so a single-view loop on 1.5.3 runs without resets while this wrapper resets on the schedule.

What cannot reach a third-party strategy: ``MCMCStrategy`` (and any strategy without a gradient
threshold) has nothing for MVAD or CRD to act on and relocates instead of cloning; it is refused.
``stats_from="last"`` (the paper preset) takes the statistics of the step's last call; they are
the last view's only when that view is rendered alone (``chunks()`` and ``batches(chunked=True)``
do so; otherwise said once).
"""

from __future__ import annotations

import collections
import contextlib
import copy
import dataclasses
import io
import math
import re
import warnings
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import duplicate, remove, reset_opa

from mvgs_plugin.adapters.gs3d import (BUDGET_GROWTH_ORDERS, OPACITY_RESET_SCOPES, WORLD_SIZE_RULES, beyond_far_line,
                                       consistency_of, faint_rows, farthest_distance, growth_that_fits, keep_scores_of,
                                       world_size_limit)
from mvgs_plugin.adapters.knn import spacing_log_scale
from mvgs_plugin.camera import Camera, scaled_size
from mvgs_plugin.config import MVGSConfig
from mvgs_plugin.controller import config_differences
from mvgs_plugin.data.images import downsample_batch, masked_downsample
from mvgs_plugin.data.init import is_forward_facing
from mvgs_plugin.data.scene import camera_normalization
from mvgs_plugin.densify import boxes_contain, top_by_score
from mvgs_plugin.schedule import StepPlan, ViewSchedule

__all__ = ["MVGSStrategy", "MVGSBatches", "MVGSBatchSampler", "MVGSLoader", "CameraViews", "views_of",
           "adopt_strategy_clock", "gsplat_batch", "IMBALANCE_MIN_STEPS", "IMBALANCE_Z"]

# The one-position imbalance warning: after this many multi-view steps of one size, a batch
# position whose mean share of the step's screen-space gradient is at least twice the fair 1/M
# and exceeds it by IMBALANCE_Z standard errors (positions are exchangeable: the sampler
# shuffles) is reported once. Measured (tests/test_gsplat_loop.py's loops, multiview, 80 steps):
# an SSIM term on colors[0] gives position 0 a 60-80 % share (z 27-177 within 6 steps); honest
# losses stay within 1.4x the fair share (|z| <= 5.5).
IMBALANCE_MIN_STEPS = 6
IMBALANCE_Z = 6.0


def gsplat_batch(cameras: Sequence[Camera], images: Tensor, image_ids: Sequence[int], backgrounds: Tensor
                 ) -> Dict[str, Tensor]:
    """A batch as gsplat's Dataset gives it: camtoworld [C, 4, 4], K [C, 3, 3], image [C, H, W, 3]
    float in 0..255 (from `images` in [0, 1]), image_id [C], plus background [C, 3]."""
    if len({(c.width, c.height) for c in cameras}) != 1:
        raise ValueError(f"a batch needs one image size, got {sorted({(c.width, c.height) for c in cameras})} "
                         "(use a chunk_size of 1 for mixed sizes)")
    return {
        "camtoworld": torch.stack([c.camera_to_world for c in cameras]).float(),
        "K": torch.stack([c.K for c in cameras]).float(),
        "image": images * 255.0,
        "image_id": torch.tensor(list(image_ids), dtype=torch.long),
        "background": backgrounds.float(),
    }


class CameraViews:
    """The cameras of a training set that loads its own images: what a ViewSchedule needs of a
    scene (train_cameras, center, extent, points for the model-size estimate, background),
    without images. Build it with :func:`views_of`."""

    def __init__(self, cameras: Sequence[Camera], points: Optional[Tensor] = None,
                 background: Optional[Sequence[float]] = None):
        self.train_cameras = list(cameras)
        if not self.train_cameras:
            raise ValueError("the training set has no views")
        self.test_cameras: List[Camera] = []
        self.points = None if points is None or len(points) == 0 else torch.as_tensor(points)
        self.background = None if background is None else tuple(float(c) for c in background)
        self.center, self.extent = camera_normalization(self.train_cameras)

    def image(self, cam, factor=1):
        raise RuntimeError("this training set loads its own images: draw them through your DataLoader "
                           "(MVGSStrategy.batch_sampler / loader) and bring them to the level with at_level")


def _host(x) -> Tensor:
    """A float64 CPU tensor of an array or a tensor on any device (a Dataset may hold CUDA ones)."""
    return (x.detach().cpu() if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))).to(torch.float64)


def _camera(uid: int, name: str, camtoworld, K, width: int, height: int) -> Camera:
    return Camera(uid=uid, name=name, K=_host(K), world_to_camera=torch.linalg.inv(_host(camtoworld)),
                  width=int(width), height=int(height))


def views_of(data) -> Any:
    """What MVGSStrategy schedules: a package :class:`~mvgs_plugin.data.Scene` as it is; a
    gsplat-style Dataset (``.parser`` with ``camtoworlds``, ``camera_ids``, ``Ks_dict``,
    ``imsize_dict``, optional ``points``; ``.indices`` its split) read from its parser without
    loading an image; a sequence of :class:`~mvgs_plugin.camera.Camera`; or any map-style
    Dataset whose items are dicts with ``camtoworld`` [4, 4], ``K`` [3, 3] and ``image``
    [H, W, 3] (each item is read once). Dataset item i is view i."""
    if hasattr(data, "train_cameras") and hasattr(data, "image"):
        return data
    parser, indices = getattr(data, "parser", None), getattr(data, "indices", None)
    if parser is not None and indices is not None:
        names = getattr(parser, "image_names", None)
        cams = []
        for i, idx in enumerate(np.asarray(indices).tolist()):
            cid = parser.camera_ids[idx]
            w, h = parser.imsize_dict[cid]
            cams.append(_camera(i, names[idx] if names is not None else str(i), parser.camtoworlds[idx],
                                parser.Ks_dict[cid], w, h))
        points = getattr(parser, "points", None)
        return CameraViews(cams, None if points is None else torch.as_tensor(np.asarray(points)))
    if isinstance(data, (list, tuple)) and data and all(isinstance(c, Camera) for c in data):
        return CameraViews(data)
    if hasattr(data, "__getitem__") and hasattr(data, "__len__"):
        cams = []
        for i in range(len(data)):
            item = data[i]
            if not (isinstance(item, dict) and {"camtoworld", "K", "image"} <= set(item)):
                raise TypeError(f"item {i} of {type(data).__name__} is not a dict with camtoworld, K and image "
                                f"(got {type(item).__name__}{sorted(item) if isinstance(item, dict) else ''})")
            h, w = item["image"].shape[-3:-1]
            cams.append(_camera(i, str(i), item["camtoworld"], item["K"], w, h))
        return CameraViews(cams)
    raise TypeError(f"MVGSStrategy needs a Scene, a gsplat-style Dataset, a list of Cameras or a Dataset of "
                    f"camera dicts, got {type(data).__name__}")


def _clock_per_step(config: MVGSConfig, steps: int) -> float:
    """Clock units per single-view step of a run of `steps`: 1 on a step clock; on a work clock
    the ratio that keeps a step-valued setting at its fraction of the run."""
    return config.clock_length / steps if config.counts_work else 1.0


def adopt_strategy_clock(config: MVGSConfig, strategy: DefaultStrategy, steps: int) -> MVGSConfig:
    """`config` with the densification clock and threshold of `strategy` (set for a run of
    `steps` single-view steps): densify_from / densify_until / densify_every from refine_start_iter /
    refine_stop_iter / refine_every, opacity_reset_every and prune_large_after from reset_every
    (DefaultStrategy prunes by size once the step exceeds reset_every), grad_threshold from
    grow_grad2d. On a work clock each value keeps its fraction of the run (times
    config.clock_length / steps)."""
    r = _clock_per_step(config, steps)
    scale = lambda v, low: max(low, int(round(v * r)))  # noqa: E731
    return dataclasses.replace(
        config, densify_from=scale(strategy.refine_start_iter, 0),
        densify_until=scale(strategy.refine_stop_iter, 0), densify_every=scale(strategy.refine_every, 1),
        opacity_reset_every=scale(strategy.reset_every, 1), prune_large_after=scale(strategy.reset_every, 0),
        grad_threshold=float(strategy.grow_grad2d))


# config.prune_faint's statistics in the strategy state: blend weight, blended pixels, views that saw the row
BLEND_KEYS = ("mvgs_blend_weight", "mvgs_blend_pixels", "mvgs_blend_seen")

class MVGSStrategy(DefaultStrategy):
    """A gsplat DefaultStrategy driven by an MVGS ViewSchedule (see the module docstring).

    Args:
        strategy: a ``gsplat.strategy.DefaultStrategy`` (or subclass), configured as for the
            single-view run; it is not modified. Its fields are copied onto this object (read
            them here; setting them here changes nothing).
        scene: the training views: a package Scene, the trainer's own training Dataset (gsplat's
            or any whose items are camera dicts) or a list of Cameras (see :func:`views_of`).
            Dataset item i is view i: the sampler yields those indices.
        config: an MVGSConfig or a preset name (mvgs_plugin.config.PRESETS).
        steps: the run's length in steps (the loop's max_steps): the config is compressed to it
            with ``with_total_steps`` and the strategy's clock read as set for that many steps.
            None: the config's own length (30k steps for the presets).
        clock: "strategy" (adopt the strategy's clock and threshold, see adopt_strategy_clock)
            or "config" (keep the config's own).
        budget_growth_order: under a binding config.max_gaussians, the order in which growth
            candidates take the room left (the cap less the rows the refine keeps: those its
            prune removes are not grown from, and a small row that gsplat both duplicates and
            splits by its screen radius takes two places), as GS3DConfig.budget_growth_order:
            "score" (by the densify score alone), "inside-first" (candidates nearer the scene centre than the far
            line, FAR_RESET_FRACTION of the initial model's farthest mean, before those beyond it,
            each group by score) or "auto" (default: "score" on a forward-facing rig or without
            a scene centre, else "inside-first"). The far line is taken at the first
            check_sanity (before the run's first step, before the budget's cut), or at the first
            refine when the loop never called it.
        world_size_rule: the size prune's limit (it runs where DefaultStrategy's does: at a refine
            after the first reset period). "extent" (default, gsplat's): prune_scale3d x
            scene_scale for every row. "distance": prune_scale3d x max(scene_scale, d), d the
            row's distance from the scene centre (the rig's centre), as GS3DConfig.world_size_rule
            (the package trainer's default): a fixed angle as seen from the rig, so a far
            background (a shell of points at twice the rig's radius, sky, a far wall) keeps the
            large Gaussians a camera sees as small instead of losing them all at the first
            refine after a reset. The wrapped strategy's own prune runs with its 3D size rule
            off and the rows above the distance limit are removed after it (gsplat's
            ops.remove): the same rows a single prune with that limit removes.
        opacity_reset_scope: "all" (default, gsplat's ops.reset_opa: every opacity capped at
            2 x prune_opa) or "inside": the same reset, but the rows beyond the far line
            (FAR_RESET_FRACTION of the initial model's farthest mean from the scene centre,
            taken as for budget_growth_order) keep their opacities, as GS3DConfig's "inside"
            (the package trainer's default). The opacities' Adam moments are zeroed for every
            row either way (ops.reset_opa's).
        Both rules are off by default: a wrapped strategy prunes and resets as gsplat's.
        prune_faint: None or 0 (off, whatever the config says: the default preset's
            MVGSConfig.prune_faint is not taken, since the cut needs a rasterizer output gsplat's
            has not) or S in (0, 1): config.prune_faint, the one cut of the faintest Gaussians
            after the refine window (MVGSConfig.prune_faint). The loop's rasterizer must report
            blend statistics: pass ``**strategy.rasterize_kwargs`` to the reference renderer's
            rasterization (``blend_stats=True``). Off: nothing is asked or collected.

    Attributes: ``schedule`` (the ViewSchedule), ``config``, ``total_steps``, ``plan`` (the
    current step's StepPlan), ``budget_growth_order`` (resolved: "score" or "inside-first"),
    ``far_distance`` (None until taken), ``world_size_rule``, ``rasterize_kwargs``, ``faint_removed``, ``opacity_reset_scope``,
    ``kept_by_distance`` (rows the extent rule would have pruned that the distance rule kept, over
    the run), ``spared_by_reset`` (rows a reset left alone, summed over the resets), ``most_held``
    (the largest count a step's render calls reported, over the run), and after each
    refine ``last_refine`` (dict: step, threshold, boxes, from_boxes, before, after,
    kept_by_distance).
    """

    def __init__(self, strategy: DefaultStrategy, scene, config: Union[MVGSConfig, str] = "default",
                 steps: Optional[int] = None, clock: str = "strategy", budget_growth_order: str = "auto",
                 world_size_rule: str = "extent", opacity_reset_scope: str = "all", prune_faint: Optional[float] = None):
        if isinstance(strategy, MVGSStrategy):
            raise TypeError("strategy is already an MVGSStrategy: wrap the DefaultStrategy itself, once")
        if not isinstance(strategy, DefaultStrategy):
            raise TypeError(f"MVGSStrategy wraps gsplat's DefaultStrategy (gradient-threshold densification), got "
                            f"{type(strategy).__name__}: MVAD and cross-ray densification act on that threshold and "
                            "clone step; an MCMC-style strategy has neither")
        if strategy.key_for_gradient != "means2d":
            raise ValueError(f"strategy.key_for_gradient must be 'means2d' (3DGS screen-space gradients), got "
                             f"{strategy.key_for_gradient!r}")
        if clock not in ("strategy", "config"):
            raise ValueError(f"clock must be 'strategy' or 'config', got {clock!r}")
        if budget_growth_order not in BUDGET_GROWTH_ORDERS:
            raise ValueError(f"budget_growth_order must be one of {', '.join(map(repr, BUDGET_GROWTH_ORDERS))}, "
                             f"got {budget_growth_order!r}")
        if world_size_rule not in WORLD_SIZE_RULES:
            raise ValueError(f"world_size_rule must be one of {', '.join(map(repr, WORLD_SIZE_RULES))}, "
                             f"got {world_size_rule!r}")
        if opacity_reset_scope not in OPACITY_RESET_SCOPES:
            raise ValueError(f"opacity_reset_scope must be one of {', '.join(map(repr, OPACITY_RESET_SCOPES))}, "
                             f"got {opacity_reset_scope!r}")
        if torch.distributed.is_available() and torch.distributed.is_initialized() and torch.distributed.get_world_size() > 1:
            raise RuntimeError(f"MVGSStrategy runs in one process: under gsplat's distributed mode "
                               f"({torch.distributed.get_world_size()} ranks) every rank's schedule would draw the same "
                               "views; the package's own trainers run MVGS on several processes (docs/distributed.md)")
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
            raise ValueError(f"steps must be a positive int (the loop's max_steps), got {steps!r}")
        if isinstance(config, str):
            config = MVGSConfig.from_preset(config)
        if not isinstance(config, MVGSConfig):
            raise TypeError(f"config must be an MVGSConfig or a preset name, got {type(config).__name__}")
        config = dataclasses.replace(config, prune_faint=prune_faint or 0.0)  # asked for here, not by a preset
        if config.stage_growth is not None:
            raise ValueError(f"config.stage_growth={config.stage_growth!r}: gsplat's DefaultStrategy has no cap on "
                             "how far a refine may grow the count; use stage_growth=None")
        if config.views_scaling != "none":
            raise ValueError(f"config.views_scaling={config.views_scaling!r}: your loop owns the optimizers, so scale "
                             "them yourself (learning rates x sqrt(M), betas ** M, eps / sqrt(M)); use views_scaling='none'")
        for f in dataclasses.fields(DefaultStrategy):  # isinstance checks and field reads (absgrad) keep working
            setattr(self, f.name, getattr(strategy, f.name))
        views = views_of(scene)
        config = config.for_scene(views)  # before the rescaling: a forward-facing rig keeps the step count
        if steps is not None:
            config = config.with_total_steps(steps)
        run_steps = config.total_steps
        if clock == "strategy":
            if strategy.refine_start_iter >= run_steps:  # gsplat's defaults are set for 30k steps
                warnings.warn(f"the strategy's refine window starts at step {strategy.refine_start_iter}, at or after "
                              f"the run's {run_steps} steps: this run never densifies; scale the DefaultStrategy's "
                              "refine_start_iter / refine_stop_iter / refine_every / reset_every to the run, or pass "
                              "clock='config' (the config's own clock, compressed to the run)", stacklevel=2)
            config = adopt_strategy_clock(config, strategy, run_steps)
        elif strategy.grow_grad2d != config.grad_threshold:  # the config's clock takes the config's threshold too
            warnings.warn(f"clock='config' uses the config's densification threshold ({config.grad_threshold:g}), not the "
                          f"strategy's grow_grad2d={strategy.grow_grad2d:g}"
                          f"{' (absgrad statistics are larger)' if strategy.absgrad else ''}; to keep yours, pass "
                          f"dataclasses.replace(config, grad_threshold={strategy.grow_grad2d:g})", stacklevel=2)
        r = _clock_per_step(config, run_steps)
        self._scale2d_until = strategy.refine_scale2d_stop_iter * r
        self._pause = strategy.pause_refine_after_reset * r
        self.strategy = strategy
        self.config = config
        self.views = views
        self.schedule = ViewSchedule(views, config, load_images=not isinstance(views, CameraViews))
        self.last_refine: Optional[Dict[str, Any]] = None
        self.faint_removed = 0  # rows the prune_faint cut removed
        self.plan: Optional[StepPlan] = None
        self._before: Optional[Dict[str, Any]] = None  # the schedule's state before the current plan
        self._queue: collections.deque = collections.deque()  # (plan, schedule state before it) drawn ahead
        self._targets: Optional[Tensor] = None  # the step's targets [M, H, W, 3] in [0, 1], for CRD
        self._reported = 0  # views of the current step reported to step_post_backward
        self._pending: Optional[Dict[str, Any]] = None  # end-of-step work deferred to the next batch
        self._warned: set = set()
        self._shares: Dict[int, List[Tensor]] = {}
        self._order_given = budget_growth_order != "auto"
        center = getattr(views, "center", None)
        self.scene_center: Optional[Tensor] = None if center is None else torch.as_tensor(center, dtype=torch.float64).reshape(3)
        if self.scene_center is None:  # no far line to order by
            budget_growth_order = "score"
        elif budget_growth_order == "auto":  # the rig decides, as GS3DAdapter.from_scene
            budget_growth_order = "score" if is_forward_facing(views.train_cameras) else "inside-first"
        self.budget_growth_order = budget_growth_order
        self.far_distance: Optional[float] = None
        self.world_size_rule, self.opacity_reset_scope = world_size_rule, opacity_reset_scope
        self.kept_by_distance, self.spared_by_reset = 0, 0
        self.most_held = 0  # the largest count a step rendered

    @property
    def total_steps(self) -> int:
        return self.schedule.total_steps

    # ---- gsplat's Strategy interface ----------------------------------------------------
    def check_sanity(self, params, optimizers) -> None:
        """The wrapped strategy's check; with config.max_gaussians, a model above the budget is
        cut to it here (gsplat's trainers call this once, before the first render; before the
        first step, to config.initial_cap()): its lowest keep scores go (see keep_scores). A cut
        before the first step also re-sizes the kept Gaussians to the spacing of the kept means:
        each log-scale moves by the change of log(root mean squared distance to the 3 nearest
        means), so a trainer's own initial factor stays and the thinned model has no holes (as
        GS3DAdapter.densify). After the first step a model above the budget is a ValueError: the
        rows' statistics are in a strategy state this call does not get."""
        self.strategy.check_sanity(params, optimizers)
        sched = self.schedule
        # before the run's first step (plans a DataLoader drew ahead have not started)
        first = self.plan is None and (self._queue[0][1]["step"] if self._queue else sched.step_count) == 0
        budget = self.config.initial_cap() if first else self.config.max_gaussians
        if first and self.far_distance is None:  # the far line of budget_growth_order: the initial model's
            self.far_distance = farthest_distance(params["means"], self.scene_center)  # farthest mean, before the cut
        if budget is not None and len(params["means"]) > budget:
            if not first:  # the rows' statistics live in a state this call is not given: cutting would misalign them
                raise ValueError(f"check_sanity after the run's first step: the model holds {len(params['means'])} "
                                 f"Gaussians, above max_gaussians={budget}; a budgeted run never holds more (resume "
                                 "from a checkpoint of this budget, or cut the model before training)")
            spacing = spacing_log_scale(params["means"])
            shed = self._shed(params, optimizers, {}, budget)
            with torch.no_grad():
                change = spacing_log_scale(params["means"]) - spacing[~shed]
                params["scales"].add_(change[:, None].to(params["scales"]))
        if first:  # the budget's growth schedule starts from the count the run starts with
            sched.primitive_count = len(params["means"])
            if sched.initial_count is not None:  # taken by a plan drawn ahead, before the cut
                sched.initial_count = sched.primitive_count

    @staticmethod
    def keep_scores(params, state: Optional[Dict[str, Any]] = None, center: Optional[Tensor] = None) -> Tensor:
        """[N] the order in which Gaussians are kept when the model must shrink to the budget
        (largest kept): opacity times the summed footprint of the window's views (pi radius^2 /
        (W H) per visit, state["mvgs_coverage"]) when any was folded in, else opacity times
        gs3d.even_cut_order(means, center) (the strategy passes its scene centre: inside and
        beyond the far line each keep their share, spread over their extent), as
        GS3DAdapter.keep_scores."""
        opacity = torch.sigmoid(params["opacities"].detach().reshape(-1))
        coverage = None if state is None else state.get("mvgs_coverage")
        if not (isinstance(coverage, Tensor) and len(coverage) == len(opacity)):
            coverage = torch.zeros_like(opacity)
        return keep_scores_of(opacity, coverage, params["means"], center)

    def _shed(self, params, optimizers, state, cap: int) -> Tensor:
        """Remove the lowest keep scores down to `cap` (gsplat's ops.remove); returns the [N] bool
        mask of the rows removed (over the rows before the call)."""
        excess = len(params["means"]) - cap
        mask = torch.zeros(len(params["means"]), dtype=torch.bool, device=params["means"].device)
        if excess > 0:
            mask[torch.sort(self.keep_scores(params, state, self.scene_center), stable=True).indices[:excess]] = True
            remove(params=params, optimizers=optimizers, state=state, mask=mask)
        return mask

    def initialize_state(self, scene_scale: float = 1.0) -> Dict[str, Any]:
        return self.strategy.initialize_state(scene_scale=scene_scale)

    @property
    def rasterize_kwargs(self) -> Dict[str, Any]:
        """Keyword arguments the loop's rasterizer call needs: {"blend_stats": True} with
        config.prune_faint (the reference renderer's blend statistics, for the cut), else {}."""
        return {"blend_stats": True} if self.config.prune_faint > 0 else {}

    def step_pre_backward(self, params, optimizers, state: Dict[str, Any], step: int, info: Dict[str, Any]) -> None:
        """As the wrapped strategy's (keeps the screen-space gradient of info["means2d"])."""
        self.strategy.step_pre_backward(params, optimizers, state, step, info)

    def step_post_backward(self, params, optimizers, state: Dict[str, Any], step: int, info: Dict[str, Any],
                           packed: bool = False, renders: Optional[Tensor] = None) -> None:
        """Fold one render call's statistics into `state`; once the step's M views are reported,
        refine and reset opacities when the schedule says so (now, or at the next step's batch
        when gradients are still unused: call it before or after the optimizer step).

        info: the render call's info; its ``n_cameras`` views are the next of the step's views
        (the whole step, or one chunk). renders: the call's rendered colours [C, H, W, 3]
        (optional; cross-ray densification needs them). step: the loop's step, for log lines.
        """
        plan = self.plan
        if plan is None:
            raise RuntimeError("step_post_backward before the step's batch was brought to its level: draw batches "
                               "from strategy.loader(...) or strategy.batches(), or call strategy.at_level(pixels, Ks) "
                               "on each batch of strategy.batch_sampler()")
        m = len(plan.views)
        c = int(info.get("n_cameras", 1))
        if self._reported + c > m:
            raise RuntimeError(f"step {step}: step_post_backward reported {self._reported + c} views for a step of "
                               f"{m}; call it once per render call of the step's views")
        last_call = self._reported + c == m
        self.most_held = max(self.most_held, len(params["means"]))  # the count this call rendered
        collect = any(plan.stats) and (self.config.stats_from == "all" or last_call)
        if collect and self.config.stats_from == "last" and c > 1 and "last" not in self._warned:
            self._warned.add("last")
            warnings.warn(f"stats_from='last' takes the statistics of the step's last render call, here {c} views: "
                          "render the last view alone (chunks() or batches(chunked=True)) for the paper's rule",
                          stacklevel=2)
        if collect:
            self._check_views(info, packed, c, m, step)
            full = info if c == m else {**info, "n_cameras": m}
            self._call_strategy(params, optimizers, state, full, packed, refine=None)
            if self.config.max_gaussians is not None:
                self._score_statistics(state, full, packed, len(params["means"]))
            if self.config.prune_faint > 0:
                self._blend_statistics(state, info, len(params["means"]), step)
        if renders is not None and plan.wants_maps and self._targets is not None:
            targets = self._targets[self._reported:self._reported + c]
            if tuple(renders.shape[:3]) != tuple(targets.shape[:3]):
                raise ValueError(f"renders must be the call's colours [{', '.join(map(str, targets.shape))}], got "
                                 f"{list(renders.shape)}")
            plan.record(list(renders[..., :3].detach()), list(targets.to(renders.device)))
        self._reported += c
        if last_call:
            self._end_of_step(params, optimizers, state, step)
            self.schedule.primitive_count = len(params["means"])  # the next step's chunk size

    # ---- the data: the user's Dataset, or the package's Scene -----------------------------------
    def batch_sampler(self) -> "MVGSBatchSampler":
        """Indices into the training Dataset, one list per step (the step's M views), for
        ``DataLoader(trainset, batch_sampler=strategy.batch_sampler(), ...)``. Each batch it
        yields must go through :meth:`at_level` before rendering (in order: workers may load
        ahead, the plans wait in a queue). A DataLoader stacks a step's images into one tensor
        and at_level takes one, so a plan with several views per step on a training set of
        several image sizes is refused here, naming the sizes."""
        multi = [s for s in self.config.stages if s.views > 1]
        sizes = collections.Counter((c.width, c.height) for c in self.views.train_cameras)
        if multi and len(sizes) > 1:
            listed = ", ".join(f"{w}x{h} ({n} views)" for (w, h), n in sorted(sizes.items()))
            most = min(max(s.views for s in multi), len(self.views.train_cameras))
            raise ValueError(f"the plan draws up to {most} views per step, and a DataLoader stacks a step's images "
                             f"into one tensor, but this training set has images of {len(sizes)} sizes: "
                             f"{listed}; use a plan of one view per step (the default and baseline presets) or "
                             "resize the images to one size")
        return MVGSBatchSampler(self)

    def loader(self, data, **dataloader_kwargs) -> "MVGSLoader":
        """The user's DataLoader (or Dataset) drawing the schedule's views at the step's level:
        a DataLoader is rebuilt on its dataset with the same workers, collate_fn, pinning and
        prefetching and ``batch_sampler=self.batch_sampler()``; each batch dict then goes through
        :meth:`at_level_dict`. Iterating it is the loop's ``next(trainloader_iter)``."""
        return MVGSLoader(self, data, **dataloader_kwargs)

    def batches(self, chunked: bool = False) -> "MVGSBatches":
        """The training data from a package Scene, one step at a time (see MVGSBatches)."""
        if isinstance(self.views, CameraViews):
            raise RuntimeError("batches() reads the package's Scene; this strategy was given a Dataset that loads its "
                               "own images: use loader(trainloader) or batch_sampler() with at_level()")
        return MVGSBatches(self, chunked)

    def at_level(self, pixels: Tensor, Ks: Tensor, image_ids: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """The batch the batch sampler's next list loaded, at the step's pyramid level: pixels
        [C, H, W, ch] resampled as the package's pyramid (any value range; pass them as the loss
        sees them, in [0, 1], for cross-ray densification) and Ks [C, 3, 3] with the x row times
        W'/W and the y row times H'/H. image_ids (optional, [C]) are checked against the views
        the schedule drew. Starts the step: call it once per step, before rendering."""
        self._close_step()
        plan, before = self._next_queued(len(pixels), image_ids)
        out_pixels, out_Ks = self._scale(plan, pixels, Ks)
        self._start(plan, out_pixels, before, out_Ks)
        return out_pixels, out_Ks

    def at_level_dict(self, data: Dict[str, Any]) -> Dict[str, Any]:
        """:meth:`at_level` for a gsplat Dataset batch dict: ``image`` (0..255) and ``K`` at the
        step's level, plus ``mask`` [C, H, W] (resampled, then > 0.5) and depth-loss ``points``
        [C, P, 2] (pixel coordinates scaled) when present; other keys as they are. With a mask,
        a coarse level's image is the weighted mean of the kept pixels, downsample(image x mask)
        / downsample(mask) (0 where none reaches), as the package's own pyramid makes it
        (Scene.image), so a pixel the mask hides gives its colour to no level."""
        pixels = data["image"]
        self._close_step()
        plan, before = self._next_queued(len(pixels), data.get("image_id"))
        out = dict(data)
        out["image"], out["K"] = self._scale(plan, pixels, data["K"])
        h, w = pixels.shape[1:3]
        h2, w2 = out["image"].shape[1:3]
        if isinstance(data.get("mask"), Tensor):
            if (w2, h2) == (w, h):
                out["mask"] = data["mask"].bool()
            else:
                keep = data["mask"].to(pixels.dtype if pixels.is_floating_point() else torch.float32)[..., None]
                out["image"], weight = masked_downsample(pixels, keep, lambda x: downsample_batch(x, w2, h2))
                out["mask"] = weight[..., 0] > 0.5
        if isinstance(data.get("points"), Tensor):
            out["points"] = data["points"] * torch.tensor([w2 / w, h2 / h], dtype=data["points"].dtype,
                                                           device=data["points"].device)
        self._start(plan, out["image"] / 255.0, before, out["K"])
        return out

    def chunks(self) -> List[Tuple[slice, float]]:
        """The current step's render calls: (slice of the batch's views, weight of that chunk's
        mean loss = len / M). The schedule's chunk size (config.chunk_size, or what
        config.chunk_memory_mb allows for the model's size); the last view alone with
        stats_from="last". Weighting each chunk's mean loss so gives the unchunked step's
        parameter gradients, and the wrapper gives the strategy the unchunked statistics."""
        if self.plan is None:
            raise RuntimeError("chunks() describes the current step: bring its batch to its level first")
        m = len(self.plan.views)
        return [(slice(c[0], c[-1] + 1), len(c) / m) for c in self.plan.chunks]

    def _next_queued(self, n: int, image_ids) -> Tuple[StepPlan, Dict[str, Any]]:
        if not self._queue:
            raise RuntimeError("at_level with no batch drawn: build the DataLoader with "
                               "batch_sampler=strategy.batch_sampler() (or use strategy.loader(trainloader))")
        plan, before = self._queue.popleft()
        if n != len(plan.views):
            raise ValueError(f"the batch has {n} views but the step drew {len(plan.views)} ({plan.views}): load it "
                             "with the DataLoader built on strategy.batch_sampler()")
        if image_ids is not None and [int(i) for i in torch.as_tensor(image_ids).reshape(-1).tolist()] != plan.views:
            raise ValueError(f"the batch holds views {torch.as_tensor(image_ids).tolist()} but the step drew "
                             f"{plan.views}: batches must arrive in the order the batch sampler gave them")
        return plan, before

    def _scale(self, plan: StepPlan, pixels: Tensor, Ks: Tensor) -> Tuple[Tensor, Tensor]:
        if pixels.ndim != 4:
            raise ValueError(f"pixels must be [C, H, W, channels], got {list(pixels.shape)}")
        if tuple(Ks.shape) != (len(pixels), 3, 3):
            raise ValueError(f"Ks must be [{len(pixels)}, 3, 3], got {list(Ks.shape)}")
        h, w = pixels.shape[1:3]
        w2, h2 = scaled_size(w, h, plan.factor)
        if (w2, h2) == (w, h):
            return pixels, Ks
        Ks = Ks.clone()
        Ks[:, 0, :] *= w2 / w
        Ks[:, 1, :] *= h2 / h
        return downsample_batch(pixels, w2, h2), Ks

    def _close_step(self) -> None:
        """Before the next step takes its plan: the current step must be complete (checked first,
        so a refused call loses no plan), and end-of-step work deferred to this moment runs."""
        if self.plan is not None and self._reported < len(self.plan.views):
            raise RuntimeError(f"step {self.plan.step} of the schedule: step_post_backward reported {self._reported} of "
                               f"its {len(self.plan.views)} views before the next batch was drawn; call it after each "
                               "render call's backward")
        if self._pending is not None:
            self._run_pending()

    def _start(self, plan: StepPlan, targets: Optional[Tensor], before: Dict[str, Any],
               Ks: Optional[Tensor] = None) -> None:
        """Begin `plan` (after _close_step). With the loop's batch (targets [M, H, W, 3] and the
        Ks it renders with), the plan's cameras become the views as rendered: that size and K.
        A parser's imsize_dict can be a pixel off its images (gsplat's Parser scales it with a
        truncating int()), and the loss maps of cross-ray densification are the renders' size."""
        if Ks is not None and targets is not None:
            h, w = targets.shape[1:3]
            plan.cameras = [dataclasses.replace(cam, K=_host(k), width=int(w), height=int(h))
                            for cam, k in zip(plan.cameras, Ks)]
        self.plan, self._targets, self._reported, self._before = plan, targets, 0, before

    def _draw(self) -> StepPlan:
        """The schedule's next plan, queued with the schedule's state before it."""
        sched = self.schedule
        if sched.step_count >= sched.total_steps:
            raise RuntimeError(f"the schedule's {sched.total_steps} steps are all drawn: the loop runs longer than the "
                               "steps MVGSStrategy was built with (pass steps=max_steps)")
        before = sched.state_dict()
        plan = sched.next()
        self._queue.append((plan, before))
        return plan

    def _rewind(self) -> None:
        """Forget plans drawn ahead but never brought to a level (an abandoned DataLoader
        iterator): the schedule goes back to where the first of them started."""
        if self._queue:
            self.schedule.load_state_dict(self._queue[0][1])
            self._queue.clear()

    # ---- what runs between steps -------------------------------------------------------------
    def _end_of_step(self, params, optimizers, state, step) -> None:
        plan, cfg = self.plan, self.config
        densify = plan.faint_cut or (plan.densify and not (self._pause > 0
                                                           and plan.clock % cfg.opacity_reset_every < self._pause))
        nxt = plan.step + 1
        handoff = (cfg.opacity_reset_at_handoff and nxt <= self.total_steps
                   and self.schedule.plan.locate(nxt).first_in_stage)
        if not (densify or plan.reset_opacity or handoff) or plan.step >= self.total_steps:
            return  # (after the run's last step nothing trains what a refine or reset would change)
        work = {"plan": plan, "before": self._before, "densify": densify, "reset": plan.reset_opacity or handoff, "step": step,
                "params": params, "optimizers": optimizers, "state": state}
        if _live_gradients(params):  # before the optimizer step: after it, at the next batch
            self._pending = work
        else:
            self._apply(work)

    def _run_pending(self) -> None:
        work, self._pending = self._pending, None
        live = _live_gradients(work["params"])
        if live:
            raise RuntimeError(f"step {work['step']}: a refine waits for the gradients of {live} to be used, but the "
                               "next batch was drawn first; step the optimizers (and zero their gradients) every step")
        self._apply(work)
        self.schedule.primitive_count = len(work["params"]["means"])

    def _apply(self, work: Dict[str, Any]) -> None:
        params, optimizers, state = work["params"], work["optimizers"], work["state"]
        with torch.no_grad():
            if work["densify"]:
                self._refine(params, optimizers, state, work["plan"], work["step"])
            if work["reset"]:
                spared = self._reset_opacities(params, optimizers, state)
                if self.verbose:
                    print(f"Step {work['step']}: opacities reset to {self.strategy.prune_opa * 2.0:g}"
                          + (f" ({spared} beyond the far line spared)." if spared else "."))

    def _score_statistics(self, state, info, packed: bool, n: int) -> None:
        """The budget's statistics beside gsplat's grad2d and count, from the same gradient
        (absgrad when the strategy uses it, scaled as gsplat scales it): the squared norm per
        visit (mvgs_grad2d_sq, for consistency) and the footprint share pi r^2 / (W H)
        (mvgs_coverage, for keep_scores). gsplat's ops carry them through grow and prune."""
        means2d = info["means2d"]
        grads = (means2d.absgrad if self.strategy.absgrad else means2d.grad).detach().clone()
        w, h, cams = info["width"], info["height"], info["n_cameras"]
        grads[..., 0] *= w / 2.0 * cams
        grads[..., 1] *= h / 2.0 * cams
        radii = info["radii"]
        if packed:  # [nnz, 2] rows, as gsplat counts them
            ids = info["gaussian_ids"]
            norms, r = grads.norm(dim=-1), radii.reshape(len(ids), -1).max(-1).values
        else:
            sel = (radii > 0).reshape(*radii.shape[:2], -1).all(-1)
            ids = torch.where(sel)[1]
            norms, r = grads[sel].norm(dim=-1), radii[sel].reshape(int(sel.sum()), -1).max(-1).values
        for key in ("mvgs_grad2d_sq", "mvgs_coverage"):
            if not isinstance(state.get(key), Tensor) or len(state[key]) != n:
                state[key] = torch.zeros(n, device=grads.device)
        state["mvgs_grad2d_sq"].index_add_(0, ids, norms.square().to(state["mvgs_grad2d_sq"]))
        state["mvgs_coverage"].index_add_(0, ids, (math.pi * r.float().square() / float(w * h)).to(state["mvgs_coverage"]))

    def _blend_statistics(self, state, info, n: int, step) -> None:
        """config.prune_faint's statistics: the blend weight and blended pixels the rasterizer
        reported (info "blend_weight", "blend_pixels" [C, N]) and the views that saw each row
        (radius > 0), summed in state (mvgs_blend_weight, mvgs_blend_pixels, mvgs_blend_seen;
        gsplat's ops carry them through grow and prune) since the last refine (each refine
        restarts them, as the package adapters' densification restarts theirs), so the cut
        judges the views after the window's last refine."""
        if "blend_weight" not in info or "blend_pixels" not in info:
            raise ValueError(f"step {step}: config.prune_faint={self.config.prune_faint} needs the blend statistics of "
                             "every render call: pass **strategy.rasterize_kwargs (blend_stats=True) to the reference "
                             "renderer's rasterization")
        weight, pixels = info["blend_weight"], info["blend_pixels"]
        seen = (info["radii"] > 0).reshape(*info["radii"].shape[:2], -1).all(-1)
        for key, value in zip(BLEND_KEYS, (weight, pixels, seen)):
            if not isinstance(state.get(key), Tensor) or len(state[key]) != n:
                state[key] = torch.zeros(n, device=weight.device)
            state[key] += value.detach().to(state[key]).reshape(-1, n).sum(0)

    def _faint_cut(self, params, optimizers, state, plan: StepPlan, step) -> None:
        """The one cut of config.prune_faint (the plan's faint_cut): gs3d.faint_rows over the
        blend statistics folded in since the refine window closed, removed with gsplat's
        ops.remove (parameters, Adam moments and state together)."""
        n = len(params["means"])
        weight, pixels, seen = (state.get(k) for k in BLEND_KEYS)
        if not (isinstance(weight, Tensor) and len(weight) == n and float(weight.sum()) > 0):
            raise ValueError(f"step {step}: config.prune_faint's cut found no blend statistics: the loop's rasterizer "
                             "must report them (**strategy.rasterize_kwargs)")
        faint = faint_rows(weight, pixels, seen > 0, self.config.prune_faint)
        if bool(faint.any()):
            remove(params, optimizers, state, faint.to(params["means"].device))
        for key in BLEND_KEYS:
            state.pop(key, None)
        self.faint_removed += int(faint.sum())
        self.last_refine = {"step": plan.step, "loop_step": step, "clock": plan.clock, "before": n,
                            "after": len(params["means"]), "faint": int(faint.sum())}
        if self.verbose:
            print(f"Step {step}: {int(faint.sum())} faintest GSs removed. Now having {len(params['means'])} GSs.")

    def _fate(self, params, state, threshold: float, prune_large: bool, scale2d: bool) -> Tuple[Tensor, Tensor, Tensor]:
        """What the wrapped strategy's refine does to each row, decided as gsplat 1.5.3's
        DefaultStrategy decides it: ([N] grows: a mean grad2d above `threshold` or, with
        `scale2d`, a screen radius above grow_scale2d; [N] the rows it adds if they grow: 2 for
        a small row that is both duplicated and split by its screen radius, else 1; [N] removed
        for certain whatever they grow: an opacity under prune_opa or, with `prune_large`, a
        screen radius above prune_scale2d (`scale2d`) or too large in the world (world_size_rule)
        without growing (copies inherit opacity and radius, ops.duplicate / ops.split; a split's
        children are smaller, so a large row that grows is not counted))."""
        s, n = self.strategy, len(params["means"])
        dev = params["means"].device
        grad2d, count, radii = state.get("grad2d"), state.get("count"), state.get("radii")
        high = torch.zeros(n, dtype=torch.bool, device=dev)
        if isinstance(grad2d, Tensor) and len(grad2d) == n:
            high = (grad2d / count.clamp_min(1) > threshold).to(dev)
        radii = radii.to(dev) if scale2d and isinstance(radii, Tensor) and len(radii) == n else None
        wide = radii > s.grow_scale2d if radii is not None else torch.zeros_like(high)
        scale = torch.exp(params["scales"].detach()).max(-1).values
        small = scale <= s.grow_scale3d * float(state["scene_scale"])
        grow = high | wide
        cost = 1 + (high & small & wide).long()
        doomed = torch.sigmoid(params["opacities"].detach().reshape(-1)) < s.prune_opa
        if prune_large:
            doomed = doomed | ((scale > self._size_limit(params, state)) & ~grow)
            if radii is not None:
                doomed = doomed | (radii > s.prune_scale2d)
        return grow, cost, doomed

    def _size_limit(self, params, state) -> Tensor:
        """[N] the largest world scale the size prune keeps per row (world_size_rule):
        prune_scale3d x scene_scale, or with "distance" x max(scene_scale, distance from the
        scene centre)."""
        return world_size_limit(params["means"].detach(), float(state["scene_scale"]), self.scene_center,
                                self.world_size_rule, self.strategy.prune_scale3d)

    def _prune_by_distance(self, params, optimizers, state) -> int:
        """world_size_rule "distance" at a refine with size pruning: remove the rows whose
        largest scale is above the distance limit (the strategy's own prune ran without its 3D
        size rule). Returns how many rows the extent rule would also have removed but this one
        keeps (added to kept_by_distance)."""
        scale = torch.exp(params["scales"].detach()).max(-1).values
        too_big = scale > self._size_limit(params, state)
        kept = int(((scale > self.strategy.prune_scale3d * float(state["scene_scale"])) & ~too_big).sum())
        if bool(too_big.any()):
            remove(params=params, optimizers=optimizers, state=state, mask=too_big)
        self.kept_by_distance += kept
        return kept

    def _take_far_line(self, means: Tensor) -> None:
        """far_distance from `means` when no check_sanity took it before the run's first step (a
        loop that never calls it): the first refine or reset that needs the far line takes it."""
        if self.far_distance is None:
            self.far_distance = farthest_distance(means, self.scene_center)

    def _far_rows(self, params) -> Optional[Tensor]:
        """bool per row: beyond the far line; None without a scene centre."""
        self._take_far_line(params["means"])
        return beyond_far_line(params["means"].detach(), self.scene_center, self.far_distance)

    def _reset_opacities(self, params, optimizers, state) -> int:
        """gsplat's ops.reset_opa at 2 x prune_opa; with opacity_reset_scope "inside" the rows
        beyond the far line get their opacities back (their Adam moments zeroed as every row's).
        Returns how many were spared."""
        spared = self._far_rows(params) if self.opacity_reset_scope == "inside" else None
        kept = None if spared is None else params["opacities"].detach()[spared].clone()
        reset_opa(params=params, optimizers=optimizers, state=state, value=self.strategy.prune_opa * 2.0)
        if spared is None or not len(kept):
            return 0
        params["opacities"].data[spared] = kept
        self.spared_by_reset += len(kept)
        return len(kept)

    def _rank_growth(self, state, threshold: float, room: int, means: Optional[Tensor] = None,
                     grow: Optional[Tensor] = None, cost: Optional[Tensor] = None) -> int:
        """Keep only the growth candidates (`grow`, default: mean gradient > threshold) with the
        best densify score (config.densify_rank, as GS3DAdapter.densify_scores; with
        budget_growth_order "inside-first" and the rows' `means`, those inside the far line
        before any beyond it) whose rows added (`cost`, default 1 each) fit in `room`, the
        longest such prefix: the others' grad2d is zeroed and their screen radius held at
        grow_scale2d before the strategy's refine, so it grows none of them. Returns how many
        fell."""
        grad2d, count = state.get("grad2d"), state.get("count")
        if not isinstance(grad2d, Tensor):
            return 0
        mean = grad2d / count.clamp_min(1)
        cand = mean > threshold if grow is None else grow
        cost = torch.ones(len(mean), dtype=torch.long, device=mean.device) if cost is None else cost.to(mean.device)
        if int(cost[cand].sum()) <= room:
            return 0
        score = mean
        sq = state.get("mvgs_grad2d_sq")
        if self.config.densify_rank == "consistency" and isinstance(sq, Tensor) and len(sq) == len(mean):
            score = mean * consistency_of(grad2d, sq, count)
        idx = cand.nonzero().squeeze(1)
        far = (beyond_far_line(means, self.scene_center, self.far_distance) if self.budget_growth_order == "inside-first"
               and means is not None and len(means) == len(mean) else None)
        dropped = idx[~growth_that_fits(score[idx], cost[idx], room, None if far is None else far[idx])]
        grad2d[dropped] = 0
        radii = state.get("radii")
        if isinstance(radii, Tensor) and len(radii) == len(mean):  # not split by their screen size either
            radii[dropped] = radii[dropped].clamp_max(self.strategy.grow_scale2d)
        return len(dropped)

    def _refine(self, params, optimizers, state, plan: StepPlan, step) -> None:
        if plan.faint_cut:
            self._faint_cut(params, optimizers, state, plan, step)
            return
        means = params["means"].detach()
        bounds = torch.stack([means.amin(0), means.amax(0)]).double().cpu() if len(means) else None
        ctx = self.schedule.densify_context(plan, None, len(means), bounds)
        before = len(means)
        cap, dropped, shed, swapped = ctx.max_primitives, 0, 0, 0
        grad2d, count = state.get("grad2d"), state.get("count")
        boxes = ctx.boxes is not None and len(ctx.boxes) > 0
        # the boxes' clones are ranked by the window's gradient, before the cap zeroes some of it
        box_score = grad2d / count.clamp_min(1) if boxes and isinstance(grad2d, Tensor) else None
        doomed = None
        if cap is not None:  # growth ranked into the room the budget leaves (see _fate)
            if self.budget_growth_order == "inside-first":
                self._take_far_line(means)
            threshold = float(ctx.grad_threshold)
            scale2d = self.strategy.refine_scale2d_stop_iter > 0 and ctx.step < self._scale2d_until
            grow, cost, doomed = self._fate(params, state, threshold, ctx.prune_large, scale2d)
            if isinstance(grad2d, Tensor):  # what the prune removes is not grown from and leaves its room
                grad2d[doomed] = 0
            grow = grow & ~doomed
            room = max(0, cap - (before - int(doomed.sum())))
            swapped, kept = self._swap_out(params, optimizers, state, grow, cost, doomed, room, cap, ctx.swap_share)
            grow, cost, doomed = grow[kept], cost[kept], doomed[kept]
            box_score = None if box_score is None else box_score[kept]
            dropped = self._rank_growth(state, threshold, room + swapped, params["means"], grow, cost)
        from_boxes = 0
        if boxes:
            from_boxes = self._clone_in_boxes(params, optimizers, state, ctx.boxes, ctx.max_new_from_boxes,
                                              box_score, doomed)
            if self.verbose:
                print(f"Step {step}: {from_boxes} GSs copied in {len(ctx.boxes)} cross-ray boxes. "
                      f"Now having {len(params['means'])} GSs.")
        self._call_strategy(params, optimizers, state, None, False, refine=ctx, step=step)
        by_distance = 0
        if ctx.prune_large and self.world_size_rule == "distance":
            by_distance = self._prune_by_distance(params, optimizers, state)
        for key in BLEND_KEYS:  # prune_faint's window restarts too
            state.pop(key, None)
        if cap is not None:
            shed = int(self._shed(params, optimizers, state, cap).sum())  # the boxes' clones may have taken room
            for key in ("mvgs_grad2d_sq", "mvgs_coverage"):  # the window restarts, as gsplat's grad2d
                if isinstance(state.get(key), Tensor):
                    state[key] = torch.zeros(len(params["means"]), device=state[key].device)
        self.last_refine = {"step": plan.step, "loop_step": step, "clock": plan.clock,
                            "threshold": float(ctx.grad_threshold),
                            "boxes": 0 if ctx.boxes is None else len(ctx.boxes), "from_boxes": from_boxes,
                            "before": before, "after": len(params["means"]), "cap": cap,
                            "dropped_by_max_gaussians": dropped, "shed_to_cap": shed, "swapped": swapped,
                            "kept_by_distance": by_distance}

    def _swap_out(self, params, optimizers, state, grow: Tensor, cost: Tensor, doomed: Tensor, room: int, cap: int,
                  share: float) -> Tuple[int, Tensor]:
        """At a binding cap (the rows the growth candidates, `grow`, would add, `cost` each, exceed
        the room), remove up to floor(share x cap) of the lowest keep scores among the rows that
        neither grow nor are `doomed` by the refine's prune, as many as the growth exceeds the
        room (gsplat's ops.remove, state included), so that more candidates grow
        (MVGSConfig.budget_swap, as GS3DAdapter.densify). Returns how many, and the [N] mask of
        the rows kept."""
        n = len(params["means"])
        kept = torch.ones(n, dtype=torch.bool, device=grow.device)
        free = ~grow & ~doomed
        want = min(int(cost[grow].sum()) - room, math.floor(share * cap), int(free.sum())) if share > 0 else 0
        if want <= 0:
            return 0, kept
        score = torch.where(free, self.keep_scores(params, state, self.scene_center).to(grow.device),
                            torch.full((n,), math.inf, device=grow.device))
        kept[torch.sort(score, stable=True).indices[:want]] = False
        remove(params=params, optimizers=optimizers, state=state, mask=~kept)
        return want, kept

    def _clone_in_boxes(self, params, optimizers, state, boxes: Tensor, cap: Optional[int],
                        score: Optional[Tensor] = None, doomed: Optional[Tensor] = None) -> int:
        """Copy every Gaussian strictly inside a box but the `doomed` (rows the refine's prune
        removes; their copies would go with them) (at most `cap`, largest `score` first: the mean
        gradient, by default state's) with gsplat's ops.duplicate; the copies start with zero
        statistics, so the strategy's own grow step that follows acts on the originals only (as
        GS3DAdapter)."""
        sel = boxes_contain(params["means"], boxes)
        if doomed is not None:
            sel = sel & ~doomed.to(sel.device)
        if cap is not None:
            if score is None:
                grad2d, count = state.get("grad2d"), state.get("count")
                score = grad2d / count.clamp_min(1) if grad2d is not None else torch.zeros(len(sel))
            sel = top_by_score(sel, score, cap)
        n = int(sel.sum())
        if n:
            duplicate(params=params, optimizers=optimizers, state=state, mask=sel)
            for key in ("grad2d", "count", "radii"):
                if isinstance(state.get(key), Tensor):
                    state[key][-n:] = 0
        return n

    def _call_strategy(self, params, optimizers, state, info, packed: bool, refine, step=None) -> None:
        """The wrapped strategy's own step_post_backward on a copy whose clock fields make its
        conditions give the schedule's decision. Statistics only (refine None): at step 1 with
        refine_start_iter 1 (no refine: needs step > start) and refine_stop_iter 2 (statistics:
        step < stop). Refine (a DensifyContext): at step 3 with refine_start_iter 0, refine_every
        1, grow_grad2d = the step's threshold, reset_every 2 when size pruning is on (it needs
        step > reset_every) else 4, with an info that adds no statistics. Neither step is a
        multiple of its reset_every, so the strategy never resets opacities itself. Its verbose
        lines are printed with the loop's step."""
        s = self.strategy
        view = copy.copy(s)
        scale2d = s.refine_scale2d_stop_iter > 0
        view.pause_refine_after_reset = 0
        if refine is None:
            view.refine_start_iter, view.refine_stop_iter, view.refine_every, view.reset_every = 1, 2, 1, 2
            view.refine_scale2d_stop_iter = 2 if scale2d else 0
            view.step_post_backward(params, optimizers, state, 1, info, packed=packed)
            return
        view.refine_start_iter, view.refine_stop_iter, view.refine_every = 0, 4, 1
        view.reset_every = 2 if refine.prune_large else 4
        if self.world_size_rule == "distance":  # the 3D size rule runs after it (_prune_by_distance)
            view.prune_scale3d = math.inf
        view.grow_grad2d = float(refine.grad_threshold)
        view.refine_scale2d_stop_iter = (4 if refine.step < self._scale2d_until else 1) if scale2d else 0
        out = io.StringIO()
        with contextlib.redirect_stdout(out) if view.verbose else contextlib.nullcontext():
            view.step_post_backward(params, optimizers, state, 3, self._empty_info(params, scale2d), packed=False)
        for line in out.getvalue().splitlines():
            print(re.sub(r"^Step 3:", f"Step {step}:", line))

    def _empty_info(self, params, scale2d: bool) -> Dict[str, Any]:
        """An info of one camera in which no Gaussian is visible: the strategy's statistics
        update adds nothing."""
        n, dev = len(params["means"]), params["means"].device
        means2d = torch.zeros(1, n, 2, device=dev)
        means2d.grad = torch.zeros_like(means2d)
        means2d.absgrad = torch.zeros_like(means2d)
        return {"width": 1, "height": 1, "n_cameras": 1, "radii": torch.zeros(1, n, 2, dtype=torch.int32, device=dev),
                "gaussian_ids": None, "means2d": means2d}

    # ---- the loop's mistakes -------------------------------------------------------------------
    def _check_views(self, info, packed: bool, c: int, m: int, step) -> None:
        """Warn once when the gradient of a multi-view call reaches only some of its views, and
        once when one batch position carries far more than 1/C of it over many steps."""
        means2d = info.get("means2d")
        grad = getattr(means2d, "grad", None)
        if c < 2 or grad is None or ("partial" in self._warned and "imbalance" in self._warned):
            return
        with torch.no_grad():
            norms = grad.norm(dim=-1)
            radii = info["radii"]
            if packed:
                cams = info["camera_ids"]
                per_view = torch.zeros(c, device=norms.device, dtype=norms.dtype).index_add_(0, cams, norms)
                seen = torch.zeros(c, device=norms.device).index_add_(
                    0, cams, (radii > 0).reshape(len(cams), -1).all(-1).float())
            else:
                per_view = norms.sum(-1)
                seen = (radii > 0).reshape(c, radii.shape[1], -1).all(-1).sum(-1).float()
            per_view, seen = per_view.double().cpu(), seen.cpu()
        missing = [i for i in range(c) if seen[i] > 0 and per_view[i] == 0]
        if missing and len(missing) < c and "partial" not in self._warned:
            self._warned.update(("partial", "imbalance"))  # one cause, said once
            warnings.warn(f"step {step}: the loss's gradient reaches {c - len(missing)} of the {c} views rendered "
                          f"together (none at batch positions {missing}): a term on colors[0] trains one view; "
                          "average every term over the batch (said once)", stacklevel=3)
        if (c != m or self.config.time_spread == "stratified" or "imbalance" in self._warned
                or bool((seen == 0).any()) or not float(per_view.sum()) > 0):
            return
        shares = self._shares.setdefault(c, [])
        shares.append(per_view / per_view.sum())
        if len(shares) < IMBALANCE_MIN_STEPS:
            return
        s = torch.stack(shares)  # [steps, c]
        z = (s.mean(0) - 1.0 / c) / (s.std(0).clamp_min(1e-6) / math.sqrt(len(s)))
        worst = int(z.argmax())
        if float(z[worst]) > IMBALANCE_Z and float(s[:, worst].mean()) >= 2.0 / c:
            self._warned.add("imbalance")
            warnings.warn(f"step {step}: over {len(s)} steps of {c} views, batch position {worst} carried "
                          f"{100 * float(s[:, worst].mean()):.0f} % of the screen-space gradient where the sampler's "
                          f"shuffling gives {100 / c:.0f} %: does a loss term use colors[{worst}] only? "
                          "Average every term over the batch (said once)", stacklevel=3)

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        """The schedule's position after the last step begun (plans a DataLoader drew ahead are
        drawn again after a resume) and any end-of-step work deferred to the next batch; taken
        between steps."""
        if self.plan is not None and self._reported < len(self.plan.views):
            raise RuntimeError(f"step {self.plan.step} is not finished ({self._reported} of {len(self.plan.views)} "
                               "views reported): checkpoint between steps")
        sched = self._queue[0][1] if self._queue else self.schedule.state_dict()
        pending = None
        if self._pending is not None:
            w = self._pending
            pending = {"plan_step": w["plan"].step, "densify": w["densify"], "reset": w["reset"], "step": w["step"],
                       "maps": [t.cpu() for t in w["plan"].recorded], "before": w["before"]}
        return {"schedule": sched, "config": self.config.to_dict(), "pending": pending,
                "growth": {"order": self.budget_growth_order, "far_distance": self.far_distance},
                "rules": {"world_size_rule": self.world_size_rule, "opacity_reset_scope": self.opacity_reset_scope,
                          "kept_by_distance": self.kept_by_distance, "spared_by_reset": self.spared_by_reset},
                "most_held": self.most_held,
                "count": self.schedule.primitive_count}  # the model size the next steps' chunks are sized by

    def load_state_dict(self, state: Dict[str, Any], params=None, optimizers=None, strategy_state=None) -> None:
        """Restore a state_dict(). When it holds deferred end-of-step work, pass the run's
        params, optimizers and strategy state too: the work runs at the next batch."""
        diff = config_differences(MVGSConfig.from_dict(state["config"]), self.config)
        if diff:
            raise ValueError("the checkpoint's MVGS config differs from this run's: "
                             + "; ".join(f"{k}: saved {a!r}, now {b!r}" for k, a, b in diff))
        # a checkpoint from before the rules were options pruned and reset as gsplat's
        rules = state.get("rules") or {"world_size_rule": "extent", "opacity_reset_scope": "all"}
        differ = [f"{k}={rules[k]!r} (this strategy: {getattr(self, k)!r})" for k in ("world_size_rule", "opacity_reset_scope")
                  if rules[k] != getattr(self, k)]
        if differ:
            raise ValueError(f"the checkpoint's run pruned and reset with {', '.join(differ)}: resume with the "
                             "checkpoint's rules")
        self.schedule.load_state_dict(state["schedule"])
        if state.get("count") is not None:  # not the fresh model's that check_sanity saw (one saved before: that)
            self.schedule.primitive_count = int(state["count"])
        # a checkpoint from before budget_growth_order ranked by score alone: its run goes on so
        growth = state.get("growth") or {"order": "score", "far_distance": None}
        if growth["order"] not in ("inside-first", "score"):
            raise ValueError(f"the checkpoint's budget_growth_order {growth['order']!r} is not 'inside-first' or 'score'")
        if self._order_given and growth["order"] != self.budget_growth_order:
            raise ValueError(f"the checkpoint's run grew with budget_growth_order={growth['order']!r}, this strategy was "
                             f"given {self.budget_growth_order!r}: resume with the checkpoint's (or 'auto')")
        self.kept_by_distance, self.spared_by_reset = int(rules.get("kept_by_distance", 0)), int(rules.get("spared_by_reset", 0))
        self.most_held = int(state.get("most_held", 0))
        self.budget_growth_order = growth["order"]
        self.far_distance = None if growth["far_distance"] is None else float(growth["far_distance"])
        self._queue.clear()
        self.plan, self._reported, self._pending, self._targets = None, 0, None, None
        pending = state.get("pending")
        if pending is not None:
            if params is None or optimizers is None or strategy_state is None:
                raise ValueError("this checkpoint holds a refine deferred to the next batch: call "
                                 "load_state_dict(state, params, optimizers, strategy_state)")
            replay = ViewSchedule(self.views, self.config, load_images=False)
            replay.load_state_dict(pending["before"])
            plan = replay.next()
            if plan.step != pending["plan_step"]:
                raise ValueError(f"the deferred refine is of step {pending['plan_step']}, its saved schedule state "
                                 f"gives step {plan.step}")
            plan.recorded = [t for t in pending["maps"]]
            self._pending = {"plan": plan, "before": pending["before"], "densify": pending["densify"], "reset": pending["reset"],
                             "step": pending["step"], "params": params, "optimizers": optimizers,
                             "state": strategy_state}


def _live_gradients(params) -> List[str]:
    """Parameters holding a gradient the optimizer has not used (non-zero)."""
    return [name for name, p in params.items() if p.grad is not None and bool(p.grad.any())]


class MVGSBatchSampler(torch.utils.data.Sampler):
    """The schedule's views as DataLoader indices: one list per step, until the run's last step.
    A new iterator (a DataLoader re-iterated) continues the schedule from the last step begun."""

    def __init__(self, strategy: MVGSStrategy):
        self.strategy = strategy

    def __iter__(self) -> Iterator[List[int]]:
        st = self.strategy
        st._rewind()
        while True:  # _draw refuses a schedule already drawn to its end, naming the cause
            yield list(st._draw().views)
            if st.schedule.step_count >= st.schedule.total_steps:
                return

    def __len__(self) -> int:
        sched = self.strategy.schedule
        return sched.total_steps - sched.step_count + len(self.strategy._queue)


class MVGSLoader:
    """The user's DataLoader on the schedule's batch sampler, each batch at its step's level (from
    MVGSStrategy.loader). Iterate it as the DataLoader it replaces."""

    def __init__(self, strategy: MVGSStrategy, data, **kwargs):
        self.strategy = strategy
        DataLoader = torch.utils.data.DataLoader
        if isinstance(data, DataLoader):
            if kwargs:
                raise TypeError(f"loader(DataLoader) takes its settings from the DataLoader; got {sorted(kwargs)}")
            if data.batch_size not in (None, 1):  # gsplat's --batch_size B also tunes its Adam for B views a step
                raise ValueError(f"the DataLoader batches {data.batch_size} views a step, but the schedule picks each "
                                 "step's views (one with the default preset): build it with batch_size=1 (gsplat: "
                                 "--batch_size 1); for M views a step use a preset or MVGSConfig stages with M views")
            kwargs = dict(num_workers=data.num_workers, collate_fn=data.collate_fn, pin_memory=data.pin_memory,
                          timeout=data.timeout, worker_init_fn=data.worker_init_fn,
                          multiprocessing_context=data.multiprocessing_context, generator=data.generator,
                          prefetch_factor=data.prefetch_factor, persistent_workers=data.persistent_workers,
                          pin_memory_device=data.pin_memory_device)
            data = data.dataset
        for key in ("batch_size", "shuffle", "sampler", "batch_sampler", "drop_last"):
            if key in kwargs:
                raise TypeError(f"loader(..., {key}=...): the schedule picks each step's views")
        if len(data) != len(strategy.views.train_cameras):
            raise ValueError(f"the Dataset has {len(data)} items but MVGSStrategy was built on "
                             f"{len(strategy.views.train_cameras)} views: build both on the same training set")
        self.dataloader = DataLoader(data, batch_sampler=strategy.batch_sampler(), **kwargs)

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        for data in self.dataloader:
            yield self.strategy.at_level_dict(data)

    def __len__(self) -> int:
        return len(self.dataloader)

    def state_dict(self) -> Dict[str, Any]:
        return self.strategy.state_dict()


class MVGSBatches:
    """Iterator over a run's steps from a package Scene (MVGSStrategy.batches): each item is one
    batch dict (chunked=False) or a list of them, one per render call (chunked=True: weight each
    one's mean loss by its share of the step's views, see MVGSStrategy.chunks), with gsplat's
    Dataset keys: camtoworld [C, 4, 4], K [C, 3, 3], image [C, H, W, 3] float in 0..255,
    image_id [C], and background [C, 3] (the colour the scene's images were composited on; black
    when none). Ends after the schedule's last step; state_dict() / load_state_dict() save and
    restore the position."""

    def __init__(self, strategy: MVGSStrategy, chunked: bool):
        self.strategy = strategy
        self.chunked = chunked

    def __iter__(self) -> Iterator:
        return self

    def __next__(self):
        st = self.strategy
        st._rewind()
        if st.schedule.step_count >= st.schedule.total_steps:
            raise StopIteration
        st._close_step()
        st._draw()
        plan, before = st._queue.popleft()
        targets = torch.stack(plan.images)  # [M, H, W, 3] in [0, 1]
        st._start(plan, targets, before)
        chunks = plan.chunks if self.chunked else [list(range(len(plan.views)))]
        out = [gsplat_batch([plan.cameras[i] for i in c], targets[c], [plan.views[i] for i in c], plan.backgrounds[c])
               for c in chunks]
        return out if self.chunked else out[0]

    def __len__(self) -> int:
        return self.strategy.total_steps

    def state_dict(self) -> Dict[str, Any]:
        return self.strategy.state_dict()

    def load_state_dict(self, state: Dict[str, Any], *args) -> None:
        self.strategy.load_state_dict(state, *args)
