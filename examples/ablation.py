"""The MVGS ablation, speed against error: cumulative variants of the paper's ablation plus the
paper preset and our default, on one scene, same seed; writes a markdown table and plots.

    python examples/ablation.py --steps 600 --views 4 --out docs/ablation/tabletop
    python examples/ablation.py --data /tmp/variants/reflective --steps 600 --out docs/ablation/reflective

Variants (our implementations of each rule, with their guards):
    baseline           plain 3DGS (1 view per step, full resolution)
    +MVRL              M views per step, summed loss, full resolution, no extra densification
    +CRD               ... plus cross-ray densification
    +MVAD              ... plus multi-view augmented densification
    +CIG (= default)   ... plus the coarse-to-fine pyramid: our default preset
    paper              the released behaviour (MVGS_METHOD.md)
Writes OUT/ablation.md (test PSNR/SSIM/LPIPS, wall time, Gaussians, peak RSS, controller
overhead), OUT/ablation.png (PSNR and Gaussians per variant) and OUT/psnr_vs_time.png (test PSNR
against training wall time for baseline and full MVGS; evaluation time excluded).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_3dgs import BUNDLED, load_scene, model_config  # noqa: E402

from adapters.gs3d import GS3DAdapter  # noqa: E402
from mvgs_plugin import MVGS, MVGSConfig, Stage  # noqa: E402


def variants(steps: int, views: int, seed: int) -> dict:
    """name -> MVGSConfig, all rescaled to `steps`."""
    base = MVGSConfig.baseline(seed=seed).with_total_steps(steps)
    mvrl = dataclasses.replace(base, stages=(Stage(1, views, steps),), preset="custom")
    crd = dataclasses.replace(mvrl, crd=True)
    mvad = dataclasses.replace(crd, mvad=True)
    full = MVGSConfig.default(seed=seed).with_total_steps(steps).with_views(views)
    paper = MVGSConfig.paper(seed=seed).with_total_steps(steps).with_views(views)
    return {"baseline": base, "+MVRL": mvrl, "+CRD": crd, "+MVAD": mvad, "+CIG (= default)": full, "paper": paper}


def run(scene, config: MVGSConfig, seed: int, curve_every: int = 0, max_seconds: float = float("inf")) -> dict:
    torch.manual_seed(seed)
    adapter = GS3DAdapter.from_scene(scene, model_config(config, seed))
    trainer = MVGS(adapter, scene, config)
    train_time, inner_time, curve, finished = 0.0, 0.0, [], True
    while trainer.step_count < trainer.total_steps:
        info = trainer.step()
        train_time += info.seconds
        inner_time += info.render_seconds + info.backward_seconds
        if curve_every and (info.step % curve_every == 0 or info.step == trainer.total_steps):
            curve.append((train_time, info.step, trainer.evaluate().psnr))  # evaluation not timed
        if train_time > max_seconds:
            finished = False
            break
    result = trainer.evaluate()
    return {
        "psnr": result.psnr, "ssim": result.ssim, "lpips": result.lpips, "seconds": train_time,
        "steps": trainer.step_count, "finished": finished, "gaussians": adapter.num_primitives(),
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        # Everything a step does besides rendering and backward: sampling, losses, MVAD, CRD,
        # densification, the optimizer and bookkeeping (an upper bound on controller overhead).
        "overhead": max(0.0, train_time - inner_time) / max(train_time, 1e-9),
        "curve": curve,
    }


def write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=path.suffix)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


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


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=BUNDLED)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--curve-points", type=int, default=6, help="test evaluations along the PSNR-vs-time curves")
    ap.add_argument("--max-minutes", type=float, default=30.0, help="stop a variant that trains longer than this")
    ap.add_argument("--only", nargs="*", default=None, help="run only these variants")
    ap.add_argument("--out", type=Path, default=Path("out/ablation"))
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(args.data)
    rows = {}
    for name, config in variants(args.steps, args.views, args.seed).items():
        if args.only and name not in args.only:
            continue
        curve_every = max(1, args.steps // args.curve_points) if name in ("baseline", "+CIG (= default)") else 0
        print(f"{name} ...", file=sys.stderr, flush=True)
        rows[name] = run(scene, config, args.seed, curve_every, args.max_minutes * 60)
    lines = [
        f"Scene `{args.data}`, {args.steps} steps, M = {args.views} at full resolution, seed {args.seed}, "
        f"{torch.get_num_threads()} threads. Command: `python examples/ablation.py "
        f"--data {args.data} --steps {args.steps} --views {args.views} --out {args.out}`",
        "",
        "| variant | test PSNR (dB) | test SSIM | LPIPS | train time (s) | Gaussians | peak RSS (MB) | controller overhead |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, r in rows.items():
        lp = "n/a" if r["lpips"] is None else f"{r['lpips']:.4f}"
        note = "" if r["finished"] else f" (stopped at step {r['steps']})"
        lines.append(f"| {name}{note} | {r['psnr']:.2f} | {r['ssim']:.4f} | {lp} | {r['seconds']:.0f} | "
                     f"{r['gaussians']} | {r['peak_mb']:.0f} | {100 * r['overhead']:.1f} % |")
    write_text(args.out / "ablation.md", "\n".join(lines) + "\n")
    plots(args.out, rows)
    print("\n".join(lines))
    return rows


if __name__ == "__main__":
    main()
