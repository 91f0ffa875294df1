"""MVGSConfig: every knob of the controller, with presets.

- ``MVGSConfig.baseline()``: the original 3DGS recipe (one view per step, one stage). With it the
  controller is plain 3DGS training, so baseline and MVGS run through the same code.
- ``MVGSConfig.paper()``: the released MVGS behaviour (docs/method.md): stages {8,4,2,1} with
  M {48,24,12,8}; schedules restart at every stage and opacities are reset at each hand-off;
  densification statistics from the last view of a step only.
- ``MVGSConfig.multiview()``: the paper's method with our fixes: one continuous schedule, no
  reset at hand-offs, statistics from all views of the step, a gradient threshold scaled to the
  image width. It beats the baseline at equal steps and loses at equal compute
  (docs/equal_compute.md).
- ``MVGSConfig.default()``: the cost-aware recipe, chosen at equal compute on the budget clock:
  cross-intrinsic guidance as a coarse-to-fine warm-up (30 / 70 % of the work at 1/2 and full
  resolution), one view per step, the width-scaled threshold.

Every deviation from the paper is a named field. Step counts follow the original 30k-step
recipe; ``with_total_steps(n)`` rescales every step-valued field for short runs.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from dataclasses import dataclass, field
from typing import Optional, Tuple, Union

from .camera import scaled_size
from .checks import check_int, is_int


def _check_finite_above(name: str, value, low: float, what: str, optional: bool = False,
                        inclusive: bool = False) -> None:
    """Raise ValueError("<name> must be <what>, got <value>") unless value is a real number (not a
    bool) with low < value < inf (low <= value with inclusive), or None when optional. NaN and
    infinities never pass."""
    if optional and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not (
            low <= value if inclusive else low < value):
        raise ValueError(f"{name} must be {what}, got {value!r}")


@dataclass(frozen=True)
class Stage:
    """One level of cross-intrinsic guidance: image pyramid factor, views per step, steps."""

    factor: int
    views: int
    steps: int

    def __post_init__(self):
        for name in ("factor", "views", "steps"):
            check_int(f"Stage.{name}", getattr(self, name), 1)


# The default's stage plan: (pyramid factor, views per step, share of the work). Until 2026-11-27
# it began with 10 % at 1/4 (then 20 % at 1/2): on seven generated scenes at 1k and 3k (two
# seeds) and three at 10k (docs/equal_compute_log.md, "The 1/4 level does not pay") moving that work
# to 1/2 was better at equal work in 21 of 29 pairs and on average at every budget.
DEFAULT_SHARES: Tuple[Tuple[int, int, float], ...] = ((2, 1, 0.30), (1, 1, 0.70))
# default()'s warmup_work_cap: the most full-resolution views' work its coarser stages get in any
# run (about the 30 % of a budget of 3000 its shares were chosen on; docs/equal_compute_log.md,
# "A warm-up of fixed length").
DEFAULT_WARMUP_WORK_CAP = 1000.0
# default()'s cut of the faintest Gaussians after densification (prune_faint): the share of the
# blend weight it may remove (docs/equal_compute_log.md, "The cut made the default's")
DEFAULT_PRUNE_FAINT = 0.01

# compact()'s data budget: training pixels per Gaussian. 0.6x the count of the baseline's data
# budget (128, fixed from 3DGS's own 70-210 on its benchmarks), the Gaussians issue 27 allows a
# recipe that is to beat the baseline; not tuned (docs/equal_compute_log.md, "The compact preset").
COMPACT_PIXELS_PER_GAUSSIAN = 213.0
# compact()'s budget_views: the views whose pixels make its data budget, whatever the rig has: the
# 48 of the generated scenes the ratio above was fixed on, so their budget is unchanged (3692 at
# 128 px). Counting every view gave the 10-view scene 769 Gaussians and cost it 5.7 dB at 10k; the
# content a rig round the scene shows does not grow with its number of views (docs/equal_compute_log.md,
# "A data budget that does not shrink with the views, and none on a rig that looks outward").
COMPACT_BUDGET_VIEWS = 48

# Upper bounds of the run's ints: a seed every RNG takes (numpy's legacy ones stop at 2^32), and
# a primitive count an int32 index holds (beyond it a budget is not a budget but an overflow).
MAX_SEED = 2**32 - 1
MAX_PRIMITIVES = 2**31 - 1

# The config fields that are clocks (steps, or work with clock_unit="work"): rescaled together.
CLOCK_FIELDS: Tuple[str, ...] = ("densify_from", "densify_until", "densify_every", "opacity_reset_every",
                                 "prune_large_after")

# The presets by name: MVGSConfig.from_preset's names (each a classmethod of that name) and the
# --preset choices of every command line, in the order --help lists them.
PRESETS: Tuple[str, ...] = ("default", "compact", "multiview", "paper", "baseline")


def checked_view_cost(view_cost) -> Tuple[float, float]:
    """MVGSConfig.view_cost as a tuple of two floats a, b >= 0 with a + b = 1, or a ValueError
    naming the value."""
    try:
        out = tuple(float(v) for v in view_cost)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 2 or not all(0.0 <= v < math.inf for v in out) or not math.isclose(sum(out), 1.0):
        raise ValueError(f"view_cost must be (a, b) with a, b >= 0 and a + b = 1, got {view_cost!r}")
    return out


def view_work(view_cost, relative_factor: float) -> float:
    """Work of one view at `relative_factor` times the finest stage's factor, in full-resolution
    view renders: a + b / relative_factor for view_cost (a, b)."""
    a, b = view_cost
    return a + b / relative_factor


def stages_from_shares(shares, total_work: float = 30_000.0, view_cost: Tuple[float, float] = (0.1, 0.9)
                       ) -> Tuple[Stage, ...]:
    """A stage plan from (factor, views, share of the work) triples: each stage gets the steps
    that make its share of `total_work` full-resolution view renders (a view at factor f costs
    a + b * f_min / f, see MVGSConfig.view_cost), at least one. with_budget() keeps the shares."""
    shares = tuple(shares)
    if not shares or any(len(t) != 3 for t in shares):
        raise ValueError(f"shares must be (factor, views, share) triples, got {shares!r}")
    total = sum(t[2] for t in shares)
    if not all(isinstance(t[2], (int, float)) and t[2] > 0 for t in shares) or not math.isclose(total, 1.0):
        raise ValueError(f"shares must be > 0 and sum to 1, got {[t[2] for t in shares]}")
    finest = min(t[0] for t in shares)
    return tuple(Stage(f, m, max(1, round(total_work * w / (m * view_work(view_cost, f / finest))))) for f, m, w in shares)



@dataclass(frozen=True)
class MVADConfig:
    """Multi-view augmented densification (densify/mvad.py): the gradient threshold is halved on
    a densification step whose cameras are far apart.

    enabled: the rule is on.
    tau: the discrepancy (chord on the unit sphere, 0..2) a pair of views needs.
    rule: "any" pair (released code) or a fraction of the pairs.
    rotation_weight: weight of the optical-axis angle / pi added to the chord (paper: 0).
    center: "origin" (the released code normalises about the world origin) or "scene" (the
        mean training camera centre, Scene.center).
    """

    enabled: bool = False
    tau: float = 1.0
    rule: Union[str, float] = "any"
    rotation_weight: float = 0.0
    center: str = "scene"

    def __post_init__(self):
        _check_finite_above("mvad.tau", self.tau, 0, "a finite discrepancy > 0 (a chord on the unit sphere is at most 2)")
        if not (isinstance(self.rule, str) and self.rule == "any") and not (
                not isinstance(self.rule, (str, bool)) and 0.0 < float(self.rule) <= 1.0):
            raise ValueError(f"mvad.rule must be 'any' or a fraction in (0, 1], got {self.rule!r}")
        if self.center not in ("origin", "scene"):
            raise ValueError(f"mvad.center must be one of ('origin', 'scene'), got {self.center!r}")
        _check_finite_above("mvad.rotation_weight", self.rotation_weight, 0, "a finite weight >= 0", inclusive=True)

    def __bool__(self) -> bool:
        """``enabled``, so that ``if config.mvad:`` (a bool in earlier releases) keeps its meaning."""
        return self.enabled


@dataclass(frozen=True)
class CRDConfig:
    """Cross-ray densification (densify/crd.py): clone what lies inside boxes where high-loss
    rays of different views cross.

    enabled: the rule is on.
    window: (rows, columns) of the loss window at full resolution (paper: 20 x 40).
    window_per_level: divide the window by the pyramid factor (ours) or keep it (paper).
    forward_only: drop pairs whose closest points lie behind a camera.
    max_miss: drop pairs whose rays pass further apart than this times the scene extent.
    pad_by_miss: grow each box by half its pair's largest miss distance.
    min_angle_deg: drop pairs whose rays are closer to parallel than this.
    clip: clip boxes to the bounding box of the model's primitives.
    max_new: cap on primitives one call may add, as a fraction of the current count.
    """

    enabled: bool = False
    window: Tuple[int, int] = (20, 40)
    window_per_level: bool = True
    forward_only: bool = True
    max_miss: Optional[float] = 0.05
    pad_by_miss: bool = True
    min_angle_deg: float = 1.0
    clip: bool = True
    max_new: Optional[float] = 0.05

    def __post_init__(self):
        object.__setattr__(self, "window", tuple(self.window))
        if len(self.window) != 2 or not all(is_int(v) and v >= 1 for v in self.window):
            raise ValueError(f"crd.window must be (rows, columns) of positive ints, got {self.window!r}")
        _check_finite_above("crd.max_new", self.max_new, 0, "None or a finite fraction > 0", optional=True)
        _check_finite_above("crd.max_miss", self.max_miss, 0, "None or a finite multiple of the extent > 0",
                            optional=True)
        _check_finite_above("crd.min_angle_deg", self.min_angle_deg, 0, "a finite angle in [0, 90) degrees", inclusive=True)
        if self.min_angle_deg >= 90:
            raise ValueError(f"crd.min_angle_deg must be a finite angle in [0, 90) degrees, got {self.min_angle_deg!r}")

    def __bool__(self) -> bool:
        """``enabled``, so that ``if config.crd:`` (a bool in earlier releases) keeps its meaning."""
        return self.enabled


# The flat field names of earlier releases: name -> (group, field). MVGSConfig(...) and
# MVGSConfig.from_dict accept them until the next release; reading them warns.
FLAT_NAMES = {
    **{f"mvad_{n}": ("mvad", n) for n in ("tau", "rule", "rotation_weight", "center")},
    **{f"crd_{n}": ("crd", n) for n in ("window", "window_per_level", "forward_only", "max_miss", "pad_by_miss",
                                         "min_angle_deg", "clip", "max_new")},
}


@dataclass
class MVGSConfig:
    """Controller settings (adapter settings live in the adapter's own config).

    stages: the stage plan (cross-intrinsic guidance); one Stage(1, M, steps) means no pyramid.
    reduction: "sum" of the per-view losses (the paper) or "mean".
    stats_from: densification statistics from "all" views of a step (ours) or the "last" one
        (the released code).
    chunk_size: views rendered and backpropagated together (one renderer call, one batched
        loss); memory grows with it, not with M. None (default): the most views whose
        estimated working memory fits chunk_memory_mb (see schedule.view_bytes: about 128 B per
        Gaussian plus 640 B per pixel per view, measured on the reference renderer), at least 1.
    chunk_memory_mb: the memory bound of chunk_size=None, in MiB. 128 keeps a step's peak memory
        within 1.25x of a one-view step at 100k Gaussians and 128 px (benchmarks/bench_memory.py)
        while 10k-Gaussian steps of 8 views at 128 px, or 48 at 16 px, still go in one call.
    lambda_dssim: weight of the SSIM term in (1 - λ) L1 + λ (1 - SSIM).
    densify_from / densify_until / densify_every / opacity_reset_every: the 3DGS clock
        (densify when from < step < until and step % every == 0; reset at multiples of
        opacity_reset_every while step < until).
    grad_threshold: β, the screen-space gradient threshold (NDC units).
    grad_threshold_width: None (3DGS, the paper: β as given at every resolution) or the image
        width in pixels β is meant for; a densification call then uses β × grad_threshold_width
        / W, W the width of the step's images at the current pyramid level. The NDC statistic
        of a Gaussian a few pixels wide grows as 1 / W for the same error per pixel (the loss
        averages over W × H pixels, the NDC factor is W / 2), so 3DGS's 2e-4, tuned on ~800 px
        images, densifies a 64 px image at a twelfth of the error; and a coarse pyramid level
        would densify detail it cannot show. See resolution_threshold().
    prune_large_after: size-based pruning is active once the step exceeds this (not with a
        budget, unless budget_size_pruning: see there).
    restart_per_stage: restart the learning-rate and densification clocks at each stage (the
        released code ran its stages as separate processes).
    opacity_reset_at_handoff: reset opacities when a stage hands over (released code: a side
        effect of its per-stage restart).
    coarse_opacity_reset: whether the periodic opacity resets (opacity_reset_every) also run
        while a coarser pyramid level trains (a stage whose factor is above the finest stage's).
        The clock is unchanged: a reset due at a coarse level is skipped, not moved. default()
        turns them off: on the generated 10-view scene a reset at 1/2 resolution left a model
        that fitted its training views and not the test views (1k: test 25.23 dB with them,
        28.67 without, training views 34.7 and 35.1; 10k: 26.92 and 30.36), and at 1k they cost
        every generated 360-degree, inside-out and arc scene 0.25-3.7 dB; on a wire fence they
        paid at 3k and 10k (docs/equal_compute_log.md, "No opacity reset at the coarse level").
    min_densify_per_reset: K, the fewest densification calls between two opacity resets when a
        schedule is compressed (with_total_steps / with_budget): 30, 3DGS's own ratio (a reset
        every 3000 steps, a densification every 100), so the uncompressed recipe is untouched.
        An opacity reset puts every opacity at 0.01 (logit -4.6); at Adam's opacity rate of 0.05
        per step a Gaussian the views need takes about 100-150 steps to come back, and the
        learning rates are not compressed. With the earlier floor of 10 a 1k-step run reset every
        100 steps, before its Gaussians had recovered from the last reset; 30 puts resets 300
        steps (work) apart below 3k and changes nothing from 3k up. Measured for every preset
        in docs/equal_compute_log.md, "Opacity resets that leave time to recover". Configs saved
        before the field read 10, the floor they were compressed with.
    background: "auto" (the colour the scene's RGBA images were composited on, else black),
        "black", "white", "random" (per view and step) or an (r, g, b) tuple.
    seed: seeds the view sampler and random backgrounds.
    budget: None (the clocks count steps) or the run's budget of work in full-resolution view
        renders (set by with_budget()). Then every clock (learning-rate decay, SH degree,
        densification window and interval, opacity resets, size pruning) counts work: a step of
        M views at pyramid factor f advances it by M * view_cost(f), so a baseline step is 1 and
        a run given budget B does B units of work whatever its recipe.
    clock_unit: what the clocks count without a budget: "steps" (3DGS; the multi-view presets,
        whose equal-steps evidence is stated in steps) or "work" (as on a budget: the clock-valued
        fields are then in full-resolution view renders of the recipe's total_work, and
        with_total_steps(N) keeps them at the same fractions of the work). default() counts
        work: its coarse steps are cheap, so 3DGS's step-valued densification window (until
        step 15000 of 30000) would end before its full-resolution stage begins (at 49 % of the
        steps, 30 % of the work).
    view_cost: (a, b): the work of one view at pyramid factor f is a + b / f full-resolution
        views (a + b = 1; f relative to the finest stage). Measured with benchmarks/bench_step.py on the reference renderer
        (10k Gaussians, 128 px, one thread; a view in a batched call): 16 px and 32 px views cost
        0.23 and 0.34 of a 128 px one and a 1 x 1 px view 0.10, so work shrinks as 1 / f (splats
        keep a footprint of a few pixels however small the image), not as the pixel count 1 / f^2.
    divergence_factor: stop with FloatingPointError when a step's loss per view exceeds this
        many times its running level (an exponential average of the past steps' losses, decay
        0.9, floored at 0.01; it starts again in every process); None: never. Normal runs stay
        below 10x (opacity resets, stage hand-offs); a learning rate of 1e3 on the colours gives
        360x at its first step.
    forward_rig: what the stage plan does on a forward-facing rig (optical axes nearly parallel,
        as in LLFF captures: mvgs_plugin.data.init.is_forward_facing): "pyramid" (run it as
        given) or "finest" (default(): drop the coarser stages and give the finest stage their
        work on a budget, their steps without one). Applied by for_scene(), which MVGS and
        ViewSchedule call. Why: on a forward-facing rig the coarse warm-up did not pay on either
        scene measured (docs/equal_compute_log.md, "Forward-facing rigs"): every view sees nearly the
        whole scene from one side, so full-resolution steps fit it from the start, and a model
        fitted at 1/4 or 1/2 resolution transfers badly to full resolution (4-12 dB below a
        baseline given the same work at the hand-off).
    views_scaling: how the optimizer treats an M-view step: "none" (the paper: the summed loss,
        the single-view learning rates) or "sqrt" (Grendel-GS's batch rule: learning rates x √M,
        Adam betas to the power M, eps / √M, M the step's views; the adapter applies it in
        set_views_per_step, which MVGS calls every step). Measured in docs/equal_compute.md.
    max_views_fraction: None, or a cap on the views of any step as a fraction of the scene's
        training views (at least 1): the sparse-view guard, so that on a scene with few views a
        step never sees most of them at once. Applied by for_scene(); a capped stage keeps its work
        on a budget (more, cheaper steps) and its steps otherwise.
    stage_growth: None, or how far densification may grow the primitive count within a stage:
        at most stage_growth times the count the stage began with (the run's initial count for
        the first stage), passed to the adapter as DensifyContext.max_primitives (the candidates
        with the largest gradients are kept). Densification tied to the stage, as DashGaussian
        ties the count to the resolution. Measured in docs/equal_compute.md.
    max_gaussians: None, or the run's budget of primitives (Gaussians; anchors for Scaffold-GS):
        the model never holds more. A model that starts above it is cut to it before the first
        step (its lowest keep scores go); growth then follows a schedule that starts at the
        initial count (at most N) and reaches N when the densification window ends,
        n0 + (N - n0) (1 - (1 - x)^2), x the share of the window passed (front-loaded: half the
        growth is allowed by a quarter of the window, as 3DGS grows most early); the candidates
        are ranked by densify_rank. Passed to the adapter as DensifyContext.max_primitives; the
        controller stops the run if an adapter exceeds it. Measured in docs/equal_compute.md.
    pixels_per_gaussian: None, or the budget as a ratio to the training data: for_scene() sets
        max_gaussians = round(training pixels / pixels_per_gaussian) (the training views' pixels at
        the finest stage's resolution) when max_gaussians is not given. 3DGS itself ends near 70
        (Mip-NeRF 360) to 210 (NeRF-synthetic) pixels per Gaussian on its benchmarks; a 128 px
        scene densified by the compressed schedule reaches 35 and overfits its views
        (docs/equal_compute_log.md, "A baseline that does not fall").
    budget_swap: the share of the cap one densification call may swap while the cap binds (the
        growth candidates outnumber the room): that many of the lowest keep scores among the rows
        that are not candidates are removed and the best-ranked candidates take their place, so a
        model at its budget keeps moving Gaussians from where they show little to where the views
        still pull. 0 (the default): growth waits for the prune rules to free room. It fits the
        training views better under the same count and measured both ways at a quarter budget
        (docs/equal_compute.md): +0.72 dB on the forward rig, -3.69 on forward-clutter, -0.04 to
        -3.60 on the 360-degree scenes (those with size pruning on). GS3DAdapter, GS4DAdapter and
        MVGSStrategy swap; Scaffold-GS's anchors do not (they ignore it).
    prune_faint: 0 (off; the field's default and every preset's but default()'s, which has
        DEFAULT_PRUNE_FAINT) or a share S in (0, 1): once densification has ended, the
        Gaussians with the least blend weight per blended pixel (alpha x transmittance, their share
        of the pixels' colours, summed over the training views since the last densification call
        and divided by the pixels they were blended at) that together carry at most S of all the
        weight are removed, in one call, after twice the training views have been rendered since
        the window closed (ViewSchedule: the statistics keep being collected until then). Needs
        an adapter that reports blend weights (GS3DAdapter, GS4DAdapter with the reference
        renderer). Measured in docs/equal_compute_log.md ("A cut of the faintest splats").
    budget_initial_share: the share of max_gaussians the initial model may hold: a model that
        starts above floor(share x N) is cut to it before the first step (lowest keep scores;
        before any view, gs3d.even_cut_order: the object's and the far background's shares,
        each spread over its extent), so that the rest of the budget is grown by the
        densify score, where the views' gradients ask for it. 1 (the default): the initial
        model may fill the budget, and a model that starts at or above it never grows.
    budget_size_pruning: whether a run with a budget (max_gaussians) still prunes by size
        (3DGS's rule after the first opacity reset: world size above max_world_size x the scene
        extent, screen radius above max_screen_size). Off by default: the budget bounds the
        count, and a small model covers the scene with large Gaussians that the size rule
        removes at every reset, so it never recovers inside the densification window (the
        generated sparse scene at 1280 Gaussians and 10k steps: 18.82 dB with the rule, 26.72
        without; docs/equal_compute.md). Without a budget size pruning runs as in 3DGS.
    budget_views: None, or how many views' pixels pixels_per_gaussian divides: that many views of
        the training views' mean size, however many the rig has (compact: 48), so a rig of 10 views
        and one of 200 of the same scene at the same resolution get the same budget. None: every
        training view counts, and the budget grows with the number of views.
    budget_rigs: the rigs pixels_per_gaussian sets a budget on: "all", or "round" (as compact()
        does): only a rig round the scene, whose optical axes spread and meet in front of it
        (data.init: axis_spread >= CONVERGING_SPREAD, look_convergence >= CONVERGING_COSINE), where
        every view shows the same content; not a forward-facing rig (on the generated ones a data
        budget cost the baseline 8.1 and 1.4 dB at 3k, as detail fitted in one view holds in the
        next one a few centimetres away), nor one that looks outward or walks through its scene,
        whose views each show other content. An explicit max_gaussians applies on every rig.
        (Before 2026-11-28 the bool forward_rig_budget: True is "all"; False exempted forward-facing
        rigs only.)
    densify_rank: which score picks the growth candidates when a cap (max_gaussians,
        stage_growth) binds: "consistency" (the mean gradient times how evenly the views of the
        window share it; see GS3DAdapter.densify_scores) or "gradient" (3DGS's mean gradient).
    warmup_work_cap: None, or the most work (full-resolution view renders) the stages coarser
        than the finest, the pyramid's warm-up, get once the run's length is set (with_budget(),
        with_total_steps()): when their share of the run would be more, each is scaled down to
        its share of the cap and the first finest stage takes over what they gave up (their work
        on a budget, their steps under with_total_steps(), so --steps N stays N steps). default():
        1000, about the 900 its 30 % share gives the 1/2 level at a budget of 3000: the plan is
        its shares up to a budget of 3333 and a warm-up of 1000 views' work beyond it (10 % at
        10k, 3.3 % at 30k). Why: the warm-up pays at 1k and 3k, where it was chosen, but at 10k
        the default with 30 % at 1/2 ended below the baseline on every 360-degree scene measured;
        measured in docs/equal_compute_log.md ("A warm-up of fixed length"). The examples set it to
        None when --stages gives the plan; with_late_views() drops it (train_4dgs.py's plan at
        --steps, whose late stage spends the warm-up's saving).
    time_spread: how a step's views spread over time in a dynamic scene (cameras with a time):
        "random" (the epoch shuffle decides), "stratified" (the M views come from M bins of
        nearly equal count along the sorted training times, one view per bin) or "instant" (a
        synchronized rig: the M views are M cameras at one time, deformed once; see sampler.py).

    mvad: multi-view augmented densification, an MVADConfig (off by default).
    crd: cross-ray densification, a CRDConfig (off by default).
    """

    stages: Tuple[Stage, ...] = (Stage(1, 1, 30_000),)
    reduction: str = "sum"
    stats_from: str = "all"
    chunk_size: Optional[int] = None
    chunk_memory_mb: float = 128.0
    lambda_dssim: float = 0.2
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    opacity_reset_every: int = 3_000
    grad_threshold: float = 2e-4
    grad_threshold_width: Optional[float] = None
    prune_large_after: int = 3_000
    restart_per_stage: bool = False
    opacity_reset_at_handoff: bool = False
    coarse_opacity_reset: bool = True
    min_densify_per_reset: int = 30
    background: Union[str, Tuple[float, float, float]] = "auto"
    seed: int = 0
    time_spread: str = "random"
    warmup_work_cap: Optional[float] = None
    forward_rig: str = "pyramid"
    views_scaling: str = "none"
    max_views_fraction: Optional[float] = None
    stage_growth: Optional[float] = None
    max_gaussians: Optional[int] = None
    pixels_per_gaussian: Optional[float] = None
    budget_views: Optional[int] = None
    densify_rank: str = "consistency"
    budget_swap: float = 0.0
    prune_faint: float = 0.0
    budget_size_pruning: bool = False
    budget_initial_share: float = 1.0
    budget_rigs: str = "all"
    divergence_factor: Optional[float] = 100.0
    clock_unit: str = "steps"
    budget: Optional[float] = None
    view_cost: Tuple[float, float] = (0.1, 0.9)
    mvad: "MVADConfig" = field(default_factory=MVADConfig)
    crd: "CRDConfig" = field(default_factory=CRDConfig)
    preset: str = field(default="custom", compare=False)

    def __post_init__(self):
        self.stages = tuple(self.stages)
        if not self.stages or not all(isinstance(s, Stage) for s in self.stages):
            raise ValueError(f"stages must be a non-empty sequence of Stage, got {self.stages!r}")
        for group, kind in (("mvad", MVADConfig), ("crd", CRDConfig)):
            value = getattr(self, group)
            if isinstance(value, bool):  # the flat bool of earlier releases: the switch alone
                warnings.warn(f"MVGSConfig({group}={value}): pass {kind.__name__}(enabled={value}) instead; a bool "
                              "is accepted until the next release", DeprecationWarning, stacklevel=3)
                setattr(self, group, kind(enabled=value))
            elif isinstance(value, dict):
                setattr(self, group, kind(**value))
            elif not isinstance(value, kind):
                raise ValueError(f"{group} must be a {kind.__name__}, got {value!r}")
        choices = {"reduction": ("sum", "mean"), "stats_from": ("all", "last"), "time_spread": ("random", "stratified", "instant"),
                   "forward_rig": ("pyramid", "finest"), "views_scaling": ("none", "sqrt"),
                   "budget_rigs": ("all", "round"),
                   "densify_rank": ("consistency", "gradient")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        lowest = {"chunk_size": 1, "densify_every": 1, "opacity_reset_every": 1, "min_densify_per_reset": 1,
                  "densify_from": 0, "densify_until": 0, "prune_large_after": 0, "seed": 0}
        for name, low in lowest.items():
            v = getattr(self, name)
            if name == "chunk_size" and v is None:
                continue
            check_int(name, v, low, MAX_SEED if name == "seed" else None)
        _check_finite_above("max_views_fraction", self.max_views_fraction, 0, "None or a fraction in (0, 1]",
                            optional=True)
        for name in ("budget_size_pruning", "coarse_opacity_reset"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
        if isinstance(self.budget_swap, bool) or not isinstance(self.budget_swap, (int, float)) or not (
                0.0 <= self.budget_swap < 1.0):
            raise ValueError(f"budget_swap must be a share of the cap in [0, 1), got {self.budget_swap!r}")
        if isinstance(self.prune_faint, bool) or not isinstance(self.prune_faint, (int, float)) or not (
                0.0 <= self.prune_faint < 1.0):
            raise ValueError(f"prune_faint must be a share of the blend weight in [0, 1), got {self.prune_faint!r}")
        if isinstance(self.budget_initial_share, bool) or not isinstance(self.budget_initial_share, (int, float)) or not (
                0.0 < self.budget_initial_share <= 1.0):
            raise ValueError(f"budget_initial_share must be a share of max_gaussians in (0, 1], "
                             f"got {self.budget_initial_share!r}")
        if self.max_views_fraction is not None and self.max_views_fraction > 1:
            raise ValueError(f"max_views_fraction must be None or a fraction in (0, 1], got {self.max_views_fraction!r}")
        _check_finite_above("stage_growth", self.stage_growth, 1, "None or a finite factor > 1", optional=True)
        if self.max_gaussians is not None:
            check_int("max_gaussians", self.max_gaussians, 1, MAX_PRIMITIVES)
        _check_finite_above("pixels_per_gaussian", self.pixels_per_gaussian, 0,
                            "None or a finite number of training pixels per Gaussian > 0", optional=True)
        if self.budget_views is not None:
            check_int("budget_views", self.budget_views, 1, MAX_PRIMITIVES)
        _check_finite_above("chunk_memory_mb", self.chunk_memory_mb, 0, "a finite number of MiB > 0")
        if not (0.0 <= self.lambda_dssim <= 1.0):
            raise ValueError(f"lambda_dssim must be in [0, 1], got {self.lambda_dssim!r}")
        _check_finite_above("grad_threshold", self.grad_threshold, 0, "a finite threshold > 0")
        _check_finite_above("grad_threshold_width", self.grad_threshold_width, 0,
                            "None or a finite width in pixels > 0", optional=True)
        self.view_cost = checked_view_cost(self.view_cost)
        _check_finite_above("divergence_factor", self.divergence_factor, 1, "None or a finite number > 1",
                            optional=True)
        _check_finite_above("budget", self.budget, 0, "None or a finite number of full-resolution views > 0",
                            optional=True)
        _check_finite_above("warmup_work_cap", self.warmup_work_cap, 0,
                            "None or a finite number of full-resolution views > 0", optional=True)
        if self.budget is not None and self.restart_per_stage:
            raise ValueError("budget needs one continuous clock (restart_per_stage=False); the paper() preset "
                             "restarts its schedules at every stage")
        if self.clock_unit not in ("steps", "work"):
            raise ValueError(f"clock_unit must be 'steps' or 'work', got {self.clock_unit!r}")
        if self.clock_unit == "work" and self.restart_per_stage:
            raise ValueError("clock_unit='work' needs one continuous clock (restart_per_stage=False)")
        bg = self.background
        if isinstance(bg, str):
            if bg not in ("auto", "black", "white", "random"):
                raise ValueError(f"background must be 'auto', 'black', 'white', 'random' or (r, g, b), got {bg!r}")
        elif len(tuple(bg)) != 3 or not all(0.0 <= float(c) <= 1.0 for c in bg):
            raise ValueError(f"background must be (r, g, b) in [0, 1], got {bg!r}")

    @property
    def total_steps(self) -> int:
        return sum(s.steps for s in self.stages)

    @property
    def finest_factor(self) -> int:
        """The smallest pyramid factor of the stage plan: "full resolution" for the work clock and
        coarse_opacity_reset (1, or the --resolution-scale factor)."""
        return min(s.factor for s in self.stages)

    def step_work(self, stage: Stage) -> float:
        """Work of one step of `stage` in full-resolution view renders (see view_cost); "full
        resolution" is the finest stage's (e.g. 1/4 of the images' with --resolution-scale 4)."""
        return stage.views * view_work(self.view_cost, stage.factor / self.finest_factor)

    @property
    def total_work(self) -> float:
        return sum(s.steps * self.step_work(s) for s in self.stages)

    @property
    def counts_work(self) -> bool:
        """Whether the clocks count work (a budget, or clock_unit="work") rather than steps."""
        return self.budget is not None or self.clock_unit == "work"

    @property
    def clock_length(self) -> int:
        """Length of the clock the schedules run on (what the model's learning-rate decay and SH
        schedule should span): the budget, else the total work when the clock counts work, else
        the last stage's steps when the clocks restart per stage, else the total steps."""
        if self.budget is not None:
            return max(1, int(round(self.budget)))
        if self.clock_unit == "work":
            return max(1, int(round(self.total_work)))
        return self.stages[-1].steps if self.restart_per_stage else self.total_steps

    # ---- presets --------------------------------------------------------------------------
    def initial_cap(self) -> Optional[int]:
        """The count the model may start with under max_gaussians: floor(budget_initial_share x
        max_gaussians), at least 1 (None without a budget)."""
        if self.max_gaussians is None:
            return None
        return max(1, int(math.floor(self.budget_initial_share * self.max_gaussians)))

    @classmethod
    def baseline(cls, **overrides) -> "MVGSConfig":
        """Plain 3DGS: one view per step, full resolution, 30k steps."""
        return cls(**{"stages": (Stage(1, 1, 30_000),), "preset": "baseline", **overrides})

    @classmethod
    def paper(cls, **overrides) -> "MVGSConfig":
        """The released MVGS code's behaviour (docs/method.md §1, §2)."""
        stages = (Stage(8, 48, 3_000), Stage(4, 24, 3_000), Stage(2, 12, 3_000), Stage(1, 8, 30_000))
        return cls(**{
            "stages": stages, "stats_from": "last", "restart_per_stage": True,
            "opacity_reset_at_handoff": True, "preset": "paper",
            "mvad": MVADConfig(enabled=True, center="origin"),
            "crd": CRDConfig(enabled=True, window_per_level=False, forward_only=False, max_miss=None,
                             pad_by_miss=False, min_angle_deg=0.0, clip=False, max_new=None),
            **overrides,
        })

    @classmethod
    def multiview(cls, **overrides) -> "MVGSConfig":
        """The paper's method with our fixes (the default before the equal-compute study):
        continuous schedule, statistics from all views, MVAD about the scene centre, and β = 2e-4
        meant for 800 px wide images (NeRF-synthetic's, where 3DGS set it), scaled to the width of
        every pyramid level (grad_threshold_width). M views at every level: it wins at equal steps
        and loses at equal compute. Cross-ray densification is off (paper() keeps it): with its
        guards it cloned almost nothing in every run measured and did not change the result
        (docs/ablation/README.md); CRDConfig(enabled=True) or --crd turns it back on with them."""
        stages = (Stage(8, 48, 3_000), Stage(4, 24, 3_000), Stage(2, 12, 3_000), Stage(1, 8, 30_000))
        return cls(**{"stages": stages, "preset": "multiview", "mvad": MVADConfig(enabled=True),
                      "grad_threshold_width": 800.0, **overrides})

    @classmethod
    def default(cls, **overrides) -> "MVGSConfig":
        """The cost-aware recipe, chosen at equal compute (docs/equal_compute.md): the image
        pyramid as a coarse-to-fine warm-up, DEFAULT_SHARES of the work (30 % at 1/2
        resolution, 70 % at full) with the warm-up held to 1000 full-resolution views' work once
        the run's length is set (warmup_work_cap: 10 % at a budget of 10k; the recipe as built
        is the 30k-work plan before that), one view per step, β scaled to the width as in multiview().
        Multi-view steps, MVAD and CRD are off: at equal work they cost optimizer steps and did
        not pay back on any scene measured (MVAD and CRD act on pairs of views, so with one view
        per step they have nothing to act on; with_views(M) turns M views back on
        at every level). On a forward-facing rig it trains at full resolution only
        (forward_rig="finest", see for_scene()). It was chosen against a baseline started from the
        scene's points alone and pruned by 3DGS's size rule. With the examples' background shell
        (mvgs_plugin.data.init) and the distance size rule (GS3DConfig.world_size_rule), both
        given to the baseline too, its stage plan was re-chosen (docs/equal_compute_log.md, "The 1/4
        level does not pay"): a 1/4 level before the 1/2 one (10 % of the work, taken from the
        1/2 level's 30 %) did worse at equal work on average at 1k and 3k, and most where the
        scene has structure thinner than a pixel at 1/4. Its opacity resets run at full
        resolution only (coarse_opacity_reset=False, measured there). Once densification has ended
        it cuts the faintest Gaussians, those that carry 1 % of the blend weight
        (prune_faint=DEFAULT_PRUNE_FAINT, since 2026-11-30: 0.65-0.84x the Gaussians at -0.10 to
        +0.10 dB on the generated scenes at 3k; docs/equal_compute.md). An adapter without blend
        statistics (Scaffold-GS) runs it without the cut (the controller warns)."""
        view_cost = checked_view_cost(overrides.get("view_cost", cls.view_cost))  # shares of the work it counts
        return cls(**{"stages": stages_from_shares(DEFAULT_SHARES, view_cost=view_cost), "preset": "default",
                      "clock_unit": "work", "coarse_opacity_reset": False, "warmup_work_cap": DEFAULT_WARMUP_WORK_CAP,
                      "grad_threshold_width": 800.0, "forward_rig": "finest", "prune_faint": DEFAULT_PRUNE_FAINT,
                      **overrides})

    @classmethod
    def compact(cls, **overrides) -> "MVGSConfig":
        """default() with a Gaussian budget from the data: the pixels of 48 training views of
        their mean size / 213 (COMPACT_BUDGET_VIEWS, COMPACT_PIXELS_PER_GAUSSIAN; 3692 Gaussians
        at 128 px, on a rig of 10 views as on one of 96), grown by the multi-view consistency
        score and never exceeded, without size pruning (budget_size_pruning). Only on a rig round
        the scene (budget_rigs="round"): on a forward-facing rig, or one that looks outward, it is
        default() (on a forward-facing rig, the baseline). Measured on the generated 360-degree
        scenes against default() and the baseline at equal work, seeds and 10k steps in
        docs/equal_compute_log.md ("The compact preset"; its budget rule: "A data budget that does
        not shrink with the views"). It keeps the default's shares at
        every budget (no warmup_work_cap): under its budget the cap is a trade between scenes, not
        a gain (at 10k +0.24 to +0.71 dB on three scenes, -0.63 / -0.94 on the clutter scene's
        two seeds; docs/equal_compute_log.md, "The compact preset with today's rules"). Nor the
        default's cut of the faintest Gaussians (prune_faint=0): not measured under its budget."""
        return cls.default(**{"preset": "compact", "pixels_per_gaussian": COMPACT_PIXELS_PER_GAUSSIAN,
                              "budget_views": COMPACT_BUDGET_VIEWS, "budget_rigs": "round",
                              "warmup_work_cap": None, "prune_faint": 0.0, **overrides})

    @classmethod
    def from_preset(cls, name: str, **overrides) -> "MVGSConfig":
        if name not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
        return getattr(cls, name)(**overrides)

    # ---- rescaling for short runs -----------------------------------------------------------
    def with_total_steps(self, total: int) -> "MVGSConfig":
        """The same recipe compressed (or stretched) to `total` steps.

        Stage lengths keep their proportions (each at least 1 step) and every step-valued clock
        (densification window and interval, opacity reset, size pruning) scales by the same
        ratio, so a 3.9k-step run densifies and resets at the same relative times as a 39k one;
        but densification never runs more often than every 10 steps, never starts before step
        50 (when the recipe's own start is later), and opacity resets never come sooner than
        min_densify_per_reset (30) densification intervals apart.

        Why the floors: the per-step learning rates are not compressed, so a model needs about
        as many steps to settle as ever. Densifying at step 3 of a 120-step run (500 / 30k
        scaled) acts on the large gradients of a model that has not fitted anything yet and
        multiplies the count for nothing: a flat textured plane went from 1.5k to 42k Gaussians
        in 70 steps that way (see tests/test_gaussian_budget.py for the plane against the
        tabletop).
        """
        if isinstance(total, bool) or not isinstance(total, int) or total < len(self.stages):
            raise ValueError(f"total steps must be an int >= the number of stages ({len(self.stages)}), got {total!r}")
        # The clocks are relative to one stage when they restart per stage, else to the whole run.
        ref = self.stages[-1].steps if self.restart_per_stage else self.total_steps
        ratio = total / self.total_steps
        steps = [max(1, round(s.steps * ratio)) for s in self.stages]
        steps[-1] = max(1, total - sum(steps[:-1]))
        stages = self._capped_warmup(tuple(Stage(s.factor, s.views, n) for s, n in zip(self.stages, steps)),
                                     keep_steps=True)
        if self.clock_unit == "work":  # the clocks keep their fractions of the work
            work = sum(s.steps * self.step_work(s) for s in stages)
            return dataclasses.replace(self, stages=stages, **self._scaled_clocks(work / self.total_work))
        clock_ratio = (stages[-1].steps if self.restart_per_stage else total) / ref
        return dataclasses.replace(self, stages=stages, **self._scaled_clocks(clock_ratio))

    def _capped_warmup(self, stages: Tuple[Stage, ...], keep_steps: bool) -> Tuple[Stage, ...]:
        """`stages` (this config's plan rescaled to a run) with its warm-up held to
        warmup_work_cap: when the stages coarser than the finest do more work than the cap, each
        keeps its share of the cap (at least one step) and the first finest stage takes over the
        steps they gave up (keep_steps: a step count stays) or their work (a budget stays)."""
        cap = self.warmup_work_cap
        finest = self.finest_factor  # rescaling keeps every stage's factor
        coarse = [i for i, s in enumerate(stages) if s.factor != finest]
        work = sum(stages[i].steps * self.step_work(stages[i]) for i in coarse)
        if cap is None or work <= cap:
            return stages
        out = list(stages)
        freed_steps, freed_work = 0, 0.0
        for i in coarse:
            s = stages[i]
            n = max(1, round(s.steps * cap / work))
            freed_steps += s.steps - n
            freed_work += (s.steps - n) * self.step_work(s)
            out[i] = Stage(s.factor, s.views, n)
        j = next(i for i, s in enumerate(stages) if s.factor == finest)
        extra = freed_steps if keep_steps else round(freed_work / self.step_work(stages[j]))
        out[j] = Stage(stages[j].factor, stages[j].views, stages[j].steps + extra)
        return tuple(out)

    def _scaled_clocks(self, ratio: float, floors: bool = True) -> dict:
        """Every clock-valued field (CLOCK_FIELDS) times `ratio`, with the floors that keep short
        runs sane: statistics need some views between densifications, and opacities need time
        to recover between resets (min_densify_per_reset: the original has 30 densifications per
        reset interval).
        floors=False scales them plainly (with_late_views: a recipe that grows, not a short run)."""
        plain = {k: max(1, round(getattr(self, k) * ratio)) for k in CLOCK_FIELDS}
        if not floors:
            return plain
        every = max(min(10, self.densify_every), plain["densify_every"])
        return {**plain, "densify_every": every,
                "densify_from": max(min(50, self.densify_from), plain["densify_from"]),
                "opacity_reset_every": max(min(self.min_densify_per_reset * every, self.opacity_reset_every),
                                           plain["opacity_reset_every"])}

    def with_budget(self, budget: float) -> "MVGSConfig":
        """The recipe run on a budget of work instead of a step count (see `budget`).

        budget: full-resolution view renders (a baseline given B does B steps). Each stage
        keeps its share of the recipe's work (its steps x step_work), so a cheap coarse stage
        keeps its many steps; every clock-valued field is the 30k-view 3DGS recipe's value times
        budget / 30000 (densification from 1/60 to 1/2 of the budget, a reset every 1/10; with
        clocks on work, times budget / the recipe's total work, 30000 for default()), with
        with_total_steps()'s floors for short runs. Baseline and MVGS given one budget thus do
        the same work on the same clock.
        """
        _check_finite_above("budget", budget, 0, "a finite number of full-resolution views > 0")
        if self.restart_per_stage:
            raise ValueError("with_budget needs one continuous clock (restart_per_stage=False); the paper() "
                             "preset restarts its schedules at every stage")
        work = [s.steps * self.step_work(s) for s in self.stages]
        steps = [max(1, round(budget * w / sum(work) / self.step_work(s))) for s, w in zip(self.stages, work)]
        stages = self._capped_warmup(tuple(Stage(s.factor, s.views, n) for s, n in zip(self.stages, steps)),
                                     keep_steps=False)
        # clocks on work are shares of the recipe's work (30k for default(); more after
        # with_late_views); clocks on steps are 3DGS's values for its 30k views
        basis = self.total_work if self.clock_unit == "work" else 30_000
        return dataclasses.replace(self, stages=stages, budget=float(budget), **self._scaled_clocks(budget / basis))

    def for_scene(self, scene) -> "MVGSConfig":
        """This config as it runs on `scene` (its train_cameras). Three scene-dependent rules, all
        keeping every clock-valued field:

        * pixels_per_gaussian (when max_gaussians is None, and the rig is round the scene
          unless budget_rigs="all"): max_gaussians = the training views' pixels at the finest
          stage's resolution / pixels_per_gaussian, rounded (a ratio that rounds it to 0 is refused);
          with budget_views V, the pixels of V views of their mean size instead.
        * max_views_fraction: every stage's views are capped at that fraction of the training
          views (at least 1); a capped stage keeps its work when the clocks count work (a budget,
          or clock_unit="work"), so it gets more steps, and its steps when they count steps.
        * forward_rig="finest" on a forward-facing rig: the stages coarser than the finest are
          dropped and the last finest stage takes over their work (clocks on work) or steps.

        Otherwise the config itself. Idempotent. Call it on the recipe, before
        with_total_steps() / with_budget(): the default's 30k-work recipe on a forward-facing rig
        then becomes 30k full-resolution steps, and a run asked for N steps (or budget B) is
        exactly the baseline's N steps (B). MVGS and ViewSchedule call it too, for configs that
        were not resolved: on an already rescaled config it keeps the work, so a --steps run may
        get fewer, dearer steps but every schedule (and clock_length) stays as planned."""
        out = self
        forward = None  # whether the rig is forward-facing: computed once, when a rule asks

        def forward_facing() -> bool:
            nonlocal forward
            if forward is None:
                from .data.init import is_forward_facing  # the data package imports this module's users
                forward = is_forward_facing(scene.train_cameras)
            return forward

        def round_the_scene() -> bool:  # axes that spread and meet in front of the cameras
            from .data.init import CONVERGING_COSINE, look_convergence
            return not forward_facing() and look_convergence(scene.train_cameras) >= CONVERGING_COSINE

        if self.pixels_per_gaussian is not None and self.max_gaussians is None and (
                self.budget_rigs == "all" or round_the_scene()):
            pixels = training_pixels(scene.train_cameras, self.finest_factor)
            what = f"the {pixels} training pixels"
            if self.budget_views is not None:  # V views of the mean size, not every view
                pixels = pixels * self.budget_views / len(scene.train_cameras)
                what = f"the {pixels:g} pixels of budget_views={self.budget_views} mean training views"
            if round(pixels / self.pixels_per_gaussian) < 1:  # a budget of no Gaussian: the user's to fix, not ours to round up
                raise ValueError(f"pixels_per_gaussian={self.pixels_per_gaussian:g} gives a budget of no Gaussian for "
                                 f"{what}; give at most {pixels:g} (a budget of one Gaussian)")
            out = dataclasses.replace(out, max_gaussians=round(pixels / self.pixels_per_gaussian))
        if self.max_views_fraction is not None:
            cap = max(1, math.floor(self.max_views_fraction * len(scene.train_cameras)))
            if any(s.views > cap for s in out.stages):
                stages = []
                for s in out.stages:
                    views = min(s.views, cap)
                    steps = s.steps
                    if self.counts_work and views != s.views:  # keep the stage's work
                        steps = max(1, round(s.steps * s.views / views))
                    stages.append(Stage(s.factor, views, steps))
                out = dataclasses.replace(out, stages=tuple(stages))
        finest = out.finest_factor
        if out.forward_rig == "pyramid" or all(s.factor == finest for s in out.stages):
            return out
        if not forward_facing():
            return out
        kept = [s for s in out.stages if s.factor == finest]
        dropped = [s for s in out.stages if s.factor != finest]
        last = kept[-1]
        if out.counts_work:
            extra = round(sum(s.steps * out.step_work(s) for s in dropped) / out.step_work(last))
        else:
            extra = sum(s.steps for s in dropped)
        return dataclasses.replace(out, stages=tuple(kept[:-1]) + (Stage(last.factor, last.views, last.steps + extra),))

    def with_views(self, views: int) -> "MVGSConfig":
        """Override M in the last (full-resolution) stage; coarser stages keep their ratio to it.

        When the clocks count work (clock_unit="work", as default()) they are stretched with the
        plan's work, as in with_late_views(): M views per step make M times the work, and clocks
        left at their values would end densification at 1/M of its share of the run (with M = 2,
        a quarter of the work instead of half)."""
        check_int("views", views, 1)
        last = self.stages[-1].views
        stages = tuple(Stage(s.factor, max(1, round(s.views * views / last)), s.steps) for s in self.stages)
        return self._stretched_clocks(dataclasses.replace(self, stages=stages))

    def _stretched_clocks(self, out: "MVGSConfig") -> "MVGSConfig":
        """`out` (this config with a new stage plan) with its work-valued clocks stretched by the
        plan's new work over the old, so every schedule keeps its share of the run; unchanged
        when the clocks count steps, or a budget already fixed the work."""
        if self.clock_unit != "work" or self.budget is not None:
            return out
        return dataclasses.replace(out, **self._scaled_clocks(out.total_work / self.total_work, floors=False))

    def with_late_views(self, views: int) -> "MVGSConfig":
        """The work the pyramid saves per step, spent as `views`-view steps at the end.

        A coarse step of one view costs step_work < 1 full view, so a pyramid run of N steps
        does less work than a single-view full-resolution run of N steps. Here the last stage's
        final n steps take `views` views, n = saving / (views - 1) (saving = the sum over the
        earlier stages of steps x (1 - step_work), rounded), so the plan's work equals its step
        count: at equal steps it does the baseline's work, and every extra view is a view of
        another camera (and, on a dynamic scene, another time) in the same optimizer step. When
        the clocks count work (clock_unit="work", as default()) they are stretched with the
        plan's work, so every schedule (densification window, resets, size pruning) keeps its
        share of the run. Measured on 4DGS, where it is train_4dgs.py's default at equal steps
        (docs/equal_compute_log.md, "4DGS: the views the pyramid saves").

        Needs a finest last stage of one view, one continuous clock (not restart_per_stage, no
        opacity reset at hand-offs: the split adds a stage) and no budget yet; a plan whose
        earlier stages save nothing (as for_scene() leaves on a forward-facing rig) is returned
        unchanged, and so is `views` = 1. The plan it returns has no warmup_work_cap (its late
        stage spends the saving of the warm-up it planned). Call it after for_scene() and before
        with_total_steps() / with_budget(), which keep its proportions."""
        if isinstance(views, bool) or not isinstance(views, int) or views < 1:
            raise ValueError(f"late views must be an int >= 1, got {views!r}")
        last = self.stages[-1]
        if views == 1:
            return self
        if last.views != 1 or last.factor != self.finest_factor:
            raise ValueError(f"late views need a last stage at the finest factor with one view per step, got "
                             f"{last} (stages {list(self.stages)})")
        if self.restart_per_stage or self.opacity_reset_at_handoff:
            raise ValueError(f"late views need one continuous clock and no opacity reset at stage hand-offs; preset "
                             f"{self.preset!r} has restart_per_stage={self.restart_per_stage}, "
                             f"opacity_reset_at_handoff={self.opacity_reset_at_handoff}")
        if self.budget is not None:
            raise ValueError(f"late views are planned on the recipe, before with_budget(); this config already "
                             f"has budget={self.budget}")
        saving = sum(s.steps * (1.0 - self.step_work(s)) for s in self.stages[:-1])
        n = round(saving / (views - 1))
        if n < 1:
            return self
        if n >= last.steps:
            raise ValueError(f"late views: the earlier stages save the work of {n} {views}-view steps, more than the "
                             f"last stage's {last.steps} steps can take (stages {list(self.stages)})")
        stages = self.stages[:-1] + (Stage(last.factor, 1, last.steps - n), Stage(last.factor, views, n))
        # The late stage spends the saving of the warm-up as planned here, so the plan keeps its
        # proportions at every length: a warm-up cut by warmup_work_cap would leave the late
        # steps more work than it saves (a run of N steps would no longer do N views' work).
        return self._stretched_clocks(dataclasses.replace(self, stages=stages, warmup_work_cap=None))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["stages"] = [dataclasses.asdict(s) for s in self.stages]
        d["crd"]["window"] = list(self.crd.window)
        d["view_cost"] = list(self.view_cost)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "MVGSConfig":
        """The config to_dict() wrote; also reads the flat layout of earlier releases (mvad: bool,
        mvad_tau, crd_window, ..., max_views_rule, forward_rig_budget) that their checkpoints and
        metrics hold."""
        d = dict(d)
        d.pop("max_views_rule", None)
        d.setdefault("min_densify_per_reset", 10)  # the floor configs were compressed with before the field
        if "forward_rig_budget" in d:  # before budget_rigs: False was compact's (no budget on a forward-facing rig)
            d.setdefault("budget_rigs", "all" if d.pop("forward_rig_budget") else "round")
        for group in ("mvad", "crd"):  # earlier releases: a bool beside flat names, read without a warning
            if isinstance(d.get(group), bool):
                d[group] = {"enabled": d[group]}
        d = _merge_flat_names(d, {k: d.pop(k) for k in list(d) if k in FLAT_NAMES})
        d["stages"] = tuple(Stage(**s) for s in d["stages"])
        if isinstance(d.get("background"), list):
            d["background"] = tuple(d["background"])
        if "view_cost" in d:
            d["view_cost"] = tuple(d["view_cost"])
        return cls(**d)


def training_pixels(cameras, factor: int = 1) -> int:
    """Pixels of the training views at pyramid factor `factor` (the sizes the pyramid renders)."""
    return sum(math.prod(scaled_size(int(c.width), int(c.height), factor)) for c in cameras)


def _merge_flat_names(kwargs: dict, flat: dict) -> dict:
    """kwargs with every flat MVAD / CRD name of `flat` (see FLAT_NAMES) merged into its group:
    the group given in kwargs (a config, a dict or the bool of earlier releases) or the default."""
    for group, kind in (("mvad", MVADConfig), ("crd", CRDConfig)):
        sub = {FLAT_NAMES[k][1]: v for k, v in flat.items() if FLAT_NAMES[k][0] == group}
        if sub:
            base = kwargs.get(group, kind())
            base = kind(enabled=base) if isinstance(base, bool) else kind(**base) if isinstance(base, dict) else base
            kwargs[group] = dataclasses.replace(base, **sub)
    return kwargs


def _flat_init(init):
    """MVGSConfig.__init__ that also takes the flat MVAD / CRD names, with a DeprecationWarning."""
    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        flat = {k: kwargs.pop(k) for k in list(kwargs) if k in FLAT_NAMES}
        if flat:
            names = ", ".join(f"{k} -> {'.'.join(FLAT_NAMES[k])}" for k in sorted(flat))
            warnings.warn(f"MVGSConfig: flat MVAD / CRD names are deprecated ({names}); pass "
                          "mvad=MVADConfig(...) / crd=CRDConfig(...)", DeprecationWarning, stacklevel=2)
        init(self, *args, **_merge_flat_names(kwargs, flat))
    return __init__


def _flat_property(group: str, name: str) -> property:
    def get(self):
        warnings.warn(f"MVGSConfig.{group}_{name} is deprecated; read MVGSConfig.{group}.{name}",
                      DeprecationWarning, stacklevel=2)
        return getattr(getattr(self, group), name)
    return property(get, doc=f"Deprecated: MVGSConfig.{group}.{name}.")


MVGSConfig.__init__ = _flat_init(MVGSConfig.__init__)
for _flat, (_group, _name) in FLAT_NAMES.items():
    setattr(MVGSConfig, _flat, _flat_property(_group, _name))
