"""How many Gaussians densification gives a scene: a flat textured plane (mvgs_plugin.testing.
plane_scene, analytic images) against the bundled tabletop (Mitsuba), same recipe, same start.

    python benchmarks/bench_gaussian_budget.py --steps 1000 --threads 1 --max-minutes 6
    python benchmarks/bench_gaussian_budget.py --steps 200 --widths 800 0

Both train at 64 x 64 (the plane's images; the tabletop's 128 px at pyramid factor x 2) from
--points initial points with MVGSConfig.multiview() (M = 4) compressed to --steps, for every
threshold policy in --widths (800: β = 2e-4 meant for 800 px images and scaled to the rendered
width, our default; 0: β fixed, as 3DGS and the released MVGS) and with MVGS's two densification
rules (MVAD, CRD) on and off. A run that trains longer than --max-minutes stops and is marked.
Prints a markdown table: scene, policy, rules, final Gaussians, test PSNR, steps, training
seconds. tests/test_gaussian_budget.py asserts the default row at 1000 steps; the analysis is
in docs/ablation/README.md ("A scene gets only the Gaussians it needs").
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin import CRDConfig, MVADConfig, MVGS, MVGSConfig, Stage
from mvgs_plugin.data import PointCloud, load_nerf_synthetic
from mvgs_plugin.testing import plane_scene

ROOT = Path(__file__).resolve().parents[1]


def train(scene, factor: int, steps: int, width: float, rules: bool, seed: int, max_seconds: float):
    """Returns (Gaussians, test PSNR, steps run, training seconds)."""
    cfg = MVGSConfig.multiview(seed=seed, grad_threshold_width=width or None, 
                                mvad=MVADConfig(enabled=rules), crd=CRDConfig(enabled=rules))
    cfg = cfg.with_total_steps(steps).with_views(4)
    cfg = dataclasses.replace(cfg, stages=tuple(Stage(s.factor * factor, s.views, s.steps) for s in cfg.stages))
    torch.manual_seed(seed)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(seed=seed, position_lr_max_steps=steps,
                                                       sh_degree_interval=max(1, steps // 20)))
    trainer = MVGS(adapter, scene, cfg)
    seconds = 0.0
    while trainer.step_count < trainer.total_steps and seconds < max_seconds:
        seconds += trainer.step().seconds
    return adapter.num_primitives(), trainer.evaluate(factor=factor).psnr, trainer.step_count, seconds


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--widths", type=float, nargs="+", default=[800.0, 0.0],
                    help="threshold policies: the image width β is meant for (0: β fixed)")
    ap.add_argument("--points", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-minutes", type=float, default=float("inf"), help="stop a run after this much training")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    plane = plane_scene(n_points=args.points, seed=args.seed)
    tabletop = load_nerf_synthetic(ROOT / "examples" / "scenes" / "tabletop")
    keep = torch.randperm(len(tabletop.points.xyz), generator=torch.Generator().manual_seed(args.seed))[:args.points]
    tabletop.points = PointCloud(tabletop.points.xyz[keep], tabletop.points.rgb[keep])
    rows = [f"| scene | threshold | MVAD + CRD | Gaussians (start {args.points}) | test PSNR (dB) | steps | train (s) |",
            "|---|---|---|---:|---:|---:|---:|"]
    for width in args.widths:
        policy = f"2e-4 at {width:g} px, scaled" if width else "2e-4 fixed"
        for rules in (True, False):
            for name, scene, factor in (("plane", plane, 1), ("tabletop", tabletop, 2)):
                n, p, done, sec = train(scene, factor, args.steps, width, rules, args.seed, args.max_minutes * 60)
                stopped = "" if done == args.steps else " (stopped)"
                rows.append(f"| {name} | {policy} | {'on' if rules else 'off'} | {n} | {p:.2f} | {done}{stopped} "
                            f"| {sec:.0f} |")
                print(rows[-1], flush=True)
    print(f"\n{args.steps} steps, MVGSConfig.multiview(), M = 4, 64 x 64, {torch.get_num_threads()} thread(s)\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
