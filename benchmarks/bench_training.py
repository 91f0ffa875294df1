"""Baseline 3DGS against MVGS on one scene: test PSNR/SSIM next to training time and model
size (prints a markdown table; each run is examples/train_3dgs.py in its own process).

    python benchmarks/bench_training.py --steps 1500
    python benchmarks/bench_training.py --data path/to/scene --steps 3000 --runs baseline multiview

At equal steps (for equal compute see bench_equal_compute.py). Runs: "baseline", "default"
(the cost-aware recipe, one view per step), "multiview" and "paper" presets at the same number
of steps; "multiview-rules-off": the multiview preset without its two densification rules (MVAD,
CRD), i.e. multi-view training and the pyramid only; "baseline-xM": the baseline given M times the steps
(the same number of rendered views as MVGS with M views per step at full resolution);
"baseline-scaled" and "baseline-scaled-xM": the same with the default's gradient threshold
policy (--threshold-width 800 instead of 3DGS's fixed β), so that only MVGS differs from multiview.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--runs", nargs="*", default=["baseline", "multiview-rules-off", "multiview", "paper", "baseline-xM"])
    ap.add_argument("--views", type=int, default=8, help="M at full resolution for the multiview and paper presets")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_training")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    rows = []
    for run in args.runs:
        preset, steps = run, args.steps
        extra = []
        if run in ("baseline-xM", "baseline-scaled-xM"):
            preset, steps = "baseline", args.steps * args.views
        if run in ("baseline-scaled", "baseline-scaled-xM"):
            preset, extra = "baseline", ["--threshold-width", "800"]
        if run == "multiview-rules-off":
            preset, extra = "multiview", ["--no-mvad", "--no-crd"]
        out = args.out / run
        cmd = [sys.executable, str(ROOT / "examples" / "train_3dgs.py"), "--preset", preset, "--steps", str(steps),
               "--out", str(out), "--seed", str(args.seed), "--no-progress", *extra]
        if preset in ("multiview", "paper"):
            cmd += ["--views", str(args.views)]
        if args.data is not None:
            cmd += ["--data", str(args.data)]
        print("$", " ".join(cmd[1:]), file=sys.stderr, flush=True)
        subprocess.run(cmd, check=True, cwd=ROOT)
        m = json.loads((out / "metrics.json").read_text())
        rows.append((run, m))

    print(f"scene: {args.data or 'bundled tabletop'}, seed {args.seed}, {rows[0][1]['threads']} threads")
    print("| run | steps | views/step (full res) | test PSNR (dB) | test SSIM | train time (s) | Gaussians | peak RSS (MB) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for run, m in rows:
        views = m["config"]["stages"][-1]["views"]
        print(f"| {run} | {m['steps']} | {views} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['train_seconds']:.0f} | "
              f"{m['num_gaussians']} | {m['peak_memory_mb']:.0f} |")


if __name__ == "__main__":
    main()
