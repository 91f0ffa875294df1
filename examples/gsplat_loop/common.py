"""What surrounds the training loop of gsplat's examples/simple_trainer.py, ported to the CPU.

The loop itself is in simple_trainer.py (single view, gsplat's DefaultStrategy as installed)
and simple_trainer_mvgs.py (the same loop trained with MVGS). This module holds what both share,
shaped as simple_trainer has it: the Config fields the loop reads, `create_splats_with_optimizers`
(a ParameterDict `splats`, one Adam per parameter, eps 1e-15, means' learning rate times the
scene scale), `rasterize_splats` (our reference_renderer.rasterization, same call shape as
gsplat's; gsplat's own on --device cuda --rasterizer gsplat), a data iterator yielding
gsplat Dataset's dicts, evaluation, and checkpoints that resume exactly.

Kept from simple_trainer: initialisation (SfM points, or a random cube of 3 x scene scale; scales
from the mean distance to the 3 nearest points; quats uniform in [0, 1)^4; opacity 0.1), the
learning rates, the means' exponential decay to 0.01, the SH degree schedule, the loss
(1 - 0.2) L1 + 0.2 (1 - SSIM) with "valid" SSIM (our ssim: fused_ssim is CUDA only), and the
order optimizer step -> scheduler -> strategy.step_post_backward. Left out: pose and appearance
optimisation, bilateral grids, depth loss, the viewer, compression, tensorboard, packed mode.
Changed: backgrounds (the colour a scene's RGBA images were composited on) are passed to the
rasterizer, and the strategy's step-valued fields scale with the run's length with the floors of
MVGSConfig.with_total_steps (densify every >= 10 steps, from >= 50, resets >= 10 intervals
apart), where simple_trainer's --steps_scaler would densify every 3 steps of a 1000-step run.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor

from mvgs_plugin.adapters.gs3d import SH_C0, knn_mean_sq_dist
from mvgs_plugin.adapters.gsplat_strategy import gsplat_batch
from mvgs_plugin.data import load_scene
from mvgs_plugin.io import atomic_write_text, load_checked, save_checked
from mvgs_plugin.metrics import psnr, ssim as ssim_metric
from mvgs_plugin.sampler import ViewSampler

from mvgs_plugin.cli import BUNDLED, check_device, check_out, float_above, int_at_least, rasterize_function  # noqa: E402

@dataclass
class Config:
    """simple_trainer's Config, the fields the ported loop reads (defaults as simple_trainer's,
    for a 30k-step run; adjust_steps() rescales)."""

    data_dir: Path = BUNDLED
    result_dir: Path = Path("out/gsplat_loop")
    preset: str = "default"  # the MVGS loop's recipe (simple_trainer_mvgs.py)
    batch_size: int = 1
    max_steps: int = 30_000
    save_steps: List[int] = field(default_factory=list)
    resume: Optional[Path] = None
    seed: int = 0
    init_num_pts: int = 100_000
    init_extent: float = 3.0
    sh_degree: int = 3
    sh_degree_interval: int = 1000
    init_opa: float = 0.1
    init_scale: float = 1.0
    ssim_lambda: float = 0.2
    near_plane: float = 0.01
    far_plane: float = 1e10
    packed: bool = False
    absgrad: bool = False
    grow_grad2d: float = 2e-4
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100
    means_lr: float = 1.6e-4
    scales_lr: float = 5e-3
    opacities_lr: float = 5e-2
    quats_lr: float = 1e-3
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20
    device: str = "cpu"
    rasterizer: str = "reference"

    def adjust_steps(self, steps: int) -> None:
        """A run of `steps` steps: every step-valued field scaled by steps / max_steps, with the
        floors described in the module docstring."""
        f = steps / self.max_steps
        self.max_steps = steps
        self.sh_degree_interval = max(1, int(self.sh_degree_interval * f))
        self.refine_every = max(min(10, self.refine_every), int(self.refine_every * f))
        self.refine_start_iter = max(min(50, self.refine_start_iter), int(self.refine_start_iter * f))
        self.refine_stop_iter = max(1, int(self.refine_stop_iter * f))
        self.reset_every = max(min(10 * self.refine_every, self.reset_every), int(self.reset_every * f))

    def strategy_kwargs(self) -> Dict:
        """The DefaultStrategy fields simple_trainer's Config sets."""
        return dict(refine_start_iter=self.refine_start_iter, refine_stop_iter=self.refine_stop_iter,
                    reset_every=self.reset_every, refine_every=self.refine_every, absgrad=self.absgrad,
                    grow_grad2d=self.grow_grad2d)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def create_splats_with_optimizers(scene, cfg: Config, scene_scale: float) -> Tuple[torch.nn.ParameterDict, Dict]:
    """simple_trainer's create_splats_with_optimizers for batch size 1 on one process."""
    if scene.points is not None and len(scene.points):
        points, rgbs = scene.points.xyz.clone(), scene.points.rgb.clone()
    else:
        points = cfg.init_extent * scene_scale * (torch.rand((cfg.init_num_pts, 3)) * 2 - 1)
        rgbs = torch.rand((cfg.init_num_pts, 3))
    dist_avg = torch.sqrt(knn_mean_sq_dist(points, k=3)).float().clamp_min(1e-7)
    scales = torch.log(dist_avg * cfg.init_scale).unsqueeze(-1).repeat(1, 3)
    n = points.shape[0]
    quats = torch.rand((n, 4))
    opacities = torch.logit(torch.full((n,), cfg.init_opa))
    colors = torch.zeros((n, (cfg.sh_degree + 1) ** 2, 3))
    colors[:, 0, :] = rgb_to_sh(rgbs)
    params = [
        ("means", points, cfg.means_lr * scene_scale), ("scales", scales, cfg.scales_lr),
        ("quats", quats, cfg.quats_lr), ("opacities", opacities, cfg.opacities_lr),
        ("sh0", colors[:, :1, :], cfg.sh0_lr), ("shN", colors[:, 1:, :], cfg.shN_lr),
    ]
    splats = torch.nn.ParameterDict({name: torch.nn.Parameter(v) for name, v, _ in params}).to(cfg.device)
    optimizers = {name: torch.optim.Adam([{"params": splats[name], "lr": lr, "name": name}], eps=1e-15,
                                         betas=(0.9, 0.999))
                  for name, _, lr in params}
    return splats, optimizers


