"""What each step trains on: the stage plan of cross-intrinsic guidance (which stage a global
step is in, and which step the learning-rate and densification clocks see: restarted per stage,
or continuous) and the ViewSchedule that turns it, with the view sampler, into one StepPlan per
step."""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from .camera import Camera
from .config import MVGSConfig, Stage
from .densify import best_windows, camera_axes, cross_ray_boxes, loss_map, mvad_threshold, resolution_threshold
from .protocol import DensifyContext
from .sampler import ViewSampler


# Working memory of one view in a renderer call (forward intermediates, what backward keeps,
# the loss's SSIM maps), measured on the reference renderer as the growth of peak RSS per added
# view: 105-110 B per Gaussian (200k Gaussians, 16 px) and 530-600 B per pixel (128 and 256 px);
# rounded up. A GPU rasterizer needs less per Gaussian; the bound is then conservative.
VIEW_BYTES_PER_GAUSSIAN = 128
VIEW_BYTES_PER_PIXEL = 640
# Model size assumed when nobody has told the schedule (ViewSchedule.primitive_count).
UNKNOWN_PRIMITIVES = 1_000_000


def view_bytes(primitives: int, height: int, width: int) -> int:
    """Estimated working memory (bytes) of one view of a renderer call."""
    return VIEW_BYTES_PER_GAUSSIAN * max(0, int(primitives)) + VIEW_BYTES_PER_PIXEL * height * width


@dataclass(frozen=True)
class StagePosition:
    """Where a global step (1-based) falls: the stage, its index, the step within the stage
    (1-based), and the clock the schedules see: `clock` (an int, what the model's schedules get)
    and the clock's value before and after this step (`before` < `after`; a step advances it by
    1, or by its work on the budget clock), for the "every k" triggers."""

    index: int
    stage: Stage
    local_step: int
    clock: int
    first_in_stage: bool
    before: float = 0.0
    after: float = 0.0

    def crosses(self, every: int) -> bool:
        """Whether this step's clock interval (before, after] holds a multiple of `every` (for a
        clock counting steps: clock % every == 0)."""
        return math.floor(self.after / every + 1e-9) > math.floor(self.before / every + 1e-9)


class StagePlan:
    """A list of stages run back to back; the model carries over from one to the next.

    step_work: None (the clocks count steps) or a function giving the work of one step of a
    stage: the clock then counts work (MVGSConfig.budget).
    """

    def __init__(self, stages: Sequence[Stage], restart_per_stage: bool = False, step_work=None):
        self.stages = tuple(stages)
        self.restart_per_stage = restart_per_stage
        self.total_steps = sum(s.steps for s in self.stages)
        self.finest_factor = min(s.factor for s in self.stages)
        self.step_work = step_work

    def locate(self, step: int) -> StagePosition:
        if not 1 <= step <= self.total_steps:
            raise ValueError(f"step must be in [1, {self.total_steps}], got {step}")
        start, done = 0, 0.0
        for i, stage in enumerate(self.stages):
            if step <= start + stage.steps:
                local = step - start
                if self.step_work is not None:
                    w = self.step_work(stage)
                    before, after = done + (local - 1) * w, done + local * w
                    return StagePosition(i, stage, local, int(math.floor(after + 1e-9)), local == 1, before, after)
                clock = local if self.restart_per_stage else step
                return StagePosition(i, stage, local, clock, local == 1, clock - 1, clock)
            start += stage.steps
            done += stage.steps * self.step_work(stage) if self.step_work is not None else 0.0
        raise AssertionError("unreachable")



