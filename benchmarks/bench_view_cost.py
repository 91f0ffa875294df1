"""What a training step at pyramid factor f with M views costs, against the budget clock's cost
model (MVGSConfig.view_cost: a view at factor f counts a + b / f of a full-resolution one,
(a, b) = (0.1, 0.9), the reference renderer's per-view times; docs/step_speed.md). Runs the model of one
example script (train_3dgs.py, train_4dgs.py or train_scaffold.py) built from that script's own
flags, so a 4DGS step includes its deformation field and the optimizer's pass over it, and a
Scaffold-GS step its per-view decoding of every anchor's neural Gaussians, which do not shrink
with the image.

For each (f, M) a trainer with one Stage(f x --resolution-scale, M, ...) and no densification
(the model stays at its initial count) takes --warmup steps, then the pairs take 10 steps each in
turn for --rounds rounds (interleaved, so drift on a shared machine hits all alike). CPU is the
process's user+sys time; run it with --threads 1 on the example's flags for the fair clock.
Prints a markdown table: ms per step, the measured cost in full-resolution one-view steps, and
the cost model's; then the A of `--view-cost A` that fits the one-view rows (least squares), which
makes a `--budget` of this model and resolution count its CPU.

    python benchmarks/bench_view_cost.py train_3dgs.py -- --threads 1
    python benchmarks/bench_view_cost.py train_scaffold.py -- --threads 1
    python benchmarks/bench_view_cost.py train_4dgs.py -- --data scenes/moving --resolution-scale 2 \\
        --init-random 2000 --init-box -1.2 -1.2 0 1.2 1.2 1.2 --threads 1
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
# (pyramid factor relative to the finest, views per step): the default's levels, and M-view steps
PAIRS = ((1, 1), (2, 1), (4, 1), (1, 2), (2, 2), (4, 4))
EXAMPLES = ("train_3dgs.py", "train_4dgs.py", "train_scaffold.py")


def load_example(name: str):
    if name not in EXAMPLES:
        raise SystemExit(f"bench_view_cost.py: the example must be one of {', '.join(EXAMPLES)}, got {name!r}")
    spec = importlib.util.spec_from_file_location(name[:-3] + "_cost", ROOT / "examples" / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def measure(name: str, argv, rounds: int, warmup: int) -> list:
    """The table's rows for example `name` run with its flags `argv` (each example's own
    build_adapter(), the model its run() trains)."""
    example = load_example(name)
    with tempfile.TemporaryDirectory(prefix="bench_view_cost_") as out:  # --out: an init cache when the scene has no points
        return _measure(example, name, argv, rounds, warmup, out)


def _measure(example, name: str, argv, rounds: int, warmup: int, out: str) -> list:
    from mvgs_plugin.camera import scaled_size
    from mvgs_plugin.cli import config_from_args, scene_from_args
    from mvgs_plugin.config import Stage, view_work
    from mvgs_plugin.controller import MVGS

    # 4DGS: no static coarse phase, so every timed step runs the deformation field
    own = ["--coarse-fraction", "0"] if name == "train_4dgs.py" else []
    args = example.parse_args(list(argv) + own + ["--preset", "baseline", "--out", out])
    if args.threads:
        torch.set_num_threads(args.threads)
    scene = scene_from_args(args, dynamic_model=name == "train_4dgs.py")
    extra = {"time_spread": args.time_spread} if name == "train_4dgs.py" else {}
    base = config_from_args(args, scene, **extra)
    s = args.resolution_scale
    trainers = {}
    for f, m in PAIRS:
        cfg = dataclasses.replace(base, stages=(Stage(f * s, m, 10**6),), densify_from=10**9, densify_until=10**9 + 1)
        torch.manual_seed(args.seed)
        trainer = MVGS(example.build_adapter(args, scene, cfg), scene, cfg)
        for _ in range(warmup):
            trainer.step()
        trainers[(f, m)] = trainer
    cpu = dict.fromkeys(trainers, 0.0)
    for _ in range(rounds):
        for key, trainer in trainers.items():
            c0 = time.process_time()
            for _ in range(10):
                trainer.step()
            cpu[key] += time.process_time() - c0
    full = cpu[(1, 1)]
    cam = scene.train_cameras[0]
    rows = []
    for (f, m), trainer in trainers.items():
        w, h = scaled_size(cam.width, cam.height, f * s)
        rows.append(dict(factor=f, views=m, px=f"{w}x{h}", gaussians=trainer.adapter.num_primitives(),
                         ms=cpu[(f, m)] / (10 * rounds) * 1000, measured=cpu[(f, m)] / full,
                         model=m * view_work(trainer.config.view_cost, f)))
    return rows


def fitted_view_cost(rows: list) -> float:
    """The A of --view-cost that fits the one-view rows best (least squares on A + (1 - A) / f =
    measured, the full-resolution row exact by construction), clipped to [0, 1]."""
    pts = [(1.0 - 1.0 / r["factor"], r["measured"] - 1.0 / r["factor"]) for r in rows if r["views"] == 1 and r["factor"] > 1]
    den = sum(u * u for u, _ in pts)
    if not pts or den == 0:
        raise ValueError("fitting A needs a one-view row at a factor > 1")
    return min(1.0, max(0.0, sum(u * c for u, c in pts) / den))


def table(rows: list) -> str:
    lines = ["| factor (x finest) | views | image | Gaussians | CPU ms / step | measured (full 1-view steps) | "
             "cost model | measured / model |", "|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['factor']} | {r['views']} | {r['px']} | {r['gaussians']} | {r['ms']:.1f} | "
                     f"{r['measured']:.2f} | {r['model']:.2f} | {r['measured'] / r['model']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    own, rest = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("example", help="train_3dgs.py, train_4dgs.py or train_scaffold.py; its flags follow --")
    ap.add_argument("--rounds", type=int, default=6, help="interleaved rounds of 10 steps per pair (default: 6)")
    ap.add_argument("--warmup", type=int, default=5, help="untimed steps per pair first (default: 5)")
    opts = ap.parse_args(own)
    if opts.rounds < 1 or opts.warmup < 0:
        ap.error(f"--rounds must be >= 1 and --warmup >= 0, got {opts.rounds} and {opts.warmup}")
    rows = measure(opts.example, rest, opts.rounds, opts.warmup)
    print(table(rows))
    print(f"\none-view steps fit --view-cost {fitted_view_cost(rows):.2f} (a view at factor f costs A + (1 - A) / f; "
          f"the default is 0.1)")


if __name__ == "__main__":
    main()
