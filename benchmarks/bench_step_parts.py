"""Where a full-resolution training view's CPU time goes, for trained models of the port of
gsplat's loop (checkpoints of examples/gsplat_loop/simple_trainer*.py); prints a markdown table.

Made to answer why a Gaussian budget cuts the count 3-4x but the CPU of a run much less: each
checkpoint's model is rendered at every training view at full resolution, its loss (0.8 L1 +
0.2 D-SSIM, the loop's) backpropagated and an Adam step taken, one thread, and the reference
renderer's compiled parts are timed apart: projection, depth binning, compositing (forward and
backward). Beside the times: the Gaussians, those visible per view, the tile-Gaussian pairs per
view (the rasterizer's lists), the screen area the visible ones cover (their 3-sigma boxes
clipped to the image, summed, per pixel), and the Gaussians the image formation blends per pixel
(alpha >= 1/255 before the pixel stops; composited again in float64 by the PyTorch backend at
each training view, in the warm-up pass: the compositing's work per pixel follows it).

    python examples/gsplat_loop/simple_trainer_mvgs.py --steps 3000 --threads 1 --save-steps 3000 --out out/a [...]
    python benchmarks/bench_step_parts.py out/a/ckpt_3000.pt out/b/ckpt_3000.pt [--data SCENE] [--repeats 2]

CPU ms per view (process time, user + sys) over --repeats passes of the training views after one
pass of warm-up; an Adam step of every parameter is included, at lr 0 (the work of a step, and
the model stays the checkpoint's, so every pass renders the same). Rows of one run compare;
runs on a loaded machine differ by their load.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path
from typing import Dict, List, NamedTuple

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import common  # noqa: E402
from mvgs_plugin.io import load_checked  # noqa: E402
from mvgs_plugin.losses import ssim  # noqa: E402
from mvgs_plugin.reference_renderer import rasterize_torch, rendering  # noqa: E402

KERNELS = ("project_forward", "bin_by_depth", "forward", "backward", "project_backward")


class KernelClock:
    """CPU seconds spent in each compiled kernel of the reference renderer while installed."""

    def __init__(self):
        self.seconds: Dict[str, float] = collections.defaultdict(float)
        self._real = {}

    def __enter__(self):
        for name in KERNELS:
            real = self._real[name] = getattr(rendering._cpp, name)
            setattr(rendering._cpp, name, self._timed(name, real))
        return self

    def __exit__(self, *exc):
        for name, real in self._real.items():
            setattr(rendering._cpp, name, real)

    def _timed(self, name, fn):
        def call(*args, **kwargs):
            c = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] += time.process_time() - c
        return call


def covered_per_pixel(info, width: int, height: int) -> float:
    """The visible Gaussians' 3-sigma boxes (means2d +- radii) clipped to the image, summed, per
    pixel, for a one-camera info."""
    r = info["radii"][0].float()
    m = info["means2d"].detach()[0].float()
    seen = (r > 0).all(-1)
    wx = ((m[:, 0] + r[:, 0]).clamp(0, width) - (m[:, 0] - r[:, 0]).clamp(0, width)).clamp_min(0)
    wy = ((m[:, 1] + r[:, 1]).clamp(0, height) - (m[:, 1] - r[:, 1]).clamp(0, height)).clamp_min(0)
    return float((wx * wy)[seen].sum()) / (width * height)


class Blending(NamedTuple):
    """What the image formation blends at one view (contributors_per_pixel)."""
    counts: torch.Tensor  # [H, W] Gaussians blended at each pixel
    trans: torch.Tensor   # [H, W] transmittance left at each pixel
    pairs: torch.Tensor   # [N] pixels each Gaussian is blended at (0 where not visible)
    weight: torch.Tensor  # [N] its blend weight alpha * T summed over those pixels


def contributors_per_pixel(info, width: int, height: int) -> Blending:
    """Per pixel of a one-camera info: how many Gaussians the image formation blends (alpha >= 1/255,
    before the transmittance would fall below 1e-4), and the transmittance left; per Gaussian: at
    how many pixels it is blended and its summed blend weight (alpha x the transmittance in front
    of it). Composited again in float64 by the renderer's PyTorch backend (rasterize_torch, its
    `stats`), over tile lists made here from the info's radii and depths (project.cpp's rule: a
    3-sigma radius covers the tiles [floor((m - r) / T), floor((m + r + T - 1) / T))), not by the
    compiled kernels, whose work per pixel is about this count (twice: forward and backward)."""
    tile = int(info["tile_size"])
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    m = info["means2d"].detach()[:1].double()
    r = info["radii"][:1, :, :1].double()
    seen = (info["radii"][:1] > 0).all(-1)
    lo, hi = torch.floor((m - r) / tile), torch.floor((m + r + tile - 1) / tile)
    limit = torch.tensor([tiles_x, tiles_y], dtype=torch.float64)
    lo, hi = torch.minimum(lo.clamp_min(0), limit), torch.minimum(hi.clamp_min(0), limit)
    rects = torch.stack([lo[..., 0], hi[..., 0], lo[..., 1], hi[..., 1]], -1).long()
    rects = torch.where(seen[..., None], rects, torch.zeros_like(rects))  # an unseen Gaussian covers no tile
    order = torch.argsort(info["depths"][:1], dim=-1, stable=True)
    offsets, ids = rasterize_torch.bin_tiles(rects, order, tiles_x, tiles_y)
    o = info["opacities"].detach()
    o = (o[:1] if o.dim() == 2 else o[None]).double()
    n = m.shape[1]
    stats: Dict[str, torch.Tensor] = {}
    with torch.no_grad():
        _, alpha = rasterize_torch.composite(m, info["conics"].detach()[:1].double(), o,
                                             torch.zeros(1, n, 1, dtype=torch.float64),
                                             torch.zeros(1, 1, dtype=torch.float64), offsets, ids, width, height,
                                             tile, stats=stats)
    return Blending(stats["counts"][0], 1.0 - alpha[0, ..., 0], stats["pairs"][0], stats["weight"][0])


def load_model(ckpt: Path):
    """A gsplat-loop checkpoint (ValueError naming it if it is not one): (the saved dict, its splats
    in float32, their SH degree, a loop Config for rendering them)."""
    saved = load_checked(str(ckpt))
    if not (isinstance(saved, dict) and "splats" in saved):
        raise ValueError(f"{ckpt}: not a checkpoint of the gsplat loop (no 'splats')")
    splats = {k: v.float() for k, v in saved["splats"].items()}
    degree = int(round((splats["shN"].shape[1] + 1) ** 0.5)) - 1
    cfg = common.Config(sh_degree=degree)
    cfg.make_strategy()
    return saved, splats, degree, cfg


def render_view(splats, cfg, parser: "common.Parser", d, degree: int, **kwargs):
    """The loop's render of one training or test item d at its full resolution (kwargs: the
    rasterizer's, e.g. blend_stats=True)."""
    h, w = d["image"].shape[:2]
    return common.rasterize_splats(splats, cfg, parser.background, d["camtoworld"][None], d["K"][None], w, h,
                                   sh_degree=degree, **kwargs)


