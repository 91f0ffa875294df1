"""Train a 3DGS model with MVGS (or as the plain 3DGS baseline) and evaluate it.

    python examples/train_3dgs.py                                   # bundled scene, default preset
    python examples/train_3dgs.py --preset baseline --steps 2000 --out out/baseline
    python examples/train_3dgs.py --data path/to/colmap_or_nerf --preset paper --views 8
    python examples/train_3dgs.py --preset multiview --views 4 --no-crd --no-mvad   # MVRL + CIG only
    python examples/train_3dgs.py --preset baseline --budget 1000        # a budget of work, not steps
    torchrun --nproc-per-node 2 examples/train_3dgs.py --views 8 --threads 1   # views sharded over 2 processes

Under torchrun every rank trains the same model on its share of each step's views
(mvgs_plugin.distributed; gloo on CPU, NCCL on GPU); only rank 0 writes outputs.

Writes OUT/metrics.json (psnr, ssim, lpips or null, train_seconds (wall), cpu_seconds (user +
sys of the process), steps, budget (null without --budget), work (full-resolution view renders
spent), num_gaussians, peak_memory_mb, preset, config, world_size), OUT/test/*.png (test renders), OUT/point_cloud.ply
and, with --checkpoint, OUT/checkpoint.pt (loadable by a single process).

The three lines that make MVGS out of a model: build the adapter, the config, and let the
controller drive (or see examples/three_line_wrap for a hand-written loop):

    adapter = GS3DAdapter.from_scene(scene)
    trainer = MVGS(adapter, scene, MVGSConfig.default().with_total_steps(steps))
    trainer.fit()
"""

from __future__ import annotations

import argparse
import sys

from mvgs_plugin.adapters.gs3d import GS3DAdapter
from mvgs_plugin.config import MVGSConfig
from mvgs_plugin.cli import (
    BUNDLED, HelpFormatter, common_args, config_from_args, launch, metrics_record, model_config_from_args,
    rasterize_function, scene_folder, train_and_evaluate, write_json, scene_from_args, world_size_arg,
)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=scene_folder, default=BUNDLED, help="scene folder (default: the bundled tabletop scene)")
    world_size_arg(common_args(ap, "out/train_3dgs"))
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    return launch(parse_args(argv), run)


def build_adapter(args, scene, config: MVGSConfig) -> GS3DAdapter:
    """The 3DGS model this command line trains on `scene` under `config` (its schedules
    compressed with the run; also what benchmarks/bench_view_cost.py times)."""
    model = model_config_from_args(config, args, rasterize=rasterize_function(args))
    return GS3DAdapter.from_scene(scene, model, device=args.device)


def run(args, dist) -> dict:
    scene = scene_from_args(args)
    config = config_from_args(args, scene)
    adapter = build_adapter(args, scene, config)
    trainer, train_seconds, result = train_and_evaluate(adapter, scene, config, args, dist)
    if result is None:  # not rank 0
        return {}

    out = args.out
    adapter.export(str(out / "point_cloud.ply"))
    metrics = metrics_record(args, config, trainer, result, train_seconds)
    write_json(out / "metrics.json", metrics)
    print(
        f"{args.preset}: test PSNR {result.psnr:.2f} dB, SSIM {result.ssim:.4f}, "
        f"{metrics['num_gaussians']} Gaussians, {train_seconds:.1f} s training -> {out}",
        file=sys.stderr,
    )
    return metrics


if __name__ == "__main__":
    main()
