"""Speed and memory of reference_renderer.rasterization on the standard scenes (prints a table).

Standard scene (so numbers compare across runs and with other renderers): fx = fy = image width,
principal point at the centre, camera at the origin looking +z; depths uniform in [2, 6]; x, y
uniform within +-45 % of the frustum half-width at that depth; per-axis scales log-uniform in
[0.01, 0.06]; opacities uniform in [0.3, 0.7]; random unit quaternions; SH degree 3 with
coefficients N(0, 0.3^2); seed 0. With C = 8 the cameras turn about the vertical axis through
(0, 0, 4) in steps of 3 degrees (-10.5 .. +10.5), all seeing the same content.

Each configuration runs in its own process so its peak memory (max RSS) is its own. Times are
medians after warm-up with torch.set_num_threads(--threads). "pairs" counts the Gaussian-pixel
pairs the tile rule asks to evaluate (every pixel of every covered tile).

    python benchmarks/bench_renderer.py                    # full table (cpp backend)
    python benchmarks/bench_renderer.py --quick            # a smaller set
    python benchmarks/bench_renderer.py --backend torch --sizes 10000x128
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import sys
import time

import torch


def standard_scene(n: int, size: int, n_cams: int, seed: int = 0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    z = 2 + 4 * u(n)
    half = 0.5 * z  # frustum half-width at depth z: z * (W/2) / fx with fx = W
    means = torch.stack([(2 * u(n) - 1) * 0.45 * half, (2 * u(n) - 1) * 0.45 * half, z], -1)
    scales = torch.exp(math.log(0.01) + (math.log(0.06) - math.log(0.01)) * u(n, 3))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    opacities = 0.3 + 0.4 * u(n)
    sh = 0.3 * torch.randn(n, 16, 3, generator=g, dtype=torch.float64)
    viewmats = []
    for c in range(n_cams):
        a = math.radians(3.0 * (c - (n_cams - 1) / 2)) if n_cams > 1 else 0.0
        # Camera-to-world: rotate by a about the y axis through (0, 0, 4).
        R = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64)
        pivot = torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)
        center = pivot - R @ pivot
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = R.T
        w2c[:3, 3] = -R.T @ center
        viewmats.append(w2c)
    K = torch.tensor([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]], dtype=torch.float64)
    cast = lambda t: t.to(dtype)  # noqa: E731
    return dict(
        means=cast(means), quats=cast(quats), scales=cast(scales), opacities=cast(opacities),
        colors=cast(sh), viewmats=cast(torch.stack(viewmats)), Ks=cast(K.expand(n_cams, 3, 3).clone()),
        width=size, height=size, sh_degree=3,
    )


def run_one(n: int, size: int, n_cams: int, backend: str, threads: int, repeats: int) -> dict:
    from mvgs_plugin.reference_renderer import rasterization

    torch.set_num_threads(threads)
    scene = standard_scene(n, size, n_cams)
    params = {k: scene[k].requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
    weights = torch.rand(n_cams, size, size, 3, generator=torch.Generator().manual_seed(1))

    def fwd():
        with torch.no_grad():
            return rasterization(**scene, backend=backend)

    def fwd_bwd():
        img, alpha, meta = rasterization(**scene, backend=backend)
        meta["means2d"].retain_grad()
        (img * weights).sum().backward()
        for p in params.values():
            p.grad = None
        return meta

    def median_time(fn):
        fn()  # warm-up (builds the compiled library on a first run)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    t_fwd = median_time(fwd)
    t_both = median_time(fwd_bwd)
    meta = fwd()[2]
    offsets = meta["isect_offsets"].reshape(-1).tolist() + [meta["flatten_ids"].numel()]
    tile = meta["tile_size"]
    pairs = sum((offsets[i + 1] - offsets[i]) for i in range(len(offsets) - 1)) * tile * tile
    return dict(
        n=n, size=size, cams=n_cams, backend=meta["backend"], fwd=t_fwd, fwd_bwd=t_both, pairs=pairs,
        peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="*", help="NxS items, e.g. 50000x256 (default: the 3x3 grid)")
    ap.add_argument("--cams", nargs="*", type=int, default=[1, 8])
    ap.add_argument("--backend", default="cpp", choices=["cpp", "torch"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="10k and 50k at 128 and 256 only")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one config, print JSON
    args = ap.parse_args()

    if args.one:
        n, size, cams = (int(v) for v in args.one.split(","))
        print(json.dumps(run_one(n, size, cams, args.backend, args.threads, args.repeats)))
        return

    if args.sizes:
        grid = [tuple(int(v) for v in s.split("x")) for s in args.sizes]
    elif args.quick:
        grid = [(n, s) for n in (10_000, 50_000) for s in (128, 256)]
    else:
        grid = [(n, s) for n in (10_000, 50_000, 200_000) for s in (128, 256, 512)]

    print(f"backend={args.backend} threads={args.threads} repeats={args.repeats} torch={torch.__version__}")
    header = "| N | image | C | forward (s) | fwd+bwd (s) | pairs (M) | fwd+bwd Mpairs/s | peak RSS (MB) |"
    print(header)
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n, size in grid:
        for cams in args.cams:
            cmd = [sys.executable, __file__, "--one", f"{n},{size},{cams}", "--backend", args.backend,
                   "--threads", str(args.threads), "--repeats", str(args.repeats)]
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode != 0:
                print(f"| {n} | {size}² | {cams} | failed: {out.stderr.strip().splitlines()[-1]} |")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(
                f"| {n} | {size}² | {cams} | {r['fwd']:.3f} | {r['fwd_bwd']:.3f} | {r['pairs'] / 1e6:.1f} "
                f"| {r['pairs'] / 1e6 / r['fwd_bwd']:.0f} | {r['peak_mb']:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
