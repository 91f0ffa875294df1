"""Wall time per MVGS step with the views of a step sharded over processes (prints a table).

Each configuration "P x T" runs P fresh processes (torch.multiprocessing spawn) with T torch
threads each on the bundled scene at full resolution (128 x 128), M views per step, no
densification (the model size stays fixed). P = 1 is the plain single-process controller; P > 1
uses mvgs_plugin.distributed over gloo on localhost. Per configuration: the median step time,
the time each process spends rendering + backpropagating its share, the time in collectives
(waiting for the slowest rank included), the pure time of the gradient all-reduce alone (after a
barrier, so without load imbalance), the bytes each rank puts into it per step, and the peak RSS
of each process.

    python benchmarks/bench_distributed.py                      # M = 8, the scene's 4000 points
    python benchmarks/bench_distributed.py --gaussians 100000 --configs 1x2 2x1 1x1
"""

from __future__ import annotations

import argparse
import datetime
import json
import resource
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def worker(rank: int, procs: int, threads: int, port: int, args: dict, out: str) -> None:
    import torch
    import torch.distributed as dist

    from mvgs_plugin.adapters.gs3d import GS3DAdapter
    from mvgs_plugin import MVGS, MVGSConfig, Stage
    from mvgs_plugin.data import PointCloud
    from mvgs_plugin.distributed import Collective, abort_on_error
    from mvgs_plugin.cli import BUNDLED, load_scene

    with abort_on_error():
        torch.set_num_threads(threads)
        coll = None
        if procs > 1:
            dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=procs,
                                    timeout=datetime.timedelta(seconds=600))
            coll = Collective(timeout=600)
        torch.manual_seed(0)
        scene = load_scene(BUNDLED)
        n = args["gaussians"]
        if n:  # jittered copies of the scene's points: a model of the size training reaches
            g = torch.Generator().manual_seed(0)
            idx = torch.randint(len(scene.points), (n,), generator=g)
            xyz = scene.points.xyz[idx] + 0.01 * scene.extent * torch.randn(n, 3, generator=g)
            scene.points = PointCloud(xyz, scene.points.rgb[idx])
        adapter = GS3DAdapter.from_scene(scene)
        total = args["warmup"] + args["steps"]
        config = MVGSConfig(stages=(Stage(1, args["views"], total),), densify_from=10**6)
        trainer = MVGS(adapter, scene, config, distributed=coll)
        infos = [trainer.step() for _ in range(total)][args["warmup"]:]
        row = {
            "step_s": statistics.median(i.seconds for i in infos),
            "compute_s": statistics.median(i.render_seconds + i.backward_seconds for i in infos),
            "comm_s": statistics.median(i.comm_seconds for i in infos),
            "rest_s": statistics.median(i.seconds - i.render_seconds - i.backward_seconds - i.comm_seconds
                                        for i in infos),
            "gaussians": adapter.num_primitives(),
            "sh_degree": adapter.config.sh_degree,
        }
        if coll is not None:
            pure, sent = [], 0
            for _ in range(10):
                coll.barrier("bench")
                t0 = time.perf_counter()
                sent = coll.all_reduce_gradients(adapter)
                pure.append(time.perf_counter() - t0)
            row["allreduce_s"], row["allreduce_bytes"] = statistics.median(pure), sent
        row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        Path(out, f"rank{rank}.json").write_text(json.dumps(row))
        if coll is not None:
            dist.destroy_process_group()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_config(procs: int, threads: int, args: dict) -> list:
    import torch.multiprocessing as mp

    with tempfile.TemporaryDirectory() as out:
        mp.start_processes(worker, args=(procs, threads, free_port(), args, out), nprocs=procs, join=True,
                           start_method="spawn")
        return [json.loads(Path(out, f"rank{r}.json").read_text()) for r in range(procs)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--steps", type=int, default=8, help="measured steps (after the warm-up)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--gaussians", type=int, default=0, help="model size (0: the scene's 4000 points)")
    ap.add_argument("--configs", nargs="*", default=["1x2", "2x1", "1x1"], help="PROCESSESxTHREADS")
    a = ap.parse_args()
    args = {"views": a.views, "steps": a.steps, "warmup": a.warmup, "gaussians": a.gaussians}
    rows = []
    for spec in a.configs:
        procs, threads = (int(v) for v in spec.lower().split("x"))
        ranks = run_config(procs, threads, args)
        rows.append((procs, threads, ranks))
        print(f"done {spec}: {ranks}", file=sys.stderr)
    first = rows[0][2][0]
    base = first["step_s"]
    load = " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"
    print(f"bundled scene, 128 x 128, M = {a.views} views per step, {first['gaussians']} Gaussians "
          f"(SH degree {first['sh_degree']}), float32, median of {a.steps} steps after {a.warmup} warm-up; "
          f"load average at the end {load}")
    print()
    print("| processes x threads | step (s) | speed-up vs first row | render + backward per process (s) | "
          "collectives, waits included (s) | rest: loss, optimizer, sampler (s) | gradient all-reduce alone (ms) | "
          "all-reduced per step per rank (MiB) | peak RSS per process (MB) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for procs, threads, ranks in rows:
        step = max(r["step_s"] for r in ranks)
        compute = " / ".join(f"{r['compute_s']:.3f}" for r in ranks)
        comm = " / ".join(f"{r['comm_s']:.3f}" for r in ranks) if procs > 1 else "-"
        pure = f"{1000 * statistics.median(r['allreduce_s'] for r in ranks):.1f}" if procs > 1 else "-"
        size = f"{ranks[0]['allreduce_bytes'] / 2**20:.2f}" if procs > 1 else "-"
        rest = " / ".join(f"{r['rest_s']:.3f}" for r in ranks)
        rss = " / ".join(f"{r['peak_rss_mb']:.0f}" for r in ranks)
        print(f"| {procs} x {threads} | {step:.3f} | {base / step:.2f} | {compute} | {comm} | {rest} | {pure} | "
              f"{size} | {rss} |")


if __name__ == "__main__":
    main()