@dataclass
class StepPlan:
    """Everything one training step needs, decided before rendering.

    views: training view indices; cameras: their cameras at this stage's pyramid level;
    images: the matching targets [H', W', 3]; backgrounds: [M, 3]; weight: multiplies every
    per-view loss (1 for "sum", 1/M for "mean"); chunks: positions in `views` rendered and
    backpropagated together; stats: per chunk, whether its densification statistics are
    collected; densify / reset_opacity / handoff_reset: what runs after the backward passes.
    faint_cut: this step's densify is MVGSConfig.prune_faint's one cut after the densification
    window (densify_context gives it no growth and DensifyContext.faint_share).
    wants_maps: whether this step's densification needs per-view loss maps (it densifies and
    cross-ray densification is on); recorded: the maps a hand-written loop handed over with
    record() (optional: see ViewSchedule.densify_context). masks: when the scene has masks
    (Scene.mask), the targets' pixel weights [H', W', 1] in view order, else None; a loop
    multiplies render and target by them before its loss (mask_for(camera) finds one).
    """

    step: int
    clock: int
    stage: int
    factor: int
    views: List[int]
    cameras: List[Camera]
    images: List[Tensor]
    backgrounds: Tensor
    weight: float
    chunks: List[List[int]]
    stats: List[bool]
    densify: bool
    reset_opacity: bool
    handoff_reset: bool
    wants_maps: bool = False
    faint_cut: bool = False
    recorded: List[Tensor] = field(default_factory=list)
    masks: Optional[List[Tensor]] = None

    def mask_for(self, camera: Camera) -> Optional[Tensor]:
        """The mask [H', W', 1] of one of this plan's cameras (as ``iter(plan)`` gives them), or
        None when the scene has none. A loop multiplies its render and target by it before the
        loss, so that ignored pixels count nothing."""
        if self.masks is None:
            return None
        for cam, mask in zip(self.cameras, self.masks):
            if cam is camera:
                return mask
        raise ValueError(f"plan.mask_for: camera {getattr(camera, 'name', camera)!r} is not one of this step's cameras "
                         f"{[c.name for c in self.cameras]}; pass a camera the plan gave")

    def record(self, images: Sequence[Tensor], targets: Sequence[Tensor]) -> None:
        """Hand the step's rendered images and their targets to the schedule, chunk by chunk in
        view order (one line after backward in a hand-written loop). Cross-ray densification
        needs their per-view loss maps; without them it is skipped with a warning. The maps are
        detached and [H', W'] each, so recording costs no graph memory; on steps that do not
        densify with CRD (wants_maps False) nothing is computed or kept. With masks, record the
        images as the loss saw them (multiplied by mask_for(camera))."""
        if self.wants_maps:
            for img, gt in zip(images, targets):
                k = len(self.recorded)
                if k >= len(self.cameras):
                    raise ValueError(f"plan.record: view {k + 1} recorded, but this step has {len(self.cameras)}: "
                                     "record each chunk's images once, in the order the plan gives them")
                m = loss_map(img, gt)
                cam = self.cameras[k]
                if tuple(m.shape) != (cam.height, cam.width):
                    raise ValueError(f"plan.record: view {k} ({cam.name!r}) gave a {m.shape[1]}x{m.shape[0]} loss map, "
                                     f"its camera at this level is {cam.width}x{cam.height}: record the images rendered "
                                     "for the plan's cameras, in its order")
                self.recorded.append(m)

    def __iter__(self) -> Iterator[Tuple[List[Camera], List[Tensor], Tensor, bool]]:
        """Per chunk: (cameras, target images, backgrounds [C, 3], collect statistics?)."""
        for chunk, collect in zip(self.chunks, self.stats):
            yield [self.cameras[i] for i in chunk], [self.images[i] for i in chunk], self.backgrounds[chunk], collect


def no_densification_message(config: MVGSConfig) -> str:
    """What a run whose densification window holds no call (densifies_at_some_step False) is
    told: by ViewSchedule's NoDensificationWarning, and by the CLI's note."""
    return (f"this run densifies at no step: its densification window, after {config.densify_from} and before "
            f"{config.densify_until} on the run's clock (every {config.densify_every}), holds no call (a short run "
            f"waits {min(50, config.densify_from)} before its first, so that densification does not act on a model "
            "that has fitted nothing yet); a longer run densifies")


