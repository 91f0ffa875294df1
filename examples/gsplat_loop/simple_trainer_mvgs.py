"""gsplat's examples/simple_trainer.py, its Runner's __init__ and train, ported to the CPU.

Shaped as gsplat 1.5.3's: Parser -> Dataset -> DataLoader (shuffled, workers), `splats` a
ParameterDict with one Adam per parameter, `cfg.strategy` a DefaultStrategy dispatched with
isinstance, the order backward -> optimizer step -> scheduler -> strategy.step_post_backward;
rendering with reference_renderer.rasterization (gsplat's call shape; gsplat's own with
--device cuda --rasterizer gsplat). simple_trainer.py trains one view per step;
simple_trainer_mvgs.py is the same file with MVGS (--preset picks the recipe): `diff
simple_trainer.py simple_trainer_mvgs.py` shows the four added lines, the same four that
gsplat_1.5.3.patch adds to gsplat's own file.

    python examples/gsplat_loop/simple_trainer.py --steps 1000 --out out/gsplat_single
    python examples/gsplat_loop/simple_trainer_mvgs.py --steps 1000 --out out/gsplat_mvgs
"""

import torch
import torch.nn.functional as F
from gsplat.strategy import DefaultStrategy, MCMCStrategy

from mvgs_plugin.adapters.gsplat_strategy import MVGSStrategy
from common import (Config, DataPosition, Dataset, Parser, create_splats_with_optimizers, load_checkpoint,
                    parse_config, rasterize_splats, run, save_checkpoint)
from mvgs_plugin.losses import ssim


class Runner:
    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.device = cfg.device
        self.parser = Parser(data_dir=cfg.data_dir, factor=cfg.data_factor, normalize=False, test_every=8,
                             background_points=cfg.background_points)
        self.trainset = Dataset(self.parser, split="train")
        self.valset = Dataset(self.parser, split="val")
        self.scene_scale = self.parser.scene_scale * 1.1
        self.cfg.strategy = MVGSStrategy(self.cfg.strategy, self.trainset, cfg.mvgs_preset, steps=cfg.max_steps, **cfg.mvgs_rules)

        self.splats, self.optimizers = create_splats_with_optimizers(self.parser, cfg, self.scene_scale)

        self.cfg.strategy.check_sanity(self.splats, self.optimizers)
        if isinstance(self.cfg.strategy, DefaultStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state(scene_scale=self.scene_scale)
        elif isinstance(self.cfg.strategy, MCMCStrategy):
            self.strategy_state = self.cfg.strategy.initialize_state()
        else:
            raise TypeError(type(self.cfg.strategy).__name__)

    def rasterize_splats(self, camtoworlds, Ks, width, height, **kwargs):
        return rasterize_splats(self.splats, self.cfg, self.parser.background, camtoworlds, Ks, width, height, **kwargs)

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

            renders, alphas, info = self.rasterize_splats(
                camtoworlds=camtoworlds,
                Ks=Ks,
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

            masks = data["mask"].to(device) if "mask" in data else None  # [C, H, W]
            if masks is not None:
                pixels = pixels * masks[..., None]
                colors = colors * masks[..., None]

            l1loss = F.l1_loss(colors, pixels)
            ssimloss = 1.0 - ssim(colors, pixels, padding="valid")
            loss = l1loss * (1.0 - cfg.ssim_lambda) + ssimloss * cfg.ssim_lambda
            loss.backward()

            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            for scheduler in schedulers:
                scheduler.step()

            if isinstance(self.cfg.strategy, DefaultStrategy):
                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    packed=cfg.packed,
                    renders=colors,
                )
            elif isinstance(self.cfg.strategy, MCMCStrategy):
                self.cfg.strategy.step_post_backward(
                    params=self.splats,
                    optimizers=self.optimizers,
                    state=self.strategy_state,
                    step=step,
                    info=info,
                    lr=schedulers[0].get_last_lr()[0],
                )

            if step + 1 in cfg.save_steps:
                save_checkpoint(cfg.result_dir / f"ckpt_{step + 1}.pt", step, self.splats, self.optimizers,
                                schedulers, self.strategy_state, position.state_dict(trainloader))


if __name__ == "__main__":
    run(Runner, parse_config(doc=__doc__))