def rasterize_splats(splats, cfg: Config, camtoworlds: Tensor, Ks: Tensor, width: int, height: int,
                     **kwargs) -> Tuple[Tensor, Tensor, Dict]:
    """simple_trainer's Runner.rasterize_splats without appearance modelling."""
    rasterization = rasterize_function(cfg)
    colors = torch.cat([splats["sh0"], splats["shN"]], 1)
    return rasterization(
        means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
        opacities=torch.sigmoid(splats["opacities"]), colors=colors, viewmats=torch.linalg.inv(camtoworlds),
        Ks=Ks, width=width, height=height, packed=cfg.packed, absgrad=cfg.absgrad, sparse_grad=False,
        rasterize_mode="classic", distributed=False, camera_model="pinhole", near_plane=cfg.near_plane,
        far_plane=cfg.far_plane, **kwargs)


class TrainBatches:
    """The single-view loop's data: an endless shuffled pass over the training views (a new
    permutation per epoch, as a DataLoader with shuffle=True), `batch_size` views per item, as
    gsplat Dataset dicts (camtoworld, K, image in 0..255, image_id, background). Resumable."""

    def __init__(self, scene, batch_size: int = 1, seed: int = 0):
        self.scene = scene
        self.batch_size = batch_size
        self.sampler = ViewSampler(len(scene.train_cameras), seed=seed)
        bg = scene.background if scene.background is not None else (0.0, 0.0, 0.0)
        self.background = torch.tensor(bg, dtype=torch.float32)

    def __iter__(self):
        return self

    def __next__(self) -> Dict[str, Tensor]:
        ids = self.sampler.sample(min(self.batch_size, len(self.scene.train_cameras)))
        cams = [self.scene.train_cameras[i] for i in ids]
        return gsplat_batch(cams, torch.stack([self.scene.image(c) for c in cams]), ids,
                            self.background.expand(len(ids), 3))

    def state_dict(self) -> Dict:
        return {"sampler": self.sampler.state_dict()}

    def load_state_dict(self, state: Dict) -> None:
        self.sampler.load_state_dict(state["sampler"])


def save_checkpoint(path: Path, step: int, splats, optimizers, schedulers, strategy_state, loader) -> None:
    """Everything a resumed run needs to continue as if never stopped (atomic, checksummed, and
    loadable without running pickled code): the next step, parameters, optimizer and scheduler
    states, the strategy's running statistics, the data iterator's position, the RNG."""
    save_checked({
        "step": step + 1, "splats": {k: v.detach().cpu() for k, v in splats.items()},
        "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "schedulers": [s.state_dict() for s in schedulers], "strategy_state": dict(strategy_state),
        "loader": loader.state_dict(), "rng": torch.get_rng_state(),
    }, str(path))


def load_checkpoint(path: Path, splats, optimizers, schedulers, strategy_state, loader) -> int:
    """Restore a save_checkpoint() file into the run's objects; returns the step to start at."""
    ckpt = load_checked(str(path))
    if set(ckpt["splats"]) != set(splats.keys()):
        raise ValueError(f"{path}: parameters {sorted(ckpt['splats'])}, this run has {sorted(splats.keys())}")
    for name, value in ckpt["splats"].items():
        splats[name] = torch.nn.Parameter(value.to(splats[name].device))
        optimizers[name].param_groups[0]["params"] = [splats[name]]
        optimizers[name].load_state_dict(ckpt["optimizers"][name])
    for s, st in zip(schedulers, ckpt["schedulers"]):
        s.load_state_dict(st)
    strategy_state.update({k: v.to(splats["means"].device) if isinstance(v, Tensor) else v
                           for k, v in ckpt["strategy_state"].items()})
    loader.load_state_dict(ckpt["loader"])
    torch.set_rng_state(ckpt["rng"])
    return int(ckpt["step"])


