"""What surrounds the training loop of gsplat's examples/simple_trainer.py, ported to the CPU.

The loop itself (the Runner's __init__ and train) is in simple_trainer.py, shaped as gsplat
1.5.3's: a Parser and a Dataset, a DataLoader (shuffle, workers), `splats` as a ParameterDict
with one Adam per parameter, `cfg.strategy` a DefaultStrategy checked with isinstance, the
order backward -> optimizer step -> scheduler -> strategy.step_post_backward.
simple_trainer_mvgs.py is that file with four lines added (MVGS); simple_trainer_chunked.py
renders each step's views in chunks. This module holds what they share: the Config fields the
loop reads, a Parser / Dataset with gsplat's attributes and item dicts on the package's scene
reader, `create_splats_with_optimizers`, `rasterize_splats`, evaluation, and checkpoints that
resume exactly (gsplat's own trainer has none: ours save the data position too).

Kept from simple_trainer: initialisation (SfM points, or a random cube of 3 x scene scale; scales
from the mean distance to the 3 nearest points; quats uniform in [0, 1)^4; opacity 0.1), the
learning rates, the means' exponential decay to 0.01, the SH degree schedule, the loss
(1 - 0.2) L1 + 0.2 (1 - SSIM) with "valid" SSIM (our ssim: fused_ssim is CUDA only). Left out:
pose and appearance optimisation, bilateral grids, depth loss, the viewer, compression,
tensorboard, packed mode. Changed: the rasterizer is given the colour a scene's RGBA images were
composited on (Parser.background), and the strategy's step-valued fields scale with the run's
length with the floors of MVGSConfig.with_total_steps (densify every >= 10 steps, from >= 50,
resets >= 10 intervals apart), where simple_trainer's --steps_scaler would densify every 3
steps of a 1000-step run. Optional, off by default: train_3dgs.py's far-background rules
(--background-points N: a shell of points round the rig, read by the Parser; --world-size-rule
distance and --opacity-reset-scope inside: MVGSStrategy's options, through Config.mvgs_rules).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from gsplat.strategy import DefaultStrategy

from mvgs_plugin.adapters.gs3d import OPACITY_RESET_SCOPES, SH_C0, WORLD_SIZE_RULES, knn_mean_sq_dist
from mvgs_plugin.adapters.gsplat_strategy import MVGSLoader
from mvgs_plugin.cli import (BUNDLED, MAX_INIT_POINTS, MAX_STEPS, budget_scope_args, check_device, check_out,
                             float_above, int_at_least, out_folder, rasterize_function)
from mvgs_plugin.config import MAX_PRIMITIVES, MAX_SEED, PRESETS, MVGSConfig
from mvgs_plugin.data import load_scene
from mvgs_plugin.io import atomic_write_text, load_checked, save_checked
from mvgs_plugin.metrics import masked_psnr, psnr, ssim as ssim_metric


@dataclass
class Config:
    """simple_trainer's Config, the fields the ported loop reads (defaults as simple_trainer's,
    for a 30k-step run; adjust_steps() rescales)."""

    data_dir: Path = BUNDLED
    data_factor: int = 1  # a COLMAP scene's images_<factor>/ (gsplat's data_factor)
    result_dir: Path = Path("out/gsplat_loop")
    mvgs_preset: Any = "default"  # the MVGS recipe: a preset name or an MVGSConfig (the chunked loop passes one)
    batch_size: int = 1
    num_workers: int = 0  # gsplat's trainer uses 4 (a GPU machine); here the CPU trains
    chunk_size: Optional[int] = None  # views per render call of simple_trainer_chunked.py (None: the memory bound)
    mvgs_flags: Tuple[str, ...] = ()  # the MVGS-only flags the command line gave (run() refuses them where unread)
    background_points: int = 0  # our port: a shell of N more initial points for the far background (Parser)
    world_size_rule: str = "extent"  # MVGSStrategy's size prune: gsplat's ("extent") or "distance"
    opacity_reset_scope: str = "all"  # MVGSStrategy's resets: gsplat's ("all") or "inside" (the far background spared)
    prune_faint: Optional[float] = None  # MVGSStrategy's cut of the faintest Gaussians (MVGSConfig.prune_faint)
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
    strategy: Any = None  # a DefaultStrategy, built by make_strategy() from the fields above

    @property
    def mvgs_rules(self) -> Dict[str, str]:
        """The size-prune, reset and faint-cut rules MVGSStrategy is built with (its keyword arguments)."""
        return {"world_size_rule": self.world_size_rule, "opacity_reset_scope": self.opacity_reset_scope,
                "prune_faint": self.prune_faint}

    def adjust_steps(self, steps: int) -> None:
        """A run of `steps` steps: every step-valued field scaled by steps / max_steps, with the
        floors described in the module docstring; the strategy is rebuilt from them."""
        f = steps / self.max_steps
        self.max_steps = steps
        self.sh_degree_interval = max(1, int(self.sh_degree_interval * f))
        self.refine_every = max(min(10, self.refine_every), int(self.refine_every * f))
        self.refine_start_iter = max(min(50, self.refine_start_iter), int(self.refine_start_iter * f))
        self.refine_stop_iter = max(1, int(self.refine_stop_iter * f))
        self.reset_every = max(min(10 * self.refine_every, self.reset_every), int(self.reset_every * f))
        self.make_strategy()

    def make_strategy(self, kind=DefaultStrategy) -> None:
        self.strategy = kind(refine_start_iter=self.refine_start_iter, refine_stop_iter=self.refine_stop_iter,
                             reset_every=self.reset_every, refine_every=self.refine_every,
                             grow_grad2d=self.grow_grad2d)


class Parser:
    """A scene folder read as gsplat's Parser exposes it: camtoworlds [N, 4, 4], camera_ids,
    Ks_dict / imsize_dict per camera id, image_names, points [P, 3] and points_rgb [P, 3]
    (uint8), scene_scale (the largest camera distance from their mean), plus background (the
    colour RGBA images were composited on, or None). Every `test_every`-th image is held out
    unless the scene names its test views. Built on mvgs_plugin.data.load_scene; our port's
    `background_points` (default 0: the scene's points only, as gsplat's) adds that many points on
    a sphere twice the rig's radius when the cameras surround the scene, as load_scene draws them
    (examples/train_3dgs.py adds 2000)."""

    def __init__(self, data_dir, factor: int = 1, normalize: bool = False, test_every: int = 8,
                 background_points: int = 0):
        if normalize:
            raise ValueError("this port reads scenes in their own coordinates (no normalize)")
        # gsplat's factor: a COLMAP scene's images_<factor>/ copies, each camera scaled to them
        self.scene = scene = load_scene(data_dir, images=None if factor == 1 else f"images_{factor}",
                                        background_points=background_points)
        cams = scene.train_cameras + scene.test_cameras
        self.n_train = len(scene.train_cameras)
        self.camtoworlds = np.stack([c.camera_to_world.numpy() for c in cams])
        self.camera_ids = list(range(len(cams)))
        self.Ks_dict = {i: c.K.numpy().astype(np.float32) for i, c in enumerate(cams)}
        self.imsize_dict = {i: (c.width, c.height) for i, c in enumerate(cams)}
        self.image_names = [c.name for c in cams]
        self.cameras = cams
        pts = scene.points
        self.points = None if pts is None else pts.xyz.numpy()
        self.points_rgb = None if pts is None else (pts.rgb.numpy() * 255).round().astype(np.uint8)
        centers = self.camtoworlds[:, :3, 3]
        self.scene_scale = float(np.linalg.norm(centers - centers.mean(0), axis=1).max())
        self.background = scene.background
        self.test_every = test_every

    def split(self, split: str) -> np.ndarray:
        n = len(self.camtoworlds)
        if self.n_train < n:  # the scene names its test views
            return np.arange(self.n_train) if split == "train" else np.arange(self.n_train, n)
        ids = np.arange(n)
        return ids[ids % self.test_every != 0] if split == "train" else ids[ids % self.test_every == 0]


class Dataset(torch.utils.data.Dataset):
    """gsplat's Dataset: item i of the split is a dict K [3, 3], camtoworld [4, 4], image
    [H, W, 3] float in 0..255, image_id i (the item's index in this split), and, in a scene with
    masks (mvgs_plugin's Scene.mask), mask [H, W] bool (True: the pixel counts), as gsplat's items
    carry one."""

    def __init__(self, parser: Parser, split: str = "train"):
        self.parser = parser
        self.split = split
        self.indices = parser.split(split)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, item: int) -> Dict[str, Tensor]:
        index = int(self.indices[item])
        cam = self.parser.cameras[index]
        out = {
            "K": torch.from_numpy(self.parser.Ks_dict[self.parser.camera_ids[index]]).float(),
            "camtoworld": torch.from_numpy(self.parser.camtoworlds[index]).float(),
            "image": self.parser.scene.image(cam) * 255.0,
            "image_id": item,
        }
        mask = self.parser.scene.mask(cam)
        if mask is not None:
            out["mask"] = mask[..., 0] >= 0.5
        return out


def rgb_to_sh(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def create_splats_with_optimizers(parser: Parser, cfg: Config, scene_scale: float
                                  ) -> Tuple[torch.nn.ParameterDict, Dict]:
    """simple_trainer's create_splats_with_optimizers for batch size 1 on one process."""
    if parser.points is not None and len(parser.points):
        points = torch.tensor(parser.points, dtype=torch.float32)  # a copy: Adam updates it in place
        rgbs = torch.tensor(parser.points_rgb / 255.0, dtype=torch.float32)
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


def rasterize_splats(splats, cfg: Config, background, camtoworlds: Tensor, Ks: Tensor, width: int, height: int,
                     **kwargs) -> Tuple[Tensor, Tensor, Dict]:
    """simple_trainer's Runner.rasterize_splats without appearance modelling, behind the scene's
    background colour (None: black, as gsplat)."""
    rasterization = rasterize_function(cfg)
    colors = torch.cat([splats["sh0"], splats["shN"]], 1)
    if background is not None and "backgrounds" not in kwargs:
        kwargs["backgrounds"] = torch.tensor(background, dtype=torch.float32,
                                             device=camtoworlds.device).expand(len(camtoworlds), 3)
    absgrad = cfg.strategy.absgrad if isinstance(cfg.strategy, DefaultStrategy) else False
    kwargs.update(getattr(cfg.strategy, "rasterize_kwargs", {}))  # MVGSStrategy's blend statistics, when it cuts
    return rasterization(
        means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
        opacities=torch.sigmoid(splats["opacities"]), colors=colors, viewmats=torch.linalg.inv(camtoworlds),
        Ks=Ks, width=width, height=height, packed=cfg.packed, absgrad=absgrad, sparse_grad=False,
        rasterize_mode="classic", distributed=False, camera_model="pinhole", **kwargs)


class DataPosition:
    """Where the loop is in its data, so a resumed run draws what the uninterrupted one would:
    for a shuffled DataLoader, the state of its generator when the current pass began and the
    batches taken since; for MVGSStrategy's loader, the strategy's state (schedule position and
    any refine deferred to the next batch)."""

    def __init__(self, generator: torch.Generator):
        self.generator = generator
        self.pass_start = generator.get_state()
        self.taken = 0

    def iterate(self, loader):
        """iter(loader), counted."""
        self.pass_start, self.taken = self.generator.get_state(), 0
        return _Counted(iter(loader), self)

    def state_dict(self, loader) -> Dict[str, Any]:
        if isinstance(loader, MVGSLoader):
            return {"mvgs": loader.strategy.state_dict()}
        return {"generator": self.pass_start, "taken": self.taken}

    def resume(self, loader, state: Dict[str, Any], splats, optimizers, strategy_state):
        """An iterator over `loader` positioned where `state` was taken (ResumeRefused when the
        strategy refuses the checkpoint's schedule)."""
        if isinstance(loader, MVGSLoader):
            try:
                loader.strategy.load_state_dict(state["mvgs"], splats, optimizers, strategy_state)
            except ValueError as err:  # another run's config or plan
                raise ResumeRefused(str(err)) from err
            return self.iterate(loader)
        self.generator.set_state(state["generator"])
        it = self.iterate(loader)
        for _ in range(state["taken"]):
            next(it)
        return it


class _Counted:
    def __init__(self, it, position: DataPosition):
        self.it, self.position = it, position

    def __iter__(self):
        return self

    def __next__(self):
        item = next(self.it)
        self.position.taken += 1
        return item


# The command's settings a checkpoint must share with the command that resumes it, beyond what
# the parameters and the strategy's state already pin down (run() sets them; the trainers call
# save_checkpoint / load_checkpoint with gsplat's arguments only, so the patch stays small).
_RUN_SETTINGS: Dict[str, Any] = {}
_CHECKPOINT_KEYS = ("step", "splats", "optimizers", "schedulers", "strategy_state", "data", "rng")


def save_checkpoint(path: Path, step: int, splats, optimizers, schedulers, strategy_state, data_state) -> None:
    """Everything a resumed run needs to continue as if never stopped (atomic, checksummed, and
    loadable without running pickled code): the next step, parameters, optimizer and scheduler
    states, the strategy's running statistics, the data position, the RNG, and the settings of
    the command (its seed)."""
    save_checked({
        "step": step + 1, "splats": {k: v.detach().cpu() for k, v in splats.items()},
        "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "schedulers": [s.state_dict() for s in schedulers], "strategy_state": dict(strategy_state),
        "data": data_state, "rng": torch.get_rng_state(), "settings": dict(_RUN_SETTINGS),
        # gsplat's split draws on the model's device: on CUDA its generators are part of the run
        "rng_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }, str(path))


class ResumeRefused(ValueError):
    """A checkpoint this run cannot continue (another run's parameters or schedule): run() ends
    the process with one line naming --resume and exit code 2, as argparse's errors."""


def load_checkpoint(path: Path, splats, optimizers, schedulers, strategy_state) -> Tuple[int, Dict]:
    """Restore a save_checkpoint() file into the run's objects; returns the step to start at and
    the data position (for DataPosition.resume)."""
    try:
        ckpt = load_checked(str(path))
    except (ValueError, RuntimeError, OSError) as err:  # damaged, foreign or unsafe file
        said = str(err).splitlines()[0] if str(err) else ""
        raise ResumeRefused(f"not a checkpoint this loop wrote, or damaged ({type(err).__name__}: {said})") from err
    missing = [k for k in _CHECKPOINT_KEYS if not (isinstance(ckpt, dict) and k in ckpt)]
    if missing:  # e.g. examples/train_3dgs.py's checkpoint: a controller's state, not this loop's
        held = sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ResumeRefused(f"not a checkpoint of this loop: it has no {missing} (it holds {held}); resume with a "
                            "ckpt_<step>.pt this script wrote")
    saved = ckpt.get("settings", {})  # none in a checkpoint of a version that did not save them
    differ = [f"--{k} {saved[k]} (this command: {v})" for k, v in _RUN_SETTINGS.items() if k in saved and saved[k] != v]
    if differ:
        raise ResumeRefused(f"the checkpoint was made with {', '.join(differ)}; resume with the flags it was "
                            "written with")
    if set(ckpt["splats"]) != set(splats.keys()):
        raise ResumeRefused(f"parameters {sorted(ckpt['splats'])}, this run has {sorted(splats.keys())}")
    for name, value in ckpt["splats"].items():
        splats[name] = torch.nn.Parameter(value.to(splats[name].device))
        optimizers[name].param_groups[0]["params"] = [splats[name]]
        optimizers[name].load_state_dict(ckpt["optimizers"][name])
    for s, st in zip(schedulers, ckpt["schedulers"]):
        s.load_state_dict(st)
    strategy_state.update({k: v.to(splats["means"].device) if isinstance(v, Tensor) else v
                           for k, v in ckpt["strategy_state"].items()})
    torch.set_rng_state(ckpt["rng"])
    cuda_states = ckpt.get("rng_cuda") or []  # none in a CPU run's checkpoint, or one of an earlier version
    if cuda_states and torch.cuda.is_available() and len(cuda_states) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda_states)
    return int(ckpt["step"]), ckpt["data"]


@torch.no_grad()
def evaluate(splats, cfg: Config, parser: Parser) -> Dict:
    """Mean PSNR and SSIM over the val split at full resolution, at the full SH degree (a view
    with a mask: the PSNR of the pixels it keeps, the SSIM of both images blacked out alike, as
    mvgs_plugin's controller reports them)."""
    valset = Dataset(parser, split="val")
    if len(valset) == 0:
        valset = Dataset(parser, split="train")
    rows = []
    for i in range(len(valset)):
        data = valset[i]
        pixels = data["image"] / 255.0
        img, _, _ = rasterize_splats(splats, cfg, parser.background, data["camtoworld"][None].to(cfg.device),
                                     data["K"][None].to(cfg.device), pixels.shape[1], pixels.shape[0],
                                     sh_degree=cfg.sh_degree, near_plane=cfg.near_plane, far_plane=cfg.far_plane)
        out = img[0].clamp(0, 1).cpu()
        name = parser.image_names[int(valset.indices[i])]
        if "mask" in data:
            keep = data["mask"][..., None].float()
            rows.append({"name": name, "psnr": masked_psnr(out, pixels, keep),
                         "ssim": ssim_metric(out * keep, pixels * keep)})
        else:
            rows.append({"name": name, "psnr": psnr(out, pixels), "ssim": ssim_metric(out, pixels)})
    return {"psnr": sum(r["psnr"] for r in rows) / len(rows), "ssim": sum(r["ssim"] for r in rows) / len(rows),
            "per_view": rows}


def parse_config(argv=None, doc: str = "") -> Config:
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=BUNDLED, help="scene folder (default: the bundled tabletop scene)")
    ap.add_argument("--data-factor", type=int_at_least(1), default=1,
                    help="gsplat's data_factor: a COLMAP scene's images_<factor>/ folder, the cameras scaled to it "
                         "(default: %(default)s, the full-size images)")
    ap.add_argument("--steps", type=int_at_least(2, MAX_STEPS), default=1000, help="training steps (default: %(default)s)")
    ap.add_argument("--preset", choices=PRESETS, default=None,
                    help="MVGS recipe of simple_trainer_mvgs.py / simple_trainer_chunked.py (default: default)")
    ap.add_argument("--out", type=out_folder, default=Path("out/gsplat_loop"), help="output folder (default: %(default)s)")
    ap.add_argument("--seed", type=int_at_least(0, MAX_SEED), default=0, help="seed (default: %(default)s)")
    ap.add_argument("--grow-grad2d", type=float_above(0.0), default=2e-4,
                    help="DefaultStrategy.grow_grad2d, the densification threshold; the MVGS loops' width-scaled presets "
                         "read it as meant for 800-px images, x 800 / W at W-px views (docs/gsplat_loop.md; default: "
                         "%(default)s, gsplat's)")
    ap.add_argument("--save-steps", type=int_at_least(1), nargs="*", default=[],
                    help="write OUT/ckpt_<step>.pt after these steps (1-based; default: none)")
    ap.add_argument("--resume", type=Path, default=None, help="continue from a checkpoint this script wrote (default: start fresh)")
    ap.add_argument("--workers", type=int_at_least(0), default=0,
                    help="DataLoader workers (default: %(default)s; gsplat's trainer uses 4)")
    ap.add_argument("--chunk-size", type=int_at_least(1), default=None,
                    help="views per render call in simple_trainer_chunked.py (default: what chunk_memory_mb allows)")
    ap.add_argument("--max-gaussians", type=int_at_least(1, MAX_PRIMITIVES), default=None,
                    help="budget of Gaussians of the MVGS loops (MVGSConfig.max_gaussians): the model is cut to it at "
                         "check_sanity and never holds more; growth follows its schedule (default: no budget)")
    ap.add_argument("--pixels-per-gaussian", type=float_above(0), default=None, metavar="P",
                    help="budget from the data (MVGSConfig.pixels_per_gaussian): --max-gaussians = the training "
                         "views' pixels / P (ignored with --max-gaussians; default: no budget)")
    budget_scope_args(ap)
    ap.add_argument("--background-points", type=int_at_least(0, MAX_INIT_POINTS), default=0, metavar="N",
                    help="our port: N more initial points on a sphere twice the rig's radius for the far background, as "
                         "train_3dgs.py adds (2000 there), when the cameras surround the scene (none on a forward-facing "
                         "rig); 0: the scene's points only, as gsplat's Parser (default: 0)")
    ap.add_argument("--world-size-rule", choices=WORLD_SIZE_RULES, default=None,
                    help="MVGSStrategy's size prune (MVGS loops): extent is gsplat's (a world scale above prune_scale3d x "
                         "scene_scale everywhere, which prunes the background shell); distance is train_3dgs.py's "
                         "(x the distance from the rig's centre beyond scene_scale) (default: extent)")
    ap.add_argument("--opacity-reset-scope", choices=OPACITY_RESET_SCOPES, default=None,
                    help="which opacities MVGSStrategy's resets cap (MVGS loops): all is gsplat's; inside is "
                         "train_3dgs.py's, the far background (beyond 3/4 of the initial points' farthest distance from "
                         "the rig's centre) kept as it is (default: all)")
    ap.add_argument("--prune-faint", type=float_above(0, inclusive=True, high=0.99), default=None, metavar="S",
                    help="MVGSStrategy's cut of the faintest Gaussians (MVGS loops, the reference renderer): once the "
                         "refine window has closed, remove those with the least blend weight per blended pixel that "
                         "carry S of all the weight (MVGSConfig.prune_faint) (default: 0, off)")
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
    beyond = sorted(k for k in set(args.save_steps) if k > args.steps)
    if beyond:  # they would never be written
        ap.error(f"--save-steps {' '.join(map(str, beyond))}: beyond the run's --steps {args.steps} (checkpoints are "
                 "written after steps 1..N)")
    if args.resume is not None and not args.resume.is_file():
        ap.error(f"--resume {args.resume}: no such checkpoint file")
    if args.threads:
        torch.set_num_threads(args.threads)
    given = tuple(flag for flag, value in (("--preset", args.preset), ("--max-gaussians", args.max_gaussians),
                                           ("--pixels-per-gaussian", args.pixels_per_gaussian),
                                           ("--budget-views", args.budget_views), ("--budget-rigs", args.budget_rigs),
                                           ("--chunk-size", args.chunk_size),
                                           ("--world-size-rule", args.world_size_rule),
                                           ("--opacity-reset-scope", args.opacity_reset_scope),
                                           ("--prune-faint", args.prune_faint)) if value is not None)
    args.preset = args.preset or "default"
    budget = {k: v for k, v in (("max_gaussians", args.max_gaussians),
                                ("pixels_per_gaussian", args.pixels_per_gaussian),
                                ("budget_rigs", args.budget_rigs)) if v is not None}
    if args.budget_views is not None:  # 0: every training view
        budget["budget_views"] = args.budget_views or None
    preset = MVGSConfig.from_preset(args.preset, **budget) if budget else args.preset
    cfg = Config(data_dir=args.data, data_factor=args.data_factor, result_dir=args.out, mvgs_preset=preset, save_steps=args.save_steps,
                 resume=args.resume, seed=args.seed, device=args.device, rasterizer=args.rasterizer,
                 grow_grad2d=args.grow_grad2d, num_workers=args.workers, chunk_size=args.chunk_size,
                 mvgs_flags=given, background_points=args.background_points,
                 world_size_rule=args.world_size_rule or "extent", opacity_reset_scope=args.opacity_reset_scope or "all",
                 prune_faint=args.prune_faint)
    cfg.adjust_steps(args.steps)
    return cfg


def unread_flags(runner, cfg: Config) -> List[str]:
    """The MVGS-only flags of cfg.mvgs_flags that `runner` does not read: all of them where its
    strategy is not MVGS (gsplat's single-view loop), --chunk-size where its MVGS config did not
    take the chunk size (only the chunked loop passes it on)."""
    mvgs = getattr(runner.cfg.strategy, "config", None)
    if mvgs is None:
        return list(cfg.mvgs_flags)
    return [f for f in cfg.mvgs_flags if f == "--chunk-size" and mvgs.chunk_size != cfg.chunk_size]


def run(runner_class, cfg: Config) -> Dict:
    """Train with `runner_class(cfg).train()`, evaluate, write OUT/metrics.json: psnr, ssim,
    num_gaussians, steps, work (full-resolution view renders), cpu_seconds (user + sys),
    train_seconds (wall; on CUDA after a synchronize, the GPU's clock), gpu_peak_memory_mb,
    strategy, preset, per view."""
    torch.manual_seed(cfg.seed)
    _RUN_SETTINGS.clear()
    _RUN_SETTINGS.update(seed=cfg.seed, background_points=cfg.background_points)
    made = not cfg.result_dir.exists()
    cfg.result_dir.mkdir(parents=True, exist_ok=True)
    try:
        runner = runner_class(cfg)
    except (ValueError, OSError) as err:  # the scene folder's content (--data, --data-factor): a usage error
        if made and not any(cfg.result_dir.iterdir()):
            cfg.result_dir.rmdir()
        flag = f"--data-factor {cfg.data_factor}" if f"images_{cfg.data_factor}" in str(err) else f"--data {cfg.data_dir}"
        print(f"{Path(sys.argv[0]).name}: error: {flag}: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    unread = unread_flags(runner, cfg)
    if unread:  # a flag this loop does not read would change nothing, without a word
        if made and not any(cfg.result_dir.iterdir()):
            cfg.result_dir.rmdir()
        script = Path(sys.argv[0]).name
        print(f"{script}: error: {' '.join(unread)}: not read by this loop ({script}, "
              f"{type(runner.cfg.strategy).__name__}); --preset, --max-gaussians, --pixels-per-gaussian, "
              "--budget-views, --budget-rigs, --world-size-rule, --opacity-reset-scope and --prune-faint are read by "
              "simple_trainer_mvgs.py and simple_trainer_chunked.py, "
              "--chunk-size by "
              "simple_trainer_chunked.py", file=sys.stderr)
        raise SystemExit(2)
    cuda = str(cfg.device).startswith("cuda")
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        runner.train()
    except ResumeRefused as err:
        if made and not any(cfg.result_dir.iterdir()):  # a refused run leaves nothing behind
            cfg.result_dir.rmdir()
        print(f"{Path(sys.argv[0]).name}: error: --resume {cfg.resume}: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    if cuda:
        torch.cuda.synchronize()  # kernels still queued belong to the training time
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    strategy = runner.cfg.strategy
    mvgs = getattr(strategy, "config", None)
    extra = {"strategy": type(strategy).__name__, "preset": mvgs.preset if mvgs else "single view",
             "work": strategy.schedule.work_done if mvgs else float(cfg.max_steps),
             "grow_grad2d": cfg.grow_grad2d, "background_points": cfg.background_points, "initial_points": 0 if runner.parser.points is None else len(runner.parser.points)}
    if mvgs:  # the strategy's size and reset rules, and what they did
        extra.update(world_size_rule=strategy.world_size_rule, opacity_reset_scope=strategy.opacity_reset_scope,
                     kept_by_distance=strategy.kept_by_distance, spared_by_reset=strategy.spared_by_reset,
                     max_gaussians=mvgs.max_gaussians, most_held=strategy.most_held,
                     prune_faint=mvgs.prune_faint, faint_removed=strategy.faint_removed)
    result = evaluate(runner.splats, cfg, runner.parser)
    metrics = {"psnr": result["psnr"], "ssim": result["ssim"], "num_gaussians": len(runner.splats["means"]),
               "steps": cfg.max_steps, "seed": cfg.seed, "cpu_seconds": cpu, "train_seconds": wall,
               "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
               "threads": torch.get_num_threads(), "data": str(cfg.data_dir), "device": str(cfg.device),
               "gpu_peak_memory_mb": torch.cuda.max_memory_allocated() / 2**20 if cuda else None, **extra,
               "per_view": result["per_view"]}
    atomic_write_text(cfg.result_dir / "metrics.json", json.dumps(metrics, indent=1))
    print(f"PSNR {metrics['psnr']:.2f} dB  SSIM {metrics['ssim']:.3f}  {metrics['num_gaussians']} Gaussians  "
          f"{cfg.max_steps} steps  {cpu:.1f} s CPU ({wall:.1f} s wall)")
    return metrics


__all__ = ["Config", "Parser", "Dataset", "create_splats_with_optimizers", "rasterize_splats", "DataPosition",
           "save_checkpoint", "load_checkpoint", "ResumeRefused", "evaluate", "parse_config", "run"]
