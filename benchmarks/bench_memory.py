"""Peak memory of an MVGS step against the number of views per step (prints a table).

Each configuration runs in its own process on the bundled scene at full resolution: load the
scene and the 3DGS adapter, run a few warm-up steps, record the resident set size, run the
measured steps, and report the peak RSS and its growth over the warm state. "chunk = 1" is our
controller rendering and backpropagating one view at a time; "chunk = M" keeps all M graphs
alive until one backward, as the released MVGS code does; "chunk = auto" is the controller's
default (MVGSConfig.chunk_size=None: as many views per renderer call as fit chunk_memory_mb).

    python benchmarks/bench_memory.py
    python benchmarks/bench_memory.py --views 1 4 8 16 --steps 5 --gaussians 100000
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def run_one(views: int, chunk: int, steps: int, threads: int, gaussians: int) -> dict:
    import torch

    from mvgs_plugin.adapters.gs3d import GS3DAdapter
    from mvgs_plugin import MVGS, MVGSConfig, Stage
    from mvgs_plugin.cli import BUNDLED, load_scene

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    scene = load_scene(BUNDLED)
    if gaussians:
        # Jittered copies of the scene's points: a model of the size training reaches.
        from mvgs_plugin.data import PointCloud

        g = torch.Generator().manual_seed(0)
        idx = torch.randint(len(scene.points), (gaussians,), generator=g)
        xyz = scene.points.xyz[idx] + 0.01 * scene.extent * torch.randn(gaussians, 3, generator=g)
        scene.points = PointCloud(xyz, scene.points.rgb[idx])
    adapter = GS3DAdapter.from_scene(scene)
    config = MVGSConfig(stages=(Stage(1, views, steps + 2),), chunk_size=chunk or None, densify_from=10**6)
    trainer = MVGS(adapter, scene, config)
    for _ in range(2):
        trainer.step()
    warm = rss_mb()
    t0 = time.perf_counter()
    for _ in range(steps):
        trainer.step()
    seconds = (time.perf_counter() - t0) / steps
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"views": views, "chunk": chunk, "warm_mb": warm, "peak_mb": peak, "growth_mb": peak - warm,
            "step_s": seconds, "gaussians": adapter.num_primitives()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, nargs="*", default=[1, 8])
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--gaussians", type=int, default=0, help="model size (0: the scene's 4000 points)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        views, chunk = (int(v) for v in args.one.split(","))
        print(json.dumps(run_one(views, chunk, args.steps, args.threads, args.gaussians)))
        return
    rows = []
    for views in args.views:
        for chunk in sorted({1, views}) + [0]:  # 0: the default, chunk_size=None
            cmd = [sys.executable, __file__, "--one", f"{views},{chunk}", "--steps", str(args.steps),
                   "--threads", str(args.threads), "--gaussians", str(args.gaussians)]
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            if out.returncode != 0:
                raise SystemExit(out.stderr)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    base = next(r for r in rows if r["views"] == min(args.views) and r["chunk"] == 1)
    print(f"bundled scene, full resolution, {base['gaussians']} Gaussians, threads={args.threads}, {args.steps} measured steps")
    print("| views M | chunk | step (s) | peak RSS (MB) | peak / M=1 peak | growth over warm state (MB) |")
    print("|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['views']} | {r['chunk'] or 'auto'} | {r['step_s']:.3f} | {r['peak_mb']:.0f} | "
              f"{r['peak_mb'] / base['peak_mb']:.2f} | {r['growth_mb']:.0f} |")


if __name__ == "__main__":
    main()
