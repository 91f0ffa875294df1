"""The compact preset (MVGSConfig.compact): default() with a Gaussian budget of the training pixels
/ 213 on every rig but a forward-facing one. The budget is recomputed here from the cameras'
sizes; the forward-rig exception against default()'s own resolved config; a run through every
phase (densification, opacity resets, both pyramid hand-offs, a checkpoint resume) grows, never
holds more than the budget, never prunes by size and resumes exactly."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest
import torch

from mvgs_plugin import MVGS, MVGSConfig, cli
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.data import load_nerf_synthetic
from mvgs_plugin.data.init import is_forward_facing
from mvgs_plugin.testing import synthetic_scene

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
STEPS = 300


@pytest.fixture(scope="module")
def orbit():
    return synthetic_scene(n_train=8, n_test=2, size=32, n_points=20)


def pixels(scene) -> int:
    return sum(c.width * c.height for c in scene.train_cameras)


def test_compact_is_the_default_with_a_data_budget(orbit):
    compact, default = MVGSConfig.compact(), MVGSConfig.default()
    differ = {f.name for f in dataclasses.fields(MVGSConfig) if getattr(compact, f.name) != getattr(default, f.name)}
    assert differ == {"preset", "pixels_per_gaussian", "forward_rig_budget", "warmup_work_cap"}
    # compact keeps the default's 30 % at 1/2 at every budget (under a budget the cap is a trade
    # between scenes, docs/equal_compute.md); the default's warm-up is held to 1000 views' work
    # beyond a budget of 3333
    assert compact.warmup_work_cap is None and default.warmup_work_cap == 1000
    for budget in (3000, 10_000):
        plan = compact.with_budget(budget).stages
        assert plan[0].steps * 0.55 == pytest.approx(0.3 * budget, abs=0.55)
    assert compact.preset == "compact" and compact.forward_rig_budget is False
    assert not is_forward_facing(orbit.train_cameras)
    assert pixels(orbit) == 8 * 32 * 32
    assert compact.for_scene(orbit).max_gaussians == round(8 * 32 * 32 / 213) == 38
    assert MVGSConfig.from_preset("compact", pixels_per_gaussian=64).for_scene(orbit).max_gaussians == 128
    assert MVGSConfig.compact(max_gaussians=7).for_scene(orbit).max_gaussians == 7


def test_on_a_forward_facing_rig_compact_is_the_default():
    scene = load_nerf_synthetic(FORWARD)
    assert is_forward_facing(scene.train_cameras)
    got = MVGSConfig.compact().for_scene(scene)
    assert got.max_gaussians is None
    assert got.stages == MVGSConfig.default().for_scene(scene).stages  # the finest level only
    # asked for, the data budget holds there too; an explicit budget always does
    assert MVGSConfig.compact(forward_rig_budget=True).for_scene(scene).max_gaussians == round(pixels(scene) / 213)
    assert MVGSConfig.compact(max_gaussians=50).for_scene(scene).max_gaussians == 50
    for bad in (1, "no", None):
        with pytest.raises(ValueError, match="forward_rig_budget"):
            MVGSConfig(forward_rig_budget=bad)


def test_compact_from_the_command_line(orbit):
    ap = cli.common_args(argparse.ArgumentParser(), out="out")
    cfg = cli.config_from_args(ap.parse_args(["--preset", "compact", "--budget", "200"]), orbit)
    assert cfg.preset == "compact" and cfg.max_gaussians == 38 and cfg.budget_size_pruning is False
    cfg = cli.config_from_args(ap.parse_args(["--preset", "compact", "--pixels-per-gaussian", "64"]), orbit)
    assert cfg.max_gaussians == 128


def test_a_compact_run_holds_its_budget_through_every_phase(orbit, tmp_path):
    def make():
        torch.manual_seed(0)
        return GS3DAdapter.from_scene(orbit, GS3DConfig(position_lr_max_steps=STEPS, sh_degree_interval=30))

    # β unscaled for 32 px views; resets 10 densifications apart (30 leaves a 300-step run none)
    cfg = MVGSConfig.compact(grad_threshold_width=None, min_densify_per_reset=10).with_total_steps(STEPS)
    trainer = MVGS(make(), orbit, cfg)
    assert trainer.config.max_gaussians == 38 and trainer.adapter.num_primitives() == 20
    seen = {"densify": 0, "reset": 0, "stages": set(), "prune_large": set()}
    counts = []
    original = trainer.adapter.densify

    def spy(ctx):
        seen["prune_large"].add(ctx.prune_large)
        return original(ctx)

    trainer.adapter.densify = spy
    for _ in range(STEPS // 2):
        info = trainer.step()
        counts.append(info.num_primitives)
        seen["stages"].add(info.stage)
        seen["reset"] += info.opacity_reset
        seen["densify"] += info.densify is not None
    trainer.save_checkpoint(str(tmp_path / "half.pt"))
    resumed = MVGS(make(), orbit, cfg)
    resumed.load_checkpoint(str(tmp_path / "half.pt"))
    for run in (trainer, resumed):
        while run.step_count < run.total_steps:
            info = run.step()
            counts.append(info.num_primitives)
            seen["stages"].add(info.stage)
            seen["reset"] += info.opacity_reset and run is trainer
            seen["densify"] += info.densify is not None and run is trainer
    assert seen["densify"] >= 5 and seen["reset"] >= 1 and seen["stages"] == set(range(len(trainer.config.stages)))
    assert max(counts) <= 38 and max(counts) > 20  # it grew, never past the budget
    assert seen["prune_large"] == {False}  # no size pruning under the budget
    for name, p in trainer.adapter.params.items():  # the resumed run is the same run
        torch.testing.assert_close(resumed.adapter.params[name], p, rtol=0, atol=0)
        assert torch.isfinite(p).all()


def test_every_preset_name_builds_its_preset_and_every_parser_offers_it():
    from mvgs_plugin.config import PRESETS

    assert set(PRESETS) == {"default", "compact", "multiview", "paper", "baseline"}
    for name in PRESETS:
        assert MVGSConfig.from_preset(name).preset == name
    with pytest.raises(ValueError, match="preset must be one of"):
        MVGSConfig.from_preset("fast")
    ap = cli.common_args(argparse.ArgumentParser(), out="out")
    assert ap.parse_args(["--preset", "compact"]).preset == "compact"
