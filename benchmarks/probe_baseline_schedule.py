"""Why the compressed 3DGS baseline can fall with more steps (issue 27, part 3): the baseline
(`--preset baseline --threshold-width 800`) trained at several lengths, with one part of its
schedule changed at a time. Each run is examples/train_3dgs.py in its own single-threaded
process (at most --parallel at a time); prints a markdown table per scene: test PSNR (training
views' PSNR in brackets, rendered from the run's point_cloud.ply) / test SSIM / Gaussians per
length, and whether test PSNR fell from one length to the next.

Variants (each a change of MVGSConfig.baseline() before it is compressed to the run's length):
  plain     the baseline as every table uses it
  noreset   no opacity resets
  every3x   densification 3x less often (every 30 steps of a 3k run instead of 10)
  window4   densification ends at 1/4 of the run instead of 1/2 (resets with it)
  sh1       SH degree 1 instead of 3 (the model's view-dependent colour, not the clock)
  lrhalf    the means' learning rate decays over half the run instead of all of it

    python benchmarks/probe_baseline_schedule.py --data scenes/reflective scenes/clutter --steps 1000 2000 3000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {"plain": {}, "noreset": {"opacity_reset_every": 10**9}, "every3x": {"densify_every": 300},
            "window4": {"densify_until": 7_500}, "sh1": {}, "lrhalf": {}}
# variants that change the model's config (mvgs_plugin.cli.model_config) rather than the clock
MODEL_VARIANTS = {"sh1": lambda c: dataclasses.replace(c, sh_degree=1),
                  "lrhalf": lambda c: dataclasses.replace(c, position_lr_max_steps=max(1, c.position_lr_max_steps // 2))}


def one(variant: str, argv) -> None:
    """In this process: train_3dgs.py with the baseline preset changed by `variant`."""
    import runpy

    from mvgs_plugin.config import MVGSConfig

    made = MVGSConfig.baseline.__func__
    MVGSConfig.baseline = classmethod(lambda cls, **o: made(cls, **{**VARIANTS[variant], **o}))
    if variant in MODEL_VARIANTS:
        from mvgs_plugin import cli

        base = cli.model_config
        cli.model_config = lambda *a, **k: MODEL_VARIANTS[variant](base(*a, **k))
    sys.argv = ["train_3dgs.py", *argv]
    runpy.run_path(str(ROOT / "examples" / "train_3dgs.py"), run_name="__main__")


def train_psnr(data: Path, folder: Path) -> float:
    """Mean PSNR over the training views of the model a run saved (its point_cloud.ply)."""
    import torch

    from mvgs_plugin.adapters.ply import read_gaussian_ply
    from mvgs_plugin.data import load_scene
    from mvgs_plugin.metrics import psnr
    from mvgs_plugin.reference_renderer import rasterization

    scene = load_scene(data, init=None)
    g = read_gaussian_ply(folder / "point_cloud.ply")
    bg = torch.tensor(scene.background or (0.0, 0.0, 0.0), dtype=torch.float32)[None]
    colors = torch.cat([g.sh0, g.shN], 1)
    values = []
    with torch.no_grad():
        for cam in scene.train_cameras:
            img, _, _ = rasterization(means=g.means, quats=g.quats, scales=torch.exp(g.scales),
                                      opacities=torch.sigmoid(g.opacities), colors=colors,
                                      viewmats=cam.world_to_camera.float()[None], Ks=cam.K.float()[None],
                                      width=cam.width, height=cam.height, sh_degree=g.sh_degree, backgrounds=bg)
            values.append(psnr(img[0].clamp(0, 1), scene.image(cam)))
    return sum(values) / len(values)


def run(data: Path, steps: int, variant: str, out: Path) -> dict:
    folder = out / f"{data.name}-{steps}-{variant}"
    if not (folder / "metrics.json").exists():
        cmd = [sys.executable, __file__, "--one", variant, "--", "--data", str(data), "--preset", "baseline",
               "--threshold-width", "800", "--steps", str(steps), "--threads", "1", "--out", str(folder)]
        subprocess.run(cmd, check=True, capture_output=True, text=True)
    metrics = json.loads((folder / "metrics.json").read_text())
    metrics["train_psnr"] = train_psnr(data, folder)
    return metrics


def main(argv=None) -> str:
    if argv is None and "--one" in sys.argv:
        i = sys.argv.index("--one")
        one(sys.argv[i + 1], sys.argv[sys.argv.index("--") + 1:])
        return ""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, nargs="+", required=True)
    ap.add_argument("--steps", type=int, nargs="+", default=[1000, 2000, 3000])
    ap.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("out/probe_baseline_schedule"))
    args = ap.parse_args(argv)
    jobs = [(d, s, v) for d in args.data for v in args.variants for s in args.steps]
    with ThreadPoolExecutor(args.parallel) as pool:
        results = dict(zip(jobs, pool.map(lambda j: run(*j, args.out), jobs)))
    lines = []
    for d in args.data:
        lines += [f"{d.name}: test PSNR (training views' PSNR) in dB / test SSIM / Gaussians", "",
                  "| variant | " + " | ".join(f"{s} steps" for s in args.steps) + " | falls |",
                  "|---|" + "---:|" * (len(args.steps) + 1)]
        for v in args.variants:
            ms = [results[(d, s, v)] for s in args.steps]
            falls = any(b["psnr"] < a["psnr"] for a, b in zip(ms, ms[1:]))
            cells = [f"{m['psnr']:.2f} ({m['train_psnr']:.2f}) / {m['ssim']:.3f} / {m['num_gaussians'] / 1000:.1f}k"
                     for m in ms]
            lines.append(f"| {v} | " + " | ".join(cells) + f" | {'yes' if falls else 'no'} |")
        lines.append("")
    text = "\n".join(lines)
    print(text)
    return text


if __name__ == "__main__":
    main()