@torch.no_grad()
def evaluate(splats, cfg: Config, scene) -> Dict:
    """Mean PSNR and SSIM over the test views at full resolution (train views when the scene
    has no test split), at the full SH degree."""
    cams = scene.test_cameras or scene.train_cameras
    rows = []
    bg = scene.background if scene.background is not None else (0.0, 0.0, 0.0)
    for cam in cams:
        c2w = torch.linalg.inv(cam.world_to_camera).float()[None].to(cfg.device)
        img, _, _ = rasterize_splats(splats, cfg, c2w, cam.K.float()[None].to(cfg.device), cam.width, cam.height,
                                     sh_degree=cfg.sh_degree,
                                     backgrounds=torch.tensor([bg], dtype=torch.float32, device=cfg.device))
        out, gt = img[0].clamp(0, 1).cpu(), scene.image(cam)
        rows.append({"name": cam.name, "psnr": psnr(out, gt), "ssim": ssim_metric(out, gt)})
    return {"psnr": sum(r["psnr"] for r in rows) / len(rows), "ssim": sum(r["ssim"] for r in rows) / len(rows),
            "per_view": rows}


def parse_config(argv=None, doc: str = "") -> Config:
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=BUNDLED, help="scene folder (default: the bundled tabletop scene)")
    ap.add_argument("--steps", type=int_at_least(2), default=1000, help="training steps (default: %(default)s)")
    ap.add_argument("--preset", choices=["default", "multiview", "paper", "baseline"], default="default",
                    help="MVGS recipe of simple_trainer_mvgs.py (default: %(default)s)")
    ap.add_argument("--out", type=Path, default=Path("out/gsplat_loop"), help="output folder (default: %(default)s)")
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="seed (default: %(default)s)")
    ap.add_argument("--grow-grad2d", type=float_above(0.0), default=2e-4,
                    help="DefaultStrategy.grow_grad2d, the densification threshold (default: %(default)s, gsplat's)")
    ap.add_argument("--save-steps", type=int_at_least(1), nargs="*", default=[],
                    help="write OUT/ckpt_<step>.pt after these steps (1-based; default: none)")
    ap.add_argument("--resume", type=Path, default=None, help="continue from a checkpoint this script wrote (default: start fresh)")
    ap.add_argument("--threads", type=int_at_least(1), default=None, help="torch threads (default: torch's)")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="where to train (default: %(default)s)")
    ap.add_argument("--rasterizer", choices=["reference", "gsplat"], default="reference",
                    help="reference (CPU) or gsplat (CUDA) rasterization (default: %(default)s)")
    args = ap.parse_args(argv)
    try:
        check_out(args.out)
        check_device(args)
    except ValueError as err:
        ap.error(str(err))
    if args.resume is not None and not args.resume.is_file():
        ap.error(f"--resume {args.resume}: no such checkpoint file")
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = Config(data_dir=args.data, result_dir=args.out, preset=args.preset, save_steps=args.save_steps,
                 resume=args.resume, seed=args.seed, device=args.device, rasterizer=args.rasterizer,
                 grow_grad2d=args.grow_grad2d)
    cfg.adjust_steps(args.steps)
    return cfg


def run(train, cfg: Config) -> Dict:
    """Train with `train(cfg, scene)` (returns the splats and the strategy), evaluate, write
    OUT/metrics.json: psnr, ssim, num_gaussians, steps, work (full-resolution view renders),
    cpu_seconds (user + sys), train_seconds (wall), strategy, preset, per view."""
    torch.manual_seed(cfg.seed)
    scene = load_scene(cfg.data_dir)
    cfg.result_dir.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    splats, strategy = train(cfg, scene)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    mvgs = getattr(strategy, "config", None)
    extra = {"strategy": type(strategy).__name__, "preset": mvgs.preset if mvgs else "single view",
             "work": strategy.schedule.work_done if mvgs else float(cfg.max_steps)}
    result = evaluate(splats, cfg, scene)
    metrics = {"psnr": result["psnr"], "ssim": result["ssim"], "num_gaussians": len(splats["means"]),
               "steps": cfg.max_steps, "cpu_seconds": cpu, "train_seconds": wall,
               "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
               "threads": torch.get_num_threads(), "data": str(cfg.data_dir), **extra,
               "per_view": result["per_view"]}
    atomic_write_text(cfg.result_dir / "metrics.json", json.dumps(metrics, indent=1))
    print(f"PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.3f}  {metrics['num_gaussians']} Gaussians  "
          f"{cfg.max_steps} steps  {cpu:.1f} s CPU ({wall:.1f} s wall)")
    return metrics


__all__ = ["Config", "create_splats_with_optimizers", "rasterize_splats", "TrainBatches", "save_checkpoint",
           "load_checkpoint", "evaluate", "parse_config", "run"]
