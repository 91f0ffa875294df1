"""MVGS: the training controller.

One step = sample M views -> render and backward them a chunk at a time (gradients accumulate,
so memory does not grow with M) -> guard against NaN/Inf -> densification triggers -> optimizer
step. It drives any model through the Adapter protocol (protocol.py) and never imports a
renderer or a model family.

With a distributed.Collective (torch.distributed, launched by torchrun) every rank holds the
full model and renders its share of each step's views; gradients, densification statistics and
the loss maps cross-ray densification needs are combined over ranks so the step is the
single-process step (see distributed.py).
"""

from __future__ import annotations

import math
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, List, Optional, Sequence

import torch

from .camera import Camera
from .checks import is_int
from .config import MVGSConfig
from .densify import loss_map
from .distributed import Collective, require_support
from .io import load_checked, save_checked
from .losses import photometric_loss
from .metrics import lpips, lpips_available, masked_psnr, psnr, ssim, ssim_3dgs
from .protocol import Adapter, DensifyReport, check_is_adapter
from .schedule import ViewSchedule

# MVGSConfig fields a resumed run may change (speed, memory and guards, not what it trains)
RUNTIME_FIELDS = ("chunk_size", "chunk_memory_mb", "divergence_factor")
# MVGSConfig fields that only shape the stage plan when a run's length is set (with_budget,
# with_total_steps): the plan they made is compared itself (stages), so a checkpoint saved before
# such a field existed, or with the same plan made another way, resumes
PLAN_FIELDS = ("warmup_work_cap",)


def config_differences(saved: MVGSConfig, current: MVGSConfig) -> List[tuple]:
    """(field, saved value, current value) for every field but RUNTIME_FIELDS and PLAN_FIELDS
    that differs, the preset's name included."""
    a, b = _flat_dict(saved.to_dict()), _flat_dict(current.to_dict())
    return [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b))
            if k not in RUNTIME_FIELDS + PLAN_FIELDS and a.get(k) != b.get(k)]


def _flat_dict(d: dict) -> dict:
    """The nested groups of MVGSConfig.to_dict() (mvad, crd) as "mvad.tau"-style keys."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        else:
            out[k] = v
    return out


def _non_finite(t) -> int:
    """How many entries of t are NaN or Inf. One sum first (no mask): a finite sum clears the
    tensor at the cost of one reduction; only a non-finite one (NaN, Inf or overflow) counts."""
    t = t.detach()
    if t.numel() == 0 or bool(torch.isfinite(t.sum())):
        return 0
    return int((~torch.isfinite(t)).sum())


# The running loss level of MVGSConfig.divergence_factor: an exponential average with this decay
# of the steps that passed the check (a diverging step never raises it), from the first step on,
# and never below _LEVEL_FLOOR: a photometric loss per view of images in [0, 1] stays below 1,
# so with the default factor 100 a loss above 1 is always caught and one near-perfect view
# cannot make the next ordinary one look like an explosion.
_LEVEL_DECAY = 0.9
_LEVEL_FLOOR = 0.01


class StageMismatch(ValueError):
    """load_checkpoint's refusal of a checkpoint made with another stage plan (the model, views
    and images being the same), so a command line can say which of its flags would give that
    plan."""


class ConfigMismatch(ValueError):
    """load_checkpoint's refusal of a checkpoint made with another MVGSConfig: `differences`
    lists (field, checkpoint value, this run's value), so a command line can word its advice."""

    def __init__(self, message: str, differences):
        super().__init__(message)
        self.differences = list(differences)


class PhaseTimer:
    """Wall seconds per phase of a step: ``with timer("render"): ...`` adds the block's time to
    ``timer.seconds["render"]`` (an exception inside a block still counts its time)."""

    def __init__(self, *phases: str):
        self.seconds: Dict[str, float] = dict.fromkeys(phases, 0.0)

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] += time.perf_counter() - t0


