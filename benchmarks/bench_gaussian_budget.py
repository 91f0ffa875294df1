"""How many Gaussians densification gives a scene: a flat textured plane (mvgs_plugin.testing.
plane_scene, analytic images) against the bundled tabletop, same recipe, same start.

    python benchmarks/bench_gaussian_budget.py --steps 200 --thresholds 2e-4 2.5e-3

Both train at 64 x 64 (the plane's images; the tabletop's 128 px at pyramid factor x 2) from
1500 initial points with MVGSConfig.default() (MVAD and CRD on, M = 4) compressed to --steps,
once per gradient threshold. Prints a markdown table: scene, threshold, final Gaussians, test
PSNR, training seconds. See docs/ablation/README.md ("A scene gets only the Gaussians it needs").
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch

from adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin import MVGS, MVGSConfig, Stage
from mvgs_plugin.data import PointCloud, load_nerf_synthetic
from mvgs_plugin.testing import plane_scene

ROOT = Path(__file__).resolve().parents[1]


def train(scene, factor: int, steps: int, threshold: float, seed: int):
    cfg = MVGSConfig.default(seed=seed, grad_threshold=threshold).with_total_steps(steps).with_views(4)
    cfg = dataclasses.replace(cfg, stages=tuple(Stage(s.factor * factor, s.views, s.steps) for s in cfg.stages))
    torch.manual_seed(seed)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(seed=seed, position_lr_max_steps=steps,
                                                       sh_degree_interval=max(1, steps // 20)))
    trainer = MVGS(adapter, scene, cfg)
    t0 = time.perf_counter()
    trainer.fit(progress=False)
    return adapter.num_primitives(), trainer.evaluate(factor=factor).psnr, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--thresholds", type=float, nargs="+", default=[2e-4])
    ap.add_argument("--points", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    plane = plane_scene(n_points=args.points, seed=args.seed)
    tabletop = load_nerf_synthetic(ROOT / "examples" / "scenes" / "tabletop")
    keep = torch.randperm(len(tabletop.points.xyz), generator=torch.Generator().manual_seed(args.seed))[:args.points]
    tabletop.points = PointCloud(tabletop.points.xyz[keep], tabletop.points.rgb[keep])
    rows = ["| scene | threshold | Gaussians (start " + str(args.points) + ") | test PSNR (dB) | train (s) |",
            "|---|---:|---:|---:|---:|"]
    for beta in args.thresholds:
        for name, scene, factor in (("plane", plane, 1), ("tabletop", tabletop, 2)):
            n, p, sec = train(scene, factor, args.steps, beta, args.seed)
            rows.append(f"| {name} | {beta:g} | {n} | {p:.2f} | {sec:.0f} |")
            print(rows[-1], flush=True)
    print(f"\n{args.steps} steps, MVGSConfig.default() with MVAD + CRD, M = 4, 64 x 64\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
