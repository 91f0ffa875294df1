"""Time of one whole MVGS training step (MVGS.step(): render, loss, backward, statistics,
optimizer step) for M views against one view, on the bundled scene examples/scenes/tabletop
(128 x 128 px, 48 train views). Prints a markdown table per thread count and a targets table.

Model: N Gaussians drawn (seed 0) from the scene's point cloud with 0.01 world-unit jitter and
the points' colours, GS3DAdapter.from_scene with SH degree 3, always rendered at degree 3. Config:
MVGSConfig.baseline with one Stage(f, M, 10_000) and no densification, so N stays fixed. The
16 / 32 px levels are pyramid factors 8 / 4; 1 x 1 px views are factor 128. The 256 px scene is
the tabletop with cameras cam.scaled(0.5) and images upsampled 2x (bilinear).

Each measurement runs in its own process so its peak memory (max RSS) is its own. Times are
medians over --steps steps after --warmup steps, with torch.set_num_threads(threads); CPU is the
process user+sys time per step (about threads x step when every thread is busy).

    python benchmarks/bench_step.py                        # 1 and 2 threads, all rows
    python benchmarks/bench_step.py --quick --threads 1    # 10k rows only, 3 steps
    python benchmarks/bench_step.py --chunk-size 8 --json step.json
    git worktree add ../before HEAD~3 && python benchmarks/bench_step.py --before ../before
    python benchmarks/bench_step.py --views-sweep --threads 1 2   # what an M-view step costs in one-view steps

--views-sweep prints only the cost of a step of M = 1, 2, 4, 8 full-resolution views in one-view
steps (10k and 30k Gaussians, 128 px), wall and CPU: the number to set against the C(M) of
benchmarks/probe_view_noise.py (an M-view step pays when it costs less than C(M) one-view steps).

--before DIR also times every configuration with the packages of another checkout (imported
from DIR first; its compiled kernels build from its own sources), interleaved with this tree's
runs, and adds its step time and the ratio: before/after comparisons from the same run.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

SCENE_DIR = Path(__file__).resolve().parents[1] / "examples" / "scenes" / "tabletop"
PARTS = ("seconds", "render_seconds", "backward_seconds", "loss_seconds", "adapter_seconds", "controller_seconds")
# (label, Gaussians, 256 px scene?, pyramid factor, views M)
ROWS = [("10k 128 px", 10_000, False, 1, 8), ("10k 16 px", 10_000, False, 8, 48),
        ("10k 32 px", 10_000, False, 4, 24), ("50k 256 px", 50_000, True, 1, 8)]
FIXED = [(10_000, False, 128, 48), (10_000, False, 128, 1)]  # 1 x 1 px: the per-view fixed cost
SWEEP_GAUSSIANS, SWEEP_VIEWS = (10_000, 30_000), (1, 2, 4, 8)  # --views-sweep


def upscaled(scene):
    """The scene at 2x the size: cameras with doubled intrinsics, images upsampled bilinearly."""
    from mvgs_plugin.data.scene import Scene

    def up(cam):
        img = scene.image(cam).permute(2, 0, 1)[None]
        big = torch.nn.functional.interpolate(img, scale_factor=2, mode="bilinear", align_corners=False)
        return big[0].permute(1, 2, 0).clamp(0, 1).contiguous()

    images = {cam.uid: up(cam) for cam in scene.cameras}
    return Scene([c.scaled(0.5) for c in scene.train_cameras], [c.scaled(0.5) for c in scene.test_cameras],
                 images=images, points=scene.points, background=scene.background)


def make_scene(n: int, big: bool):
    from mvgs_plugin.data import PointCloud, load_nerf_synthetic

    scene = load_nerf_synthetic(SCENE_DIR)
    if big:
        scene = upscaled(scene)
    pts, g = scene.points, torch.Generator().manual_seed(0)
    idx = torch.randint(len(pts), (n,), generator=g)
    scene.points = PointCloud(pts.xyz[idx] + 0.01 * torch.randn(n, 3, generator=g), pts.rgb[idx])
    return scene


def run_one(n: int, big: bool, factor: int, views: int, threads: int, warmup: int, steps: int, chunk) -> dict:
    from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
    from mvgs_plugin.config import MVGSConfig, Stage
    from mvgs_plugin.controller import MVGS

    class SH3Adapter(GS3DAdapter):
        # MVGS.step() calls set_step() before it renders, and set_step() derives the active SH
        # degree from the step (0 for the first 1000 steps): pin it here, not after the step.
        def set_step(self, step: int) -> None:
            super().set_step(step)
            self.active_sh_degree = self.config.sh_degree

    torch.set_num_threads(threads)
    scene = make_scene(n, big)
    adapter = SH3Adapter.from_scene(scene, GS3DConfig(sh_degree=3))
    extra = {} if chunk is None else {"chunk_size": chunk}
    cfg = MVGSConfig.baseline(stages=(Stage(factor, views, 10_000),), densify_from=10**9, **extra)
    mvgs = MVGS(adapter, scene, cfg)
    for cam in scene.train_cameras:  # decode and downscale every target now: steady-state steps only
        scene.image(cam, factor)
    rows = []
    for i in range(warmup + steps):
        c0 = time.process_time()  # user+sys like os.times(), but ns resolution, not 10 ms ticks
        info = mvgs.step()
        cpu = time.process_time() - c0
        assert adapter.active_sh_degree == 3 and info.num_primitives == n
        if i >= warmup:
            rows.append({p: getattr(info, p) for p in PARTS} | {"cpu": cpu})
    out = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    return out | dict(n=n, big=big, factor=factor, views=views, threads=threads, chunk_size=cfg.chunk_size,
                      px=(256 if big else 128) // factor, steps=steps,
                      peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


def measure(spec, threads: int, args, cache: dict, src=None):
    """Runs one (n, big, factor, views) in a fresh process (with the packages of checkout `src`
    when given); None (and a note) when it fails."""
    key = (*spec, threads, src)
    if src is None and args.before:
        measure(spec, threads, args, cache, args.before)  # interleaved: both see the same machine
    if key not in cache:
        job = dict(spec=list(spec), threads=threads, warmup=args.warmup, steps=args.steps, chunk=args.chunk_size,
                   src=src)
        out = subprocess.run([sys.executable, __file__, "--worker", json.dumps(job)], capture_output=True, text=True)
        if out.returncode != 0:
            tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
            print(f"<!-- {spec} threads={threads} failed: {tail} -->", flush=True)
            cache[key] = None
        else:
            cache[key] = json.loads(out.stdout.strip().splitlines()[-1])
    return cache[key]


def fmt_row(label: str, r, same=None, full=None, before=None) -> str:
    if r is None:
        return f"| {label} | | | failed |"
    old = "" if before is None else f" {1e3 * before['seconds']:.1f} | {r['seconds'] / before['seconds']:.2f} |"
    ms = lambda s: f"{1e3 * s:.1f}"  # noqa: E731
    ratio = lambda ref: "" if ref is None else f"{r['seconds'] / ref['seconds']:.2f}"  # noqa: E731
    return (f"| {label} | {r['views']} | {r['px']} | {ms(r['seconds'])} | {ms(r['render_seconds'])} "
            f"| {ms(r['backward_seconds'])} | {ms(r['loss_seconds'])} "
            f"| {ms(r['adapter_seconds'] + r['controller_seconds'])} | {ms(r['seconds'] / r['views'])} "
            f"| {ratio(same)} | {ratio(full)} | {ms(r['cpu'])} | {r['peak_mb']:.0f} |{old}")


def table(threads: int, rows, args, cache: dict) -> list:
    """Prints one thread count's table; returns its target checks."""
    print(f"\n### threads={threads}\n")
    extra = (" before (ms) | after / before |", "---:|---:|") if args.before else ("", "")
    print("| config | views | px | step (ms) | render | backward | loss | adapter+controller | per view (ms) "
          "| ratio to 1 view same size | ratio to 1 view full res | CPU (ms) | peak RSS (MB) |" + extra[0])
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + extra[1])
    old = lambda spec: measure(spec, threads, args, cache, args.before) if args.before else None  # noqa: E731
    got, shown = {}, set()
    ok = lambda *rs: all(x is not None for x in rs)  # noqa: E731
    for label, n, big, f, m in rows:
        multi, same, full = (measure((n, big, ff, mm), threads, args, cache) for ff, mm in ((f, m), (f, 1), (1, 1)))
        print(fmt_row(label, multi, same if ok(multi, same) else None, full if ok(multi, full) else None,
                      old((n, big, f, m))), flush=True)
        got[label] = (multi, full)
        for spec, r in (((n, big, f, 1), same), ((n, big, 1, 1), full)):
            if spec not in shown:  # the 1-view rows once each, next to the first row using them
                shown.add(spec)
                print(fmt_row(label, r, None, full if ok(r, full) else None, old(spec)), flush=True)
    t48, t1 = (measure(s, threads, args, cache) for s in FIXED)
    for r, spec in zip((t48, t1), FIXED):
        print(fmt_row("10k 1 px", r, before=old(spec)), flush=True)
    checks = []
    if t48 and t1:
        fixed = (t48["seconds"] - t1["seconds"]) / 47
        checks.append(("per-view fixed cost (10k, 1x1 px) <= 3 ms", f"{1e3 * fixed:.2f} ms "
                       f"(t(1 view) {1e3 * t1['seconds']:.1f} ms)", fixed <= 3e-3))
    for label, name, limit in (("10k 16 px", "48-view 16 px step / one 128 px view", 1.5),
                               ("10k 128 px", "8-view 128 px step / one 128 px view", 7.0)):
        multi, full = got.get(label, (None, None))
        if multi and full:
            r = multi["seconds"] / full["seconds"]
            checks.append((f"{name} <= {limit}x", f"{r:.2f}x", r <= limit))
    return [(threads, *c) for c in checks]


