"""A scene gets only the Gaussians it needs: with MVGS's extra densification on (MVAD and CRD,
our default guards, cap and width-scaled threshold), a single flat textured plane ends with far
fewer Gaussians than the bundled tabletop trained the same way, while being fitted well.

The plane's images come from exact ray-plane intersection (mvgs_plugin.testing.plane_scene), the
tabletop's from Mitsuba: neither from our renderer. Both start from 300 points and train at
64 x 64 pixels for 1000 steps (the 39k-step recipe compressed: pyramid levels 8/4/2/1 of 77, 77,
77, 769 steps, densification from step 50 to 385): long enough for the plane to converge, which
is when a gradient rule can see that it needs nothing more. The same comparison at 200 steps,
and with 3DGS's unscaled threshold, is in benchmarks/bench_gaussian_budget.py.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin import MVGS, MVGSConfig, Stage
from mvgs_plugin.data import PointCloud, load_nerf_synthetic
from mvgs_plugin.testing import plane_scene

ROOT = Path(__file__).resolve().parents[1]
STEPS = 1000
POINTS = 300


def _train(name: str) -> tuple[int, float]:
    """MVGSConfig.multiview() (MVAD + CRD) compressed to STEPS, M = 4, on "plane" (64 px images)
    or "tabletop" (128 px images, every pyramid factor doubled: 64 px as well), one torch
    thread. Returns (final Gaussians, test PSNR)."""
    torch.set_num_threads(1)
    if name == "plane":
        scene, factor = plane_scene(n_points=POINTS, seed=0), 1
    else:
        scene, factor = load_nerf_synthetic(ROOT / "examples" / "scenes" / "tabletop"), 2
        keep = torch.randperm(len(scene.points.xyz), generator=torch.Generator().manual_seed(0))[:POINTS]
        scene.points = PointCloud(scene.points.xyz[keep], scene.points.rgb[keep])
    assert scene.train_cameras[0].width == 64 * factor
    cfg = MVGSConfig.multiview(seed=0).with_total_steps(STEPS).with_views(4)
    cfg = dataclasses.replace(cfg, stages=tuple(Stage(s.factor * factor, s.views, s.steps) for s in cfg.stages))
    torch.manual_seed(0)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(seed=0, position_lr_max_steps=STEPS,
                                                       sh_degree_interval=STEPS // 20))
    trainer = MVGS(adapter, scene, cfg)
    trainer.fit(progress=False)
    return adapter.num_primitives(), trainer.evaluate(factor=factor).psnr


@pytest.mark.slow
def test_plane_ends_with_far_fewer_gaussians_than_the_tabletop():
    # The two trainings run side by side in their own processes (one thread each: at 64 px a
    # second thread barely helps), which halves the test's wall time on two cores.
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        plane, tabletop = pool.submit(_train, "plane"), pool.submit(_train, "tabletop")
        (n_plane, psnr_plane), (n_table, psnr_table) = plane.result(), tabletop.result()
    # Both fitted: a low count from a model that learnt nothing would prove nothing.
    assert psnr_plane > 33.0, f"the plane is not fitted: {psnr_plane:.2f} dB"
    assert psnr_table > 22.0, f"the tabletop is not fitted: {psnr_table:.2f} dB"
    assert n_plane < 0.5 * n_table, (f"plane {n_plane} Gaussians ({psnr_plane:.2f} dB) vs tabletop {n_table} "
                                     f"({psnr_table:.2f} dB)")
