"""The scene's image cache under a bound (Scene(cache_bytes=...)): resident memory and read time
when a run's images do not fit (prints a table).

Writes a synthetic capture of N PNG images (smooth noise, so they compress as photographs do
not, but decode at a photograph's cost per pixel) to a temporary folder, then in one process
per bound: loads it as a Scene, reads every training image in a shuffled order for two epochs
(as a one-view-per-step run does), and reports the peak resident set size, the images held at
the end and the mean time of a read in the second epoch (a hit when held, a decode when not).

    python benchmarks/bench_image_cache.py
    python benchmarks/bench_image_cache.py --images 120 --size 1024 768 --bounds 0 0.25 1
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def write_capture(folder: Path, n: int, width: int, height: int) -> None:
    import numpy as np
    import skimage.io

    rng = np.random.default_rng(0)
    base = rng.random((height // 8 + 1, width // 8 + 1, 3))
    for k in range(n):
        img = np.kron(np.roll(base, k, axis=1), np.ones((8, 8, 1)))[:height, :width]
        img = img + 0.1 * rng.random((height, width, 3))
        skimage.io.imsave(folder / f"{k:04d}.png", (255 * img / img.max()).astype(np.uint8), check_contrast=False)


def run_one(folder: Path, n: int, width: int, height: int, share: float) -> dict:
    import numpy as np
    import torch

    from mvgs_plugin.camera import Camera
    from mvgs_plugin.data import Scene

    torch.set_num_threads(1)
    K = np.array([[width, 0.0, width / 2], [0.0, width, height / 2], [0.0, 0.0, 1.0]])
    cams = []
    for k in range(n):
        w2c = np.eye(4)
        w2c[0, 3] = 0.01 * k
        cams.append(Camera(uid=k, name=f"{k:04d}.png", K=K, world_to_camera=w2c, width=width, height=height))
    total = n * width * height * 3 * 4
    bound = None if share < 0 else int(share * total)
    scene = Scene(cams, [], {c.uid: folder / c.name for c in cams}, cache_bytes=bound)
    gen = torch.Generator().manual_seed(0)
    times = []
    for epoch in range(2):
        for i in torch.randperm(n, generator=gen).tolist():
            t0 = time.perf_counter()
            scene.image(cams[i])
            if epoch == 1:
                times.append(time.perf_counter() - t0)
    return {"share": share, "bound_mb": None if bound is None else bound / 2**20, "all_mb": total / 2**20,
            "peak_rss_mb": peak_rss_mb(), "held": len(scene._cache), "read_ms": 1000 * sum(times) / len(times)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=60)
    ap.add_argument("--size", type=int, nargs=2, default=(1024, 768), metavar=("W", "H"))
    ap.add_argument("--bounds", type=float, nargs="+", default=(-1.0, 0.5, 0.25, 0.0),
                    help="cache_bytes as a share of the decoded capture's size (-1: the default, half the machine)")
    ap.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    w, h = args.size
    if args.child is not None:
        print(json.dumps(run_one(Path(args.child[0]), args.images, w, h, float(args.child[1]))))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        write_capture(Path(tmp), args.images, w, h)
        rows = []
        for share in args.bounds:  # one process per bound: peak RSS is the process's own
            out = subprocess.run([sys.executable, __file__, "--images", str(args.images), "--size", str(w), str(h),
                                  "--child", tmp, str(share)], capture_output=True, text=True, check=True, cwd=ROOT)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"{args.images} images of {w} x {h}: {rows[0]['all_mb']:.0f} MB decoded (float32)\n")
    print("| cache_bytes | peak RSS MB | images held | mean read, second epoch (ms) |")
    print("|---|---:|---:|---:|")
    for r in rows:
        bound = "default (half the machine)" if r["bound_mb"] is None else f"{r['share']:g} of the capture ({r['bound_mb']:.0f} MB)"
        print(f"| {bound} | {r['peak_rss_mb']:.0f} | {r['held']} | {r['read_ms']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