def loop_loss(colors: torch.Tensor, d, cfg) -> torch.Tensor:
    """The loop's loss of a render `colors` [1, H, W, 3] of item d: (1 - ssim_lambda) L1 +
    ssim_lambda (1 - SSIM), inside d's mask if it has one."""
    pixels = d["image"][None] / 255.0
    if "mask" in d:
        pixels = pixels * d["mask"][None, ..., None]
        colors = colors * d["mask"][None, ..., None]
    return (1.0 - cfg.ssim_lambda) * F.l1_loss(colors, pixels) + cfg.ssim_lambda * (
        1.0 - ssim(colors, pixels, padding="valid"))


def measure(ckpt: Path, parser: "common.Parser", repeats: int) -> Dict[str, float]:
    """One checkpoint's row: counts and CPU ms per full-resolution training view."""
    _, loaded, degree, cfg = load_model(ckpt)
    splats = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in loaded.items()})
    optimizers = {k: torch.optim.Adam([splats[k]], lr=0.0, eps=1e-15) for k in splats}
    views = common.Dataset(parser, "train")
    parts = collections.defaultdict(float)
    counts = collections.defaultdict(float)
    blended = [0.0, 0]
    n = 0
    for rep in range(repeats + 1):
        timed = rep > 0  # the first pass warms up
        with KernelClock() as clock:
            for i in range(len(views)):
                d = views[i]
                h, w = d["image"].shape[:2]
                c0 = time.process_time()
                colors, _, info = render_view(splats, cfg, parser, d, degree)
                c1 = time.process_time()
                loss = loop_loss(colors, d, cfg)
                c2 = time.process_time()
                loss.backward()
                c3 = time.process_time()
                for opt in optimizers.values():
                    opt.step()
                    opt.zero_grad(set_to_none=True)
                c4 = time.process_time()
                if not timed:  # once per view, outside the timed passes
                    blended[0] += float(contributors_per_pixel(info, w, h).counts.mean())
                    blended[1] += 1
                if timed:
                    n += 1
                    parts["render"] += c1 - c0
                    parts["loss"] += c2 - c1
                    parts["backward"] += c3 - c2
                    parts["adam"] += c4 - c3
                    counts["visible"] += int((info["radii"] > 0).all(-1).sum())
                    counts["pairs"] += len(info["flatten_ids"])
                    counts["covered"] += covered_per_pixel(info, w, h)
        if timed:
            for k, v in clock.seconds.items():
                parts["k_" + k] += v
    row = {"checkpoint": str(ckpt), "gaussians": len(splats["means"]), "views": n}
    row.update({k: 1000.0 * v / n for k, v in parts.items()})
    row.update({k: v / n for k, v in counts.items()})
    row["blended"] = blended[0] / max(blended[1], 1)
    row["total"] = row["render"] + row["loss"] + row["backward"] + row["adam"]
    return row


