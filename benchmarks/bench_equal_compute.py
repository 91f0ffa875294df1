"""Baseline 3DGS against MVGS at equal compute: every run gets the same budget of work and is
judged on PSNR against CPU time (user + sys of a single-threaded process).

For each budget (full-resolution view renders, MVGSConfig.with_budget: a baseline step is 1, a
view at pyramid factor f counts 0.1 + 0.9 / f) and each run kind, one training in its own
process with one torch thread, two processes side by side at most; the test views are evaluated
at --points points of the budget (evaluation is not timed). Writes OUT/equal_compute.md (the
table: PSNR, SSIM, Gaussians, steps, work, CPU and wall seconds; each MVGS row with the
baseline at the same budget beside it) and OUT/psnr_vs_cpu.png (every run's evaluation curve),
and OUT/runs.json with everything.

    python benchmarks/bench_equal_compute.py --budgets 1000 3000
    python benchmarks/bench_equal_compute.py --data path/to/scene --budgets 3000 --runs baseline default

Run kinds: "baseline" (plain 3DGS with the default's width-scaled gradient threshold, so that
only MVGS differs), "baseline-fixed" (3DGS's fixed threshold), "default" (MVGSConfig.default(),
the cost-aware recipe: coarse-to-fine, one view per step), "multiview" (MVGSConfig.multiview(),
the former default, with --views M at full resolution), "multiview-rules-off" (the same without
MVAD and CRD), and the candidates tried for the default (see RUNS and docs/equal_compute.md).
--clock steps gives every run B steps instead (the equal-steps comparison).

    python benchmarks/bench_equal_compute.py --summary docs/equal_compute/*/runs.json

prints one table over scenes and budgets from earlier runs (each run kind against the baseline
of the same file and budget).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mvgs_plugin.cli import repo_path  # noqa: E402
from mvgs_plugin.io import atomic_write_text  # noqa: E402
RUNS = {
    "baseline": ["--preset", "baseline", "--threshold-width", "800"],
    "baseline-fixed": ["--preset", "baseline"],
    "default": ["--preset", "default"],
    # the default with its pyramid kept on a forward-facing rig (the default before forward_rig)
    "default-pyramid": ["--preset", "default", "--forward-rig", "pyramid"],
    # the default with densification capped at twice the count each stage began with
    "default-growth2": ["--preset", "default", "--stage-growth", "2"],
    "multiview": ["--preset", "multiview"],
    "multiview-rules-off": ["--preset", "multiview", "--no-mvad", "--no-crd"],
    # multiview with Grendel-GS's batch rule for the optimizer; with the sparse-view guard
    "multiview-sqrt": ["--preset", "multiview", "--views-scaling", "sqrt"],
    "multiview-capped": ["--preset", "multiview", "--max-views-fraction", "0.25"],
    # Candidates tried for the cost-aware default (docs/equal_compute.md): the pyramid's coarse
    # levels with many (cheap) views and one at full resolution; the same pyramid with one view
    # per step; the default's pyramid with as many views per coarse step as cost about one full
    # view (3 at 1/4, 2 at 1/2), MVAD and CRD on; the default with 2-view steps at full
    # resolution once densification has ended (the same gradients as accumulating two
    # consecutive single-view steps).
    "coarse-mv": ["--preset", "multiview", "--stages", "8:16:1000,4:8:1000,2:4:1000,1:1:30000"],
    "pyramid-only": ["--preset", "multiview", "--no-mvad", "--no-crd", "--stages", "8:1:1000,4:1:1000,2:1:1000,1:1:30000"],
    "coarse-mv-1x": ["--preset", "multiview", "--stages", "4:3:3077,2:2:5455,1:1:21000"],
    "late-mv": ["--preset", "default", "--stages", "4:1:9231,2:1:10909,1:1:6000,1:2:7500"],
}


def train(data, kind: str, budget: float, views: int, points: int, seed: int, scale: int, clock: str = "budget") -> dict:
    """One run, in this process (one thread): trains on the budget and evaluates at `points`
    evenly spaced points of the step count; returns the final metrics and the curve."""
    import torch

    from mvgs_plugin import cli as ex  # the examples' own CLI contract: same config as `train_3dgs.py --budget`
    from mvgs_plugin.adapters.gs3d import GS3DAdapter
    from mvgs_plugin import MVGS

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    length = ["--budget", str(budget)] if clock == "budget" else ["--steps", str(int(budget))]
    argv = [*RUNS[kind], *length, "--seed", str(seed), "--resolution-scale", str(scale)]
    if kind.startswith("multiview"):
        argv += ["--views", str(views)]  # the candidates keep their own stage plans
    if data is not None:
        argv += ["--data", str(data)]
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", type=ex.scene_folder, default=ex.BUNDLED)
    args = ex.common_args(parser, "out/bench").parse_args(argv)
    scene = ex.load_scene(args.data)
    config = ex.config_from_args(args, scene)
    adapter = GS3DAdapter.from_scene(scene, ex.model_config(config, seed))
    trainer = MVGS(adapter, scene, config)
    marks = {round(trainer.total_steps * (i + 1) / points) for i in range(points)}
    cpu, wall, curve = 0.0, 0.0, []
    while trainer.step_count < trainer.total_steps:
        c0, w0 = time.process_time(), time.perf_counter()
        trainer.step()
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        if trainer.step_count in marks:
            curve.append({"cpu": cpu, "step": trainer.step_count, "work": trainer.schedule.work_done,
                          "psnr": trainer.evaluate(factor=scale).psnr})
    result = trainer.evaluate(factor=scale)
    return {"kind": kind, "budget": budget, "clock": clock, "views": config.stages[-1].views,
            "psnr": result.psnr, "ssim": result.ssim, "gaussians": adapter.num_primitives(),
            "steps": trainer.step_count, "work": trainer.schedule.work_done, "cpu": cpu, "wall": wall,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "curve": curve}


def baseline_of(rows: list, r: dict):
    """The baseline run of `rows` at r's budget, or None."""
    return next((b for b in rows if b["kind"] == "baseline" and b["budget"] == r["budget"]), None)