@dataclass
class StepInfo:
    """What one step did (threshold and boxes: the gradient threshold and the number of CRD
    boxes of its densification call, when it made one; mvad_fired: MVAD halved that threshold;
    seconds: the whole step, of which render_seconds and backward_seconds were spent in the
    adapter's render and in backward, loss_seconds in the photometric loss (and CRD's loss
    maps, and the adapter's regulariser), adapter_seconds in the adapter's other work
    (statistics, densification, opacity reset, optimizer step), comm_seconds in collectives
    across ranks, waiting for the slowest rank included; controller_seconds is the rest).
    In a distributed run, loss is the sum over every rank's views."""

    step: int
    stage: int
    factor: int
    views: List[int]
    loss: float
    num_primitives: int
    densify: Optional[DensifyReport] = None
    opacity_reset: bool = False
    threshold: Optional[float] = None
    boxes: int = 0
    seconds: float = 0.0
    render_seconds: float = 0.0
    backward_seconds: float = 0.0
    comm_seconds: float = 0.0
    mvad_fired: bool = False
    loss_seconds: float = 0.0
    adapter_seconds: float = 0.0
    budget_cut: int = 0  # rows the Gaussian budget cut before the step rendered (a model above max_gaussians)

    @property
    def controller_seconds(self) -> float:
        """The controller's own time: sampling and the step plan, MVAD, CRD's windows and boxes,
        the finiteness checks and bookkeeping; everything but the adapter's render and its
        other work (statistics, densification, optimizer), backward, the loss and collectives."""
        return max(0.0, self.seconds - self.render_seconds - self.backward_seconds - self.comm_seconds
                   - self.loss_seconds - self.adapter_seconds)


@dataclass
class EvalResult:
    psnr: float
    ssim: float
    lpips: Optional[float]
    per_view: List[Dict] = field(default_factory=list)  # name, psnr, ssim, ssim_3dgs, lpips, image [H, W, 3] per view
    ssim_3dgs: Optional[float] = None  # the original 3DGS evaluation's SSIM (zero-padded): metrics.ssim_3dgs

    def __repr__(self) -> str:  # the per-view images stay out of a print
        lp = "None" if self.lpips is None else f"{self.lpips:.4f}"
        return (f"EvalResult(psnr={self.psnr:.4f}, ssim={self.ssim:.4f}, lpips={lp}, "
                f"per_view=[{len(self.per_view)} views: name, psnr, ssim, lpips, image])")


