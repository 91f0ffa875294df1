"""The Adapter protocol: what the MVGS controller asks of a Gaussian model and its renderer.

The controller knows cameras, images, losses and schedules; an adapter owns everything
model-specific: its parameters and optimizer groups, how it renders, what statistics its
densification needs, how it densifies and prunes, and how it is saved. Implement this protocol
for your own model and renderer (gsplat, the original CUDA rasterizer, ...) without touching
`mvgs_plugin`; run `mvgs_plugin.testing.check_adapter` on it.

One step of the controller, for the M views the sampler picked (rendered in chunks of
`config.chunk_size` views so memory does not grow with M):

    adapter.set_step(step)                         # learning rates, SH degree, ...
    for chunk in views:
        result = adapter.render(chunk_cameras, backgrounds)
        loss = sum of per-view photometric losses (+ adapter.regularization(step), once)
        loss.backward()                            # gradients accumulate in .grad
        adapter.accumulate_stats(result)           # all views, or only the last ("last")
    (NaN/Inf guard on adapter.named_gradients())
    if densification is due: adapter.densify(DensifyContext(...))
    adapter.optimizer_step(); adapter.zero_grad()

Training over several processes (mvgs_plugin.distributed) needs three more methods, listed in
DistributedAdapter: the parameters whose gradients are summed over ranks, and the densification
statistics with how they combine.

The controller never assumes one Gaussian per trainable row (Scaffold-GS decodes a different set
of Gaussians per view) nor a static scene (cameras carry `time`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Protocol, Sequence, Tuple, runtime_checkable

from torch import Tensor

from .camera import Camera


@dataclass
class RenderResult:
    """What an adapter returns for a chunk of C views (all of one size).

    images: [C, H, W, 3] linear colour, differentiable w.r.t. the adapter's parameters.
    alphas: [C, H, W, 1] accumulated opacity, or None.
    aux: anything the adapter needs later in `accumulate_stats` (e.g. gsplat's meta dict with
        means2d and radii). The controller never looks inside.
    """

    images: Tensor
    alphas: Optional[Tensor] = None
    aux: Any = None


@dataclass
class DensifyContext:
    """Everything the controller decided for one densification call.

    step: the clock the schedules run on at this step (StepPlan.clock), the value set_step got:
        the step number (1-based, as the original 3DGS counts) when the clocks count steps; the
        work done so far in full-resolution view renders, an int, when they count work (a
        budget, or clock_unit="work", as the default preset) so cheap coarse steps advance it by
        less than 1 and consecutive calls may see the same value; counted per stage with
        restart_per_stage. 0 for the cut to the budget before the first step.
    grad_threshold: screen-space gradient threshold (NDC units, 2e-4 by default) after the
        multi-view augmented rule (MVAD) has possibly lowered it for this step.
    scene_extent: the scene scale used by size thresholds (Scene.extent).
    scene_center: [3] the centre the extent is measured from (Scene.center), or None; a size
        rule may grow with the distance from it (GS3DConfig.world_size_rule).
    boxes: [B, 2, 3] axis-aligned boxes (min corner, max corner) from cross-ray densification
        (CRD): primitives strictly inside any box are densified once; None when CRD is off.
    max_new_from_boxes: cap on how many primitives the boxes may add in this call (None = no cap).
    prune_large: whether size-based pruning (screen radius / world size) is active now (the
        original 3DGS turns it on after the first opacity reset).
    cameras: the cameras of the step that triggered the call (stage resolution).
    max_primitives: a cap on the primitive count after the call (None: no cap from the
        controller; MVGSConfig.max_gaussians and stage_growth set it). Growth stops at it; a model
        that already holds more after its prune rules sheds its lowest-ranked rows down to it (the
        bundled adapters rank by keep score: GS3DAdapter.keep_scores). The controller checks the
        count after the call and stops the run when an adapter exceeds the cap.
    rank_by: which score orders the growth candidates when a cap binds: "consistency" (the
        gradient weighted by how evenly the views share it, GS3DAdapter.densify_scores) or
        "gradient" (3DGS's mean gradient). MVGSConfig.densify_rank sets it.
    swap_share: while the cap binds (more growth candidates than room), the adapter may remove
        up to floor(swap_share x cap) of its lowest-ranked rows that are not candidates and grow
        that many more of the best candidates in their place (MVGSConfig.budget_swap; 0 = never).
    faint_share: 0, or (the one call MVGSConfig.prune_faint schedules after densification, with
        grad_threshold inf and no boxes) the share S of the blend weight whose faintest carriers
        the call removes (GS3DAdapter: gs3d.faint_rows over its blend statistics).
    """

    step: int
    grad_threshold: float
    scene_extent: float
    boxes: Optional[Tensor] = None
    max_new_from_boxes: Optional[int] = None
    prune_large: bool = False
    cameras: Sequence[Camera] = ()
    max_primitives: Optional[int] = None
    rank_by: str = "consistency"
    swap_share: float = 0.0
    scene_center: Optional[Tensor] = None
    faint_share: float = 0.0


@dataclass
class DensifyReport:
    """What a densification call did (counts of primitives: Gaussians, or anchors)."""

    before: int
    after: int
    cloned: int = 0
    split: int = 0
    pruned: int = 0
    from_boxes: int = 0
    extra: Dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Adapter(Protocol):
    """A Gaussian model plus its renderer and optimizer, as the controller drives it."""

    def render(self, cameras: Sequence[Camera], backgrounds: Tensor) -> RenderResult:
        """Render C views of one size. backgrounds: [C, 3]. Returns images [C, H, W, 3]."""

    def regularization(self, step: int) -> Optional[Tensor]:
        """A scalar added once per step to the summed loss (e.g. Scaffold's volume term), or None."""

    def accumulate_stats(self, result: RenderResult) -> None:
        """Fold the densification statistics of a rendered chunk in, after its backward."""

    def densify(self, ctx: DensifyContext) -> DensifyReport:
        """Grow and prune using the accumulated statistics, then reset them. Optimizer state must
        stay aligned with the parameters."""

    def reset_opacity(self) -> None:
        """The periodic opacity reset of 3DGS (a no-op for models without one)."""

    def set_step(self, step: int) -> None:
        """Called at the start of every step with the clock the schedules run on (the value
        DensifyContext.step gets: the step number, or the work done so far, which may repeat
        over cheap coarse steps and starts at 0): learning-rate schedule, SH degree, stage
        switches. Schedule on it, not on a count of calls; it never decreases within a stage."""

    def named_gradients(self) -> Dict[str, Optional[Tensor]]:
        """Current gradients of every trainable group by name (for the NaN/Inf guard)."""

    def optimizer_step(self) -> None:
        """Apply the accumulated gradients."""

    def zero_grad(self) -> None:
        """Clear the gradients (after the optimizer step)."""

    def positions(self) -> Tensor:
        """[P, 3] positions of the primitives (Gaussians or anchors) for region queries."""

    def num_primitives(self) -> int:
        """Number of primitives (Gaussians, or anchors for Scaffold-GS)."""

    def state_dict(self) -> Dict[str, Any]:
        """Parameters, optimizer state, statistics and schedule state (everything to resume)."""

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        """Restore what state_dict() returned (the primitive count may differ from now)."""

    def export(self, path: str, camera: Optional[Camera] = None) -> None:
        """Write the model in its standard interchange format (a 3DGS PLY for Gaussians); the
        camera is for models that decode Gaussians per view."""


ADAPTER_METHODS = ("render", "regularization", "accumulate_stats", "densify", "reset_opacity", "set_step",
                   "named_gradients", "optimizer_step", "zero_grad", "positions", "num_primitives", "state_dict",
                   "load_state_dict", "export")


def check_is_adapter(adapter, what: str = "adapter") -> None:
    """TypeError unless `adapter` is an instance with every Adapter method (a class, None, or an
    object missing some is named with what it lacks): a missing method would otherwise end a
    run at the step that first calls it (reset_opacity: the first opacity reset)."""
    if isinstance(adapter, type):
        raise TypeError(f"{what} must be an adapter instance, got the class {adapter.__name__} (build one, e.g. "
                        f"{adapter.__name__}.from_scene(scene, ...))")
    missing = [m for m in ADAPTER_METHODS if not callable(getattr(adapter, m, None))]
    if missing:
        raise TypeError(f"{what} must implement the Adapter protocol (mvgs_plugin.protocol.Adapter): "
                        f"{type(adapter).__name__} has no {', '.join(missing)}" +
                        (" (a model without an opacity reset implements reset_opacity as a no-op; one without a "
                         "regularizer returns None from regularization)" if {"reset_opacity", "regularization"} &
                         set(missing) else ""))


class ScaledViewsAdapter(Protocol):
    """An optional method for MVGSConfig.views_scaling="sqrt": MVGS calls it before every
    set_step with the step's number of views M; the adapter then sets its optimizer for an M-view
    step (Grendel-GS's rule: learning rates x √M, Adam betas to the power M, eps / √M; M = 1 gives
    the single-view values). The bundled adapters implement it (mvgs_plugin.adapters.ops.scale_for_views)."""

    def set_views_per_step(self, views: int) -> None:
        """Scale the optimizer for steps of `views` views from the next set_step on."""


class ClockedAdapter(Protocol):
    """An optional method for a model whose own schedules (learning-rate decays, a static first
    stage) are set in steps: MVGS calls it once with the run's clock length (config.clock_length)
    and warns with what it returns. The bundled adapters implement it; their configs' for_run(run)
    puts the schedules on the run's clock."""

    def clock_mismatch(self, clock: int) -> Optional[Tuple[str, int, str]]:
        """None when the model's schedules span `clock`; else (what: the config field and what it
        does, the steps it spans, the fix: e.g. "GS3DConfig.for_run(config)")."""


@runtime_checkable
class DistributedAdapter(Protocol):
    """Optional extra methods an adapter implements to be trained over several processes
    (mvgs_plugin.distributed): every rank holds the full model and renders a share of each
    step's views, so the controller sums the gradients and the densification statistics over
    ranks before the optimizer step and before densification.

    check_adapter runs check_distributed_support on adapters that implement these methods.
    """

    def gradient_parameters(self) -> Dict[str, Tensor]:
        """Every trainable tensor by the names named_gradients() uses. The controller sums their
        ``.grad`` over ranks in place, and gives a zero ``.grad`` to a tensor that has none on
        this rank while another rank has one (a rank that rendered no view)."""

    def statistics(self) -> Dict[str, Tuple[Tensor, str]]:
        """The densification statistics accumulated so far, by name: (tensor, how ranks combine
        it: "sum" or "max"). Combining the statistics of two adapters that rendered disjoint sets
        of views must give the statistics of one adapter that rendered them all."""

    def load_statistics(self, stats: Dict[str, Tensor]) -> None:
        """Replace the statistics by tensors of the same names and shapes as statistics()."""
