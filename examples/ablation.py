"""The MVGS ablation, speed against error: cumulative variants of the paper's ablation plus the
paper preset and our default, on one scene, same seed; writes a markdown table and plots.

    python examples/ablation.py --steps 600 --views 4 --out docs/ablation/tabletop
    python tools/make_scene.py --variant reflective --out scenes/reflective
    python examples/ablation.py --data scenes/reflective --steps 600 --out docs/ablation/reflective

Variants (our implementations of each rule, with their guards):
    baseline           plain 3DGS (1 view per step, full resolution)
    +MVRL              M views per step, summed loss, full resolution, no extra densification
    +CRD               ... plus cross-ray densification
    +MVAD              ... plus multi-view augmented densification
    +CIG (= default)   ... plus the coarse-to-fine pyramid: the multiview preset (the default before
                       the equal-compute study)
    paper              the released behaviour (docs/method.md)
    baseline, equal time   plain 3DGS trained for as many steps as fit in the full run's time
All but paper scale the gradient threshold to the rendered image width as MVGSConfig.multiview()
does (--threshold-width, 0 for 3DGS's fixed threshold), so they differ only by MVGS's parts.
Each variant runs in its own process (its own peak memory). Writes OUT/ablation.md (test
PSNR/SSIM/LPIPS, wall time, Gaussians, peak RSS, controller overhead (its own time: sampling,
MVAD, CRD geometry, checks, bookkeeping; and, as an upper bound, everything outside render and
backward), how often MVAD lowered the threshold, CRD boxes and the Gaussians cloned in them, the equal-steps and equal-time
comparisons), OUT/ablation.png (PSNR and Gaussians per variant) and OUT/psnr_vs_time.png (test
PSNR against training wall time for baseline, full MVGS and the equal-time baseline; evaluation
time excluded).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import multiprocessing
import resource
import sys
from pathlib import Path
from typing import Optional

import torch

from mvgs_plugin.cli import (  # noqa: E402
    BUNDLED, HelpFormatter, float_above, int_at_least, load_scene, model_config, scene_folder,
)

from mvgs_plugin.adapters.gs3d import GS3DAdapter  # noqa: E402
from mvgs_plugin import CRDConfig, MVADConfig, MVGS, MVGSConfig, Stage  # noqa: E402
from mvgs_plugin.io import atomic_write_text  # noqa: E402

DEFAULT_WIDTH = MVGSConfig.multiview().grad_threshold_width


def variants(steps: int, views: int, seed: int, threshold_width: Optional[float] = DEFAULT_WIDTH) -> dict:
    """name -> MVGSConfig, all rescaled to `steps`. Every variant but `paper` uses our default's
    threshold policy (grad_threshold_width = threshold_width), so the rows differ only by the
    MVGS components; `paper` keeps the released one (β unscaled)."""
    base = MVGSConfig.baseline(seed=seed, grad_threshold_width=threshold_width).with_total_steps(steps)
    mvrl = dataclasses.replace(base, stages=(Stage(1, views, steps),), preset="custom")
    crd = dataclasses.replace(mvrl, crd=CRDConfig(enabled=True))
    mvad = dataclasses.replace(crd, mvad=MVADConfig(enabled=True))
    full = MVGSConfig.multiview(seed=seed, grad_threshold_width=threshold_width).with_total_steps(steps).with_views(views)
    paper = MVGSConfig.paper(seed=seed).with_total_steps(steps).with_views(views)
    return {"baseline": base, "+MVRL": mvrl, "+CRD": crd, "+MVAD": mvad, "+CIG (= default)": full, "paper": paper}


def scaled(config: MVGSConfig, factor: int) -> MVGSConfig:
    """The same recipe trained at 1/factor resolution (every stage's pyramid factor times it)."""
    if factor == 1:
        return config
    return dataclasses.replace(config, stages=tuple(Stage(s.factor * factor, s.views, s.steps) for s in config.stages))


def run(data: Path, config: MVGSConfig, seed: int, factor: int = 1, curve_every: int = 0,
        max_seconds: float = float("inf"), threads: int = 0) -> dict:
    """Trains one variant and evaluates it on the test views (at 1/factor resolution) with
    `threads` torch threads (0: torch's default; the C++ kernels use as many)."""
    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    scene = load_scene(data)
    adapter = GS3DAdapter.from_scene(scene, model_config(config, seed))
    trainer = MVGS(adapter, scene, scaled(config, factor))
    train_time, inner_time, own_time, curve, finished = 0.0, 0.0, 0.0, [], True
    calls = fired = boxes = from_boxes = 0
    while trainer.step_count < trainer.total_steps:
        info = trainer.step()
        train_time += info.seconds
        inner_time += info.render_seconds + info.backward_seconds
        own_time += info.controller_seconds
        if info.threshold is not None:
            calls += 1
            fired += info.mvad_fired
            boxes += info.boxes
            from_boxes += 0 if info.densify is None else info.densify.from_boxes
        if curve_every and (info.step % curve_every == 0 or info.step == trainer.total_steps):
            curve.append((train_time, info.step, trainer.evaluate(factor=factor).psnr))  # evaluation not timed
        if train_time > max_seconds:
            finished = False
            break
    result = trainer.evaluate(factor=factor)
    return {
        "psnr": result.psnr, "ssim": result.ssim, "lpips": result.lpips, "seconds": train_time,
        "steps": trainer.step_count, "finished": finished, "gaussians": adapter.num_primitives(),
        # Each variant runs in its own process, so this peak is the variant's own.
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        # Everything a step does besides rendering and backward: sampling, losses, MVAD, CRD,
        # densification, the optimizer and bookkeeping (an upper bound on controller overhead) ...
        "outside": max(0.0, train_time - inner_time) / max(train_time, 1e-9),
        # ... of which the controller's own: sampling, MVAD, CRD geometry, checks, bookkeeping
        # (not the loss, nor the adapter's statistics, densification and optimizer step).
        "overhead": own_time / max(train_time, 1e-9),
        "densify_calls": calls, "mvad_fired": fired, "crd_boxes": boxes, "crd_cloned": from_boxes,
        "curve": curve,
    }


def run_isolated(*args) -> dict:
    """run() in a fresh process: peak memory per variant, and no state shared between them."""
    # An executor, not a Pool: a worker that cannot start (or dies) raises BrokenProcessPool here
    # instead of being restarted for ever.
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(run, *args).result()


def plots(out: Path, rows: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(rows)
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    axes[0].bar(names, [rows[n]["psnr"] for n in names], color="tab:blue")
    axes[0].set_ylabel("test PSNR (dB)")
    axes[1].bar(names, [rows[n]["gaussians"] for n in names], color="tab:orange")
    axes[1].set_ylabel("Gaussians")
    for ax in axes:
        ax.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    fig.savefig(out / "ablation.png", dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for n in names:
        if rows[n]["curve"]:
            t, _, p = zip(*rows[n]["curve"])
            ax.plot(t, p, marker="o", label=n)
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "psnr_vs_time.png", dpi=110)
    plt.close(fig)


FULL = "+CIG (= default)"


def equal_time_steps(rows: dict, steps: int) -> int:
    """Baseline steps that take as long as the full MVGS run (from the two runs' step times)."""
    base, full = rows["baseline"], rows[FULL]
    per_base = base["seconds"] / base["steps"]
    full_time = full["seconds"] / full["steps"] * steps  # what the full run takes to finish
    return max(steps, round(full_time / per_base))


def table(rows: dict, args) -> str:
    lines = [
        f"Scene `{args.data}`, {args.steps} steps, M = {args.views} at full resolution, resolution 1/"
        f"{args.resolution_scale}, seed {args.seed}, gradient threshold meant for "
        f"{'any width' if not args.threshold_width else f'{args.threshold_width:g} px images'} (all but paper), "
        f"{args.threads or torch.get_num_threads()} thread(s) per "
        f"variant, every variant in its own process. Command: `python examples/ablation.py --data {args.data} "
        f"--steps {args.steps} --views {args.views} --resolution-scale {args.resolution_scale} "
        f"--threads {args.threads} --threshold-width {args.threshold_width:g} --out {args.out}`",
        "",
        "| variant | test PSNR (dB) | test SSIM | LPIPS | train time (s) | Gaussians | peak RSS (MB) "
        "| controller overhead | outside render + backward | MVAD fired | CRD boxes / cloned |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows.items():
        lp = "n/a" if r["lpips"] is None else f"{r['lpips']:.4f}"
        note = "" if r["finished"] else f" (stopped at step {r['steps']})"
        fired = f"{r['mvad_fired']}/{r['densify_calls']}" if r["densify_calls"] else "-"
        lines.append(f"| {name}{note} | {r['psnr']:.2f} | {r['ssim']:.4f} | {lp} | {r['seconds']:.0f} | "
                     f"{r['gaussians']} | {r['peak_mb']:.0f} | {100 * r['overhead']:.1f} % | {100 * r['outside']:.1f} % | {fired} | "
                     f"{r['crd_boxes']} / {r['crd_cloned']} |")
    if "baseline" in rows and FULL in rows:
        base, full = rows["baseline"], rows[FULL]
        lines += ["", f"Full MVGS vs baseline at equal steps: {full['psnr'] - base['psnr']:+.2f} dB PSNR, "
                      f"{full['ssim'] - base['ssim']:+.4f} SSIM, {full['seconds'] / base['seconds']:.2f}x the time, "
                      f"{full['gaussians'] / max(1, base['gaussians']):.2f}x the Gaussians."]
        eq = next((r for n, r in rows.items() if n.startswith("baseline, equal time")), None)
        if eq is not None:
            lines.append(f"At equal wall time (baseline trained {eq['steps']} steps, {eq['seconds']:.0f} s vs "
                         f"{full['seconds']:.0f} s): {full['psnr'] - eq['psnr']:+.2f} dB PSNR, "
                         f"{full['ssim'] - eq['ssim']:+.4f} SSIM, {full['gaussians'] / max(1, eq['gaussians']):.2f}x "
                         "the Gaussians.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=scene_folder, default=BUNDLED, help="scene folder (default: the bundled tabletop scene)")
    ap.add_argument("--steps", type=int_at_least(2), default=600, help="steps of every variant")
    ap.add_argument("--views", type=int_at_least(1), default=4, help="views per step M at full resolution")
    ap.add_argument("--resolution-scale", type=int_at_least(1), default=1, help="train and evaluate at 1/s resolution")
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="seed of every run")
    ap.add_argument("--threads", type=int_at_least(0), default=0,
                    help="torch threads per variant (0: torch's default); 1 is steadier on a shared machine")
    ap.add_argument("--threshold-width", type=float_above(0, inclusive=True), default=DEFAULT_WIDTH,
                    help="image width the gradient threshold is meant for, for every variant but paper "
                         f"(0: never scaled, as 3DGS; default {DEFAULT_WIDTH:g}, as MVGSConfig.multiview())")
    ap.add_argument("--curve-points", type=int_at_least(1), default=6, help="test evaluations along the PSNR-vs-time curves")
    ap.add_argument("--max-minutes", type=float_above(0), default=30.0, help="stop a variant that trains longer than this")
    ap.add_argument("--no-equal-time", action="store_true",
                    help="skip the extra baseline run as long as the full MVGS run")
    ap.add_argument("--only", nargs="*", default=None, help="run only these variants (default: all)")
    ap.add_argument("--out", type=Path, default=Path("out/ablation"), help="output folder (tables, plots, runs)")
    args = ap.parse_args(argv)
    if args.resolution_scale < 1:
        raise ValueError(f"--resolution-scale must be >= 1, got {args.resolution_scale}")
    if args.only:
        names = list(variants(args.steps, args.views, args.seed))
        unknown = [n for n in args.only if n not in names]
        if unknown:
            ap.error(f"--only {' '.join(unknown)}: no such variant; the variants are {', '.join(repr(n) for n in names)}")
    args.out.mkdir(parents=True, exist_ok=True)
    load_scene(args.data)  # fail here, not in a worker, on a bad path
    rows, curves = {}, ("baseline", FULL)
    width = args.threshold_width or None
    for name, config in variants(args.steps, args.views, args.seed, width).items():
        if args.only and name not in args.only:
            continue
        curve_every = max(1, args.steps // args.curve_points) if name in curves else 0
        print(f"{name} ...", file=sys.stderr, flush=True)
        rows[name] = run_isolated(args.data, config, args.seed, args.resolution_scale, curve_every,
                                  args.max_minutes * 60, args.threads)
        atomic_write_text(args.out / "ablation.md", table(rows, args))  # a stopped run keeps what it has
    if not args.no_equal_time and "baseline" in rows and FULL in rows:
        n = equal_time_steps(rows, args.steps)
        config = MVGSConfig.baseline(seed=args.seed, grad_threshold_width=width).with_total_steps(n)
        print(f"baseline for {n} steps (equal time) ...", file=sys.stderr, flush=True)
        rows[f"baseline, equal time ({n} steps)"] = run_isolated(
            args.data, config, args.seed, args.resolution_scale, max(1, n // args.curve_points), args.max_minutes * 60,
            args.threads)
    text = table(rows, args)
    atomic_write_text(args.out / "ablation.md", text)
    plots(args.out, rows)
    print(text)
    return rows


if __name__ == "__main__":
    main()
