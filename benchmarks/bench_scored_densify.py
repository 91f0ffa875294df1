"""What scored densification and the Gaussian budget cost (issue 27): the extra statistics every
step folds in (grad_sq_accum, coverage_accum) and a densification call that ranks and cuts to a
cap, against a whole one-view step, on the bundled tabletop (128 x 128 px).

    python benchmarks/bench_scored_densify.py                  # 10k and 50k Gaussians, one thread
    python benchmarks/bench_scored_densify.py --sizes 10000 --repeats 5

Model: N Gaussians drawn (seed 0) from the scene's points with 0.01 jitter (as bench_step.py),
SH degree 3. Per N, medians over --repeats of:
  step       MVGS.step() of one full-resolution view, no densification (render, loss, backward,
             statistics, optimizer): the unit the others are compared to;
  stats      accumulate_stats of that view (all five statistics), and the part of it the two new
             statistics add (the same call with them removed from the code path: timed as the
             3DGS three-statistic update written out here);
  densify    one densification call after 20 views were folded in, with a threshold that makes
             the top tenth of the visible Gaussians candidates: uncapped (3DGS's rule), and
             with a cap that binds (growth ranked by the consistency score into the room left,
             inside the far line first: GS3DConfig.budget_growth_order on this 360-degree rig;
             and by score alone), with the same cap and a swap of 2 % of it (MVGSConfig.budget_swap: the lowest keep
             scores make way for more candidates), and with a cap below the count (the lowest
             keep scores are cut);
  optimizer  the adapter's optimizer step (Adam on every group) with GS3DConfig.means_lr_rule
             "extent" (3DGS's), "distance" and "disparity" (a per-row factor on the means' step);
  faint      MVGSConfig.prune_faint: the step again with the blend statistics asked of the renderer
             and folded in (collect_blend_stats), and the one cut of the faintest Gaussians that
             carry 1 % of the blend weight of 20 folded-in views (no growth).
Prints a markdown table; the "share of a step" column is the time of the call over one step's;
a densification call runs once per densify_every steps (10-100), so its share of the run is
that divided by densify_every.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import statistics
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def make(n: int, run):
    """The bundled scene with n points, and a 3DGS adapter on `run`'s clock (GS3DConfig.for_run)."""
    from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
    from mvgs_plugin.data import PointCloud, load_nerf_synthetic

    scene = load_nerf_synthetic(ROOT / "examples" / "scenes" / "tabletop")
    pts, g = scene.points, torch.Generator().manual_seed(0)
    idx = torch.randint(len(pts), (n,), generator=g)
    scene.points = PointCloud(pts.xyz[idx] + 0.01 * torch.randn(n, 3, generator=g), pts.rgb[idx])
    torch.manual_seed(0)
    return scene, GS3DAdapter.from_scene(scene, GS3DConfig.for_run(run, sh_degree=3))


def timed(fn, repeats: int) -> float:
    out = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        out.append(time.process_time() - t0)
    return statistics.median(out) * 1000.0


def three_stats(adapter, result) -> None:
    """The 3DGS statistics alone (grad_accum, denom, max_radii2D), as accumulate_stats computes them."""
    meta = result.aux
    grad, radii = meta["means2d"].grad, meta["radii"]
    visible, radius = (radii > 0).all(dim=-1), radii.max(dim=-1).values
    norms = (grad.detach() * grad.new_tensor([meta["width"] / 2.0, meta["height"] / 2.0])).norm(dim=-1)
    vis = visible.to(norms.dtype)
    adapter.grad_accum += (norms * vis).sum(dim=0)
    adapter.denom += vis.sum(dim=0)
    radius = torch.where(visible, radius.to(norms.dtype), torch.zeros_like(adapter.max_radii2D))
    adapter.max_radii2D = torch.maximum(adapter.max_radii2D, radius.max(dim=0).values)