def table(rows: List[Dict[str, float]]) -> str:
    lines = ["| checkpoint | Gaussians | visible / view | tile pairs / view | covered / pixel | blended / pixel | project | bin | "
             "composite fwd | loss | composite bwd | project bwd | Adam | whole view (ms) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['checkpoint']} | {r['gaussians']} | {r['visible']:.0f} | {r['pairs']:.0f} | {r['covered']:.1f} | {r['blended']:.1f} | "
                     + " | ".join(f"{r.get(k, 0.0):.2f}" for k in ("k_project_forward", "k_bin_by_depth", "k_forward", "loss",
                                                                     "k_backward", "k_project_backward", "adam"))
                     + f" | {r['total']:.2f} |")
    return "\n".join(lines) + "\n"


def checkpoint_arguments(doc: str, argv=None, more=None, check=None):
    """The arguments of a script that measures checkpoints of the gsplat loop (this one,
    probe_blend_weight.py and probe_view_noise.py): checkpoints, --data, --repeats (more(ap) adds
    its own, check(ap, args) checks them), checked; one thread set. Returns (args, the scene's
    common.Parser)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", type=Path, nargs="+", help="ckpt_<step>.pt files of the gsplat loop")
    ap.add_argument("--data", type=Path, default=ROOT / "examples" / "scenes" / "tabletop",
                    help="the scene they were trained on (default: the bundled tabletop)")
    ap.add_argument("--repeats", type=int, default=2, help="timed passes over the training views (default: 2)")
    if more is not None:
        more(ap)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: at least 1")
    if check is not None:
        check(ap, args)
    missing = [str(p) for p in args.checkpoints if not p.is_file()]
    if missing:
        ap.error(f"no such checkpoint: {', '.join(missing)}")
    torch.set_num_threads(1)
    return args, common.Parser(args.data)


def main(argv=None) -> str:
    args, parser = checkpoint_arguments(__doc__, argv)
    rows = [measure(ckpt, parser, args.repeats) for ckpt in args.checkpoints]
    text = (f"Scene: {args.data}; CPU ms per full-resolution training view, one thread, {args.repeats} timed "
            "passes; project / bin / composite / project bwd are the reference renderer's compiled kernels.\n\n"
            + table(rows))
    print(text)
    return text


if __name__ == "__main__":
    main()
