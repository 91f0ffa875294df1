"""Train a 4DGS model (canonical Gaussians + HexPlane deformation) with MVGS, or as the plain
4DGS baseline, on a dynamic scene (the D-NeRF layout, a HyperNeRF capture, or a multi-camera
video in DyNeRF's layout: docs/data.md), and evaluate it.

    python tools/make_scene.py --variant moving --out scenes/moving   # the scene
    python examples/train_4dgs.py --data scenes/moving --preset baseline --steps 600 --out out/4dgs
    python examples/train_4dgs.py --data scenes/moving --preset multiview --views 4 --steps 600
    torchrun --nproc-per-node 2 examples/train_4dgs.py --data scenes/moving --views 8 --threads 1

Same CLI contract as train_3dgs.py (plus the 4DGS options below). Writes OUT/metrics.json (psnr,
ssim, lpips or null, train_seconds, steps, num_gaussians, model_mb, peak_memory_mb, preset,
config, model_config), OUT/test/*.png (each test view rendered at its own time),
OUT/point_cloud.ply (the canonical Gaussians), OUT/point_cloud_t<time>.ply (baked at each
--export-times entry) and OUT/deformation.pt (the field); model_mb is the size of the canonical
PLY plus the deformation file (what it takes to render any time).

The step budget is split into the coarse (static) stage and the fine (deformation) stage by
--coarse-fraction (the original D-NeRF recipe: 3000 of 23000 steps). With M > 1 views per step
--time-spread chooses how they spread over time: "stratified" (default: one view from each of M
time bins) or "random". With the pyramid presets (default, compact) the work the coarse steps
save is spent as 2-view steps at the end (--late-views, MVGSConfig.with_late_views), so a run of N
steps does the baseline's N steps of work, and its last steps see two times of the scene each.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from mvgs_plugin import MVGSConfig
from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
from mvgs_plugin.cli import (
    MAX_INIT_POINTS, HelpFormatter, common_args, config_from_args, float_above, int_at_least, launch, listed_in,
    metrics_record, model_config_from_args, rasterize_function, remove_stale_outputs, scene_folder, train_and_evaluate, write_json,
    scene_from_args, world_size_arg, late_views_arg, resolve_late_views, UsageError,
)
from mvgs_plugin.data.load import scene_layout
from mvgs_plugin.data.llff import is_video
from mvgs_plugin.data.nerf import is_dynamic

ORIGINAL_COARSE_FRACTION = 3000 / 23000  # 4DGS on D-NeRF: 3000 coarse + 20000 fine steps
# --late-views' default with the pyramid presets: the work the coarse steps save, spent as 2-view
# steps (two times of the scene) at the end (docs/equal_compute_log.md, "4DGS: the views the pyramid saves")
LATE_VIEWS = 2


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=scene_folder, required=True,
                    help="dynamic scene: the D-NeRF layout (frames with 'time'), a HyperNeRF capture, or a "
                         "multi-camera video (DyNeRF / Neu3D: poses_bounds.npy and frames in cam00/images/, ...); "
                         "required")
    world_size_arg(common_args(ap, "out/train_4dgs"))  # --steps: coarse + fine together
    late_views_arg(ap, LATE_VIEWS)
    # 4DGS
    ap.add_argument("--coarse-fraction", type=float_above(0, inclusive=True, high=0.999999), default=ORIGINAL_COARSE_FRACTION,
                    help="share of the steps in the static coarse stage, in [0, 1) (default: 3000/23000, the original's)")
    ap.add_argument("--time-spread", choices=["random", "stratified", "instant"], default="stratified",
                    help="how the M views of a step spread over time (MVGSConfig.time_spread); instant: M cameras "
                         "of one time, for a multi-camera video (one deformation for the M views)")
    ap.add_argument("--init-random", type=int_at_least(0, MAX_INIT_POINTS), default=0,
                    help="extra random initial points (the scene's points may miss the moving objects)")
    ap.add_argument("--init-box", type=float_above(-math.inf), nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                    help="box of the extra random points (default: the scene points' box widened to a cube)")
    ap.add_argument("--export-times", type=float_above(0, inclusive=True, high=1.0), nargs="*", default=[0.0, 0.5, 1.0],
                    help="times in [0, 1] at which to bake a PLY")
    args = resolve_late_views(ap.parse_args(argv), LATE_VIEWS)
    if args.lambda_dssim is None:  # 4DGS trains on L1 alone (its lambda_dssim is 0 in every config it ships)
        args.lambda_dssim = 0.0
    return args


def gs4d_config(config: MVGSConfig, args) -> GS4DConfig:
    """The canonical 3DGS schedules compressed with the run (as train_3dgs.py) and the coarse /
    fine split of the clock the adapter sees (the whole run; with restart_per_stage, as the paper
    preset, the clock restarts at every pyramid stage, so each stage begins with a coarse part)."""
    box = None if args.init_box is None else (tuple(args.init_box[:3]), tuple(args.init_box[3:]))
    canonical = model_config_from_args(config, args, rasterize=rasterize_function(args))
    return GS4DConfig.for_run(config, args.coarse_fraction, canonical, init_random_points=args.init_random,
                              init_box=box)


def build_adapter(args, scene, config: MVGSConfig) -> GS4DAdapter:
    """The 4DGS model this command line trains on `scene` under `config` (also what
    benchmarks/bench_view_cost.py times)."""
    return GS4DAdapter.from_scene(scene, gs4d_config(config, args), device=args.device)


def main(argv=None) -> dict:
    return launch(parse_args(argv), run)


def run(args, dist) -> dict:
    """Trains (on every rank under torchrun, each on its share of a step's views); rank 0
    evaluates and writes."""
    names = [f"point_cloud_t{t:.3f}.ply" for t in args.export_times]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # a bake would replace another
        raise UsageError(f"--export-times {' '.join(f'{t:g}' for t in args.export_times)}: times that round to the "
                         f"same 3 decimals write one file ({', '.join(twice)}); give each time once")
    taken = [n for n in names if (Path(args.out) / n).is_dir()]
    if taken:  # found before training, not when the bake would fail after it
        raise UsageError(f"--out {args.out}: {Path(args.out) / taken[0]} is a folder, where the run writes the baked "
                         f"{taken[0]}")
    if args.init_box is not None and not all(lo < hi for lo, hi in zip(args.init_box[:3], args.init_box[3:])):
        raise UsageError(f"--init-box {' '.join(f'{v:g}' for v in args.init_box)}: expected X0 Y0 Z0 X1 Y1 Z1 with "
                         "each minimum below its maximum")
    if args.init_box is not None and args.init_random == 0:
        raise UsageError(f"--init-box {' '.join(f'{v:g}' for v in args.init_box)}: the box places the --init-random "
                         "points, and --init-random is 0, so it would change nothing; give --init-random N too")
    try:  # a static NeRF-layout or LLFF scene, before it is read (and its points triangulated)
        layout = scene_layout(args.data)
        static = (layout == "nerf" and not is_dynamic(args.data)) or (layout == "llff" and not is_video(args.data))
    except ValueError as err:  # a malformed transforms_train.json, named
        raise UsageError(f"--data {args.data}: {err}") from err
    if static:
        raise UsageError(f"--data {args.data}: 4DGS needs a dynamic scene: the D-NeRF layout (transforms_train.json "
                         "whose frames carry a 'time'), a HyperNeRF capture (dataset.json, camera/) or a multi-camera "
                         "video (poses_bounds.npy and frames in cam00/, cam01/, ...)")
    scene = scene_from_args(args, dynamic_model=True)
    untimed = [c.name for c in scene.train_cameras + scene.test_cameras if c.time is None]
    if untimed:
        raise UsageError(f"--data {args.data}: 4DGS needs a dynamic scene (D-NeRF frames with 'time'); "
                         f"{len(untimed)} cameras have none, e.g. {untimed[0]!r}")
    lo, hi = min(c.time for c in scene.train_cameras), max(c.time for c in scene.train_cameras)
    beyond = [c for c in scene.test_cameras if not lo <= c.time <= hi]
    if beyond:  # the deformation field is fitted on [lo, hi] only
        print(f"{Path(sys.argv[0]).name}: note: {len(beyond)} of the {len(scene.test_cameras)} test views lie outside the "
              f"training views' times [{lo:g}, {hi:g}] (e.g. {beyond[0].name!r} at {beyond[0].time:g}): the deformation "
              "is extrapolated there, and their metrics measure that", file=sys.stderr)
    # 4DGS's recipe keeps no cut of the faintest Gaussians unless asked (--prune-faint S): on the moving scenes it
    # takes 4-6 % of the model at -0.01 dB (docs/equal_compute_log.md, "The cut made the default's")
    config = config_from_args(args, scene, time_spread=args.time_spread, prune_faint=0.0)
    adapter = build_adapter(args, scene, config)
    if args.init_random:  # metrics.json's "init" says where every initial point came from
        box = (f"the box {' '.join(f'{v:g}' for v in args.init_box)}" if args.init_box is not None
               else "the scene's own points' box widened to a cube" if scene.points is not None
               else "where the cameras look")
        said = f"plus {args.init_random} --init-random points in {box}"
        scene.points_origin = f"{scene.points_origin}; {said}" if scene.points_origin else said
    trainer, train_seconds, result = train_and_evaluate(adapter, scene, config, args, dist)
    model_cfg = adapter.gs4d_config  # after a resume, the checkpoint's (the same as the command's: checked)
    if result is None:  # not rank 0
        return {}

    out = args.out
    adapter.export(str(out / "point_cloud.ply"))
    adapter.save_deformation(str(out / "deformation.pt"))
    baked = [f"point_cloud_t{t:.3f}.ply" for t in args.export_times]
    for t, name in zip(args.export_times, baked):
        adapter.export_at_time(str(out / name), t)
    remove_stale_outputs(out, listed_in(out / "metrics.json", "baked"), baked, prefix="point_cloud_t", suffix=".ply")
    model_bytes = os.path.getsize(out / "point_cloud.ply") + os.path.getsize(out / "deformation.pt")
    metrics = metrics_record(
        args, config, trainer, result, train_seconds,
        model_mb=model_bytes / 2**20,
        deformation_parameters=sum(p.numel() for p in adapter.field.parameters()),
        model_config={"coarse_steps": model_cfg.coarse_steps, "fine_steps": model_cfg.fine_steps,
                      **{k: v for k, v in model_cfg.saved_values().items() if k not in ("coarse_steps", "fine_steps")},
                      "canonical": model_cfg.canonical.saved_values()},
    )
    metrics["baked"] = baked
    write_json(out / "metrics.json", metrics)
    print(
        f"{args.preset}: test PSNR {result.psnr:.2f} dB, SSIM {result.ssim:.4f}, "
        f"{metrics['num_gaussians']} Gaussians, {metrics['model_mb']:.2f} MB, {train_seconds:.1f} s training "
        f"-> {out}",
        file=sys.stderr,
    )
    return metrics


if __name__ == "__main__":
    main()
