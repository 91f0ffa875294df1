"""Hand-written 3DGS training loops: single_view.py is the single-view baseline a user
already has, mvgs.py is the same loop trained with MVGS. Every line of the step stays the
user's own (render, loss, backward, statistics, densification, optimizer); the schedule decides
which views each step sees, at which pyramid level, and when densification runs.
`diff single_view.py mvgs.py` shows the lines that change: the config (any preset), and one
line handing the rendered images to the plan for cross-ray densification's loss maps (without
it that rule is skipped with a warning; nothing else needs it).

    python examples/three_line_wrap/single_view.py --steps 300
    python examples/three_line_wrap/mvgs.py --steps 300
"""

import argparse

import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin import MVGSConfig, ViewSchedule
from mvgs_plugin.losses import photometric_loss

from mvgs_plugin.cli import BUNDLED, HelpFormatter, int_at_least, load_scene, scene_folder  # noqa: E402
from mvgs_plugin.config import MAX_SEED


def train(scene, steps: int, seed: int = 0, **config) -> GS3DAdapter:
    torch.manual_seed(seed)
    schedule = ViewSchedule(scene, MVGSConfig.baseline(seed=seed, **config).for_scene(scene).with_total_steps(steps))
    model = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(schedule.config))  # its lr decay and SH steps on the run's clock
    cut = schedule.initial_cut(model.num_primitives())  # with a budget (max_gaussians): a larger model is cut first
    if cut is not None:
        model.densify(cut)
    for plan in schedule:
        model.set_step(plan.clock)
        if plan.handoff_reset:  # a preset that resets opacities when a pyramid stage hands over (paper)
            model.reset_opacity()
        for cams, targets, backgrounds, collect_stats in plan:
            out = model.render(cams, backgrounds)
            loss = plan.weight * sum(photometric_loss(img, gt) for img, gt in zip(out.images, targets))
            loss.backward()
            if collect_stats:
                model.accumulate_stats(out)
        with torch.no_grad():
            if plan.densify:
                model.densify(schedule.densify_context(plan, adapter=model))  # the model's size and bounds: CRD's cap and clip
            if plan.reset_opacity:
                model.reset_opacity()
        model.optimizer_step()
        model.zero_grad()
    return model


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=scene_folder, default=BUNDLED, help="scene folder (default: the bundled tabletop scene)")
    ap.add_argument("--steps", type=int_at_least(1), default=300, help="training steps")
    ap.add_argument("--seed", type=int_at_least(0, MAX_SEED), default=0, help="torch's seed and the schedule's")
    ap.add_argument("--threads", type=int_at_least(0), default=0, help="torch threads (0: torch's default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    model = train(load_scene(args.data), args.steps, args.seed)
    print(f"trained {model.num_primitives()} Gaussians in {args.steps} steps")
