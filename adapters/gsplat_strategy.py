"""MVGS for a gsplat-style trainer: :class:`MVGSStrategy` wraps gsplat's ``DefaultStrategy``.

gsplat's ``simple_trainer.py`` keeps its Gaussians in a ``ParameterDict`` (``splats``), one Adam
per parameter, and densifies with a strategy object called around backward. MVGSStrategy has the
strategy's two hooks and adds a batch source, so such a loop trains with MVGS by changing the
line that builds the strategy, the line that builds the data iterator, and (for cross-ray
densification) one keyword (see ``examples/gsplat_loop/``)::

    strategy = MVGSStrategy(DefaultStrategy(...), scene, "default", steps=max_steps)
    trainloader_iter = strategy.batches()          # per step: M views at the stage's level
    ...
    strategy.step_post_backward(..., info=info, packed=packed, renders=colors)

What reaches the wrapped strategy, and how:

- **M views per step.** A batch holds the step's M cameras (``camtoworld`` [M, 4, 4], ``K``
  [M, 3, 3], ``image`` [M, H, W, 3] in 0..255 as gsplat's Dataset gives them); one render call
  gives one ``info`` for all of them, and the strategy's statistics count every view.
- **The loss reduction: keep gsplat's mean.** The strategy multiplies the screen-space gradient
  by ``info["n_cameras"]`` because simple_trainer's loss averages over the batch; with a mean,
  every view's statistic is then exactly its single-view gradient (tested against one render
  per view). MVGS's paper sums the per-view losses instead; under Adam a constant factor on the
  loss changes the update only through eps (1e-15 in simple_trainer), so the mean trains the
  same model and keeps the statistics in the units 2e-4 was set for. A summed loss would make
  them M times too large.
- **The pyramid.** A batch's cameras are the stage's scaled cameras (intrinsics divided by the
  factor) and its images the matching downsampled targets; the strategy normalises gradients by
  the batch's own width and height.
- **One clock.** The strategy's step-valued fields (``refine_start_iter``, ``refine_stop_iter``,
  ``refine_every``, ``reset_every``, ``refine_scale2d_stop_iter``, ``pause_refine_after_reset``)
  are read once, as the user set them for a run of ``steps`` single-view steps, and become the
  schedule's densification window, interval, opacity-reset period and size-pruning start
  (keeping their fraction of the run when the schedule's clock counts work). From then on the
  schedule alone decides when statistics are collected, when the strategy refines and when
  opacities are reset; the ``step`` passed to the hooks is not used.
- **MVAD.** The strategy's ``grow_grad2d`` is β; each refine runs with the schedule's threshold
  for that step (β scaled to the image width when the preset says so, halved when the step's
  cameras are far apart).
- **CRD.** With ``renders=`` given to ``step_post_backward``, the step's per-view loss maps give
  cross-ray boxes; before the strategy refines, every Gaussian inside a box (at most
  ``crd_max_new`` of the count, largest mean gradient first) is copied with gsplat's
  ``ops.duplicate``, the copies starting with empty statistics. Without ``renders`` the rule is
  skipped with one warning.
- **Chunked views.** ``batches(chunked=True)`` yields each step as a list of batches of at most
  the schedule's chunk size (views rendered and backpropagated together). Call
  ``step_post_backward`` once per batch, after the optimizer step (as simple_trainer orders
  it): statistics are gathered from every batch and the strategy refines once, at the step's
  last call.
- **No gradient lost.** Refining and resetting opacities replace parameters (gsplat's ops make
  new tensors without gradients). A call that would do so while a parameter still holds a
  gradient the optimizer has not consumed raises instead of dropping it.

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
``stats_from="last"`` (the paper preset) needs ``batches(chunked=True)``: an unchunked batch
renders all views in one call, so its statistics come from all of them (said once).
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from typing import Any, Dict, Iterator, List, Optional, Sequence, Union

import torch
from torch import Tensor

from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import duplicate, reset_opa

from mvgs_plugin.camera import Camera
from mvgs_plugin.config import MVGSConfig
from mvgs_plugin.controller import config_differences
from mvgs_plugin.densify import boxes_contain, top_by_score
from mvgs_plugin.schedule import StepPlan, ViewSchedule

__all__ = ["MVGSStrategy", "MVGSBatches", "adopt_strategy_clock", "gsplat_batch"]


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


class MVGSStrategy:
    """A gsplat DefaultStrategy driven by an MVGS ViewSchedule (see the module docstring).

    Args:
        strategy: a ``gsplat.strategy.DefaultStrategy`` (or subclass), configured as for the
            single-view run; it is not modified.
        scene: a :class:`mvgs_plugin.data.Scene` (cameras and images).
        config: an MVGSConfig or a preset name ("default", "multiview", "paper", "baseline").
        steps: the run's length in steps (the loop's max_steps): the config is compressed to it
            with ``with_total_steps`` and the strategy's clock read as set for that many steps.
            None: the config's own length (30k steps for the presets).
        clock: "strategy" (adopt the strategy's clock and threshold, see adopt_strategy_clock)
            or "config" (keep the config's own).

    Attributes: ``schedule`` (the ViewSchedule), ``config``, ``total_steps``, and after each
    refine ``last_refine`` (dict: step, threshold, boxes, from_boxes, before, after).
    """

    def __init__(self, strategy: DefaultStrategy, scene, config: Union[MVGSConfig, str] = "default",
                 steps: Optional[int] = None, clock: str = "strategy"):
        if not isinstance(strategy, DefaultStrategy):
            raise TypeError(f"MVGSStrategy wraps gsplat's DefaultStrategy (gradient-threshold densification), got "
                            f"{type(strategy).__name__}: MVAD and cross-ray densification act on that threshold and "
                            "clone step; an MCMC-style strategy has neither")
        if strategy.key_for_gradient != "means2d":
            raise ValueError(f"strategy.key_for_gradient must be 'means2d' (3DGS screen-space gradients), got "
                             f"{strategy.key_for_gradient!r}")
        if clock not in ("strategy", "config"):
            raise ValueError(f"clock must be 'strategy' or 'config', got {clock!r}")
        if isinstance(config, str):
            config = MVGSConfig.from_preset(config)
        if not isinstance(config, MVGSConfig):
            raise TypeError(f"config must be an MVGSConfig or a preset name, got {type(config).__name__}")
        if config.stage_growth is not None:
            raise ValueError(f"config.stage_growth={config.stage_growth!r}: gsplat's DefaultStrategy has no cap on "
                             "how far a refine may grow the count; use stage_growth=None")
        if config.views_scaling != "none":
            raise ValueError(f"config.views_scaling={config.views_scaling!r}: your loop owns the optimizers, so scale "
                             "them yourself (learning rates x sqrt(M), betas ** M, eps / sqrt(M)); use views_scaling='none'")
        config = config.for_scene(scene)  # before the rescaling: a forward-facing rig keeps the step count
        if steps is not None:
            config = config.with_total_steps(steps)
        run_steps = config.total_steps
        if clock == "strategy":
            config = adopt_strategy_clock(config, strategy, run_steps)
        r = _clock_per_step(config, run_steps)
        self._scale2d_until = strategy.refine_scale2d_stop_iter * r
        self._pause = strategy.pause_refine_after_reset * r
        self.strategy = strategy
        self.config = config
        self.schedule = ViewSchedule(scene, config)
        self.last_refine: Optional[Dict[str, Any]] = None
        self._plan: Optional[StepPlan] = None
        self._targets: List[Tensor] = []
        self._calls_expected = 0
        self._calls = 0
        self._warned_last = False

    @property
    def total_steps(self) -> int:
        return self.schedule.total_steps

    # ---- gsplat's Strategy interface ----------------------------------------------------
    def check_sanity(self, params, optimizers) -> None:
        self.strategy.check_sanity(params, optimizers)

    def initialize_state(self, scene_scale: float = 1.0) -> Dict[str, Any]:
        return self.strategy.initialize_state(scene_scale=scene_scale)

    def step_pre_backward(self, params, optimizers, state: Dict[str, Any], step: int, info: Dict[str, Any]) -> None:
        """As the wrapped strategy's (keeps the screen-space gradient of info["means2d"])."""
        self.strategy.step_pre_backward(params, optimizers, state, step, info)

    def step_post_backward(self, params, optimizers, state: Dict[str, Any], step: int, info: Dict[str, Any],
                           packed: bool = False, renders: Optional[Tensor] = None) -> None:
        """Fold one batch's statistics into `state`; at the step's last batch, refine and reset
        opacities when the schedule says so.

        renders: the batch's rendered colours [C, H, W, 3] (optional; cross-ray densification
        needs them for its loss maps). `step` is not used: the schedule's clock decides.
        Call once per batch the step's batches() draw yielded, after the optimizer step.
        """
        plan = self._plan
        if plan is None:
            raise RuntimeError("step_post_backward before any batch: draw the step's batch from batches() first")
        if self._calls >= self._calls_expected:
            raise RuntimeError(f"step {plan.step}: step_post_backward called {self._calls + 1} times for "
                               f"{self._calls_expected} batch(es) drawn")
        if self._collect[self._calls]:
            self._call_strategy(params, optimizers, state, info, packed, refine=None)
        if renders is not None and plan.wants_maps:
            targets = self._targets[self._calls]
            if tuple(renders.shape[:3]) != tuple(targets.shape[:3]):
                raise ValueError(f"renders must be the batch's colours [{', '.join(map(str, targets.shape))}], got "
                                 f"{list(renders.shape)}")
            plan.record(list(renders[..., :3].detach()), list(targets.to(renders.device)))
        self._calls += 1
        if self._calls == self._calls_expected:
            self._end_of_step(params, optimizers, state)
            self.schedule.primitive_count = len(params["means"])  # the next step's chunk size

    # ---- batches ----------------------------------------------------------------------------
    def batches(self, chunked: bool = False) -> "MVGSBatches":
        """The training data, one step at a time, from the schedule (see MVGSBatches)."""
        return MVGSBatches(self, chunked)

    def _begin(self, plan: StepPlan, chunked: bool) -> List[Dict[str, Tensor]]:
        if self._plan is not None and self._calls < self._calls_expected:
            raise RuntimeError(f"step {self._plan.step}: step_post_backward was called {self._calls} times for "
                               f"{self._calls_expected} batch(es); call it once per batch before drawing the next "
                               "step")
        if chunked:
            chunks, collect = plan.chunks, plan.stats
        else:
            chunks, collect = [list(range(len(plan.views)))], [any(plan.stats)]
            if self.config.stats_from == "last" and not self._warned_last:
                self._warned_last = True
                warnings.warn("stats_from='last' needs batches(chunked=True): an unchunked batch renders all "
                              "views in one call, so its statistics come from all of them", stacklevel=3)
        self._plan, self._collect, self._calls, self._calls_expected = plan, collect, 0, len(chunks)
        self._targets = [torch.stack([plan.images[i] for i in c]) for c in chunks]  # [C, H, W, 3] in [0, 1]
        return [gsplat_batch([plan.cameras[i] for i in c], t, [plan.views[i] for i in c], plan.backgrounds[c])
                for c, t in zip(chunks, self._targets)]

    # ---- what runs between steps -------------------------------------------------------------
    def _end_of_step(self, params, optimizers, state) -> None:
        plan, cfg = self._plan, self.config
        densify = plan.densify and not (self._pause > 0 and plan.clock % cfg.opacity_reset_every < self._pause)
        nxt = plan.step + 1
        handoff = (cfg.opacity_reset_at_handoff and nxt <= self.total_steps
                   and self.schedule.plan.locate(nxt).first_in_stage)
        if not (densify or plan.reset_opacity or handoff):
            return
        live = [name for name, p in params.items() if p.grad is not None and bool(p.grad.any())]
        if live:
            raise RuntimeError(f"step {plan.step}: refining or resetting opacities now would drop the gradients of "
                               f"{live} the optimizer has not used; call step_post_backward after the optimizer step "
                               "(as gsplat's simple_trainer does), keeping each batch's info until then")
        with torch.no_grad():
            if densify:
                self._refine(params, optimizers, state, plan)
            if plan.reset_opacity or handoff:
                reset_opa(params=params, optimizers=optimizers, state=state, value=self.strategy.prune_opa * 2.0)

    def _refine(self, params, optimizers, state, plan: StepPlan) -> None:
        means = params["means"].detach()
        bounds = torch.stack([means.amin(0), means.amax(0)]).double().cpu() if len(means) else None
        ctx = self.schedule.densify_context(plan, None, len(means), bounds)
        before = len(means)
        from_boxes = 0
        if ctx.boxes is not None and len(ctx.boxes):
            from_boxes = self._clone_in_boxes(params, optimizers, state, ctx.boxes, ctx.max_new_from_boxes)
        self._call_strategy(params, optimizers, state, None, False, refine=ctx)
        self.last_refine = {"step": plan.step, "clock": plan.clock, "threshold": float(ctx.grad_threshold),
                            "boxes": 0 if ctx.boxes is None else len(ctx.boxes), "from_boxes": from_boxes,
                            "before": before, "after": len(params["means"])}

    def _clone_in_boxes(self, params, optimizers, state, boxes: Tensor, cap: Optional[int]) -> int:
        """Copy every Gaussian strictly inside a box (at most `cap`, largest mean gradient
        first) with gsplat's ops.duplicate; the copies start with zero statistics, so the
        strategy's own grow step that follows acts on the originals only (as GS3DAdapter)."""
        sel = boxes_contain(params["means"], boxes)
        if cap is not None:
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

    def _call_strategy(self, params, optimizers, state, info, packed: bool, refine) -> None:
        """The wrapped strategy's own step_post_backward on a copy whose clock fields make its
        conditions give the schedule's decision. Statistics only (refine None): at step 1 with
        refine_start_iter 1 (no refine: needs step > start) and refine_stop_iter 2 (statistics:
        step < stop). Refine (a DensifyContext): at step 3 with refine_start_iter 0, refine_every
        1, grow_grad2d = the step's threshold, reset_every 2 when size pruning is on (it needs
        step > reset_every) else 4, with an info that adds no statistics. Neither step is a
        multiple of its reset_every, so the strategy never resets opacities itself."""
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
        view.grow_grad2d = float(refine.grad_threshold)
        view.refine_scale2d_stop_iter = (4 if self._plan.clock < self._scale2d_until else 1) if scale2d else 0
        view.step_post_backward(params, optimizers, state, 3, self._empty_info(params, scale2d), packed=False)

    def _empty_info(self, params, scale2d: bool) -> Dict[str, Any]:
        """An info of one camera in which no Gaussian is visible: the strategy's statistics
        update adds nothing."""
        n, dev = len(params["means"]), params["means"].device
        means2d = torch.zeros(1, n, 2, device=dev)
        means2d.grad = torch.zeros_like(means2d)
        means2d.absgrad = torch.zeros_like(means2d)
        return {"width": 1, "height": 1, "n_cameras": 1, "radii": torch.zeros(1, n, 2, dtype=torch.int32, device=dev),
                "gaussian_ids": None, "means2d": means2d}

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> Dict[str, Any]:
        """The schedule's position (sampler, background RNG); taken between steps."""
        if self._plan is not None and self._calls < self._calls_expected:
            raise RuntimeError(f"step {self._plan.step} is not finished ({self._calls} of {self._calls_expected} "
                               "batches reported): checkpoint between steps")
        return {"schedule": self.schedule.state_dict(), "config": self.config.to_dict()}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        diff = config_differences(MVGSConfig.from_dict(state["config"]), self.config)
        if diff:
            raise ValueError("the checkpoint's MVGS config differs from this run's: "
                             + "; ".join(f"{k}: saved {a!r}, now {b!r}" for k, a, b in diff))
        self.schedule.load_state_dict(state["schedule"])
        self._plan, self._calls, self._calls_expected = None, 0, 0


class MVGSBatches:
    """Iterator over a run's steps (from MVGSStrategy.batches): each item is one batch dict
    (chunked=False) or a list of them (chunked=True), with gsplat's Dataset keys: camtoworld
    [C, 4, 4], K [C, 3, 3], image [C, H, W, 3] float in 0..255, image_id [C], and background
    [C, 3] (the colour the scene's images were composited on; black when none). Ends after the
    schedule's last step; state_dict() / load_state_dict() save and restore the position."""

    def __init__(self, strategy: MVGSStrategy, chunked: bool):
        self.strategy = strategy
        self.chunked = chunked

    def __iter__(self) -> Iterator:
        return self

    def __next__(self):
        sched = self.strategy.schedule
        if sched.step_count >= sched.total_steps:
            raise StopIteration
        out = self.strategy._begin(sched.next(), self.chunked)
        return out if self.chunked else out[0]

    def __len__(self) -> int:
        return self.strategy.total_steps

    def state_dict(self) -> Dict[str, Any]:
        return self.strategy.state_dict()

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.strategy.load_state_dict(state)