def densifies_at_some_step(config: MVGSConfig) -> bool:
    """Whether the config's densification window (clock > densify_from and < densify_until,
    where the clock crosses a multiple of densify_every: ViewSchedule.next's rule) holds a call.
    Exact for a clock counting steps; a clock counting work can also fire just past a multiple
    equal to densify_from, so a window shorter than one interval may be judged empty."""
    first = (config.densify_from // config.densify_every + 1) * config.densify_every
    return first < config.densify_until


class NoDensificationWarning(UserWarning):
    """A run whose densification window holds no call (the CLI prints its own note instead)."""


class ViewSchedule:
    """The sequence of StepPlans of a run: sampler + stage plan + densification clock.

    This is the part of the controller a hand-written training loop can use directly (see
    examples/three_line_wrap): the same loop trains plain 3DGS with MVGSConfig.baseline() and
    MVGS with MVGSConfig.default().

    primitive_count: the model's current size, for the memory bound of chunk_size=None and (its
    value when a stage begins) the cap of config.stage_growth; the controller sets it every step. A loop of your own may set it too; until then the scene's
    point count is assumed, or UNKNOWN_PRIMITIVES without points (small chunks: safe, slower).
    """

    def __init__(self, scene, config: MVGSConfig, load_images: bool = True):
        if not hasattr(scene, "train_cameras"):
            raise TypeError(f"scene must be a mvgs_plugin.data.Scene (e.g. load_scene(folder)), got "
                            f"{type(scene).__name__}")
        if isinstance(config, str):  # a preset name, as MVGSStrategy takes
            config = MVGSConfig.from_preset(config)
        if not isinstance(config, MVGSConfig):
            raise TypeError(f"config must be an MVGSConfig or a preset name, got {type(config).__name__}")
        if not scene.train_cameras:
            raise ValueError("scene has no training cameras")
        self.scene = scene
        self.load_images = load_images  # False: plans carry no images (a loop that loads its own data)
        resolved = config.for_scene(scene)
        if config.budget is None and resolved.total_steps != config.total_steps:
            warnings.warn(f"on this rig the plan's coarser stages hand their work to the full-resolution stage "
                          f"(MVGSConfig.for_scene): this run takes {resolved.total_steps} steps, not the config's "
                          f"{config.total_steps}; for {config.total_steps} steps resolve the recipe first, "
                          f"config.for_scene(scene).with_total_steps(N), as the examples' --steps does", stacklevel=3)
        self.config = config = resolved
        if not densifies_at_some_step(config):
            warnings.warn(no_densification_message(config), NoDensificationWarning, stacklevel=2)
        self.plan = StagePlan(config.stages, config.restart_per_stage,
                              config.step_work if config.counts_work else None)
        times = [c.time for c in scene.train_cameras] if config.time_spread != "random" else None
        self.sampler = ViewSampler(len(scene.train_cameras), seed=config.seed, times=times,
                                   time_spread=config.time_spread)
        self._bg_gen = torch.Generator().manual_seed(config.seed + 1)
        self._scaled: Dict[Tuple[int, int], Camera] = {}
        self.step_count = 0
        self.stage_start_count: Optional[int] = None  # primitive_count when the current stage began
        self.initial_count: Optional[int] = None  # primitive_count when the first step began
        self._warned_no_maps = False
        self._warned_no_count = False
        # MVGSConfig.prune_faint: views whose statistics were collected since the window closed, and
        # whether the cut was made (it comes after 2 x the training views)
        self.faint_views = 0
        self.faint_done = False
        self._faint_adapter = None  # the adapter enable_faint_cut() asked for blend statistics
        points = getattr(scene, "points", None)
        self.primitive_count = len(points) if points is not None and len(points) else UNKNOWN_PRIMITIVES
        self._views = views_fingerprint(scene.train_cameras)  # recorded in state_dict(); the views never change
        self._digests: Optional[List[str]] = None  # _image_digests(), made at the first state_dict() or resume
        n_views = len(scene.train_cameras)
        over = [f"stage {k} ({st.views} views at 1/{st.factor:g})" for k, st in enumerate(config.stages)
                if st.views > n_views]
        if over:
            verb, whose = ("ask", "their") if len(over) > 1 else ("asks", "its")
            warnings.warn(f"{', '.join(over)} {verb} for more views per step than the scene's {n_views} training "
                          f"views: each of {whose} steps renders all {n_views} (the plan and its record keep the "
                          "number asked)", stacklevel=2)

    @property
    def total_steps(self) -> int:
        return self.plan.total_steps

    def __iter__(self) -> Iterator[StepPlan]:
        while self.step_count < self.plan.total_steps:
            yield self.next()

    def next(self) -> StepPlan:
        """The plan of the next step (advances the sampler and the step counter)."""
        if self.step_count >= self.plan.total_steps:
            raise RuntimeError(f"training is complete ({self.plan.total_steps} steps); nothing left to run")
        cfg = self.config
        s = self.step_count + 1
        pos = self.plan.locate(s)
        if pos.first_in_stage or self.stage_start_count is None:
            self.stage_start_count = self.primitive_count
        if self.initial_count is None:
            self.initial_count = self.primitive_count
        ids = self.sampler.sample(min(pos.stage.views, len(self.scene.train_cameras)))
        cams = [self._camera(i, pos.stage.factor) for i in ids]
        images = ([self.scene.image(self.scene.train_cameras[i], pos.stage.factor) for i in ids]
                  if self.load_images else [])
        masks = ([self.scene.mask(self.scene.train_cameras[i], pos.stage.factor) for i in ids]
                 if self.load_images and getattr(self.scene, "has_masks", False) else None)
        chunks = self._chunks(len(ids), self.chunk_size(len(ids), cams[0].height, cams[0].width))
        window = pos.clock < cfg.densify_until
        densify = window and pos.clock > cfg.densify_from and pos.crosses(cfg.densify_every)
        # after the window, prune_faint keeps collecting until its cut (2 x the training views later);
        # a run whose window densified at no step (too short: NoDensificationWarning) makes no cut
        faint_cut, collect = False, window
        if cfg.prune_faint > 0 and not window and not self.faint_done and densifies_at_some_step(cfg):
            collect = True
            self.faint_views += len(ids)
            faint_cut = densify = self.faint_views >= 2 * len(self.scene.train_cameras)
            self.faint_done = faint_cut
        stats = [collect and (cfg.stats_from == "all" or c[-1] == len(ids) - 1) for c in chunks]
        self.step_count = s
        return StepPlan(
            step=s, clock=pos.clock, stage=pos.index, factor=pos.stage.factor, views=ids, cameras=cams,
            images=images, backgrounds=self._backgrounds(len(ids)),
            weight=1.0 if cfg.reduction == "sum" else 1.0 / len(ids), chunks=chunks, stats=stats,
            densify=densify,
            reset_opacity=window and pos.crosses(cfg.opacity_reset_every) and (
                cfg.coarse_opacity_reset or pos.stage.factor == self.plan.finest_factor),
            handoff_reset=pos.first_in_stage and pos.index > 0 and cfg.opacity_reset_at_handoff,
            wants_maps=densify and cfg.crd.enabled and not faint_cut, masks=masks, faint_cut=faint_cut,
        )

    @property
    def work_done(self) -> float:
        """Work rendered so far, in full-resolution view renders (MVGSConfig.budget's unit):
        each view at pyramid factor f counts view_cost(f), whichever clock the run is on."""
        n_train, left, work = len(self.scene.train_cameras), self.step_count, 0.0
        for stage in self.plan.stages:
            n = min(left, stage.steps)
            work += n * self.config.step_work(stage) * min(stage.views, n_train) / stage.views
            left -= n
        return work

    def base_threshold(self, plan: StepPlan) -> float:
        """β before MVAD: config.grad_threshold, times config.grad_threshold_width / W when that
        is set (W the mean width of the step's images at its pyramid level). The statistics of
        a densification call may include views from the previous level when a stage has just
        handed over; the current level decides."""
        cfg = self.config
        width = sum(c.width for c in plan.cameras) / len(plan.cameras)
        return resolution_threshold(cfg.grad_threshold, width, cfg.grad_threshold_width)

    def enable_faint_cut(self, adapter) -> bool:
        """Ask `adapter` for the blend statistics config.prune_faint's cut needs (its
        collect_blend_stats()). An adapter that cannot report them (none of that method, as
        Scaffold-GS's anchors, or a rasterizer without the keyword: it returns False) runs
        without the cut: config.prune_faint becomes 0 and a warning says so. The controller calls
        it when built; densify_context(adapter=...) at the first densification of a hand-written
        loop (early enough: the cut uses the statistics after the window's last call). Returns
        whether the cut stays on."""
        if self.config.prune_faint <= 0:
            return False
        if self._faint_adapter is adapter:
            return True
        collect = getattr(adapter, "collect_blend_stats", None)
        if callable(collect) and collect() is not False:
            self._faint_adapter = adapter
            return True
        warnings.warn(f"config.prune_faint={self.config.prune_faint}: {type(adapter).__name__} reports no blend "
                      "weights (collect_blend_stats(); GS3DAdapter and GS4DAdapter with the reference renderer do), "
                      "so this run makes no cut of the faintest Gaussians (prune_faint=0)", stacklevel=3)
        self.config = dataclasses.replace(self.config, prune_faint=0.0)
        return False

    def densify_context(self, plan: StepPlan, loss_maps: Optional[Sequence[Tensor]] = None,
                        primitive_count: Optional[int] = None, bounds: Optional[Tensor] = None,
                        stage_start_count: Optional[int] = None, adapter=None) -> DensifyContext:
        """The densification context of a step: the threshold (scaled to the step's image width
        when config.grad_threshold_width is set, halved by MVAD when the step's cameras are far
        apart), the scene scale, size pruning, and the cross-ray boxes (CRD)
        from the step's per-view loss maps [H', W'] (same order as plan.cameras). Without
        loss_maps, the maps a loop recorded with plan.record() are used; with neither, CRD is
        skipped for the step (boxes None) and a warning says so once per schedule.
        stage_start_count: the primitive count when the step's stage began, for the cap of
        config.stage_growth (None: the count primitive_count had when next() began the stage).
        primitive_count (the model's size, for CRD's max_new cap) and bounds (its positions' [2, 3]
        min and max, for CRD's clip) come from `adapter` when given (anything with
        num_primitives() and positions(), as a hand-written loop's model); without either, the
        count the schedule was last told (self.primitive_count) is used, with a warning once when
        the cap needs it."""
        if adapter is not None:
            self.enable_faint_cut(adapter)  # nothing without prune_faint; once per adapter
        cfg = self.config
        if plan.faint_cut:  # prune_faint's cut: no growth, no boxes
            return DensifyContext(step=plan.clock, grad_threshold=math.inf, scene_extent=float(self.scene.extent),
                                  scene_center=self.scene.center, prune_large=False, cameras=tuple(plan.cameras),
                                  max_primitives=self._growth_cap(stage_start_count, plan.clock),
                                  rank_by=cfg.densify_rank, faint_share=cfg.prune_faint)
        if adapter is not None:
            primitive_count = adapter.num_primitives() if primitive_count is None else primitive_count
            if bounds is None:
                positions = adapter.positions().detach()
                bounds = torch.stack([positions.amin(0), positions.amax(0)]).double().cpu() if len(positions) else None
        threshold = self.base_threshold(plan)
        if cfg.mvad.enabled:
            mvad = cfg.mvad
            cams = [self.scene.train_cameras[i] for i in plan.views]
            centers = torch.stack([c.center for c in cams])
            origin = torch.zeros(3, dtype=torch.float64) if mvad.center == "origin" else self.scene.center
            threshold = mvad_threshold(centers, threshold, origin=origin, tau=mvad.tau, rule=mvad.rule,
                                       axes=camera_axes(cams) if mvad.rotation_weight else None,
                                       rotation_weight=mvad.rotation_weight)
        boxes, cap = None, None
        crd = cfg.crd
        if crd.enabled and loss_maps is None:
            if len(plan.recorded) == len(plan.views):
                loss_maps = plan.recorded
            elif not self._warned_no_maps:
                self._warned_no_maps = True
                warnings.warn(f"step {plan.step}: cross-ray densification (config.crd) is skipped: it needs the "
                              f"step's per-view loss maps ({len(plan.recorded)} of {len(plan.views)} recorded); "
                              "call plan.record(images, targets) after each chunk's backward, or pass "
                              "densify_context(plan, loss_maps). Said once per schedule.", stacklevel=2)
        if crd.enabled and loss_maps is not None:
            h, w = crd.window
            if crd.window_per_level:
                h, w = max(1, round(h / plan.factor)), max(1, round(w / plan.factor))
            maps = [m.detach().cpu() for m in loss_maps]  # a few [H, W] maps: the windows and rays are CPU work
            if len({tuple(m.shape) for m in maps}) == 1:
                windows = best_windows(torch.stack(maps), (h, w))
            else:  # images of mixed sizes: one view at a time
                windows = torch.cat([best_windows(m[None], (h, w)) for m in maps])
            boxes, _ = cross_ray_boxes(
                plan.cameras, windows, forward_only=crd.forward_only,
                max_miss=None if crd.max_miss is None else crd.max_miss * float(self.scene.extent),
                min_angle_deg=crd.min_angle_deg, bounds=bounds if crd.clip else None, pad_by_miss=crd.pad_by_miss)
            if crd.max_new is not None:
                if primitive_count is None:
                    primitive_count = self.primitive_count
                    if not self._warned_no_count:
                        self._warned_no_count = True
                        warnings.warn(f"step {plan.step}: cross-ray densification caps its clones at {crd.max_new} x the "
                                      f"model's size, which densify_context was not given; the schedule's last count "
                                      f"({primitive_count}) is used. Pass densify_context(plan, adapter=model) or "
                                      "primitive_count=. Said once per schedule.", stacklevel=2)
                cap = int(math.ceil(crd.max_new * primitive_count))
        return DensifyContext(
            step=plan.clock,
            grad_threshold=threshold,
            scene_extent=float(self.scene.extent),
            scene_center=self.scene.center,
            boxes=boxes,
            max_new_from_boxes=cap,
            prune_large=plan.clock > cfg.prune_large_after and (cfg.max_gaussians is None or cfg.budget_size_pruning),
            cameras=tuple(plan.cameras),
            max_primitives=self._growth_cap(stage_start_count, plan.clock),
            rank_by=cfg.densify_rank,
            swap_share=cfg.budget_swap,
        )

    def _growth_cap(self, stage_start_count: Optional[int], clock: float) -> Optional[int]:
        """The lower of the stage_growth cap and budget_cap(clock), or None when neither is set."""
        start = self.stage_start_count if stage_start_count is None else stage_start_count
        caps = [self.budget_cap(clock)]
        if self.config.stage_growth is not None and start is not None:
            caps.append(int(math.floor(self.config.stage_growth * start)))
        caps = [c for c in caps if c is not None]
        return min(caps) if caps else None

    def budget_cap(self, clock: float) -> Optional[int]:
        """The primitive count config.max_gaussians allows at clock `clock` (None without a
        budget): n0 + (N - n0) (1 - (1 - x)^2), n0 the count the run began with (at most N) and x
        the share of the densification window passed, reaching 1 at its last call
        (densify_until - densify_every), so the last densification may fill the budget."""
        n = self.config.max_gaussians
        if n is None:
            return None
        start = self.initial_count if self.initial_count is not None else self.primitive_count
        n0 = min(int(start), n)
        lo, hi = self.config.densify_from, self.config.densify_until - self.config.densify_every
        x = 1.0 if hi <= lo else min(1.0, max(0.0, (float(clock) - lo) / (hi - lo)))
        return int(math.floor(n0 + (n - n0) * (1.0 - (1.0 - x) ** 2)))

    def initial_cut(self, count: int) -> Optional[DensifyContext]:
        """For a loop that drives its own model: before the first step, the densification
        context that cuts a model of `count` primitives to config.initial_cap() (a call that
        grows nothing and keeps the highest keep scores, as MVGS.step() does), or None when
        there is no budget, the model fits, or the run has begun. The schedule's growth then
        starts from the count after the cut."""
        cap = self.config.initial_cap()
        if cap is None or self.step_count > 0:
            return None
        self.primitive_count = min(int(count), cap)
        if int(count) <= cap:
            return None
        return self.cut_context(cap)

    def cut_context(self, cap: int) -> DensifyContext:
        """A densification call that grows nothing (threshold +inf) with `cap` as its bound, so
        the adapter drops its lowest keep scores down to it."""
        return DensifyContext(step=self.step_count, grad_threshold=math.inf, scene_extent=float(self.scene.extent),
                              scene_center=self.scene.center, max_primitives=cap, rank_by=self.config.densify_rank)

    def chunk_size(self, m: int, height: int, width: int) -> int:
        """Views per renderer call for a step of m views of height x width: config.chunk_size,
        or (None) the most views whose view_bytes() fit config.chunk_memory_mb, in [1, m]."""
        if self.config.chunk_size is not None:
            return self.config.chunk_size
        per_view = view_bytes(self.primitive_count, height, width)
        return max(1, min(m, int(self.config.chunk_memory_mb * 2**20 // max(1, per_view))))

    def _chunks(self, m: int, size: int) -> List[List[int]]:
        """View positions grouped for rendering, `size` per chunk. With stats_from="last" the
        last view renders alone, so its statistics can be taken without the others'."""
        head = m - 1 if self.config.stats_from == "last" else m
        chunks = [list(range(i, min(i + size, head))) for i in range(0, head, size)]
        return chunks + ([[m - 1]] if self.config.stats_from == "last" else [])

    def _camera(self, index: int, factor: int) -> Camera:
        key = (index, factor)
        if key not in self._scaled:
            cam = self.scene.train_cameras[index]
            self._scaled[key] = cam if factor == 1 else cam.scaled(factor)
        return self._scaled[key]

    def background_value(self) -> Tuple[float, float, float]:
        """The fixed background colour: the test renders' and the metrics'. "random" trains on a
        new colour every step and has no single one, so it evaluates on the scene's own (the
        colour its images were composited on: black without one), as "auto" does."""
        bg = self.config.background
        if bg in ("auto", "random"):
            return (0.0, 0.0, 0.0) if self.scene.background is None else tuple(float(c) for c in self.scene.background)
        return {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}.get(bg, bg)

    def _backgrounds(self, n: int) -> Tensor:
        if self.config.background == "random":
            return torch.rand(n, 3, generator=self._bg_gen)
        return torch.tensor(self.background_value(), dtype=torch.float32).expand(n, 3).clone()

    def state_dict(self) -> Dict:
        return {"step": self.step_count, "sampler": self.sampler.state_dict(), "background_rng": self._bg_gen.get_state(),
                "stage_start_count": self.stage_start_count, "initial_count": self.initial_count,
                "views": self._views, "images": self._image_digests(), "plan": self._plan_key(),
                "faint": [self.faint_views, self.faint_done]}

    def _image_digests(self) -> Optional[List[str]]:
        """Per training view, in order, the digest of its image (Scene.image_digest), or None for a
        scene object without digests (a user's own scene class); computed once."""
        if self._digests is None:
            digest = getattr(self.scene, "image_digest", None)
            if digest is None:
                return None
            self._digests = [digest(cam) for cam in self.scene.train_cameras]
        return self._digests

    def _plan_key(self) -> Dict:
        """What a state's step count means: the stage plan and the densification clock."""
        c = self.config
        return {"stages": [[float(st.factor), int(st.views), int(st.steps)] for st in c.stages],
                "clock": [c.densify_from, c.densify_until, c.densify_every, c.opacity_reset_every]}

    def check_views_of(self, state: Dict) -> None:
        """ValueError unless a state_dict() was saved on these training views (check_same_views)
        and their images (check_same_images); a state saved before views or images were
        recorded, or a scene object without Scene.image_digest, passes that part."""
        saved = state.get("views") if isinstance(state, dict) else None
        if saved is not None:
            check_same_views(saved, self._views)
        saved = state.get("images") if isinstance(state, dict) else None
        if saved is not None:
            mine = self._image_digests()
            if mine is not None:
                check_same_images(saved, mine, self.scene.train_cameras)

    def load_state_dict(self, state: Dict) -> None:
        """Restore a state_dict(). A state saved on other training views (names, sizes,
        intrinsics, poses, times, the content of their image files) is refused with a ValueError
        naming the first view that differs, before anything is changed; so is a state saved by
        another stage plan or densification clock (another preset, step count or views per
        step); states saved before these were recorded load without those checks."""
        self.check_views_of(state)
        saved, mine = (state.get("plan") if isinstance(state, dict) else None), self._plan_key()
        if saved is not None and saved != mine:  # absent in states saved before it was recorded
            key = "stages" if saved["stages"] != mine["stages"] else "clock"
            what = {"stages": "stage plan (factor, views, steps)",
                    "clock": "densification clock (densify_from, densify_until, densify_every, opacity_reset_every)"}[key]
            raise ValueError(f"this state was saved by a schedule with another {what}: {saved[key]}, this one has "
                             f"{mine[key]}; resume with the config (preset, steps, views) it was saved with")
        self.step_count = int(state["step"])
        self.sampler.load_state_dict(state["sampler"])
        self._bg_gen.set_state(state["background_rng"])
        self.stage_start_count = state.get("stage_start_count")  # absent in checkpoints before stage_growth
        self.initial_count = state.get("initial_count")  # absent in checkpoints before max_gaussians
        self.faint_views, self.faint_done = state.get("faint", (0, False))  # absent before prune_faint


def check_same_images(saved: Sequence[str], current: Sequence[str], cameras: Sequence[Camera]) -> None:
    """ValueError unless two lists of image digests (Schedule._image_digests) agree, naming the
    views whose images differ; the cameras were checked first (check_same_views), so the lists
    have one entry per view of the same names."""
    differ = [i for i, (a, b) in enumerate(zip(saved, current)) if a != b]
    if len(saved) != len(current) or differ:
        named = ", ".join(f"{i} ({cameras[i].name!r})" for i in differ[:3]) + (" ..." if len(differ) > 3 else "")
        raise ValueError(f"the checkpoint was made on other images of the same cameras: {len(differ)} of "
                         f"{len(current)} training views' image files differ in content (view {named}); resume on "
                         "the images the checkpoint was written with")


def views_fingerprint(cameras: Sequence[Camera]) -> List[List]:
    """One entry per training view, in order: [name, width, height, [its intrinsics (9), pose
    (the 12 numbers of world_to_camera's top rows) and time, as floats]], what
    check_same_views() compares."""
    out = []
    for cam in cameras:
        values = cam.K.reshape(-1).tolist() + cam.world_to_camera[:3].reshape(-1).tolist()
        values.append(-1.0 if cam.time is None else float(cam.time))
        out.append([cam.name, int(cam.width), int(cam.height), values])
    return out


# relative tolerance of check_same_views on a view's numbers: the same files loaded on another
# machine may differ in the last bits of a matrix inverse; another camera differs by far more
VIEWS_TOLERANCE = 1e-6


def check_same_views(saved: Sequence[Sequence], current: Sequence[Sequence]) -> None:
    """ValueError unless two views_fingerprint() lists agree (names and sizes exactly, the
    numbers to VIEWS_TOLERANCE relative to the view's largest), naming the first difference."""
    hint = "resume on the scene the checkpoint was written with"
    if len(saved) != len(current):
        raise ValueError(f"the checkpoint was made on {len(saved)} training views, this run has {len(current)}: {hint}")
    for i, (a, b) in enumerate(zip(saved, current)):
        if a[0] != b[0]:
            what = f"its image is {a[0]!r} in the checkpoint and {b[0]!r} here"
        elif list(a[1:3]) != list(b[1:3]):
            what = f"its size is {a[1]}x{a[2]} px in the checkpoint and {b[1]}x{b[2]} here"
        else:
            x, y = torch.tensor(a[3], dtype=torch.float64), torch.tensor(b[3], dtype=torch.float64)
            if x.shape == y.shape and float((x - y).abs().max()) <= VIEWS_TOLERANCE * (
                    1.0 + float(torch.maximum(x.abs(), y.abs()).max())):
                continue
            what = "its intrinsics, pose or time differ"
        raise ValueError(f"the checkpoint was made on other training views: view {i} ({b[0]!r}): {what}; {hint}")
