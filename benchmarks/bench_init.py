"""Initial points for scenes without them: what each --init gives, and what triangulation costs.

Accuracy (--scenes): for every scene folder given (each with its own point file, which is the
reference), trains plain 3DGS (``--preset baseline --threshold-width 800``, --steps steps, one
torch thread, one process per run, two side by side) from the scene's points and, on a copy
of the folder without the point file (links, made under OUT), from each --inits method ("tracks": the triangulated points alone, the ablation
of the fill). Prints
and writes OUT/init.md: PSNR, SSIM and Gaussians on the test views, the init's points, CPU and
wall seconds, and the training's CPU seconds.

    python benchmarks/bench_init.py --scenes scenes/forward scenes/forward-clutter scenes/corridor

Cost (--cost-scene): a scene with at least max(--cost-views) training views; for each view
count V and image width W, the first V training views resized to W (a NeRF-synthetic copy
under OUT) are triangulated with one thread: seconds of each pycolmap stage and of the fill.

    python benchmarks/bench_init.py --cost-scene scenes/corridor300 --cost-views 50 300 --cost-sizes 128 800
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mvgs_plugin.io import atomic_write_text  # noqa: E402

POINT_FILES = ("points3d.ply", "sparse")
INITS = ("triangulate", "random", "frusta", "cube")


def bare_copy(scene: Path, out: Path) -> Path:
    """``scene`` without its point file: a folder of links to everything else."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for item in scene.iterdir():
        if item.name not in POINT_FILES:
            (out / item.name).symlink_to(item.resolve())
    return out


def train(data: Path, init: str, steps: int, seed: int, out: Path) -> dict:
    """One baseline run in this process (one thread) from ``init`` ("points": the scene's file)."""
    import torch

    from mvgs_plugin import MVGS
    from mvgs_plugin import cli as ex
    from mvgs_plugin.adapters.gs3d import GS3DAdapter

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    argv = ["--preset", "baseline", "--threshold-width", "800", "--steps", str(steps), "--seed", str(seed),
            "--data", str(data), "--out", str(out), "--threads", "1", "--init", init if init in INITS else "triangulate"]
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", type=ex.scene_folder)
    args = ex.common_args(parser, str(out)).parse_args(argv)
    c0, w0 = time.process_time(), time.perf_counter()
    if init == "tracks":  # the ablation: triangulated tracks only, no fill
        from mvgs_plugin.data.triangulate import initial_points

        scene = ex.load_scene(args.data, init=None)
        made = initial_points(scene, "triangulate", seed=seed, threads=1, fill=False)
        scene.points, scene.points_origin = made.points, made.description
    else:
        scene = ex.scene_from_args(args)
    init_cpu, init_wall = time.process_time() - c0, time.perf_counter() - w0
    config = ex.config_from_args(args, scene)
    adapter = GS3DAdapter.from_scene(scene, ex.model_config(config, seed))
    trainer = MVGS(adapter, scene, config)
    c0, w0 = time.process_time(), time.perf_counter()
    while trainer.step_count < trainer.total_steps:
        trainer.step()
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    result = trainer.evaluate()
    return {"scene": data.name, "init": init, "init_points": len(scene.points), "init_cpu": init_cpu,
            "init_wall": init_wall, "origin": scene.points_origin, "psnr": result.psnr, "ssim": result.ssim,
            "gaussians": adapter.num_primitives(), "steps": trainer.step_count, "cpu": cpu, "wall": wall}


