"""Single view against MVGS in gsplat's loop on a GPU, at equal steps and at equal GPU time.

The gsplat-loop table of docs/gsplat_loop.md for a CUDA machine: every run is
examples/gsplat_loop/simple_trainer*.py with `--device cuda --rasterizer gsplat` (gsplat's own
CUDA rasterization), one at a time (one GPU), its own process. The clock is the training loop's
wall time after a CUDA synchronize (on a GPU the host's CPU time is mostly waiting); peak GPU
memory beside it. Rows, per scene:

- single view, gsplat's DefaultStrategy as installed (grow_grad2d 2e-4), `--steps` steps;
- single view with grow_grad2d = 2e-4 x 800 / W (the threshold the presets use at width W);
- each MVGS preset in `--presets` at `--steps` steps;
- equal time: the single-view loop given the steps that cost each preset's time, and each
  preset given the single-view run's time (steps x time ratio of the first runs).

Here (no CUDA) it says so and exits 0 without writing anything; nothing needs changing to run it
on a GPU machine:

    pip install torch==2.13.0 && pip install -e ".[gsplat]"   # a CUDA build of torch there
    python benchmarks/bench_gpu.py --steps 7000 --data path/to/scene --table out/gpu_table.md

`--device cpu` runs the same table with the CPU rasterizer (for trying the script itself).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOOP = ROOT / "examples" / "gsplat_loop"


def run(script: str, steps: int, out: Path, data, device: str, preset=None, seed: int = 0,
        extra=()) -> dict:
    """One run of a loop; `preset` only for the MVGS loops (the single-view loop refuses it)."""
    cmd = [sys.executable, str(LOOP / script), "--steps", str(steps), "--out", str(out),
           *(["--preset", preset] if preset else []), "--seed", str(seed), *extra]
    if device == "cuda":
        cmd += ["--device", "cuda", "--rasterizer", "gsplat"]
    else:
        cmd += ["--threads", "1"]
    if data is not None:
        cmd += ["--data", str(data)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads((out / "metrics.json").read_text())


def clock(m: dict, device: str) -> float:
    """The fair clock: GPU wall time on CUDA, CPU time (user + sys, one thread) on the CPU."""
    return m["train_seconds"] if device == "cuda" else m["cpu_seconds"]


def row(name: str, m: dict, device: str) -> str:
    mem = m.get("gpu_peak_memory_mb")
    return (f"| {name} | {m['steps']} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m['num_gaussians']} | "
            f"{clock(m, device):.1f} | {m['train_seconds']:.1f} | {'-' if mem is None else f'{mem:.0f}'} |")


def table(data, steps: int, presets, device: str, out: Path, seed: int) -> str:
    from mvgs_plugin.data import load_scene

    width = load_scene(data or ROOT / "examples" / "scenes" / "tabletop").train_cameras[0].width
    scaled = ["--grow-grad2d", f"{2e-4 * 800 / width:.6g}"]
    first = {"single": run("simple_trainer.py", steps, out / "single", data, device, seed=seed),
             "scaled": run("simple_trainer.py", steps, out / "scaled", data, device, seed=seed, extra=scaled)}
    for p in presets:
        first[p] = run("simple_trainer_mvgs.py", steps, out / p, data, device, p, seed)
    base = clock(first["single"], device)
    second = {}
    for p in presets:
        ratio = clock(first[p], device) / base
        second[f"single@{p}"] = run("simple_trainer.py", max(2, round(steps * ratio)), out / f"single_at_{p}",
                                    data, device, seed=seed)
        second[f"{p}@single"] = run("simple_trainer_mvgs.py", max(2, round(steps / ratio)), out / f"{p}_at_single",
                                    data, device, p, seed)
    unit = "GPU s" if device == "cuda" else "CPU s"
    lines = [f"Scene: {data or 'bundled tabletop'} ({width} px); seed {seed}; device {device}; clock = {unit}.", "",
             f"| run | steps | PSNR (dB) | SSIM | Gaussians | {unit} | wall (s) | GPU MB |",
             "|---|---:|---:|---:|---:|---:|---:|---:|",
             row("single view (DefaultStrategy, grow_grad2d 2e-4)", first["single"], device),
             row(f"single view, grow_grad2d {scaled[1]}", first["scaled"], device)]
    lines += [row(f"MVGS {p}, equal steps", first[p], device) for p in presets]
    for p in presets:
        lines.append(row(f"single view at MVGS {p}'s time", second[f"single@{p}"], device))
        lines.append(row(f"MVGS {p} at single view's time", second[f"{p}@single"], device))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, nargs="*", default=[None], help="scene folders (default: the bundled one)")
    ap.add_argument("--steps", type=int, default=7000, help="steps of the equal-steps runs (default: %(default)s)")
    ap.add_argument("--presets", nargs="+", default=["default", "multiview"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    ap.add_argument("--out", type=Path, default=Path("out/bench_gpu"))
    ap.add_argument("--table", type=Path, default=None, help="also write the tables here")
    args = ap.parse_args(argv)
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        print(f"bench_gpu.py: torch {torch.__version__} sees no CUDA device here; nothing to run "
              "(it needs a GPU and gsplat's CUDA rasterizer; --device cpu tries the script on the CPU)")
        return 0
    text = "\n".join(table(d, args.steps, args.presets, args.device, args.out / (d.name if d else "tabletop"),
                           args.seed) for d in args.data)
    print(text)
    if args.table is not None:
        from mvgs_plugin.io import atomic_write_text

        atomic_write_text(args.table, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