def table(rows: list, scene: str) -> str:
    lines = [f"Scene: {scene}. One torch thread per run; CPU = user + sys of the training steps "
             "(evaluation excluded); work in full-resolution view renders.", "",
             f"| {'budget' if rows and rows[0].get('clock', 'budget') == 'budget' else 'steps'} | run | views/step | steps | work | test PSNR (dB) | vs baseline | test SSIM | vs baseline "
             "| Gaussians | CPU (s) | wall (s) |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        base = baseline_of(rows, r)
        d_psnr = "" if base is None or r is base else f"{r['psnr'] - base['psnr']:+.2f}"
        d_ssim = "" if base is None or r is base else f"{r['ssim'] - base['ssim']:+.3f}"
        lines.append(f"| {r['budget']:g} | {r['kind']} | {r['views']} | {r['steps']} | {r['work']:.0f} "
                     f"| {r['psnr']:.2f} | {d_psnr} | {r['ssim']:.4f} | {d_ssim} | {r['gaussians']:,} "
                     f"| {r['cpu']:.0f} | {r['wall']:.0f} |")
    return "\n".join(lines) + "\n"


def plot(rows: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for r in rows:
        xs = [0.0] + [p["cpu"] for p in r["curve"]]
        ys = [float("nan")] + [p["psnr"] for p in r["curve"]]
        ax.plot(xs, ys, marker="o", ms=3, label=f"{r['kind']} @ {r['budget']:g}",
                linestyle="-" if r["kind"].startswith("baseline") else "--")
    ax.set_xlabel("CPU seconds (one thread, evaluation excluded)")
    ax.set_ylabel("test PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def summary(paths) -> str:
    """One markdown table over runs.json files: per scene (the file's folder) and budget, the
    baseline's numbers and every other run kind's difference to it."""
    lines = ["| scene | seed | clock | B | baseline PSNR / SSIM | run | PSNR | Δ PSNR | Δ SSIM | Gaussians vs baseline "
             "| CPU vs baseline | steps |", "|---|---:|---|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for path in paths:
        saved = json.loads(Path(path).read_text())
        rows, data = saved["runs"], saved["args"].get("data", "None")
        scene = "tabletop (bundled)" if data == "None" else Path(data).name
        seed = saved["args"].get("seed", "0")
        for r in rows:
            base = baseline_of(rows, r)
            if base is None or r is base:
                continue
            lines.append(f"| {scene} | {seed} | {r.get('clock', 'budget')} | {r['budget']:g} | {base['psnr']:.2f} / "
                         f"{base['ssim']:.3f} | {r['kind']} | {r['psnr']:.2f} | {r['psnr'] - base['psnr']:+.2f} "
                         f"| {r['ssim'] - base['ssim']:+.3f} | {r['gaussians'] / base['gaussians']:.2f}x "
                         f"| {r['cpu'] / base['cpu']:.2f}x | {r['steps']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="scene folder (default: the bundled tabletop)")
    ap.add_argument("--budgets", type=float, nargs="+", default=[1000, 3000])
    ap.add_argument("--runs", nargs="+", default=["baseline", "default"], choices=sorted(RUNS))
    ap.add_argument("--views", type=int, default=4, help="M at full resolution for the multiview runs")
    ap.add_argument("--clock", choices=["budget", "steps"], default="budget",
                    help="budget: each run gets --budgets B of work (equal compute); steps: each run makes "
                         "B steps (equal steps, the recipes' work differs)")
    ap.add_argument("--points", type=int, default=8, help="evaluations along each run")
    ap.add_argument("--resolution-scale", type=int, default=1)
    ap.add_argument("--processes", type=int, default=2, help="runs side by side (one thread each)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "equal_compute")
    ap.add_argument("--summary", type=Path, nargs="+", default=None, metavar="RUNS_JSON",
                    help="print one table from these runs.json files and exit (no training)")
    args = ap.parse_args(argv)
    if args.summary:
        text = summary(args.summary)
        print(text)
        return text
    if any(not b > 0 for b in args.budgets):
        ap.error(f"--budgets must be > 0, got {args.budgets}")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out {args.out} exists and is not a folder")
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.data, kind, b, args.views, args.points, args.seed, args.resolution_scale, args.clock)
            for b in args.budgets for kind in args.runs]
    # spawn: a fresh interpreter per run (its own peak memory, nothing shared); one task each.
    with multiprocessing.get_context("spawn").Pool(args.processes, maxtasksperchild=1) as pool:
        rows = pool.starmap(train, jobs)
    scene = repo_path(args.data) if args.data else "bundled tabletop"
    recorded = {k: repo_path(v) if isinstance(v, Path) else str(v) for k, v in vars(args).items()}  # no machine paths
    atomic_write_text(args.out / "runs.json", json.dumps({"args": recorded,
                                                    "runs": rows}, indent=1))
    atomic_write_text(args.out / "equal_compute.md", table(rows, scene))
    plot(rows, args.out / "psnr_vs_cpu.png")
    print(table(rows, scene))
    return rows


if __name__ == "__main__":
    main()