def accuracy_table(rows: list) -> str:
    lines = ["| scene | init | init points | init CPU / wall s | PSNR | SSIM | Δ PSNR vs points | Gaussians | train CPU s |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        ref = next((p for p in rows if p["scene"] == r["scene"] and p["init"] == "points"), None)
        delta = "" if ref is None or r is ref else f"{r['psnr'] - ref['psnr']:+.2f}"
        lines.append(f"| {r['scene']} | {r['init']} | {r['init_points']} | {r['init_cpu']:.1f} / {r['init_wall']:.1f} | "
                     f"{r['psnr']:.2f} | {r['ssim']:.3f} | {delta} | {r['gaussians']} | {r['cpu']:.0f} |")
    return "\n".join(lines) + "\n"


def subset(scene: Path, views: int, width: int, out: Path) -> Path:
    """The first ``views`` training views of a NeRF-synthetic scene, resized to ``width``."""
    import numpy as np
    from PIL import Image

    meta = json.loads((scene / "transforms_train.json").read_text())
    if len(meta["frames"]) < views:
        raise SystemExit(f"{scene} has {len(meta['frames'])} training views, fewer than {views}")
    if out.exists():
        shutil.rmtree(out)
    (out / "train").mkdir(parents=True)
    frames = []
    for k, frame in enumerate(meta["frames"][:views]):
        src = scene / (frame["file_path"] if Path(frame["file_path"]).suffix else frame["file_path"] + ".png")
        img = Image.open(src).convert("RGB")
        height = round(img.height * width / img.width)
        img.resize((width, height), Image.LANCZOS).save(out / "train" / f"{k:04d}.png")
        frames.append({"file_path": f"train/{k:04d}.png", "transform_matrix": frame["transform_matrix"]})
        if k == 0:
            size = (width, height)
    fx = 0.5 * size[0] / np.tan(0.5 * meta["camera_angle_x"])
    header = {"camera_angle_x": meta["camera_angle_x"], "fl_x": fx, "fl_y": fx, "cx": size[0] / 2, "cy": size[1] / 2}
    (out / "transforms_train.json").write_text(json.dumps({**header, "frames": frames}))
    (out / "transforms_test.json").write_text(json.dumps({**header, "frames": frames[:1]}))
    return out


def cost(scene: Path, views: int, width: int, out: Path) -> dict:
    """Seconds of each triangulation stage and of the fill, one thread."""
    import tempfile

    import torch

    from mvgs_plugin.data import load_nerf_synthetic
    from mvgs_plugin.data.triangulate import fill_points, triangulate

    torch.set_num_threads(1)
    folder = subset(scene, views, width, out / f"cost_{views}x{width}")
    s = load_nerf_synthetic(folder)
    c0, w0 = time.process_time(), time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        tracks = triangulate(s, work, threads=1)
    tri_cpu, tri_wall = time.process_time() - c0, time.perf_counter() - w0
    c0, w0 = time.process_time(), time.perf_counter()
    n_fill = max(0, 10_000 - len(tracks))
    if n_fill:
        fill_points(s, torch.from_numpy(tracks.xyz), n_fill, torch.Generator().manual_seed(0))
    fill_cpu, fill_wall = time.process_time() - c0, time.perf_counter() - w0
    shutil.rmtree(folder)
    return {"views": views, "width": width, "tracks": len(tracks), "pairs": tracks.pairs, **tracks.seconds,
            "triangulate_cpu": tri_cpu, "triangulate_wall": tri_wall, "fill": n_fill, "fill_cpu": fill_cpu,
            "fill_wall": fill_wall}


def cost_table(rows: list) -> str:
    lines = ["| views | width | tracks | view pairs | extract s | match s | triangulate s | pycolmap CPU / wall s "
             "| fill points | fill CPU / wall s | total CPU s |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['views']} | {r['width']} | {r['tracks']} | {r['pairs']} | {r['extract']:.1f} | "
                     f"{r['match']:.1f} | {r['triangulate']:.1f} | {r['triangulate_cpu']:.1f} / {r['triangulate_wall']:.1f} | "
                     f"{r['fill']} | {r['fill_cpu']:.1f} / {r['fill_wall']:.1f} | {r['triangulate_cpu'] + r['fill_cpu']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=Path, nargs="*", default=[], help="scene folders with a point file")
    ap.add_argument("--inits", nargs="+", default=["triangulate", "random"], choices=[*INITS, "tracks"],
                    help="methods run on the copies without points (tracks: triangulated points only, no fill)")
    ap.add_argument("--steps", type=int, default=1000, help="baseline steps per run")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--processes", type=int, default=2, help="runs side by side (one thread each)")
    ap.add_argument("--cost-scene", type=Path, default=None, help="a NeRF-synthetic scene with many training views")
    ap.add_argument("--cost-views", type=int, nargs="+", default=[50, 300])
    ap.add_argument("--cost-sizes", type=int, nargs="+", default=[128, 800])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_init")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    text = ""
    if args.scenes:
        jobs = []
        for scene in args.scenes:
            bare = bare_copy(scene, args.out / "bare" / scene.name)
            jobs.append((scene, "points", args.steps, args.seed, args.out / "runs" / f"{scene.name}_points"))
            jobs += [(bare, m, args.steps, args.seed, args.out / "runs" / f"{scene.name}_{m}") for m in args.inits]
        # a fresh interpreter per run; workers leave on their own (a pool's terminate would kill
        # them mid-teardown, which torch and pycolmap report as a crash)
        with ProcessPoolExecutor(args.processes, mp_context=multiprocessing.get_context("spawn"),
                                 max_tasks_per_child=1) as pool:
            rows = list(pool.map(train, *zip(*jobs)))
        atomic_write_text(args.out / "init_runs.json", json.dumps(rows, indent=1))
        text += f"Baseline, {args.steps} steps, seed {args.seed}, one thread:\n\n" + accuracy_table(rows)
    if args.cost_scene is not None:
        rows = [cost(args.cost_scene, v, w, args.out) for v in args.cost_views for w in args.cost_sizes]
        atomic_write_text(args.out / "cost_runs.json", json.dumps(rows, indent=1))
        text += "\nTriangulation cost, one thread:\n\n" + cost_table(rows)
    atomic_write_text(args.out / "init.md", text)
    print(text)


if __name__ == "__main__":
    main()