def measure(n: int, repeats: int) -> dict:
    from mvgs_plugin import MVGS, MVGSConfig, Stage
    from mvgs_plugin.losses import photometric_loss
    from mvgs_plugin.protocol import DensifyContext

    config = MVGSConfig.baseline(stages=(Stage(1, 1, 10_000),), densify_from=10**9)
    scene, adapter = make(n, config)
    trainer = MVGS(adapter, scene, config)
    for cam in scene.train_cameras:
        scene.image(cam)
    for _ in range(2):
        trainer.step()
    step = timed(trainer.step, repeats)

    cams = scene.train_cameras
    bg = torch.zeros(1, 3)

    def rendered(i):
        res = adapter.render([cams[i % len(cams)]], bg)
        photometric_loss(res.images, torch.stack([scene.image(cams[i % len(cams)])]), 0.2).backward()
        return res

    res = rendered(0)
    stats_all = timed(lambda: adapter.accumulate_stats(res), repeats)
    stats_three = timed(lambda: three_stats(adapter, res), repeats)
    adapter.zero_grad()
    adapter._reset_stats()
    for i in range(20):  # a window of views folded in
        adapter.accumulate_stats(rendered(i))
        adapter.zero_grad()
    saved = copy.deepcopy(adapter.state_dict())
    seen = adapter.denom > 0
    # a threshold that makes a tenth of the visible Gaussians candidates, so every cap has work
    beta = float(torch.quantile(adapter.mean_grads()[seen].double(), 0.9))
    base = dict(step=500, grad_threshold=beta, scene_extent=float(scene.extent))

    def densify(state=saved, **kw):
        def run():
            adapter.load_state_dict(state)
            with torch.no_grad():
                adapter.densify(DensifyContext(**base, **kw))
        return run

    load = timed(lambda: adapter.load_state_dict(saved), repeats)
    rows = {"step": step, "stats (5 statistics)": stats_all, "stats (3DGS's 3)": stats_three}
    adapter.load_state_dict(saved)
    grown = DensifyContext(**base)
    with torch.no_grad():
        free_growth = adapter.densify(grown).after - n
    rows["densify, no cap"] = timed(densify(), repeats) - load
    rows[f"densify, cap binds ({max(1, free_growth // 2)} of {free_growth} new)"] = timed(
        densify(max_primitives=n + max(1, free_growth // 2)), repeats) - load
    # the tabletop's rig surrounds it: growth under the cap is inside-first (budget_growth_order "auto");
    # the same call ordered by score alone, the order before 2026-11-28
    by_score = copy.deepcopy(saved)
    by_score["config"]["budget_growth_order"] = "score"
    rows[f"densify, cap binds, by score alone ({max(1, free_growth // 2)} of {free_growth} new)"] = timed(
        densify(by_score, max_primitives=n + max(1, free_growth // 2)), repeats) - load
    rows[f"densify, cap binds, swap 2 % ({max(1, free_growth // 2) + n // 50} new)"] = timed(
        densify(max_primitives=n + max(1, free_growth // 2), swap_share=0.02), repeats) - load
    rows[f"densify, cut to {n // 2}"] = timed(densify(max_primitives=n // 2), repeats) - load
    # the means' step rule (GS3DConfig.means_lr_rule): Adam on every group, then per-row factors
    adapter.load_state_dict(saved)
    gen = torch.Generator().manual_seed(1)
    for p in adapter.params.values():
        p.grad = 1e-6 * torch.randn(p.shape, generator=gen, dtype=p.dtype)
    kept = adapter.config
    for rule in ("extent", "distance", "disparity"):
        adapter.config = dataclasses.replace(kept, means_lr_rule=rule)
        rows[f"optimizer step, means_lr_rule={rule}"] = timed(adapter.optimizer_step, repeats)
    adapter.config = kept
    # the cut of the faintest (MVGSConfig.prune_faint): the step with blend statistics, then the cut
    adapter.load_state_dict(saved)
    adapter.zero_grad()
    adapter.collect_blend_stats()
    trainer.step()
    rows["step, collecting blend statistics"] = timed(trainer.step, repeats)
    adapter._reset_stats()
    for i in range(20):
        adapter.accumulate_stats(rendered(i))
        adapter.zero_grad()
    faint_state = copy.deepcopy(adapter.state_dict())
    cut = dict(base, grad_threshold=math.inf, faint_share=0.01)

    def faint_cut():
        adapter.load_state_dict(faint_state)
        with torch.no_grad():
            return adapter.densify(DensifyContext(**cut))
    removed = faint_cut().extra["faint"]
    rows[f"densify, faint cut 1 % ({removed} removed)"] = timed(faint_cut, repeats) - load
    return rows


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    lines = [f"threads={args.threads}; CPU ms (user + sys), medians of {args.repeats}", "",
             "| Gaussians | call | CPU (ms) | share of a one-view step |", "|---:|---|---:|---:|"]
    for n in args.sizes:
        rows = measure(n, args.repeats)
        for name, ms in rows.items():
            share = "" if name == "step" else f"{ms / rows['step']:.1%}"
            lines.append(f"| {n} | {name} | {ms:.2f} | {share} |")
    text = "\n".join(lines)
    print(text)
    return text


if __name__ == "__main__":
    main()
