"""Probe the default's coarse-to-fine hand-off on one scene (docs/equal_compute_log.md,
"Forward-facing rigs"): where the coarse model stands when it hands over, and two changes that
were tried against the forward-facing loss and not kept.

    # the model after `--stop-work` units of work, evaluated at every level and at full
    # resolution with the coarse level's screen-space dilation
    python benchmarks/probe_handoff.py --data scenes/forward --budget 3000 --stop-work 890
    python benchmarks/probe_handoff.py --data scenes/forward --budget 3000 --stop-work 890 --preset baseline
    # trained to the end with one change
    python benchmarks/probe_handoff.py --data scenes/forward --budget 3000 --flat-beta
    python benchmarks/probe_handoff.py --data scenes/forward --budget 3000 --bake

--flat-beta: every level densifies with β scaled to the finest level's width (the default
raises it on coarse levels). --bake: at each hand-off, every Gaussian is widened by the
screen-space dilation it loses, σ² = eps2d (f_old² − f_new²) / ν², ν its largest focal / depth
over the training views that see it (Mip-Splatting's sampling rate), so its footprint in the
finer pixels matches what the coarser level showed. One process, one thread; prints one line.
"""

from __future__ import annotations

import argparse
import resource
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
from mvgs_plugin.cli import BUNDLED, model_config  # noqa: E402

from mvgs_plugin.adapters.gs3d import GS3DAdapter  # noqa: E402
from mvgs_plugin import MVGS, MVGSConfig  # noqa: E402
from mvgs_plugin.data import load_scene  # noqa: E402
from mvgs_plugin.densify import resolution_threshold  # noqa: E402

EPS2D = 0.3  # the reference renderer's screen-space dilation, px²


@torch.no_grad()
def sampling_rate(means: torch.Tensor, cameras) -> torch.Tensor:
    """[N] largest focal / depth (pixels per world unit) over the cameras whose image holds the
    point; 0 where none does."""
    nu = torch.zeros(len(means), dtype=torch.float64)
    for cam in cameras:
        w2c = cam.world_to_camera
        p = means.double() @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2].clamp_min(1e-9)
        u, v = cam.fx * p[:, 0] / z + cam.cx, cam.fy * p[:, 1] / z + cam.cy
        seen = (p[:, 2] > 1e-2) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        nu = torch.maximum(nu, torch.where(seen, 0.5 * (cam.fx + cam.fy) / z, torch.zeros_like(z)))
    return nu


@torch.no_grad()
def bake(adapter: GS3DAdapter, cameras, f_old: int, f_new: int) -> None:
    """Widen every Gaussian (isotropically, in world units) by the dilation it loses at the hand-off."""
    nu = sampling_rate(adapter.params["means"], cameras)
    var = torch.where(nu > 0, EPS2D * (f_old ** 2 - f_new ** 2) / nu.clamp_min(1e-12) ** 2, torch.zeros_like(nu))
    log_s = adapter.params["scales"]
    log_s.copy_((0.5 * torch.log(torch.exp(2 * log_s.double()) + var[:, None])).to(log_s.dtype))


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=BUNDLED)
    ap.add_argument("--budget", type=float, default=3000)
    ap.add_argument("--preset", choices=["default", "baseline"], default="default")
    ap.add_argument("--stop-work", type=float, default=None, help="stop after this much work and evaluate per level")
    ap.add_argument("--flat-beta", action="store_true")
    ap.add_argument("--bake", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    scene = load_scene(args.data)
    recipe = (MVGSConfig.baseline(grad_threshold_width=800.0, seed=args.seed) if args.preset == "baseline"
              else MVGSConfig.default(seed=args.seed, forward_rig="pyramid"))
    config = recipe.with_budget(args.budget)
    adapter = GS3DAdapter.from_scene(scene, model_config(config, args.seed))
    trainer = MVGS(adapter, scene, config)
    if args.flat_beta:
        finest, cam = min(s.factor for s in config.stages), scene.train_cameras[0]
        width = cam.width if finest == 1 else cam.scaled(finest).width
        trainer.schedule.base_threshold = lambda plan: resolution_threshold(
            config.grad_threshold, width, config.grad_threshold_width)
    stop = args.stop_work if args.stop_work is not None else float("inf")
    before = resource.getrusage(resource.RUSAGE_SELF)
    while trainer.step_count < trainer.total_steps and trainer.schedule.work_done < stop:
        nxt = trainer.schedule.plan.locate(trainer.step_count + 1)
        if args.bake and nxt.first_in_stage and nxt.index > 0:
            bake(adapter, scene.train_cameras, config.stages[nxt.index - 1].factor, nxt.stage.factor)
        trainer.step()
    after = resource.getrusage(resource.RUSAGE_SELF)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    head = (f"{args.data.name} {args.preset}{' flat-beta' if args.flat_beta else ''}{' bake' if args.bake else ''} "
            f"budget {args.budget:g}: step {trainer.step_count}, work {trainer.schedule.work_done:.1f}, "
            f"{adapter.num_primitives()} Gaussians, CPU {cpu:.1f} s")
    if args.stop_work is None:
        r = trainer.evaluate()
        line = f"{head}; test PSNR {r.psnr:.2f} dB, SSIM {r.ssim:.4f}"
    else:
        parts = [f"at 1/{f} {trainer.evaluate(factor=f).psnr:.2f} dB" for f in (4, 2, 1)]
        level = trainer.schedule.plan.locate(max(1, trainer.step_count)).stage.factor
        if level > 1:
            adapter.config.rasterize_kwargs["eps2d"] = EPS2D * level ** 2
            parts.append(f"at 1/1 with the 1/{level} dilation {trainer.evaluate().psnr:.2f} dB")
            del adapter.config.rasterize_kwargs["eps2d"]
        line = f"{head}; test PSNR " + ", ".join(parts)
    print(line)
    return line


if __name__ == "__main__":
    main()
