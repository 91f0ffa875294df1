"""The MVGS loop of simple_trainer_mvgs.py with each step's views rendered in chunks.

A step of M views that does not fit in memory as one render call is rendered and
backpropagated in chunks (MVGSStrategy.chunks(): the schedule's chunk_size, or what
chunk_memory_mb allows for the model's size). The weighting: each chunk's mean loss times
len(chunk) / M, so the parameter gradients are those of one call over all M views; the
strategy then gets n_cameras = M for every chunk, so the densification statistics are that
call's too (tests/test_gsplat_loop.py checks both). step_post_backward follows each chunk's
backward, before the optimizer step: a refine due at the step's end waits for the next batch.

    python examples/gsplat_loop/simple_trainer_chunked.py --preset multiview --chunk-size 2 --steps 1000
"""

import dataclasses

import torch
import torch.nn.functional as F

import simple_trainer_mvgs
from common import Config, DataPosition, load_checkpoint, parse_config, run, save_checkpoint
from mvgs_plugin import MVGSConfig
from mvgs_plugin.losses import ssim


class Runner(simple_trainer_mvgs.Runner):
    """simple_trainer_mvgs.py's Runner (its MVGSStrategy built on the preset with
    cfg.chunk_size) with train() rendering each step in chunks."""

    def __init__(self, cfg: Config):
        mvgs = (dataclasses.replace(cfg.mvgs_preset, chunk_size=cfg.chunk_size) if isinstance(cfg.mvgs_preset, MVGSConfig)
                else MVGSConfig.from_preset(cfg.mvgs_preset, chunk_size=cfg.chunk_size))
        super().__init__(dataclasses.replace(cfg, mvgs_preset=mvgs))  # MVGSStrategy takes a config or a name

    def train(self):
        cfg = self.cfg
        device = self.device
        max_steps = cfg.max_steps
        init_step = 0

        schedulers = [torch.optim.lr_scheduler.ExponentialLR(self.optimizers["means"], gamma=0.01 ** (1.0 / max_steps))]

        generator = torch.Generator().manual_seed(cfg.seed)  # our port: a seeded shuffle, for exact resume
        trainloader = torch.utils.data.DataLoader(
            self.trainset,
            batch_size=cfg.batch_size,
            shuffle=True,
            num_workers=cfg.num_workers,
            persistent_workers=cfg.num_workers > 0,
            generator=generator,
        )
        trainloader = self.cfg.strategy.loader(trainloader)
        position = DataPosition(generator)
        trainloader_iter = position.iterate(trainloader)
        if cfg.resume is not None:
            init_step, data_state = load_checkpoint(cfg.resume, self.splats, self.optimizers, schedulers,
                                                    self.strategy_state)
            trainloader_iter = position.resume(trainloader, data_state, self.splats, self.optimizers,
                                               self.strategy_state)

        for step in range(init_step, max_steps):
            try:
                data = next(trainloader_iter)
            except StopIteration:
                trainloader_iter = position.iterate(trainloader)
                data = next(trainloader_iter)

            camtoworlds = data["camtoworld"].to(device)  # [C, 4, 4]
            Ks = data["K"].to(device)  # [C, 3, 3]
            pixels = data["image"].to(device) / 255.0  # [C, H, W, 3]
            height, width = pixels.shape[1:3]

            sh_degree_to_use = min(step // cfg.sh_degree_interval, cfg.sh_degree)

            # M views in chunks: each chunk's mean loss weighted by its share of the views, so the
            # gradients are the one-call step's; step_post_backward right after each backward
            # (MVGSStrategy defers a refine due at the step's end to the next batch)
            for part, weight in self.cfg.strategy.chunks():
                renders, alphas, info = self.rasterize_splats(
                    camtoworlds=camtoworlds[part],
                    Ks=Ks[part],
                    width=width,
                    height=height,
                    sh_degree=sh_degree_to_use,
                    near_plane=cfg.near_plane,
                    far_plane=cfg.far_plane,
                )
                colors = renders

                self.cfg.strategy.step_pre_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                )

                target = pixels[part]
                if "mask" in data:  # [C, H, W]
                    keep = data["mask"].to(device)[part][..., None]
                    target, colors = target * keep, colors * keep
                l1loss = F.l1_loss(colors, target)
                ssimloss = 1.0 - ssim(colors, target, padding="valid")
                loss = l1loss * (1.0 - cfg.ssim_lambda) + ssimloss * cfg.ssim_lambda
                (loss * weight).backward()

                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    packed=cfg.packed,
                    renders=colors,
                )

            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            for scheduler in schedulers:
                scheduler.step()

            if step + 1 in cfg.save_steps:
                save_checkpoint(cfg.result_dir / f"ckpt_{step + 1}.pt", step, self.splats, self.optimizers,
                                schedulers, self.strategy_state, position.state_dict(trainloader))


if __name__ == "__main__":
    run(Runner, parse_config(doc=__doc__))
