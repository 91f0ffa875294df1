"""A training loop shaped like the original 3DGS train.py (graphdeco-inria), trained with MVGS.

The recipe for a code base with a graphdeco GaussianModel (gaussian_model.py here stands in for
yours: same attributes, same methods). Lines marked `# MVGS` are what changes in train.py:

- the ViewSchedule replaces `viewpoint_stack.pop(...)`: each step gets its views at the stage's
  pyramid level (cameras with scaled intrinsics, downsampled images) and the clock the
  learning-rate, SH and densification schedules read (`plan.clock`);
- the step renders its views one camera at a time (the original's render is single-camera),
  calls backward per view on `plan.weight` times the view's loss (gradients add up in `.grad`,
  memory stays that of one view) and hands the renders to `plan.record` for cross-ray
  densification's loss maps;
- every view's screen-space gradient goes to `add_densification_stats` (per view: each is one
  visit, so a Gaussian's statistic is its mean over the views that saw it);
- densification and opacity resets run when the plan says (on a white background one more reset
  where the clock reaches densify_from, as train.py's -w does), with the schedule's threshold (MVAD
  halves it for spread cameras) as `max_grad`, after the Gaussians inside cross-ray boxes are
  cloned through `densification_postfix` (largest mean gradient first, at most crd_max_new of
  the count);
- with a Gaussian budget (`--max-gaussians N`, or the `compact` preset's budget from the data)
  the run never holds more than N: points beyond the budget are cut before the model is built
  (a subset spread over the scene, so the kept points' spacing sizes them), and each
  densification lets only the candidates with the best multi-view score grow, as many as fit the
  count the schedule allows at that step (`limit_growth`: it zeroes the others' statistics, so
  the model's own densify_and_prune passes them over; the score needs each view's squared
  gradient beside the model's sum, one more line after add_densification_stats).

train_3dgs.py's far-background rules, off by default here (3DGS's init and rules) and each a flag:
`--background-points N` (the scene's points plus a shell of N on a sphere twice the rig's radius,
as load_scene draws it: 2000 in train_3dgs.py), `--world-size-rule distance` (the size prune's
limit grows with the distance from the rig's centre: too_large, run after the model's
densify_and_prune) and `--opacity-reset-scope inside` (resets leave the far background's
opacities as they are: reset_opacity). Without them the shell is pruned as too large at the
first densification after a reset, and capped by every reset.

    python examples/graphdeco_loop/train_mvgs.py --steps 1000 --preset multiview
    python examples/graphdeco_loop/train_mvgs.py --steps 3000 --background-points 2000 --world-size-rule distance --opacity-reset-scope inside
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Optional

import torch

from gaussian_model import GaussianModel, inverse_sigmoid, render
from mvgs_plugin import MVGSConfig, ViewSchedule
from mvgs_plugin.adapters.gs3d import (OPACITY_RESET_SCOPES, WORLD_SIZE_RULES, beyond_far_line, consistency_of,
                                       even_cut_order, farthest_distance, growth_that_fits, world_size_limit)
from mvgs_plugin.checks import check_float
from mvgs_plugin.config import MAX_SEED, PRESETS
from mvgs_plugin.data import load_scene
from mvgs_plugin.data.init import is_forward_facing
from mvgs_plugin.densify import boxes_contain, top_by_score
from mvgs_plugin.io import atomic_write_text, load_checked, save_checked
from mvgs_plugin.losses import l1_loss, ssim
from mvgs_plugin.metrics import psnr

from mvgs_plugin.cli import (BUNDLED, MAX_INIT_POINTS, MAX_PRIMITIVES, MAX_STEPS, HelpFormatter, background_colour,  # noqa: E402
                             float_above, int_at_least, scene_background, scene_folder)


MIN_OPACITY = 0.005  # densify_and_prune's min_opacity, as train.py passes it
MAX_SCREEN_SIZE = 20  # densify_and_prune's max_screen_size once large Gaussians are pruned, as train.py passes it
MAX_WORLD_SIZE = 0.1  # densify_and_prune's world-size limit, in units of the extent


def too_large(gaussians: GaussianModel, ctx, world_size_rule: str = "extent") -> torch.Tensor:
    """[N] bool: the rows densify_and_prune's world-size rule removes once ctx.prune_large (largest
    scale above MAX_WORLD_SIZE x extent). world_size_rule "distance" (train_3dgs.py's default,
    --world-size-rule) lets the limit grow with the distance d from the scene centre,
    MAX_WORLD_SIZE x max(extent, d): the far background keeps the Gaussians a camera sees as small
    (the extent rule prunes the whole background shell). Its screen-size rule never removes a row:
    growth zeroes max_radii2D before the prune reads it, as in the released 3DGS code."""
    size = gaussians.get_scaling.detach().max(dim=1).values
    return size > world_size_limit(gaussians.get_xyz, ctx.scene_extent, ctx.scene_center, world_size_rule, MAX_WORLD_SIZE)


def doomed(gaussians: GaussianModel, ctx, world_size_rule: str = "extent") -> torch.Tensor:
    """[N] bool: the rows densify_and_prune's prune removes (opacity below MIN_OPACITY; with
    ctx.prune_large, too_large()). Their clones and split children inherit the opacity, and
    children are smaller, so none of those stays either."""
    gone = gaussians.get_opacity.detach().squeeze(-1) < MIN_OPACITY
    if ctx.prune_large:
        gone = gone | too_large(gaussians, ctx, world_size_rule)
    return gone


def densify_and_prune(gaussians: GaussianModel, ctx, world_size_rule: str = "extent") -> int:
    """The model's densify_and_prune at the schedule's threshold; with world_size_rule "distance"
    its size rules are left to too_large(), run on the rows it leaves (the rows the model's own
    prune tests: it prunes after growing). Returns how many rows the distance rule kept that the
    extent rule would have pruned."""
    if world_size_rule == "extent":
        gaussians.densify_and_prune(ctx.grad_threshold, MIN_OPACITY, ctx.scene_extent,
                                    MAX_SCREEN_SIZE if ctx.prune_large else None)
        return 0
    gaussians.densify_and_prune(ctx.grad_threshold, MIN_OPACITY, ctx.scene_extent, None)
    if not ctx.prune_large:
        return 0
    gone = too_large(gaussians, ctx, world_size_rule)
    kept = int((too_large(gaussians, ctx, "extent") & ~gone).sum())
    gaussians.prune_points(gone)
    return kept


def reset_opacity(gaussians: GaussianModel, scope: str, center: torch.Tensor, far_distance: Optional[float]) -> int:
    """The model's reset_opacity (opacities capped at 0.01, the group's Adam moments zeroed), or
    with scope "inside" (--opacity-reset-scope, train_3dgs.py's default) the same cap on every row
    but those beyond the far line (FAR_RESET_FRACTION x far_distance from `center`: the far
    background), which keep their opacities: a reset that leaves the background shell as it is.
    Returns how many rows it spared."""
    spared = beyond_far_line(gaussians.get_xyz, center, far_distance) if scope == "inside" else None
    if spared is None:
        gaussians.reset_opacity()
        return 0
    raw = gaussians._opacity.detach()
    capped = inverse_sigmoid(torch.clamp_max(gaussians.get_opacity.detach(), 0.01))
    gaussians._opacity = gaussians.replace_tensor_to_optimizer(torch.where(spared[:, None], raw, capped),
                                                               "opacity")["opacity"]
    return int(spared.sum())


def budget_room(ctx, gone: torch.Tensor) -> int:
    """The rows a densification may add under the Gaussian budget (ctx.max_primitives): the count
    allowed at this step minus the rows that stay after the prune (`gone`: doomed()), which frees
    the room of the rows it removes."""
    return max(0, ctx.max_primitives - int((~gone).sum()))


def limit_growth(gaussians: GaussianModel, grad_sq: torch.Tensor, ctx, far_distance: Optional[float],
                 inside_first: bool, world_size_rule: str = "extent") -> int:
    """A Gaussian budget in densify_and_prune's own terms: of the growth candidates (mean
    gradient >= ctx.grad_threshold, rows the prune keeps), the best by densify score whose rows
    fit budget_room keep their statistics; the others' are zeroed, so densify_and_prune grows
    none of them (a clone adds one row, a split of 2 children one). The score: the mean gradient,
    times (ctx.rank_by "consistency") how evenly the views since the last densification share it,
    (sum g)^2 / (n sum g^2) from the model's sum, its visit count and `grad_sq` [N'] (each visit's
    squared gradient, rows past N' have none: cross-ray clones); with `inside_first`, candidates
    beyond the far line (0.75 x far_distance from the scene centre) after all others. Returns how
    many candidates fell (0 without a budget)."""
    if ctx.max_primitives is None:
        return 0
    gone = doomed(gaussians, ctx, world_size_rule)
    accum, denom = gaussians.xyz_gradient_accum.squeeze(-1), gaussians.denom.squeeze(-1)
    mean = torch.where(denom > 0, accum / denom.clamp_min(1), torch.zeros_like(accum))
    idx = ((mean >= ctx.grad_threshold) & ~gone).nonzero().squeeze(1)
    score = mean
    if ctx.rank_by == "consistency":
        sq = torch.cat([grad_sq, grad_sq.new_zeros(len(accum) - len(grad_sq))])
        score = mean * consistency_of(accum, sq, denom)
    far = beyond_far_line(gaussians.get_xyz.detach(), ctx.scene_center, far_distance) if inside_first else None
    fits = growth_that_fits(score[idx], torch.ones(len(idx), dtype=torch.long), budget_room(ctx, gone),
                            None if far is None else far[idx])
    gaussians.xyz_gradient_accum[idx[~fits]] = 0.0
    return int((~fits).sum())


def clone_in_boxes(gaussians: GaussianModel, ctx, world_size_rule: str = "extent") -> int:
    """Cross-ray densification on a graphdeco model: copy the Gaussians strictly inside
    ctx.boxes (the largest mean gradients first, at most ctx.max_new_from_boxes, and under a
    Gaussian budget at most budget_room) with densification_postfix. The copies come before
    densify_and_prune, which then resets the statistics: so the gradient rules see the
    statistics of the originals only (the copies have none), as GS3DAdapter orders it."""
    if ctx.boxes is None or not len(ctx.boxes):
        return 0
    sel = boxes_contain(gaussians.get_xyz, ctx.boxes)
    room = None
    if ctx.max_primitives is not None:  # what the prune removes is not copied into the budget's room
        gone = doomed(gaussians, ctx, world_size_rule)
        sel, room = sel & ~gone, budget_room(ctx, gone)
    limits = [k for k in (ctx.max_new_from_boxes, room) if k is not None]
    if limits:
        score = (gaussians.xyz_gradient_accum / gaussians.denom.clamp_min(1)).squeeze(-1)
        sel = top_by_score(sel, score, min(limits))
    n, accum, denom = int(sel.sum()), gaussians.xyz_gradient_accum, gaussians.denom
    if n:
        radii = gaussians.max_radii2D
        gaussians.densification_postfix(*gaussians._rows(sel))
        # densification_postfix zeroes the statistics, as the original's; keep the originals'
        gaussians.xyz_gradient_accum = torch.cat([accum, torch.zeros(n, 1)])
        gaussians.denom = torch.cat([denom, torch.zeros(n, 1)])
        gaussians.max_radii2D = torch.cat([radii, torch.zeros(n)])
    return n


def crosses_densify_from(schedule: ViewSchedule, step: int) -> bool:
    """Whether the step's clock interval (before, after] reaches the start of densification: the
    step of train.py's `iteration == densify_from_iter` on a step clock, and on a budget clock too."""
    at = schedule.plan.locate(step)
    return at.before < schedule.config.densify_from <= at.after


def training(scene, iterations: int, preset: str = "default", seed: int = 0, checkpoint_iterations=(),
             start_checkpoint=None, out: Path = Path("out/graphdeco_loop"), lambda_dssim: float = 0.2,
             views=None, world_size_rule: str = "extent", reset_scope: str = "all", opacity_lr: float = 2.5e-2,
             **overrides):
    """Returns the trained GaussianModel and a log of what ran (densify / reset steps).
    views: M of the full-resolution stage (coarser stages keep their ratio), None: the preset's;
    world_size_rule "extent" (3DGS) or "distance" (too_large); reset_scope "all" (3DGS) or
    "inside" (resets spare the Gaussians beyond the far line: reset_opacity); opacity_lr: Adam's step
    on the opacity logits (graphdeco's 2.5e-2; 5e-2 in its 2023 release and the package's GS3DAdapter);
    overrides: MVGSConfig fields given to the preset (e.g. crd=CRDConfig(enabled=True))."""
    if world_size_rule not in WORLD_SIZE_RULES:
        raise ValueError(f"world_size_rule must be one of {', '.join(map(repr, WORLD_SIZE_RULES))}, got {world_size_rule!r}")
    if reset_scope not in OPACITY_RESET_SCOPES:
        raise ValueError(f"reset_scope must be one of {', '.join(map(repr, OPACITY_RESET_SCOPES))}, got {reset_scope!r}")
    opacity_lr = check_float("opacity_lr", opacity_lr, positive=True)
    torch.manual_seed(seed)
    # MVGS: densify_and_prune has no cut of the faintest Gaussians (the default preset's prune_faint):
    # its plan's step would run as one more densification after the window
    if overrides.get("prune_faint"):
        raise ValueError(f"prune_faint={overrides['prune_faint']!r}: this loop's densify_and_prune has no cut of the "
                         "faintest Gaussians (MVGSConfig.prune_faint); leave it out")
    overrides = {**overrides, "prune_faint": 0.0}
    config = MVGSConfig.from_preset(preset, seed=seed, **overrides).with_total_steps(iterations)  # MVGS
    schedule = ViewSchedule(scene, config if views is None else config.with_views(views))  # MVGS
    xyz, rgb = scene.points.xyz, scene.points.rgb
    far_distance = farthest_distance(xyz, scene.center)  # MVGS: a budget grows the far background last
    inside_first = not is_forward_facing(scene.train_cameras)  # MVGS: ... on a rig round the scene
    cut = schedule.initial_cut(len(xyz))  # MVGS: with a budget, more points than it holds are cut first
    if cut is not None:
        keep = torch.sort(even_cut_order(xyz, scene.center), descending=True, stable=True).indices[:cut.max_primitives]
        xyz, rgb = xyz[keep], rgb[keep]
    gaussians = GaussianModel(sh_degree=3)
    gaussians.create_from_pcd(xyz, rgb, spatial_lr_scale=scene.extent)
    clock_length = schedule.config.clock_length  # MVGS: the schedules' length (steps, or work on a work clock)
    gaussians.training_setup(clock_length, opacity_lr=opacity_lr)
    grad_sq = torch.zeros(len(xyz))  # MVGS: each visit's squared gradient, for the budget's score
    if start_checkpoint:
        model_params, first_iter, schedule_state, rng, *rest = load_checked(str(start_checkpoint))
        grad_sq = rest[0] if rest else torch.zeros(len(model_params[1]))  # MVGS (a checkpoint from before: none)
        gaussians.restore(model_params, clock_length, opacity_lr=opacity_lr)
        schedule.load_state_dict(schedule_state)  # MVGS
        torch.set_rng_state(rng)
    log = {"max_gaussians": schedule.config.max_gaussians, "threshold_width": schedule.config.grad_threshold_width,  # MVGS
           "densify": [], "reset": [], "from_boxes": 0, "dropped_by_budget": 0, "counts": [], "clocks": [],
           "spared_by_reset": 0, "kept_by_distance": 0}
    # 3DGS's -w: on a white background one more reset where densification starts (iteration ==
    # densify_from_iter in train.py), so the initial points' colours do not stand in for the background
    white = overrides.get("background") != "random" and scene.background is not None and \
        tuple(float(v) for v in scene.background) == (1.0, 1.0, 1.0)
    sh_interval = max(1, round(1000 * clock_length / 30_000))

    for plan in schedule:  # MVGS: instead of viewpoint_stack.pop(randint(...))
        iteration = plan.step
        gaussians.update_learning_rate(plan.clock)
        gaussians.active_sh_degree = min(plan.clock // sh_interval, gaussians.max_sh_degree)
        if plan.handoff_reset:  # MVGS (paper preset): reset opacities when a pyramid stage hands over
            log["spared_by_reset"] += reset_opacity(gaussians, reset_scope, scene.center, far_distance)

        visits = []
        for cameras, targets, backgrounds, collect_stats in plan:  # MVGS: the step's views, chunk by chunk
            for viewpoint_cam, gt_image, bg in zip(cameras, targets, backgrounds):
                render_pkg = render(viewpoint_cam, gaussians, bg)
                image = render_pkg["render"].permute(1, 2, 0)
                mask = plan.mask_for(viewpoint_cam)  # MVGS: a scene with masks (mask_path): ignored pixels count nothing
                if mask is not None:
                    image, gt_image = image * mask, gt_image * mask
                Ll1 = l1_loss(image, gt_image)
                loss = (1.0 - lambda_dssim) * Ll1 + lambda_dssim * (1.0 - ssim(image, gt_image, padding="zero"))  # 3DGS's SSIM
                (plan.weight * loss).backward()  # MVGS: the step's loss is the weighted sum over its views
                plan.record([image], [gt_image])  # MVGS: cross-ray densification's loss maps
                if collect_stats:
                    visits.append(render_pkg)

        with torch.no_grad():
            for render_pkg in visits:  # MVGS: every view's statistics
                visibility_filter, radii = render_pkg["visibility_filter"], render_pkg["radii"].float()
                gaussians.max_radii2D[visibility_filter] = torch.max(gaussians.max_radii2D[visibility_filter],
                                                                     radii[visibility_filter])
                gaussians.add_densification_stats(render_pkg["viewspace_points"], visibility_filter)
                grad_sq[visibility_filter] += render_pkg["viewspace_points"].grad[visibility_filter, :2].square().sum(-1)  # MVGS
            if plan.densify:  # MVGS: the schedule's clock
                xyz = gaussians.get_xyz.detach()
                ctx = schedule.densify_context(plan, primitive_count=len(xyz),
                                               bounds=torch.stack([xyz.amin(0), xyz.amax(0)]).double())
                log["from_boxes"] += clone_in_boxes(gaussians, ctx, world_size_rule)  # MVGS: cross-ray densification
                log["dropped_by_budget"] += limit_growth(gaussians, grad_sq, ctx, far_distance, inside_first,  # MVGS
                                                         world_size_rule)
                log["kept_by_distance"] += densify_and_prune(gaussians, ctx, world_size_rule)  # MVGS: the model's
                grad_sq = torch.zeros(gaussians.get_xyz.shape[0])  # MVGS: the window restarts with the model's sums
                log["densify"].append(iteration)
            if plan.reset_opacity or (white and crosses_densify_from(schedule, iteration)):  # MVGS: the schedule's clock
                log["spared_by_reset"] += reset_opacity(gaussians, reset_scope, scene.center, far_distance)  # MVGS
                log["reset"].append(iteration)
            gaussians.optimizer.step()
            gaussians.optimizer.zero_grad(set_to_none=True)
            schedule.primitive_count = gaussians.get_xyz.shape[0]  # MVGS: sizes the next step's chunks
        log["counts"].append(gaussians.get_xyz.shape[0])
        log["clocks"].append(plan.clock)

        if iteration in checkpoint_iterations:
            out.mkdir(parents=True, exist_ok=True)
            save_checked((gaussians.capture(), iteration, schedule.state_dict(), torch.get_rng_state(), grad_sq),
                         str(out / f"chkpnt{iteration}.pth"))
    return gaussians, log


@torch.no_grad()
def evaluate(gaussians: GaussianModel, scene) -> float:
    bg = torch.tensor(scene.background if scene.background is not None else (0.0, 0.0, 0.0), dtype=torch.float32)
    cams = scene.test_cameras or scene.train_cameras
    return sum(psnr(render(c, gaussians, bg)["render"].permute(1, 2, 0).clamp(0, 1), scene.image(c))
               for c in cams) / len(cams)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=scene_folder, default=BUNDLED, help="scene folder with points (default: the bundled one)")
    ap.add_argument("--steps", type=int_at_least(2, MAX_STEPS), default=1000, help="iterations")
    ap.add_argument("--preset", choices=PRESETS, default="default",
                    help="the MVGS recipe (MVGSConfig.from_preset)")
    ap.add_argument("--views", type=int_at_least(1), default=None, help="views per full-resolution step (default: "
                    "the preset's)")
    ap.add_argument("--max-gaussians", type=int_at_least(1, MAX_PRIMITIVES), default=None, metavar="N",
                    help="a Gaussian budget: the run never holds more than N; growth follows a schedule that reaches N "
                         "when densification ends, the candidates ranked by multi-view score (MVGSConfig.max_gaussians; "
                         "default: the preset's, none but compact's)")
    ap.add_argument("--threshold-width", type=float_above(0, inclusive=True), default=None, metavar="W",
                    help="the densification threshold (2e-4) is meant for W px images and scaled to each level's width "
                         "(MVGSConfig.grad_threshold_width; default: the preset's: 800 for default, none for baseline, "
                         "3DGS's fixed threshold)")
    ap.add_argument("--seed", type=int_at_least(0, MAX_SEED), default=0, help="torch's seed and the schedule's")
    ap.add_argument("--threads", type=int_at_least(0), default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--out", type=Path, default=None, help="write metrics.json here (PSNR, Gaussians, the most held, "
                    "CPU and wall seconds of training)")
    ap.add_argument("--images", type=str, default=None, metavar="DIR",
                    help="3DGS's -i: a COLMAP scene's image folder, relative to --data; a downscaled copy (images_4) "
                         "scales the cameras to it (default: images/, else --data)")
    ap.add_argument("--background", type=background_colour, default="auto", metavar="auto|black|white|random|R,G,B",
                    help="3DGS's -w is white: the colour behind the Gaussians and the one RGBA images are composited "
                         "on (default: auto, the scene's: see docs/data.md); random is 3DGS's --random_background "
                         "(a new colour behind every training view, images composited as with auto)")
    ap.add_argument("--background-points", type=int_at_least(0, MAX_INIT_POINTS), default=0, metavar="N",
                    help="N more initial points on a sphere twice the rig's radius for the far background, as "
                         "train_3dgs.py adds (2000 there), when the cameras surround the scene (none on a forward-facing "
                         "rig or an object on a backdrop); 0: the scene's points only, 3DGS's init (default: 0)")
    ap.add_argument("--world-size-rule", choices=WORLD_SIZE_RULES, default="extent",
                    help="size pruning: extent is 3DGS's (world size above 0.1 x the extent everywhere, which prunes "
                         "the background shell); distance is train_3dgs.py's (0.1 x the distance from the rig's centre "
                         "beyond the extent; too_large) (default: extent)")
    ap.add_argument("--opacity-reset-scope", choices=OPACITY_RESET_SCOPES, default="all",
                    help="which opacities a reset caps: all is 3DGS's; inside is train_3dgs.py's, the far background "
                         "(beyond 3/4 of the initial points' farthest distance from the rig's centre) kept as it is "
                         "(default: all)")
    ap.add_argument("--opacity-lr", type=float_above(0), default=2.5e-2, metavar="LR",
                    help="Adam's learning rate on the opacity logits: 2.5e-2 is graphdeco's train.py today, 5e-2 its "
                         "2023 release's and train_3dgs.py's; with a few thousand steps (resets 300 apart) 5e-2 lets "
                         "opacities recover between resets (docs/gsplat_loop.md) (default: 2.5e-2)")
    ap.add_argument("--checkpoint-iterations", type=int_at_least(1, MAX_STEPS), nargs="+", default=[], metavar="N",
                    help="also write --out/chkpnt<N>.pth after these iterations (graphdeco's --checkpoint_iterations; "
                         "default: none)")
    ap.add_argument("--start-checkpoint", type=Path, default=None, metavar="PATH",
                    help="continue from a chkpnt<N>.pth this script wrote, with the flags it was written with "
                         "(graphdeco's --start_checkpoint; default: start fresh)")
    args = ap.parse_args()
    if args.start_checkpoint is not None and not args.start_checkpoint.is_file():
        ap.error(f"--start-checkpoint {args.start_checkpoint}: no such file")
    try:  # a scene without points gets them (triangulated, else drawn where the cameras look)
        scene = load_scene(args.data, images=args.images, background=scene_background(args),
                           background_points=args.background_points)  # MVGS: the far background's shell
    except (ValueError, OSError) as err:
        ap.error(f"--data {args.data}: {err}")
    random_bg = {"background": "random"} if args.background == "random" else {}  # MVGS: ViewSchedule draws them
    if args.threads:
        torch.set_num_threads(args.threads)
    budget = {} if args.max_gaussians is None else {"max_gaussians": args.max_gaussians}
    if args.threshold_width is not None:
        budget["grad_threshold_width"] = args.threshold_width or None
    cpu, wall = time.process_time(), time.perf_counter()
    model, log = training(scene, args.steps, args.preset, seed=args.seed, views=args.views,
                          world_size_rule=args.world_size_rule, reset_scope=args.opacity_reset_scope,
                          opacity_lr=args.opacity_lr, checkpoint_iterations=set(args.checkpoint_iterations),
                          start_checkpoint=args.start_checkpoint, out=args.out or Path("out/graphdeco_loop"),
                          **random_bg, **budget)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    metrics = {"psnr": evaluate(model, scene), "num_gaussians": model.get_xyz.shape[0], "most_held": max(log["counts"]),
               "max_gaussians": log["max_gaussians"], "background_points": args.background_points,
               "world_size_rule": args.world_size_rule, "opacity_reset_scope": args.opacity_reset_scope,
               "opacity_lr": args.opacity_lr, "threshold_width": log["threshold_width"], "preset": args.preset, "steps": args.steps, "seed": args.seed,
               "densify_calls": len(log["densify"]), "resets": log["reset"], "from_boxes": log["from_boxes"],
               "dropped_by_budget": log["dropped_by_budget"],
               "spared_by_reset": log["spared_by_reset"], "kept_by_distance": log["kept_by_distance"], "cpu_seconds": cpu, "train_seconds": wall}
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "metrics.json", json.dumps(metrics, indent=1))
    print(f"PSNR {metrics['psnr']:.2f} dB, {metrics['num_gaussians']} Gaussians (at most {metrics['most_held']}), "
          f"densified at {len(log['densify'])} steps, opacity resets at {log['reset']}, {log['from_boxes']} cloned "
          f"from boxes, {log['dropped_by_budget']} candidates held back by the budget, {cpu:.1f} s CPU")
