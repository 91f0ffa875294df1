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
- densification and opacity resets run when the plan says, with the schedule's threshold (MVAD
  halves it for spread cameras) as `max_grad`, after the Gaussians inside cross-ray boxes are
  cloned through `densification_postfix` (largest mean gradient first, at most crd_max_new of
  the count).

    python examples/graphdeco_loop/train_mvgs.py --steps 1000 --preset multiview
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from gaussian_model import GaussianModel, render
from mvgs_plugin import MVGSConfig, ViewSchedule
from mvgs_plugin.config import PRESETS
from mvgs_plugin.data import load_scene
from mvgs_plugin.densify import boxes_contain, top_by_score
from mvgs_plugin.io import load_checked, save_checked
from mvgs_plugin.losses import l1_loss, ssim
from mvgs_plugin.metrics import psnr

from mvgs_plugin.cli import (BUNDLED, MAX_STEPS, HelpFormatter, background_colour, int_at_least,  # noqa: E402
                             scene_background, scene_folder)


def clone_in_boxes(gaussians: GaussianModel, ctx) -> int:
    """Cross-ray densification on a graphdeco model: copy the Gaussians strictly inside
    ctx.boxes (the largest mean gradients first, at most ctx.max_new_from_boxes) with
    densification_postfix. The copies come before densify_and_prune, which then resets the
    statistics: so the gradient rules see the statistics of the originals only (the copies have
    none), as GS3DAdapter orders it."""
    if ctx.boxes is None or not len(ctx.boxes):
        return 0
    sel = boxes_contain(gaussians.get_xyz, ctx.boxes)
    if ctx.max_new_from_boxes is not None:
        score = (gaussians.xyz_gradient_accum / gaussians.denom.clamp_min(1)).squeeze(-1)
        sel = top_by_score(sel, score, ctx.max_new_from_boxes)
    n, accum, denom = int(sel.sum()), gaussians.xyz_gradient_accum, gaussians.denom
    if n:
        radii = gaussians.max_radii2D
        gaussians.densification_postfix(*gaussians._rows(sel))
        # densification_postfix zeroes the statistics, as the original's; keep the originals'
        gaussians.xyz_gradient_accum = torch.cat([accum, torch.zeros(n, 1)])
        gaussians.denom = torch.cat([denom, torch.zeros(n, 1)])
        gaussians.max_radii2D = torch.cat([radii, torch.zeros(n)])
    return n


def training(scene, iterations: int, preset: str = "default", seed: int = 0, checkpoint_iterations=(),
             start_checkpoint=None, out: Path = Path("out/graphdeco_loop"), lambda_dssim: float = 0.2,
             views=None, **overrides):
    """Returns the trained GaussianModel and a log of what ran (densify / reset steps).
    views: M of the full-resolution stage (coarser stages keep their ratio), None: the preset's;
    overrides: MVGSConfig fields given to the preset (e.g. crd=CRDConfig(enabled=True))."""
    torch.manual_seed(seed)
    gaussians = GaussianModel(sh_degree=3)
    gaussians.create_from_pcd(scene.points.xyz, scene.points.rgb, spatial_lr_scale=scene.extent)
    config = MVGSConfig.from_preset(preset, seed=seed, **overrides).with_total_steps(iterations)  # MVGS
    schedule = ViewSchedule(scene, config if views is None else config.with_views(views))  # MVGS
    clock_length = schedule.config.clock_length  # MVGS: the schedules' length (steps, or work on a work clock)
    gaussians.training_setup(clock_length)
    if start_checkpoint:
        model_params, first_iter, schedule_state, rng = load_checked(str(start_checkpoint))
        gaussians.restore(model_params, clock_length)
        schedule.load_state_dict(schedule_state)  # MVGS
        torch.set_rng_state(rng)
    log = {"densify": [], "reset": [], "from_boxes": 0}
    sh_interval = max(1, round(1000 * clock_length / 30_000))

    for plan in schedule:  # MVGS: instead of viewpoint_stack.pop(randint(...))
        iteration = plan.step
        gaussians.update_learning_rate(plan.clock)
        gaussians.active_sh_degree = min(plan.clock // sh_interval, gaussians.max_sh_degree)
        if plan.handoff_reset:  # MVGS (paper preset): reset opacities when a pyramid stage hands over
            gaussians.reset_opacity()

        visits = []
        for cameras, targets, backgrounds, collect_stats in plan:  # MVGS: the step's views, chunk by chunk
            for viewpoint_cam, gt_image, bg in zip(cameras, targets, backgrounds):
                render_pkg = render(viewpoint_cam, gaussians, bg)
                image = render_pkg["render"].permute(1, 2, 0)
                mask = plan.mask_for(viewpoint_cam)  # MVGS: a scene with masks (mask_path): ignored pixels count nothing
                if mask is not None:
                    image, gt_image = image * mask, gt_image * mask
                Ll1 = l1_loss(image, gt_image)
                loss = (1.0 - lambda_dssim) * Ll1 + lambda_dssim * (1.0 - ssim(image, gt_image))
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
            if plan.densify:  # MVGS: the schedule's clock
                xyz = gaussians.get_xyz.detach()
                ctx = schedule.densify_context(plan, primitive_count=len(xyz),
                                               bounds=torch.stack([xyz.amin(0), xyz.amax(0)]).double())
                log["from_boxes"] += clone_in_boxes(gaussians, ctx)  # MVGS: cross-ray densification
                size_threshold = 20 if ctx.prune_large else None
                gaussians.densify_and_prune(ctx.grad_threshold, 0.005, ctx.scene_extent, size_threshold)
                log["densify"].append(iteration)
            if plan.reset_opacity:  # MVGS: the schedule's clock
                gaussians.reset_opacity()
                log["reset"].append(iteration)
            gaussians.optimizer.step()
            gaussians.optimizer.zero_grad(set_to_none=True)
            schedule.primitive_count = gaussians.get_xyz.shape[0]  # MVGS: sizes the next step's chunks

        if iteration in checkpoint_iterations:
            save_checked((gaussians.capture(), iteration, schedule.state_dict(), torch.get_rng_state()),
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
    ap.add_argument("--images", type=str, default=None, metavar="DIR",
                    help="3DGS's -i: a COLMAP scene's image folder, relative to --data; a downscaled copy (images_4) "
                         "scales the cameras to it (default: images/, else --data)")
    ap.add_argument("--background", type=background_colour, default="auto", metavar="auto|black|white|random|R,G,B",
                    help="3DGS's -w is white: the colour behind the Gaussians and the one RGBA images are composited "
                         "on (default: auto, the scene's: see docs/data.md); random is 3DGS's --random_background "
                         "(a new colour behind every training view, images composited as with auto)")
    args = ap.parse_args()
    try:  # a scene without points gets them (triangulated, else drawn where the cameras look)
        scene = load_scene(args.data, images=args.images, background=scene_background(args))
    except (ValueError, OSError) as err:
        ap.error(f"--data {args.data}: {err}")
    random_bg = {"background": "random"} if args.background == "random" else {}  # MVGS: ViewSchedule draws them
    model, log = training(scene, args.steps, args.preset, views=args.views, **random_bg)
    print(f"PSNR {evaluate(model, scene):.2f} dB, {model.get_xyz.shape[0]} Gaussians, densified at "
          f"{len(log['densify'])} steps, opacity resets at {log['reset']}, {log['from_boxes']} cloned from boxes")
