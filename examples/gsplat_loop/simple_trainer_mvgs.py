"""The training loop of gsplat's examples/simple_trainer.py, ported to the CPU.

Its `splats` ParameterDict, one Adam per parameter, gsplat's DefaultStrategy as installed, its
loss, its order of optimizer step, scheduler and strategy hooks; rendering with
reference_renderer.rasterization (gsplat's call shape; gsplat's own with --device cuda
--rasterizer gsplat). simple_trainer.py trains one view per step; simple_trainer_mvgs.py is the
same file trained with MVGS (--preset picks the recipe); `diff simple_trainer.py
simple_trainer_mvgs.py` shows every line that changes (four).

    python examples/gsplat_loop/simple_trainer.py --steps 1000 --out out/gsplat_single
    python examples/gsplat_loop/simple_trainer_mvgs.py --steps 1000 --out out/gsplat_mvgs
"""

import torch
import torch.nn.functional as F
from gsplat.strategy import DefaultStrategy

from mvgs_plugin.adapters.gsplat_strategy import MVGSStrategy
from common import (Config, TrainBatches, create_splats_with_optimizers, load_checkpoint, parse_config,
                    rasterize_splats, run, save_checkpoint)
from mvgs_plugin.losses import ssim


def train(cfg: Config, scene):
    device = cfg.device
    scene_scale = scene.extent
    splats, optimizers = create_splats_with_optimizers(scene, cfg, scene_scale)
    strategy = MVGSStrategy(DefaultStrategy(**cfg.strategy_kwargs()), scene, cfg.preset, steps=cfg.max_steps)
    strategy.check_sanity(splats, optimizers)
    strategy_state = strategy.initialize_state(scene_scale=scene_scale)
    schedulers = [torch.optim.lr_scheduler.ExponentialLR(optimizers["means"], gamma=0.01 ** (1.0 / cfg.max_steps))]
    trainloader_iter = strategy.batches()
    init_step = 0
    if cfg.resume is not None:
        init_step = load_checkpoint(cfg.resume, splats, optimizers, schedulers, strategy_state, trainloader_iter)

    for step in range(init_step, cfg.max_steps):
        data = next(trainloader_iter)
        camtoworlds = data["camtoworld"].to(device)  # [C, 4, 4]
        Ks = data["K"].to(device)  # [C, 3, 3]
        pixels = data["image"].to(device) / 255.0  # [C, H, W, 3]
        height, width = pixels.shape[1:3]
        sh_degree_to_use = min(step // cfg.sh_degree_interval, cfg.sh_degree)

        renders, alphas, info = rasterize_splats(splats, cfg, camtoworlds, Ks, width, height,
                                                 sh_degree=sh_degree_to_use,
                                                 backgrounds=data["background"].to(device))
        colors = renders
        strategy.step_pre_backward(params=splats, optimizers=optimizers, state=strategy_state, step=step, info=info)

        l1loss = F.l1_loss(colors, pixels)
        ssimloss = 1.0 - ssim(colors, pixels, padding="valid")
        loss = l1loss * (1.0 - cfg.ssim_lambda) + ssimloss * cfg.ssim_lambda
        loss.backward()

        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        for scheduler in schedulers:
            scheduler.step()

        strategy.step_post_backward(
            params=splats,
            optimizers=optimizers,
            state=strategy_state,
            step=step,
            info=info,
            packed=cfg.packed,
            renders=colors,
        )
        if step + 1 in cfg.save_steps:
            save_checkpoint(cfg.result_dir / f"ckpt_{step + 1}.pt", step, splats, optimizers, schedulers,
                            strategy_state, trainloader_iter)
    return splats, strategy


if __name__ == "__main__":
    run(train, parse_config(doc=__doc__))
