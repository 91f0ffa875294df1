"""Train a Scaffold-GS model (anchors + neural Gaussians) with MVGS, or as the plain Scaffold-GS
baseline, and evaluate it.

    python examples/train_scaffold.py --preset baseline --steps 300 --resolution-scale 2 --out out/sc_base
    python examples/train_scaffold.py --preset multiview --views 4 --steps 300 --resolution-scale 2 --out out/sc_mvgs
    python examples/train_scaffold.py --data scenes/reflective --voxel-size 0.02
    torchrun --nproc-per-node 2 examples/train_scaffold.py --views 8 --threads 1   # views over 2 processes

Same CLI contract as train_3dgs.py (plus the Scaffold options below). Writes OUT/metrics.json
(psnr, ssim, lpips or null, train_seconds, steps, num_gaussians (= anchors, the primitives the
controller counts), num_anchors, decoded_gaussians (mean over the test views of the neural
Gaussians rendered), model_mb (anchors, their parameters and the MLPs, float32), peak_memory_mb,
preset, config, model_config), OUT/test/*.png, OUT/point_cloud.ply (the neural Gaussians decoded
for the first test view, a standard 3DGS PLY) and OUT/anchors.pt (the native checkpoint:
ScaffoldAdapter.state_dict()).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

from mvgs_plugin import MVGSConfig
from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig
from mvgs_plugin.cli import (
    BUNDLED, HelpFormatter, common_args, config_from_args, float_above, launch, metrics_record,
    rasterize_function, scene_folder, train_and_evaluate, write_json, scene_from_args,
)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=scene_folder, default=BUNDLED, help="scene folder (default: the bundled tabletop scene)")
    common_args(ap, "out/train_scaffold")  # --max-gaussians: the budget of anchors
    ap.add_argument("--voxel-size", type=float_above(0), default=None,
                    help="anchor voxel edge (default: the median over the scene's own points, not the background "
                         "shell's, of their RMS distance to the 3 nearest others)")
    ap.add_argument("--use-distance", action="store_true", help="feed the camera distance to the MLPs")
    args = ap.parse_args(argv)
    if args.budget_swap:  # the adapter would take it and do nothing
        ap.error(f"--budget-swap {args.budget_swap:g}: Scaffold-GS anchors do not swap (the swap acts on 3DGS and 4DGS "
                 "Gaussians and in the gsplat strategy); leave it out")
    if args.prune_faint:  # the controller would warn and run without it
        ap.error(f"--prune-faint {args.prune_faint:g}: Scaffold-GS decodes its Gaussians from anchors every view, so "
                 "there are no blend weights of lasting Gaussians to cut by (the cut acts on 3DGS and 4DGS); leave it out")
    return args


def scaffold_config(config: MVGSConfig, args) -> ScaffoldConfig:
    """The MLP and offset learning-rate decays (30k steps in the original) compressed with the
    run, as train_3dgs.py compresses the 3DGS schedules."""
    return ScaffoldConfig.for_run(config, voxel_size=args.voxel_size, use_distance=args.use_distance, seed=args.seed)


def build_adapter(args, scene, config: MVGSConfig) -> ScaffoldAdapter:
    """The Scaffold-GS model this command line trains on `scene` under `config` (also what
    benchmarks/bench_view_cost.py times)."""
    model_cfg = dataclasses.replace(scaffold_config(config, args), rasterize=rasterize_function(args))
    return ScaffoldAdapter.from_scene(scene, model_cfg, device=args.device)


def main(argv=None) -> dict:
    return launch(parse_args(argv), run)


def run(args, dist) -> dict:
    """Trains (on every rank under torchrun, each on its share of a step's views); rank 0
    evaluates and writes."""
    scene = scene_from_args(args)
    config = config_from_args(args, scene, prune_faint=0.0)  # no cut of the faintest: anchors decode new ones every view
    adapter = build_adapter(args, scene, config)
    model_cfg = adapter.config
    trainer, train_seconds, result = train_and_evaluate(adapter, scene, config, args, dist)
    if result is None:  # not rank 0
        return {}

    out = args.out
    views = [c if args.resolution_scale == 1 else c.scaled(args.resolution_scale) for c in scene.test_cameras]
    with torch.no_grad():
        decoded = [int((adapter.decode(v)[1]["opacities"] > 0).sum()) for v in views]
    adapter.export(str(out / "point_cloud.ply"), views[0])
    adapter.save_anchors(str(out / "anchors.pt"))
    model_numel = adapter.anchors.numel() + sum(p.numel() for p in adapter.gradient_parameters().values())
    metrics = metrics_record(
        args, config, trainer, result, train_seconds,
        num_anchors=adapter.num_primitives(), decoded_gaussians=sum(decoded) / len(decoded),
        voxel_size=adapter.voxel_size, model_mb=model_numel * 4 / 2**20, model_config=model_cfg.saved_values(),
    )
    write_json(out / "metrics.json", metrics)
    print(
        f"{args.preset}: test PSNR {result.psnr:.2f} dB, SSIM {result.ssim:.4f}, {metrics['num_anchors']} anchors, "
        f"{metrics['decoded_gaussians']:.0f} decoded Gaussians, {metrics['model_mb']:.2f} MB, "
        f"{train_seconds:.1f} s training -> {out}",
        file=sys.stderr,
    )
    return metrics


if __name__ == "__main__":
    main()
