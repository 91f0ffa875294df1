"""Which Gaussians of a trained model cost compositing work and give the image little: a probe.

Per Gaussian, summed over the training views: the pixels it is blended at (alpha >= 1/255 before
the pixel stops: the compositing kernels' work, forward and backward) and its blend weight there
(alpha x the transmittance in front of it: its share of the pixels' colours). Ordered by weight
per blended pixel, the Gaussians that carry the lowest `share` of all the weight are removed
(those never blended first), and the model without them is measured as it is, not retrained:
the pixels they took, the Gaussians blended per pixel, the test PSNR and a training view's CPU
(benchmarks/bench_step_parts.py's clock: render, loss, backward, Adam at lr 0, one thread).

    python examples/gsplat_loop/simple_trainer_mvgs.py --steps 3000 --threads 1 --save-steps 3000 --out out/a [...]
    python benchmarks/probe_blend_weight.py out/a/ckpt_3000.pt [--data SCENE] [--shares 0.0025 0.005 0.01] [--repeats 2]
    python benchmarks/probe_blend_weight.py out/a/ckpt_2000.pt --shares 0.0025 --write-pruned out/p   # then:
    python examples/gsplat_loop/simple_trainer_mvgs.py --steps 3000 --resume out/p/ckpt_2000_pruned_0.0025.pt [...]

The blend weights are the renderer's own (rasterization(..., blend_stats=True), summed over the
training views in float64) and the Gaussians removed are those the package's rule names
(adapters.gs3d.faint_rows, MVGSConfig.prune_faint's, every Gaussian judged); the blended-per-pixel
column and the view time are bench_step_parts.measure's, about a minute per model and share on a
128 px scene of 48 views; the test PSNR is the mean over the test views of the clamped render
against the image.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Dict, List, Optional

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import bench_step_parts  # noqa: E402
import common  # noqa: E402
from mvgs_plugin.adapters.gs3d import faint_rows  # noqa: E402
from mvgs_plugin.io import save_checked  # noqa: E402


def test_psnr(splats, cfg, parser, degree) -> float:
    """Mean over the test views of the clamped render's PSNR against the image."""
    views = common.Dataset(parser, "test")
    total = 0.0
    for i in range(len(views)):
        d = views[i]
        with torch.no_grad():
            colors, _, _ = bench_step_parts.render_view(splats, cfg, parser, d, degree)
        mse = ((colors[0].clamp(0, 1) - d["image"] / 255.0) ** 2).mean().clamp_min(1e-20)
        total += float(-10.0 * torch.log10(mse))
    return total / len(views)


def _rows(v, keep: torch.Tensor):
    """v without the rows keep drops, when v has a row per Gaussian; v itself otherwise."""
    return v[keep].clone() if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == len(keep) else v


def pruned_checkpoint(saved: Dict, keep: torch.Tensor) -> Dict:
    """The gsplat loop's checkpoint without the Gaussians where keep is False, still resumable:
    the parameters, their Adam moments and the strategy's per-Gaussian statistics lose the same
    rows, and the MVGS state's count follows."""
    out = dict(saved)
    out["splats"] = {k: _rows(v, keep) for k, v in saved["splats"].items()}
    out["optimizers"] = {name: {**opt, "state": {i: {k: _rows(v, keep) for k, v in st.items()}
                                                 for i, st in opt["state"].items()}}
                         for name, opt in saved["optimizers"].items()}
    out["strategy_state"] = {k: _rows(v, keep) for k, v in saved["strategy_state"].items()}
    out["data"] = {**saved["data"], "mvgs": {**saved["data"]["mvgs"], "count": int(keep.sum())}}
    return out


def probe(ckpt: Path, parser, shares: List[float], repeats: int,
          write_to: Optional[Path] = None) -> List[Dict[str, float]]:
    saved, splats, degree, cfg = bench_step_parts.load_model(ckpt)
    views = common.Dataset(parser, "train")
    n = len(splats["means"])
    pairs = torch.zeros(n, dtype=torch.float64)
    weight = torch.zeros(n, dtype=torch.float64)
    for i in range(len(views)):
        with torch.no_grad():
            _, _, info = bench_step_parts.render_view(splats, cfg, parser, views[i], degree, blend_stats=True)
        pairs += info["blend_pixels"][0].double()
        weight += info["blend_weight"][0].double()
    every = torch.ones(n, dtype=torch.bool)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for share in [0.0, *shares]:
            keep = ~faint_rows(weight, pairs, every, share)  # least weight per blended pixel first
            k = n - int(keep.sum())
            # the cut model, resumable; bench_step_parts.measure reads its splats
            folder = write_to if write_to is not None and share > 0 else Path(tmp)
            path = folder / f"{ckpt.stem}_pruned_{share}.pt"
            save_checked(pruned_checkpoint(saved, keep), str(path))
            timed = bench_step_parts.measure(path, parser, repeats)
            rows.append({"checkpoint": str(ckpt), "share": share, "removed": k, "gaussians": n - k,
                         "removed_weight": float(weight[~keep].sum() / weight.sum()),
                         "removed_pairs": float(pairs[~keep].sum() / pairs.sum()),
                         "blended": timed["blended"], "psnr": test_psnr({name: v[keep] for name, v in splats.items()},
                                                                       cfg, parser, degree),
                         "view_ms": timed["total"]})
    return rows


def table(rows: List[Dict[str, float]]) -> str:
    lines = ["| checkpoint | weight share removed (asked / removed) | Gaussians removed | kept | pixels they were blended at "
             "| blended / pixel | test PSNR, not retrained | training view (ms) |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['checkpoint']} | {r['share']:.2%} / {r['removed_weight']:.2%} | {r['removed']} | "
                     f"{r['gaussians']} | {r['removed_pairs']:.1%} | {r['blended']:.1f} | {r['psnr']:.3f} | "
                     f"{r['view_ms']:.2f} |")
    return "\n".join(lines) + "\n"


def _shares(ap):
    ap.add_argument("--shares", type=float, nargs="+", default=[0.0025, 0.005, 0.01],
                    help="shares of the summed blend weight to remove (default: 0.0025 0.005 0.01)")
    ap.add_argument("--write-pruned", type=Path, default=None, metavar="DIR",
                    help="also write each pruned model as a checkpoint the loop resumes (--resume): "
                         "DIR/<checkpoint>_pruned_<share>.pt (default: none)")


def _check_shares(ap, args):
    bad = [s for s in args.shares if not 0.0 < s < 1.0]
    if bad:
        ap.error(f"--shares {bad[0]}: each share must be in (0, 1)")
    if args.write_pruned is not None and not args.write_pruned.is_dir():
        ap.error(f"--write-pruned {args.write_pruned}: no such directory")


def main(argv=None) -> str:
    args, parser = bench_step_parts.checkpoint_arguments(__doc__, argv, _shares, _check_shares)
    rows = [r for ckpt in args.checkpoints
            for r in probe(ckpt, parser, sorted(args.shares), args.repeats, args.write_pruned)]
    text = (f"Scene: {args.data}; one thread; the removed Gaussians carry the least blend weight per blended pixel; "
            "the models are not retrained.\n\n" + table(rows))
    print(text)
    return text


if __name__ == "__main__":
    main()
