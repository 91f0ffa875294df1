"""Baseline 3DGS against MVGS at equal compute: every run gets the same budget of work and is
judged on PSNR against CPU time (user + sys of a single-threaded process).

For each budget (full-resolution view renders, MVGSConfig.with_budget: a baseline step is 1, a
view at pyramid factor f counts 0.1 + 0.9 / f) and each run kind, one training in its own
process with one torch thread, two processes side by side at most; the test views are evaluated
at --points points of the budget (evaluation is not timed). Writes OUT/equal_compute.md (the
table: PSNR, SSIM, Gaussians, steps, work, CPU and wall seconds; each MVGS row with the
baseline at the same budget beside it) and OUT/psnr_vs_cpu.png (every run's evaluation curve),
and OUT/runs.json with everything (each run's test PSNR per view too; the tables give the median
view's beside the mean, which the few views a far horizon crosses can move by a dB).

    python benchmarks/bench_equal_compute.py --budgets 1000 3000
    python benchmarks/bench_equal_compute.py --data path/to/scene --budgets 3000 --runs baseline default

Run kinds: "baseline" (plain 3DGS with the default's width-scaled gradient threshold, so that
only MVGS differs), "baseline-fixed" (3DGS's fixed threshold), "default" (MVGSConfig.default(),
the cost-aware recipe: coarse-to-fine, one view per step, the faintest Gaussians cut once after
densification since 2026-11-30; "default-no-faint" is it without the cut), "multiview" (MVGSConfig.multiview(),
the former default, with --views M at full resolution), "multiview-rules-off" (the same without
MVAD and CRD), and the candidates tried for the default (see RUNS and docs/equal_compute.md).
--clock steps gives every run B steps instead (the equal-steps comparison).

    python benchmarks/bench_equal_compute.py --summary docs/equal_compute/*/runs.json

prints one table over scenes and budgets from earlier runs (each run kind against the baseline
of the same file and budget, else of another file of the same scene and seed), with a column
against the baseline's best so far: the best evaluation point of any of its runs of that scene
within the row's CPU seconds (an oracle early stop on the test views; it cannot fall with more
compute), and one at equal CPU: the baseline's final PSNR linear between its two runs (of any
budget) whose CPU brackets the row's ("at 0.69x" where the row used less CPU than its cheapest
run); then a table over the seeds the files hold (mean, min to max).
--reference KIND compares with another run kind instead (e.g. baseline-budget).
Issue 27's kinds: "baseline-budget" (the baseline with a Gaussian budget of the training
pixels / 128), "default-budget", "coarse-mv-budget" (4 views per step at 1/4 resolution, 2 at
1/2) and "coarse-mv-sqrt-budget" (with Grendel-GS's sqrt(M) rule), all at pixels / 213;
"default-budget128", the default at the baseline's pixels / 128; "compact" (MVGSConfig.compact(), the
default at pixels / 213 where the rig is not forward-facing); with the shell and the distance
size rule, "coarse-mv4" (4 views per step at 1/4, 2 at 1/2, no budget) and "coarse-mv4-cap" /
"default-cap" (the same and the default at the budget --max-gaussians N). "baseline-r10" and
"default-r10" are the two with the floor on opacity resets before 2026-11-27 (10 densification
calls apart in a compressed clock, MVGSConfig.min_densify_per_reset; now 30).
"baseline-reset-inside" and "default-reset-inside" are the two with opacity resets that leave the
far background alone (--opacity-reset-scope inside, every kind's default since 2026-11-28);
"baseline-reset-all" and "default-reset-all" reset every opacity, as 3DGS (the default before).
"baseline-cap" and "baseline-score-cap" are the baseline at --max-gaussians N, its growth ordered
as GS3DConfig.budget_growth_order "auto" orders it (inside the far line first, on a rig round the
scene; the default since 2026-11-28) and by score alone (before).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import multiprocessing
import resource
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from mvgs_plugin.cli import int_at_least, repo_path, scene_folder  # noqa: E402
from mvgs_plugin.io import atomic_write_text  # noqa: E402

COARSE_MV4 = ["--stages", "4:4:2308,2:2:5455,1:1:21000"]  # 4 views per step at 1/4, 2 at 1/2, one at full
RUNS = {
    "baseline": ["--preset", "baseline", "--threshold-width", "800"],
    "baseline-fixed": ["--preset", "baseline"],
    "default": ["--preset", "default"],
    # the default with its pyramid kept on a forward-facing rig (the default before forward_rig)
    "default-pyramid": ["--preset", "default", "--forward-rig", "pyramid"],
    # the default with densification capped at twice the count each stage began with
    "default-growth2": ["--preset", "default", "--stage-growth", "2"],
    # the default's two plans spelled out (docs/equal_compute_log.md, "The 1/4 level does not pay"):
    # today's, 30 % of the work at 1/2 and 70 % at full; the one before 2026-11-27, 10 % at 1/4,
    # 20 % at 1/2, 70 % at full
    "default-half": ["--preset", "default", "--stages", "2:1:16364,1:1:21000"],
    "default-quarter": ["--preset", "default", "--stages", "4:1:9231,2:1:10909,1:1:21000"],
    # the default with its periodic opacity resets at the 1/2 level too (before 2026-11-27, evening;
    # docs/equal_compute_log.md, "No opacity reset at the coarse level")
    "default-coarse-reset": ["--preset", "default", "--coarse-opacity-reset"],
    # the default's pyramid with 10 % of the work at 1/2 at every budget (docs/equal_compute_log.md, "Opacity
    # resets that leave time to recover"; at a budget of 10k it is today's default, "A warm-up of fixed length")
    "default-coarse10": ["--preset", "default", "--stages", "2:1:5455,1:1:27000"],
    # the default before its warm-up was held to 1000 views' work (2026-11-28): 30 % at 1/2 at every budget
    "default-warmup-shares": ["--preset", "default", "--warmup-work-cap", "0"],
    # the baseline and the default with the floor on opacity resets before 2026-11-27 (night): no sooner
    # than 10 densification calls apart when the schedule is compressed (now 30, 3DGS's own ratio;
    # docs/equal_compute_log.md, "Opacity resets that leave time to recover")
    "baseline-r10": ["--preset", "baseline", "--threshold-width", "800", "--min-densify-per-reset", "10"],
    "default-r10": ["--preset", "default", "--min-densify-per-reset", "10"],
    # the baseline and the default with resets that leave the far background alone
    # (GS3DConfig.opacity_reset_scope "inside", every kind's since 2026-11-28; docs/equal_compute_log.md,
    # "Resets that spare the far background"), and with 3DGS's reset of every opacity (before it)
    "baseline-reset-inside": ["--preset", "baseline", "--threshold-width", "800", "--opacity-reset-scope", "inside"],
    "default-reset-inside": ["--preset", "default", "--opacity-reset-scope", "inside"],
    "baseline-reset-all": ["--preset", "baseline", "--threshold-width", "800", "--opacity-reset-scope", "all"],
    "default-reset-all": ["--preset", "default", "--opacity-reset-scope", "all"],
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
    # Issue 27: a budget from the data (MVGSConfig.pixels_per_gaussian). The baseline at 128 training
    # pixels per Gaussian (3DGS ends at 70-210 on its benchmarks); the candidates at 213, 0.6x its
    # count: the default's pyramid with one view per step, and with 4 views per step at 1/4
    # resolution and 2 at 1/2 (the same work shares, 10 / 20 / 70 %), with and without
    # Grendel-GS's sqrt(M) optimizer rule. Growth is ranked by the multi-view consistency score.
    "baseline-budget": ["--preset", "baseline", "--threshold-width", "800", "--pixels-per-gaussian", "128"],
    "default-budget": ["--preset", "default", "--pixels-per-gaussian", "213"],
    # the default with the baseline's data budget (pixels / 128; no size pruning under a budget):
    # the strongest run at 10k steps on the 360-degree scenes (docs/equal_compute.md)
    "default-budget128": ["--preset", "default", "--pixels-per-gaussian", "128"],
    # the compact preset: default-budget as a preset (no budget on a forward-facing rig)
    "compact": ["--preset", "compact"],
    "coarse-mv-budget": ["--preset", "default", *COARSE_MV4, "--pixels-per-gaussian", "213"],
    "coarse-mv-sqrt-budget": ["--preset", "default", *COARSE_MV4, "--pixels-per-gaussian", "213", "--views-scaling", "sqrt"],
    # Issue 27 with the background shell and the distance size rule: the M = 4 recipe without a
    # budget, and the M = 4 recipe and the default with the budget --max-gaussians N of this
    # script (the kinds ending in "-cap"; e.g. a quarter of the baseline's count)
    "coarse-mv4": ["--preset", "default", *COARSE_MV4],
    "coarse-mv4-cap": ["--preset", "default", *COARSE_MV4],
    "default-cap": ["--preset", "default"],
    # the baseline at the budget --max-gaussians N: growth under it orders candidates as
    # GS3DConfig.budget_growth_order "auto" does (the object before the far background on a rig
    # round the scene, since 2026-11-28), and by score alone (the order before)
    "baseline-cap": ["--preset", "baseline", "--threshold-width", "800"],
    "baseline-score-cap": ["--preset", "baseline", "--threshold-width", "800", "--budget-growth-order", "score"],
    # the baseline and the default with the faintest splats cut once after densification, those with
    # the least blend weight per blended pixel that carry 1 % of the weight (MVGSConfig.prune_faint)
    "baseline-faint": ["--preset", "baseline", "--threshold-width", "800", "--prune-faint", "0.01"],
    "default-faint": ["--preset", "default", "--prune-faint", "0.01"],
    # the default as it was before 2026-11-30, when the cut became its own (DEFAULT_PRUNE_FAINT)
    "default-no-faint": ["--preset", "default", "--prune-faint", "0"],
    "default-no-faint-cap": ["--preset", "default", "--prune-faint", "0"],
}
CAPPED = tuple(k for k in RUNS if k.endswith("-cap"))  # the kinds that take --max-gaussians


def run_argv(kind: str, budget: float, views: int, seed: int, scale: int, clock: str = "budget",
             background_points: int | None = None, max_gaussians: int | None = None) -> list:
    """The examples' command line of one run (train_3dgs.py's flags, without --data)."""
    if kind in CAPPED and max_gaussians is None:
        raise ValueError(f"run kind {kind!r} needs --max-gaussians N (the budget it is run at)")
    length = ["--budget", str(budget)] if clock == "budget" else ["--steps", str(int(budget))]
    argv = [*RUNS[kind], *length, "--seed", str(seed), "--resolution-scale", str(scale)]
    if background_points is not None:
        argv += ["--background-points", str(background_points)]
    if kind in CAPPED:
        argv += ["--max-gaussians", str(int(max_gaussians))]
    if kind.startswith("multiview"):
        argv += ["--views", str(views)]  # the candidates keep their own stage plans
    return argv


def train(data, kind: str, budget: float, views: int, points: int, seed: int, scale: int, clock: str = "budget",
          background_points: int | None = None, max_gaussians: int | None = None) -> dict:
    """One run, in this process (one thread): trains on the budget and evaluates at `points`
    evenly spaced points of the step count; returns the final metrics and the curve."""
    import torch

    from mvgs_plugin import cli as ex  # the examples' own CLI contract: same config as `train_3dgs.py --budget`
    from mvgs_plugin.adapters.gs3d import GS3DAdapter
    from mvgs_plugin import MVGS

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    argv = run_argv(kind, budget, views, seed, scale, clock, background_points, max_gaussians)
    if data is not None:
        argv += ["--data", str(data)]
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", type=ex.scene_folder, default=ex.BUNDLED)
    args = ex.world_size_arg(ex.common_args(parser, "out/bench")).parse_args(argv)
    scene = ex.load_scene(args.data, background_points=args.background_points,  # the examples' init
                          background_radius=args.background_radius)
    ex.check_resolution(scene, args.resolution_scale)
    config = ex.config_from_args(args, scene)
    adapter = GS3DAdapter.from_scene(scene, ex.model_config_from_args(config, args))
    trainer = MVGS(adapter, scene, config)
    marks = {round(trainer.total_steps * (i + 1) / points) for i in range(points)}
    cpu, wall, curve = 0.0, 0.0, []
    tally = ex.DensifyTally(adapter.num_primitives())
    while trainer.step_count < trainer.total_steps:
        c0, w0 = time.process_time(), time.perf_counter()
        info = trainer.step()
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        tally.add(info)
        if trainer.step_count in marks:
            curve.append({"cpu": cpu, "step": trainer.step_count, "work": trainer.schedule.work_done,
                          "psnr": trainer.evaluate(factor=scale).psnr})
    result = trainer.evaluate(factor=scale)
    per_view = [float(v["psnr"]) for v in result.per_view]
    return {"kind": kind, "budget": budget, "clock": clock, "views": config.stages[-1].views,
            "max_gaussians": config.max_gaussians,
            "psnr": result.psnr, "ssim": result.ssim, "gaussians": adapter.num_primitives(),
            "peak_gaussians": tally.totals["peak_primitives"], "faint_removed": tally.totals["faint"],
            "per_view_psnr": per_view, "psnr_median": statistics.median(per_view) if per_view else result.psnr,
            "steps": trainer.step_count, "work": trainer.schedule.work_done, "cpu": cpu, "wall": wall,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "curve": curve}


def baseline_of(rows: list, r: dict, reference: str = "baseline"):
    """The `reference` run of `rows` at r's budget and clock, or None."""
    return next((b for b in rows if b["kind"] == reference and b["budget"] == r["budget"]
                 and b.get("clock", "budget") == r.get("clock", "budget")), None)