def sweep_table(threads: int, args, cache: dict) -> None:
    """--views-sweep: a step of M full-resolution views against a one-view step, wall and CPU."""
    print(f"\n### threads={threads}: a step of M views in one-view steps (128 px)\n")
    print("| Gaussians | views M | step (ms) | CPU (ms) | step / one-view step | CPU / one-view step's |")
    print("|---:|---:|---:|---:|---:|---:|")
    for n in SWEEP_GAUSSIANS:
        one = measure((n, False, 1, 1), threads, args, cache)
        for m in SWEEP_VIEWS:
            r = measure((n, False, 1, m), threads, args, cache)
            if r is None or one is None:
                print(f"| {n} | {m} | | failed | | |")
                continue
            print(f"| {n} | {m} | {1e3 * r['seconds']:.1f} | {1e3 * r['cpu']:.1f} | {r['seconds'] / one['seconds']:.2f} "
                  f"| {r['cpu'] / one['cpu']:.2f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--steps", type=int, default=None, help="timed steps (default 5, 3 with --quick)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--chunk-size", type=int, default=None, help="views per render call (default: the config's)")
    ap.add_argument("--quick", action="store_true", help="only the 10k rows, 3 steps")
    ap.add_argument("--views-sweep", action="store_true",
                    help="only the cost of an M-view step in one-view steps (M = 1, 2, 4, 8; 10k and 30k Gaussians)")
    ap.add_argument("--json", help="write every raw number here")
    ap.add_argument("--before", help="another checkout to time beside this one (see the module doc)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)  # internal: run one measurement, print JSON
    args = ap.parse_args()

    if args.worker:
        job = json.loads(args.worker)
        if job.get("src"):
            sys.path.insert(0, job["src"])  # before the editable install of this tree
        print(json.dumps(run_one(*job["spec"], job["threads"], job["warmup"], job["steps"], job["chunk"])))
        return

    if args.views_sweep and (args.before or args.json or args.quick):
        ap.error("--views-sweep prints its own table only: drop --before, --json and --quick")
    args.steps = args.steps or (3 if args.quick else 5)
    rows = [r for r in ROWS if not (args.quick and r[1] != 10_000)]
    print(f"scene={SCENE_DIR.name} steps={args.steps} warmup={args.warmup} chunk_size={args.chunk_size or 'default'} "
          f"torch={torch.__version__}")
    cache, checks = {}, []
    if args.views_sweep:
        for threads in args.threads:
            sweep_table(threads, args, cache)
        return
    for threads in args.threads:
        checks += table(threads, rows, args, cache)
    print("\n### targets\n\n| threads | target | measured | |\n|---:|---|---|---|")
    for threads, name, value, met in checks:
        print(f"| {threads} | {name} | {value} | {'met' if met else 'missed'} |")
    if args.json:
        raw = [dict(r, key=list(k)) for k, r in cache.items() if r is not None]  # key ends with src (None: here)
        targets = [dict(threads=t, target=n, measured=v, met=m) for t, n, v, m in checks]
        from mvgs_plugin.cli import without_machine_paths

        text = json.dumps(dict(args=vars(args), results=raw, targets=targets), indent=1)
        Path(args.json).write_text(without_machine_paths(text))  # the --before checkout as .../name


if __name__ == "__main__":
    main()