class MVGS:
    """Multi-view regulated training of an adapter's model on a scene.

    Args:
        adapter: the model, its renderer and optimizer (see protocol.Adapter).
        scene: a mvgs_plugin.data.Scene (train/test cameras, images, extent).
        config: MVGSConfig (presets: baseline(), paper(), default()), run as config.for_scene(scene)
            (the default trains a forward-facing rig at full resolution only).
        distributed: a distributed.Collective to shard each step's views over the ranks of a
            process group (every rank builds the same MVGS with the same config and seed);
            None: one process. The adapter must implement protocol.DistributedAdapter.
    """

    def __init__(self, adapter: Adapter, scene, config: Optional[MVGSConfig] = None,
                 distributed: Optional[Collective] = None):
        check_is_adapter(adapter)
        if not (hasattr(scene, "train_cameras") and hasattr(scene, "test_cameras")):
            path = isinstance(scene, (str, bytes)) or hasattr(scene, "__fspath__")
            raise TypeError(f"scene must be a mvgs_plugin.data.Scene (train_cameras, test_cameras, images), got "
                            f"{type(scene).__name__}" + (" (a path: load it with mvgs_plugin.data.load_scene)" if path else ""))
        if config is not None and not isinstance(config, MVGSConfig):
            hint = f" (a preset by name: MVGSConfig.from_preset({config!r}))" if isinstance(config, str) else ""
            raise TypeError(f"config must be an MVGSConfig or None, got {type(config).__name__} {config!r}{hint}")
        self.adapter = adapter
        self.scene = scene
        # without a config: the default recipe run at its own length, 30k views' work (with_budget
        # applies its warm-up cap, as --budget 30000 would)
        self.schedule = ViewSchedule(scene, config or MVGSConfig.default().with_budget(30_000))
        self.config = self.schedule.config  # resolved for the scene (MVGSConfig.for_scene)
        self._warn_other_clock(adapter)
        if self.config.views_scaling != "none" and not callable(getattr(adapter, "set_views_per_step", None)):
            raise ValueError(f"config.views_scaling={self.config.views_scaling!r} needs the adapter's "
                             f"set_views_per_step(views) ({type(adapter).__name__} has none); use views_scaling='none'")
        self.schedule.enable_faint_cut(adapter)  # nothing without prune_faint
        self.config = self.schedule.config  # prune_faint 0 when the adapter cannot report blend weights
        if distributed is not None:
            if not isinstance(distributed, Collective):
                raise TypeError(f"distributed must be a mvgs_plugin.distributed.Collective or None, "
                                f"got {type(distributed).__name__}")
            require_support(adapter)
        self.distributed = distributed
        self._loss_level: Optional[float] = None  # running loss per view; None before the first step
        # a caller's running totals over the run (str -> number: the examples' densification tally),
        # saved with every checkpoint and put back by a resume, so a resumed run's record is the whole run's
        self.record: Dict[str, float] = {}

    def _warn_other_clock(self, adapter) -> None:
        """Warn when the model's own schedules are on another clock than this run's (its config
        built without for_run): the decays would stop part-way, or 4DGS's deformation field would
        start late or never. Asks the adapter (ClockedAdapter.clock_mismatch, optional)."""
        clock = self.config.clock_length
        ask = getattr(adapter, "clock_mismatch", None)
        found = ask(clock) if callable(ask) else None
        if found is not None:
            what, steps, fix = found
            warnings.warn(f"the adapter's own schedules run over {steps} steps (its config's {what}) but this run's "
                          f"clock is {clock}; build its config with {fix}, as the examples do", stacklevel=3)

    @property
    def is_main(self) -> bool:
        """Whether this process writes outputs (rank 0, or the only process)."""
        return self.distributed is None or self.distributed.is_main

    @property
    def step_count(self) -> int:
        return self.schedule.step_count

    @property
    def total_steps(self) -> int:
        return self.schedule.total_steps

    # ---- one step ---------------------------------------------------------------------------
    def step(self) -> StepInfo:
        """Runs the next training step and returns what it did."""
        t_step = time.perf_counter()
        budget = self.config.max_gaussians
        before = self.adapter.num_primitives()
        cut = self.schedule.initial_cut(before)
        if cut is not None:  # the run's first step: a larger model is cut to its initial share of the budget
            self._shrink_to(cut.max_primitives)
        elif budget is not None and before > budget:
            self._shrink_to(budget)
        budget_cut = before - self.adapter.num_primitives()
        self.schedule.primitive_count = self.adapter.num_primitives()
        plan = self.schedule.next()
        adapter = self.adapter
        timer = PhaseTimer("render", "backward", "comm", "loss", "adapter")
        with timer("adapter"):
            if plan.handoff_reset:
                adapter.reset_opacity()
            if self.config.views_scaling == "sqrt":
                adapter.set_views_per_step(len(plan.views))
            adapter.set_step(plan.clock)
        maps = [] if plan.wants_maps else None
        dist = self.distributed
        mine = list(range(len(plan.views))) if dist is None else dist.positions(len(plan.views))
        error: Optional[BaseException] = None
        try:
            total = self._render_and_backward(plan, mine, maps, timer)
        except Exception as exc:
            if dist is None:
                raise
            total, error = 0.0, exc  # reported to every rank below, then raised here
        if dist is not None:
            with timer("comm"):
                total, maps = self._combine_ranks(plan, error, total, maps)
        self._check_gradients(plan)
        report, ctx = None, None
        if plan.densify:
            with torch.no_grad():
                ctx = self.schedule.densify_context(plan, maps, adapter=adapter)
                with timer("adapter"):
                    report = adapter.densify(ctx)
                self._check_cap(ctx.max_primitives)
        with timer("adapter"):
            if plan.reset_opacity:
                with torch.no_grad():
                    adapter.reset_opacity()
            self._check_loss(plan, total)
            try:
                adapter.optimizer_step()
            except FloatingPointError as exc:
                raise FloatingPointError(f"step {plan.step}: after the optimizer step, {exc}") from exc
            self._check_parameters(plan)
            adapter.zero_grad()
        seconds = timer.seconds
        return StepInfo(
            step=plan.step, stage=plan.stage, factor=plan.factor, views=plan.views, loss=total,
            num_primitives=adapter.num_primitives(), densify=report, opacity_reset=plan.reset_opacity,
            threshold=None if ctx is None else ctx.grad_threshold,
            boxes=0 if ctx is None or ctx.boxes is None else int(ctx.boxes.shape[0]),
            seconds=time.perf_counter() - t_step, render_seconds=seconds["render"],
            backward_seconds=seconds["backward"], comm_seconds=seconds["comm"],
            mvad_fired=ctx is not None and ctx.grad_threshold < self.schedule.base_threshold(plan),
            loss_seconds=seconds["loss"], adapter_seconds=seconds["adapter"], budget_cut=budget_cut,
        )

    def _shrink_to(self, budget: int) -> None:
        """Cut a model above config.max_gaussians to it before a step renders (its lowest-ranked
        rows go: GS3DAdapter.keep_scores)."""
        with torch.no_grad():
            self.adapter.densify(self.schedule.cut_context(budget))
        self._check_cap(budget)

    def _check_cap(self, cap: Optional[int]) -> None:
        n = self.adapter.num_primitives()
        if cap is not None and n > cap:
            raise RuntimeError(f"{type(self.adapter).__name__}.densify left {n} primitives, above the cap "
                               f"{cap} it was given (DensifyContext.max_primitives, from config.max_gaussians or "
                               "stage_growth): the adapter must not hold more than the cap after a densify call")

    def _render_and_backward(self, plan, mine: Sequence[int], maps: Optional[List], timer: "PhaseTimer") -> float:
        """Renders and backpropagates the step's views at positions `mine`, chunk by chunk (the
        gradients accumulate), folds in their statistics and appends their loss maps to `maps`.
        Returns the sum of their losses."""
        adapter, total = self.adapter, 0.0
        for positions, collect in self._chunks(plan, mine):
            cams = [plan.cameras[i] for i in positions]
            gts = [plan.images[i] for i in positions]
            with timer("render"):
                result = adapter.render(cams, plan.backgrounds[positions])
            with timer("loss"):
                # One batched loss for the chunk: the mean over its views times their number is the
                # sum of the per-view losses (same image size), with one SSIM filter call.
                images = result.images if isinstance(result.images, torch.Tensor) else torch.stack(list(result.images))
                target = torch.stack(gts).to(images)
                if plan.masks is not None:  # ignored pixels are black in both, as nerfstudio's masked loss
                    weight = torch.stack([plan.masks[i] for i in positions]).to(images)
                    images, target = images * weight, target * weight
                if maps is not None:
                    maps += [loss_map(img, gt) for img, gt in zip(images, target)]
                loss = plan.weight * len(gts) * photometric_loss(images, target, self.config.lambda_dssim)
                if positions[0] == 0:  # the regulariser counts once per step (on one rank), not once per view
                    reg = adapter.regularization(plan.clock)
                    if reg is not None:
                        loss = loss + reg
                if not bool(torch.isfinite(loss)):
                    raise FloatingPointError(
                        f"step {plan.step}: the loss is {loss.item()} for views {[c.name for c in cams]}; "
                        "stopping before the optimizer step"
                    )
            with timer("backward"):
                loss.backward()  # gradients accumulate; this chunk's graph is freed here
            total += loss.item()
            if collect:
                with timer("adapter"):
                    adapter.accumulate_stats(result)
            del result, loss
        return total

    def _combine_ranks(self, plan, error: Optional[BaseException], total: float, maps: Optional[List]):
        """The collectives of a distributed step: status (raises on every rank if one failed),
        gradient sum, and on densification steps the loss maps of all views and the statistics
        of all ranks. Returns the global loss and the step's loss maps (all views, or None)."""
        dist, adapter = self.distributed, self.adapter
        total = dist.exchange_status(plan.step, error, total, adapter.num_primitives(), plan.views)
        dist.all_reduce_gradients(adapter, plan.step)
        if maps is not None:
            ref = adapter.positions()
            sizes = [(c.height, c.width) for c in plan.cameras]
            maps = dist.gather_loss_maps(maps, len(plan.views), max(h for h, _ in sizes), max(w for _, w in sizes),
                                         ref.dtype, ref.device, plan.step, sizes)
        if plan.densify:
            dist.all_reduce_statistics(adapter, plan.step)
        return total, maps

    @staticmethod
    def _chunks(plan, mine: Sequence[int]):
        """(positions, collect statistics?) per chunk of the plan, restricted to this rank's
        positions (all of them in one process): a chunk split between ranks renders its part
        on each. A chunk whose cameras differ in size (a scene with images of mixed sizes) is
        rendered as one part per size, in order of first appearance."""
        held = set(mine)
        for chunk, collect in zip(plan.chunks, plan.stats):
            by_size: Dict[tuple, List[int]] = {}
            for i in chunk:
                if i in held:
                    by_size.setdefault((plan.cameras[i].width, plan.cameras[i].height), []).append(i)
            for part in by_size.values():
                yield part, collect

    def _check_gradients(self, plan) -> None:
        for name, g in self.adapter.named_gradients().items():
            bad = 0 if g is None else _non_finite(g)
            if bad:
                raise FloatingPointError(
                    f"step {plan.step}: {bad} non-finite gradient entries in group {name!r} after views "
                    f"{[c.name for c in plan.cameras]}; stopping before the optimizer step"
                )

    def _check_loss(self, plan, total: float) -> None:
        """Stops a diverging run: the loss per view against its running level (see
        MVGSConfig.divergence_factor). The level starts again in every process (not saved)."""
        factor = self.config.divergence_factor
        per_view = total / (plan.weight * len(plan.views))
        old = self._loss_level
        if old is None:
            self._loss_level = per_view
            return
        level = max(old, _LEVEL_FLOOR)
        if factor is not None and per_view > factor * level:
            raise FloatingPointError(
                f"step {plan.step}: the loss per view is {per_view:.4g}, {per_view / level:.3g} times its running "
                f"level {level:.4g} (> divergence_factor {factor:g}): the run diverges (a learning rate too high?); "
                "stopping before the optimizer step")
        self._loss_level = _LEVEL_DECAY * old + (1 - _LEVEL_DECAY) * per_view

    def _check_parameters(self, plan) -> None:
        """Every trainable tensor finite after the optimizer step (adapters with
        gradient_parameters(); one sum per group, the exact count only when it is not)."""
        if not hasattr(self.adapter, "gradient_parameters"):
            return
        for name, p in self.adapter.gradient_parameters().items():
            bad = _non_finite(p)
            if bad:
                raise FloatingPointError(f"step {plan.step}: {bad} non-finite values in group {name!r} after the "
                                         "optimizer step: the run diverges (a learning rate too high?)")

    # ---- the whole run --------------------------------------------------------------------
    def fit(self, steps: Optional[int] = None, callback: Optional[Callable[[StepInfo], None]] = None,
            progress: bool = True) -> "MVGS":
        """Runs the remaining steps (or `steps` more) with a progress bar (rank 0 only, and only
        when stderr is a terminal: a log file or a pipe gets no bar). In a distributed run every
        rank must call it with the same `steps`."""
        if steps is not None and not (is_int(steps) and steps >= 1):
            raise ValueError(f"steps must be None (the rest of the run) or an int >= 1, got {steps!r}")
        remaining = self.total_steps - self.step_count
        n = remaining if steps is None else min(steps, remaining)
        bar = None
        if progress and self.is_main:
            from tqdm import tqdm

            bar = tqdm(total=n, desc="MVGS", unit="step", dynamic_ncols=True, disable=None)  # None: a TTY only
        for _ in range(n):
            info = self.step()
            if callback is not None:
                callback(info)
            if bar is not None:
                bar.update(1)
                if info.step % 10 == 0 or info.step == self.total_steps:
                    bar.set_postfix(loss=f"{info.loss:.4f}", n=info.num_primitives, s=info.factor)
        if bar is not None:
            bar.close()
        return self

    # ---- evaluation -------------------------------------------------------------------------
    @torch.no_grad()
    def evaluate(self, cameras: Optional[Sequence[Camera]] = None, factor: int = 1) -> EvalResult:
        """PSNR / SSIM (/ LPIPS when available) on the test views at pyramid factor `factor`.
        Local: no collective (every rank holds the same model; rank 0 alone may call it)."""
        cameras = list(self.scene.test_cameras if cameras is None else cameras)
        if not cameras:
            raise ValueError("no cameras to evaluate (the scene has no test split)")
        bg = torch.tensor([self.schedule.background_value()])
        rows = []
        for cam in cameras:
            view = cam if factor == 1 else cam.scaled(factor)
            img = self.adapter.render([view], bg).images[0].clamp(0, 1).float()
            gt = self.scene.image(cam, factor).float()
            mask = self.scene.mask(cam, factor) if getattr(self.scene, "has_masks", False) else None
            if mask is None:
                rows.append({"name": cam.name, "psnr": psnr(img, gt), "ssim": ssim(img, gt), "ssim_3dgs": ssim_3dgs(img, gt),
                             "lpips": lpips(img, gt) if lpips_available() else None, "image": img})
            else:  # the pixels the mask keeps: PSNR of their MSE; SSIM and LPIPS of the images blacked out alike
                w = mask.float()
                shown, target = img * w, gt * w
                rows.append({"name": cam.name, "psnr": masked_psnr(img, gt, w), "ssim": ssim(shown, target),
                             "ssim_3dgs": ssim_3dgs(shown, target), "lpips": lpips(shown, target) if lpips_available() else None, "image": img})
        finite = [r["psnr"] for r in rows if math.isfinite(r["psnr"])]
        lp = [r["lpips"] for r in rows if r["lpips"] is not None]
        return EvalResult(
            psnr=sum(finite) / len(finite) if finite else math.inf,
            ssim=sum(r["ssim"] for r in rows) / len(rows),
            lpips=sum(lp) / len(lp) if lp else None,
            per_view=rows,
            ssim_3dgs=sum(r["ssim_3dgs"] for r in rows) / len(rows),
        )

    # ---- checkpoints ------------------------------------------------------------------------
    def state_dict(self) -> Dict:
        """Everything to resume. Distributed: a collective (call it on every rank); the
        densification statistics in it are the ones combined over ranks, so a single process can
        resume from it."""
        if self.distributed is None:
            adapter_state = self.adapter.state_dict()
        else:
            local = {name: t.clone() for name, (t, _) in self.adapter.statistics().items()}
            self.adapter.load_statistics(self.distributed.reduce_statistics(self.adapter, self.step_count))
            try:
                adapter_state = self.adapter.state_dict()
            finally:
                self.adapter.load_statistics(local)  # keep this rank's own share for the next densify
        return {
            "config": self.config.to_dict(),
            "schedule": self.schedule.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "adapter": adapter_state,
            "record": dict(self.record),
        }

    def load_state_dict(self, state: Dict, strict: bool = True) -> None:
        """Restore a state_dict(). The checkpoint's config must be this run's (preset, seed,
        stages, rules, schedules: every MVGSConfig field but RUNTIME_FIELDS, which only change
        speed or guards): strict refuses a difference with a ValueError naming each field, its
        saved and its current value; strict=False keeps this run's values and warns naming
        them. Stages must match either way. Distributed: every rank loads the same state; the
        summed statistics stay on rank 0 only (the others start from zero), so the next
        densification sums them once."""
        own = self.adapter.state_dict()  # also the backup below
        kinds = [st.get("format") if isinstance(st, dict) else None for st in (state["adapter"], own)]
        if None not in kinds and kinds[0] != kinds[1]:  # another model first: its config differs as a consequence
            raise ValueError(f"the checkpoint holds a {kinds[0]!r} model and this run trains a {kinds[1]!r} model "
                             f"({type(self.adapter).__name__}): it was written by another script or adapter")
        self.schedule.check_views_of(state["schedule"])  # another scene: said as such, not as its stage plan
        saved = MVGSConfig.from_dict(state["config"])
        if saved.stages != self.config.stages:
            def plan(stages):
                return ", ".join(f"{st.steps} steps of {st.views} view(s) at 1/{st.factor:g}" for st in stages)
            raise StageMismatch(f"checkpoint was made with stages {saved.stages}, this run has {self.config.stages} "
                             f"(the checkpoint's plan: {plan(saved.stages)}; this run's: {plan(self.config.stages)}). "
                             "The plan follows the preset and the run's length (--steps / --budget), and the "
                             "flags that change its levels or views (--resolution-scale, --views, --stages, "
                             "--late-views, --warmup-work-cap): resume with the ones the checkpoint was written with "
                             "(a default run of a budget above 3333 saved before the warm-up cap: --warmup-work-cap 0)")
        differ = config_differences(saved, self.config)
        if differ:
            said = "; ".join(f"{name}: checkpoint {a!r}, this run {b!r}" for name, a, b in differ)
            if strict:
                raise ConfigMismatch(f"the checkpoint was made by another run's config ({said}); build the trainer "
                                     "with the checkpoint's config (MVGSConfig.from_dict(state['config'])), or pass "
                                     "strict=False to keep this run's values", differ)
            warnings.warn(f"checkpoint config differs, this run's values are kept: {said}", stacklevel=2)
        # All or nothing: if any part fails to load, the trainer is put back as it was (a caller
        # who catches the error and trains on must not get a half-restored run).
        backup = (self.schedule.state_dict(), torch.get_rng_state(), own)
        try:
            self.schedule.load_state_dict(state["schedule"])
            torch.set_rng_state(state["torch_rng"])
            self.adapter.load_state_dict(state["adapter"])
        except BaseException:
            self.schedule.load_state_dict(backup[0])
            torch.set_rng_state(backup[1])
            self.adapter.load_state_dict(backup[2])
            raise
        self.record = dict(state.get("record") or {})  # absent in checkpoints before it was kept
        if self.distributed is not None and not self.distributed.is_main:
            stats = self.adapter.statistics()
            self.adapter.load_statistics({name: torch.zeros_like(t) if how == "sum" else t.clone()
                                          for name, (t, how) in stats.items()})

    def save_checkpoint(self, path: str) -> None:
        """Controller, adapter, optimizer and sampler state in one file, written atomically (a
        crash mid-write leaves the previous checkpoint intact) with a checksum of its payload
        (io.save_checked). Distributed: call it on every rank; rank 0 writes, the others wait
        until the file is there."""
        state = self.state_dict()
        if self.is_main:
            save_checked(state, path)
        if self.distributed is not None:
            self.distributed.barrier("checkpoint", self.step_count)

    def load_checkpoint(self, path: str, strict: bool = True) -> None:
        """Load a save_checkpoint() file. It is read with torch.load(weights_only=True): tensors
        and plain containers only, so a crafted file cannot run code on load (a pickle that
        would is refused with an error naming the file); its checksum is verified (a damaged
        file is refused); loading is all or nothing (load_state_dict, which also says what
        `strict` does about a checkpoint of another config)."""
        try:
            state = load_checked(path)
        except FileNotFoundError:
            raise
        except Exception as exc:  # unpickling refused, truncated or foreign file
            raise ValueError(f"cannot load checkpoint {path!r}: not a checkpoint written by save_checkpoint, or "
                             f"damaged ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from exc
        missing = {"config", "schedule", "torch_rng", "adapter"} - (set(state) if isinstance(state, dict) else set())
        if missing:
            raise ValueError(f"cannot load checkpoint {path!r}: missing {sorted(missing)} (expected a dict written "
                             "by save_checkpoint)")
        try:
            self.load_state_dict(state, strict)
        except ConfigMismatch as exc:
            raise ConfigMismatch(f"cannot load checkpoint {path!r}: {exc}", exc.differences) from exc
        except StageMismatch as exc:
            raise StageMismatch(f"cannot load checkpoint {path!r}: {exc}") from exc
        except ValueError as exc:
            raise ValueError(f"cannot load checkpoint {path!r}: {exc}") from exc
