"""Single view against MVGS in the port of gsplat's simple_trainer loop, at equal steps and at
equal CPU time; prints a markdown table (and writes it with --table).

Every run is its own single-threaded process (examples/gsplat_loop/simple_trainer*.py, one
thread), at most `--parallel` at a time. Rows:
- single view, gsplat's DefaultStrategy as installed, `--steps` steps;
- single view through MVGSStrategy's baseline preset (the same strategy on the schedule's clock,
  which also resets opacities: gsplat 1.5.3's strategy alone never does);
- single view with grow_grad2d = 2e-4 x 800 / W (W the images' width): the threshold the
  default preset uses at full resolution, so that row differs from "MVGS default" only by the
  pyramid warm-up and the opacity resets;
- each MVGS preset in `--presets` at `--steps` steps;
- equal CPU: for each MVGS preset, the single-view loop given the steps that cost the preset's
  CPU time (its steps x preset CPU / single-view CPU), and the preset given the single-view
  run's CPU time the same way.

    python benchmarks/bench_gsplat_loop.py --steps 1000 --table docs/gsplat_loop.md

With --graphdeco-budget F it runs the graphdeco-shaped loop (examples/graphdeco_loop/train_mvgs.py)
instead: "baseline" and each of --presets without a budget, then each with --max-gaussians F x
the unbudgeted baseline's final count (a quarter: issue 27's gate), at --steps steps, with
--threshold-width W on every run when given (800: the package's baseline) and, with
--package-rules, train_3dgs.py's far-background rules on every run (a shell of 2000 points, the
distance size rule, resets that spare the far background) and with --opacity-lr LR every run's
--opacity-lr (5e-2: train_3dgs.py's; the loop's own is graphdeco's 2.5e-2); the table
gives PSNR and its difference to the unbudgeted baseline, the final and the largest count held,
CPU and wall seconds.

    python benchmarks/bench_gsplat_loop.py --graphdeco-budget 0.25 --steps 3000 --presets default --threshold-width 800 [--package-rules] [--opacity-lr 0.05]

--gsplat-budget F makes the same table in the port of gsplat's loop (simple_trainer_mvgs.py): its
"baseline" preset is given --grow-grad2d 2e-4 x 800 / W (the package baseline's threshold at W-px
images; the other presets scale gsplat's 2e-4 themselves), and --package-rules gives every run the
shell and MVGSStrategy's distance size rule and resets that spare the far background.

    python benchmarks/bench_gsplat_loop.py --gsplat-budget 0.25 --steps 3000 --presets default [--package-rules]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOOP = ROOT / "examples" / "gsplat_loop"
GRAPHDECO = ROOT / "examples" / "graphdeco_loop" / "train_mvgs.py"


def run(script: str, steps: int, out: Path, data, preset=None, seed: int = 0, extra=()) -> dict:
    """One run of a loop (`script` under examples/gsplat_loop, or an absolute path); `preset` only
    for the MVGS loops (the single-view loop refuses it)."""
    cmd = [sys.executable, str(LOOP / script), "--steps", str(steps), "--out", str(out), "--threads", "1",
           *(["--preset", preset] if preset else []), "--seed", str(seed), *extra]
    if data is not None:
        cmd += ["--data", str(data)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads((out / "metrics.json").read_text())


# --package-rules: train_3dgs.py's far-background rules given to the graphdeco loop
PACKAGE_RULES = ("--background-points", "2000", "--world-size-rule", "distance", "--opacity-reset-scope", "inside")


def run_graphdeco(steps: int, out: Path, data, preset: str, seed: int = 0, budget=None, width=None,
                  rules: bool = False, opacity_lr=None) -> dict:
    """One run of the graphdeco-shaped loop (run() on its script), with `budget` as --max-gaussians,
    `width` as --threshold-width and `opacity_lr` as --opacity-lr when given and, with `rules`,
    PACKAGE_RULES."""
    extra = [*(["--max-gaussians", str(budget)] if budget else []),
             *(["--threshold-width", f"{width:g}"] if width is not None else []),
             *(["--opacity-lr", f"{opacity_lr:g}"] if opacity_lr is not None else []),
             *(PACKAGE_RULES if rules else ())]
    return run(str(GRAPHDECO), steps, out, data, preset, seed, extra)


def run_gsplat(steps: int, out: Path, data, preset: str, seed: int = 0, budget=None, width=None,
               rules: bool = False) -> dict:
    """One run of the port of gsplat's loop with MVGSStrategy (simple_trainer_mvgs.py), with
    `budget` as --max-gaussians, for the baseline preset --grow-grad2d 2e-4 x 800 / `width` (the
    images' width) and, with `rules`, PACKAGE_RULES."""
    extra = [*(["--max-gaussians", str(budget)] if budget else []),
             *(["--grow-grad2d", f"{2e-4 * 800 / width:.6g}"] if preset == "baseline" else []),
             *(PACKAGE_RULES if rules else ())]
    return run("simple_trainer_mvgs.py", steps, out, data, preset, seed, extra)


def budget_table(args, loop: str) -> str:
    """The graphdeco loop or the port of gsplat's (`loop`) without and with a budget of F x the
    baseline's count (F: args.graphdeco_budget or args.gsplat_budget)."""
    presets = ["baseline", *[p for p in args.presets if p != "baseline"]]
    if loop == "graphdeco":
        share, width, name = args.graphdeco_budget, args.threshold_width, "the graphdeco-shaped loop"
        runner = partial(run_graphdeco, opacity_lr=args.opacity_lr)
    else:
        from mvgs_plugin.data import load_scene

        share, runner, name = args.gsplat_budget, run_gsplat, "the port of gsplat's loop (MVGSStrategy)"
        width = load_scene(args.data or ROOT / "examples" / "scenes" / "tabletop").train_cameras[0].width
    with ThreadPoolExecutor(args.parallel) as pool:
        free = {p: pool.submit(runner, args.steps, args.out / f"{loop}_{p}", args.data, p, args.seed,
                               None, width, args.package_rules) for p in presets}
        free = {p: f.result() for p, f in free.items()}
        n = max(1, round(share * free["baseline"]["num_gaussians"]))
        capped = {p: pool.submit(runner, args.steps, args.out / f"{loop}_{p}_budget", args.data, p,
                                 args.seed, n, width, args.package_rules) for p in presets}
        capped = {p: f.result() for p, f in capped.items()}
    ref = free["baseline"]["psnr"]
    if loop == "graphdeco":
        threshold = "the presets' own" if width is None else f"{width:g} px"
    else:
        threshold = f"2e-4 x 800 / {width} px (baseline's --grow-grad2d)"
    lines = [f"Scene: {args.data or 'bundled tabletop'}; {name}, {args.steps} steps, seed {args.seed}; "
             f"threshold width {threshold}; {'train_3dgs.py' if args.package_rules else '3DGS'}'s far-background rules; "
             f"{'' if args.opacity_lr is None else f'opacity learning rate {args.opacity_lr:g}; '}"
             f"one thread per run; budget N = {share:g} x the unbudgeted baseline's "
             f"{free['baseline']['num_gaussians']} Gaussians = {n}; CPU = user + sys of the training loop.", "",
             "| run | budget | PSNR (dB) | vs baseline | Gaussians | most held | CPU (s) | wall (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for p in presets:
        for m in (free[p], capped[p]):
            lines.append(f"| {p} | {m.get('max_gaussians') or '-'} | {m['psnr']:.2f} | {m['psnr'] - ref:+.2f} | "
                         f"{m['num_gaussians']} | {m.get('most_held', '-')} | {m['cpu_seconds']:.0f} | "
                         f"{m['train_seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def row(name: str, m: dict) -> str:
    return (f"| {name} | {m['steps']} | {m['work']:.0f} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m['num_gaussians']} "
            f"| {m['cpu_seconds']:.0f} | {m['train_seconds']:.0f} |")


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="scene folder (default: the bundled tabletop scene)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--presets", nargs="+", default=["default", "multiview"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/bench_gsplat_loop"))
    ap.add_argument("--table", type=Path, default=None, help="also write the table here")
    ap.add_argument("--graphdeco-budget", type=float, default=None, metavar="F",
                    help="run the graphdeco-shaped loop without and with a budget of F x its baseline's count instead")
    ap.add_argument("--gsplat-budget", type=float, default=None, metavar="F",
                    help="the same table in the port of gsplat's loop (simple_trainer_mvgs.py) instead")
    ap.add_argument("--threshold-width", type=float, default=None, metavar="W",
                    help="with --graphdeco-budget: every run's --threshold-width (800: the package's baseline "
                         "threshold; default: each preset's own)")
    ap.add_argument("--package-rules", action="store_true",
                    help="with --graphdeco-budget or --gsplat-budget: every run with train_3dgs.py's far-background rules ("
                         + " ".join(PACKAGE_RULES) + "; default: 3DGS's, the scene's points only)")
    ap.add_argument("--opacity-lr", type=float, default=None, metavar="LR",
                    help="with --graphdeco-budget: every run's --opacity-lr (5e-2: train_3dgs.py's; default: the "
                         "loop's, graphdeco's 2.5e-2)")
    args = ap.parse_args(argv)
    if args.opacity_lr is not None and args.graphdeco_budget is None:
        ap.error("--opacity-lr is the graphdeco loop's: give it with --graphdeco-budget")
    if args.graphdeco_budget is not None or args.gsplat_budget is not None:
        if args.graphdeco_budget is not None and args.gsplat_budget is not None:
            ap.error("--graphdeco-budget and --gsplat-budget make two tables: give one")
        text = budget_table(args, "graphdeco" if args.graphdeco_budget is not None else "gsplat")
        print(text)
        if args.table is not None:
            args.table.write_text(text)
        return text
    n, out = args.steps, args.out

    from mvgs_plugin.data import load_scene

    width = load_scene(args.data or ROOT / "examples" / "scenes" / "tabletop").train_cameras[0].width
    scaled = ["--grow-grad2d", f"{2e-4 * 800 / width:.6g}"]
    jobs = {"single": ("simple_trainer.py", n, None, ()),
            "single-mvgs-clock": ("simple_trainer_mvgs.py", n, "baseline", ()),
            "single-scaled": ("simple_trainer.py", n, None, scaled)}
    jobs.update({p: ("simple_trainer_mvgs.py", n, p, ()) for p in args.presets})
    with ThreadPoolExecutor(args.parallel) as pool:
        futures = {k: pool.submit(run, s, steps, out / k, args.data, p, args.seed, x)
                   for k, (s, steps, p, x) in jobs.items()}
        first = {k: f.result() for k, f in futures.items()}
        single = first["single"]
        second = {}
        for p in args.presets:
            ratio = first[p]["cpu_seconds"] / single["cpu_seconds"]
            second[f"single@{p}"] = pool.submit(run, "simple_trainer.py", max(2, round(n * ratio)), out / f"single_at_{p}",
                                                args.data, None, args.seed)
            second[f"{p}@single"] = pool.submit(run, "simple_trainer_mvgs.py", max(2, round(n / ratio)), out / f"{p}_at_single",
                                                args.data, p, args.seed)
            ratio_scaled = first[p]["cpu_seconds"] / first["single-scaled"]["cpu_seconds"]
            if ratio_scaled > 1.05:  # the scaled single view is cheaper: give it the preset's CPU time
                second[f"scaled@{p}"] = pool.submit(run, "simple_trainer.py", max(2, round(n * ratio_scaled)),
                                                    out / f"single_scaled_at_{p}", args.data, None, args.seed,
                                                    scaled)
            elif ratio_scaled < 0.95:  # the preset is cheaper: give it the scaled single view's CPU time
                second[f"{p}@scaled"] = pool.submit(run, "simple_trainer_mvgs.py", max(2, round(n / ratio_scaled)),
                                                    out / f"{p}_at_single_scaled", args.data, p, args.seed)
        second = {k: f.result() for k, f in second.items()}

    lines = [f"Scene: {args.data or 'bundled tabletop'}; seed {args.seed}; one thread per run; CPU = user + sys of the "
             "training loop, wall beside it; work = full-resolution view renders.", "",
             "| run | steps | work | PSNR (dB) | SSIM | Gaussians | CPU (s) | wall (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|",
             row("single view (DefaultStrategy as installed)", single),
             row("single view, MVGSStrategy baseline preset (schedule's clock, with resets)", first["single-mvgs-clock"]),
             row(f"single view, grow_grad2d {scaled[1]} (the default's threshold at {width} px)",
                 first["single-scaled"])]
    for p in args.presets:
        lines.append(row(f"MVGS {p}, equal steps", first[p]))
    for p in args.presets:
        lines.append(row(f"single view at MVGS {p}'s CPU time", second[f"single@{p}"]))
        lines.append(row(f"MVGS {p} at single view's CPU time", second[f"{p}@single"]))
        if f"scaled@{p}" in second:
            lines.append(row(f"single view, grow_grad2d {scaled[1]}, at MVGS {p}'s CPU time", second[f"scaled@{p}"]))
        if f"{p}@scaled" in second:
            lines.append(row(f"MVGS {p} at the grow_grad2d {scaled[1]} single view's CPU time", second[f"{p}@scaled"]))
    text = "\n".join(lines) + "\n"
    print(text)
    if args.table is not None:
        args.table.write_text(text)
    return text


if __name__ == "__main__":
    main()