def median_delta(r: dict, base) -> str:
    """r's median test view PSNR minus the reference's, or "" (no reference, or a run saved before
    the median was recorded)."""
    if base is None or r is base or r.get("psnr_median") is None or base.get("psnr_median") is None:
        return ""
    return f"{r['psnr_median'] - base['psnr_median']:+.2f}"


def table(rows: list, scene: str, reference: str = "baseline") -> str:
    lines = [f"Scene: {scene}. One torch thread per run; CPU = user + sys of the training steps "
             "(evaluation excluded); work in full-resolution view renders; the median view's PSNR beside the "
             "mean, which a few views can move by a dB.", "",
             f"| {'budget' if rows and rows[0].get('clock', 'budget') == 'budget' else 'steps'} | run | views/step | steps | work | test PSNR (dB) | vs baseline | test SSIM | vs baseline "
             "| Gaussians | CPU (s) | wall (s) | median view (dB) | vs baseline |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        base = baseline_of(rows, r, reference)
        d_psnr = "" if base is None or r is base else f"{r['psnr'] - base['psnr']:+.2f}"
        d_ssim = "" if base is None or r is base else f"{r['ssim'] - base['ssim']:+.3f}"
        med = "" if r.get("psnr_median") is None else f"{r['psnr_median']:.2f}"
        lines.append(f"| {r['budget']:g} | {r['kind']} | {r['views']} | {r['steps']} | {r['work']:.0f} "
                     f"| {r['psnr']:.2f} | {d_psnr} | {r['ssim']:.4f} | {d_ssim} | {r['gaussians']:,} "
                     f"| {r['cpu']:.0f} | {r['wall']:.0f} | {med} | {median_delta(r, base)} |")
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


def reference_runs(rows: list, reference: str) -> list:
    """The `reference` runs of `rows` on the budget clock (the ones a CPU comparison may use)."""
    return [b for b in rows if b["kind"] == reference and b.get("clock", "budget") == "budget"]


def compared(files: list, pooled: dict, reference: str):
    """(scene, seed, run, its reference run) for every run of `files` (read_runs) that is not the
    reference kind and has one: the reference of its own file at its budget first, else of
    another file of the same scene and seed."""
    for (scene, seed), rows in files:
        for r in rows:
            base = baseline_of(rows, r, reference) or baseline_of(pooled[(scene, seed)], r, reference)
            if base is not None and r["kind"] != reference:
                yield scene, seed, r, base


def best_so_far(rows: list, reference: str, cpu: float):
    """The best test PSNR any `reference` run of `rows` showed at an evaluation point reached within
    `cpu` CPU seconds (its curve; the runs of every budget), or None: the reference with an oracle
    early stop on the test views, which cannot fall with more compute."""
    seen = [p["psnr"] for b in reference_runs(rows, reference) for p in b.get("curve", []) if p["cpu"] <= cpu]
    return max(seen) if seen else None


def summary(paths, reference: str = "baseline") -> str:
    """One markdown table over runs.json files: per scene (the data the file's runs trained on),
    seed, clock and budget, the `reference` run's numbers (from any of the files) and every other
    run kind's difference to it; and the difference to the reference's best so far (best_so_far:
    the best evaluation point of any of its runs of that scene and seed within the run's CPU)."""
    lines = [f"| scene | seed | clock | B | {reference} PSNR / SSIM / Gaussians / CPU s | run | PSNR | Δ PSNR | Δ SSIM "
             f"| Δ PSNR vs its best so far | Gaussians vs {reference} | CPU vs {reference} | steps | Δ median view "
             f"| Δ PSNR at equal CPU |",
             "|---|---:|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    files, pooled = read_runs(paths)
    for scene, seed, r, base in compared(files, pooled, reference):
        best = best_so_far(pooled[(scene, seed)], reference, r["cpu"]) if r.get("clock", "budget") == "budget" else None
        d_best = "" if best is None else f"{r['psnr'] - best:+.2f}"
        lines.append(f"| {scene} | {seed} | {r.get('clock', 'budget')} | {r['budget']:g} | {base['psnr']:.2f} / "
                     f"{base['ssim']:.3f} / {base['gaussians']:,} / {base['cpu']:.0f} | {r['kind']} | {r['psnr']:.2f} | {r['psnr'] - base['psnr']:+.2f} "
                     f"| {r['ssim'] - base['ssim']:+.3f} | {d_best} | {r['gaussians'] / base['gaussians']:.2f}x "
                     f"| {r['cpu'] / base['cpu']:.2f}x | {r['steps']} | {median_delta(r, base)} "
                     f"| {equal_cpu_delta(pooled[(scene, seed)], reference, r)} |")
    return "\n".join(lines) + "\n"


def read_runs(paths):
    """The runs of each runs.json file keyed by (scene, seed), in file order, and pooled by key."""
    files = []
    for path in paths:
        saved = json.loads(Path(path).read_text())
        data = saved["args"].get("data", "None")
        scene = "tabletop (bundled)" if data == "None" else Path(data).name
        files.append(((scene, saved["args"].get("seed", "0")), saved["runs"]))
    pooled: dict = {}
    for key, rows in files:
        pooled.setdefault(key, []).extend(rows)
    return files, pooled


def equal_cpu_psnr(rows: list, reference: str, cpu: float):
    """The `reference` runs' final PSNR at `cpu` CPU seconds, linear between the two runs (of any
    budget; budget clock) whose CPU brackets it, or None outside their range (fewer than two runs,
    or a run cheaper than the cheapest reference run or dearer than the dearest)."""
    points = sorted((b["cpu"], b["psnr"]) for b in reference_runs(rows, reference))
    if len(points) < 2 or not points[0][0] <= cpu <= points[-1][0]:
        return None
    for (c0, p0), (c1, p1) in zip(points, points[1:]):
        if c0 <= cpu <= c1:
            return p0 if c1 == c0 else p0 + (p1 - p0) * (cpu - c0) / (c1 - c0)


def equal_cpu_delta(rows: list, reference: str, r: dict) -> str:
    """r's PSNR minus the reference's at r's CPU (equal_cpu_psnr); "at 0.69x" where r used less
    CPU than the cheapest reference run (the ratio to it), "" where there is nothing to compare."""
    if r.get("clock", "budget") != "budget":
        return ""
    at = equal_cpu_psnr(rows, reference, r["cpu"])
    if at is not None:
        return f"{r['psnr'] - at:+.2f}"
    cheapest = min((b["cpu"] for b in reference_runs(rows, reference)), default=None)
    return f"at {r['cpu'] / cheapest:.2f}x" if cheapest and r["cpu"] < cheapest else ""


def seed_summary(paths, reference: str = "baseline") -> str:
    """Per scene, clock, budget and run kind over the seeds the runs.json files hold: the mean
    (min to max) of the difference to the reference at equal work and at equal CPU (the seeds
    where the run's CPU is inside the reference's range), and the mean ratios of Gaussians and CPU."""
    files, pooled = read_runs(paths)
    groups: dict = {}
    for scene, seed, r, base in compared(files, pooled, reference):
        at = equal_cpu_psnr(pooled[(scene, seed)], reference, r["cpu"]) if r.get("clock", "budget") == "budget" else None
        g = groups.setdefault((scene, r.get("clock", "budget"), r["budget"], r["kind"]), {})
        g[seed] = (r["psnr"] - base["psnr"], None if at is None else r["psnr"] - at,
                   r["gaussians"] / base["gaussians"], r["cpu"] / base["cpu"])

    def spread(values):
        if not values:
            return ""
        mean = sum(values) / len(values)
        return f"{mean:+.2f}" if len(values) == 1 else f"{mean:+.2f} ({min(values):+.2f} to {max(values):+.2f})"

    lines = [f"Over seeds: Δ PSNR against {reference} as mean (min to max); at equal CPU only the seeds whose run "
             f"falls inside {reference}'s CPU range.", "",
             f"| scene | clock | B | run | seeds | Δ PSNR at equal work | Δ PSNR at equal CPU (seeds) "
             f"| Gaussians vs {reference} | CPU vs {reference} |",
             "|---|---|---:|---|---|---:|---:|---:|---:|"]
    for (scene, clock, budget, kind), by_seed in groups.items():
        vals = list(by_seed.values())
        cpu_d = [v[1] for v in vals if v[1] is not None]
        lines.append(f"| {scene} | {clock} | {budget:g} | {kind} | {' '.join(sorted(by_seed))} | {spread([v[0] for v in vals])} "
                     f"| {spread(cpu_d)}{f' ({len(cpu_d)})' if cpu_d else ''} | {sum(v[2] for v in vals) / len(vals):.2f}x "
                     f"| {sum(v[3] for v in vals) / len(vals):.2f}x |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=scene_folder, default=None, help="scene folder (default: the bundled tabletop)")
    ap.add_argument("--budgets", type=float, nargs="+", default=[1000, 3000])
    ap.add_argument("--runs", nargs="+", default=["baseline", "default"], choices=sorted(RUNS))
    ap.add_argument("--views", type=int_at_least(1), default=4, help="M at full resolution for the multiview runs")
    ap.add_argument("--clock", choices=["budget", "steps"], default="budget",
                    help="budget: each run gets --budgets B of work (equal compute); steps: each run makes "
                         "B steps (equal steps, the recipes' work differs)")
    ap.add_argument("--points", type=int_at_least(1), default=8, help="evaluations along each run")
    ap.add_argument("--resolution-scale", type=int_at_least(1), default=1)
    ap.add_argument("--processes", type=int_at_least(1), default=2, help="runs side by side (one thread each)")
    ap.add_argument("--seed", type=int_at_least(0), default=0)
    ap.add_argument("--background-points", type=int_at_least(0), default=None, metavar="N",
                    help="initial points on the background shell (default: the examples' default; 0: 3DGS's init)")
    ap.add_argument("--max-gaussians", type=int_at_least(1), default=None, metavar="N",
                    help=f"the Gaussian budget of the run kinds {', '.join(CAPPED)} (required with them)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "equal_compute")
    ap.add_argument("--summary", type=Path, nargs="+", default=None, metavar="RUNS_JSON",
                    help="print one table from these runs.json files and exit (no training)")
    ap.add_argument("--reference", default="baseline", choices=sorted(RUNS),
                    help="the run kind every other row is compared with (default: %(default)s)")
    args = ap.parse_args(argv)
    if args.summary:
        text = summary(args.summary, args.reference) + "\n" + seed_summary(args.summary, args.reference)
        print(text)
        return text
    if args.max_gaussians is None and any(k in CAPPED for k in args.runs):
        ap.error(f"--runs {' '.join(k for k in args.runs if k in CAPPED)} need --max-gaussians N")
    if args.max_gaussians is not None and not any(k in CAPPED for k in args.runs):
        ap.error(f"--max-gaussians is the budget of the run kinds {', '.join(CAPPED)}; --runs {' '.join(args.runs)} has none")
    if any(not b > 0 for b in args.budgets):
        ap.error(f"--budgets must be > 0, got {args.budgets}")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out {args.out} exists and is not a folder")
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.data, kind, b, args.views, args.points, args.seed, args.resolution_scale, args.clock,
             args.background_points, args.max_gaussians)
            for b in args.budgets for kind in args.runs]
    # spawn: a fresh interpreter per run (its own peak memory, nothing shared); one task each. An
    # executor, not a Pool: a worker that fails (a usage error found once the scene is read) or dies
    # ends the benchmark with its error instead of leaving the Pool waiting for ever.
    with concurrent.futures.ProcessPoolExecutor(args.processes, mp_context=multiprocessing.get_context("spawn"),
                                                max_tasks_per_child=1) as pool:
        futures = [pool.submit(train, *job) for job in jobs]
        try:
            rows = [f.result() for f in futures]
        except (SystemExit, ValueError) as err:  # argparse's exit, UsageError: the user's to fix
            for f in futures:
                f.cancel()
            ap.error(str(err) or "a run's arguments were refused (its message is above)")
    scene = repo_path(args.data) if args.data else "bundled tabletop"
    recorded = {k: repo_path(v) if isinstance(v, Path) else str(v) for k, v in vars(args).items()}  # no machine paths
    atomic_write_text(args.out / "runs.json", json.dumps({"args": recorded,
                                                    "runs": rows}, indent=1))
    atomic_write_text(args.out / "equal_compute.md", table(rows, scene, args.reference))
    plot(rows, args.out / "psnr_vs_cpu.png")
    print(table(rows, scene, args.reference))
    return rows


if __name__ == "__main__":
    main()
