"""MVGSConfig.coarse_opacity_reset: default() resets opacities at the finest pyramid level only;
every other preset (and a config given coarse_opacity_reset=True) resets wherever the clock
crosses opacity_reset_every inside the densification window."""

import argparse
import dataclasses
import math

import pytest
import torch

from mvgs_plugin import cli
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.config import MVGSConfig, Stage
from mvgs_plugin.controller import MVGS
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import synthetic_scene


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=8, n_test=1, size=16, n_points=20)


def expected_resets(config, coarse: bool):
    """The steps (1-based) whose plan resets opacities, walked from the stages and the documented
    view cost (0.1 + 0.9 / f per view) without the schedule: the work clock crosses a multiple of
    opacity_reset_every inside the densification window, at a coarse level only when `coarse`."""
    finest = min(s.factor for s in config.stages)
    work, step, out = 0.0, 0, []
    for stage in config.stages:
        for _ in range(stage.steps):
            step += 1
            lo, hi = work, work + stage.views * (0.1 + 0.9 / stage.factor)
            work = hi
            clock = math.floor(hi + 1e-9)
            k = config.opacity_reset_every
            crossed = math.floor(hi / k + 1e-9) > math.floor(lo / k + 1e-9)
            if crossed and clock < config.densify_until and (coarse or stage.factor == finest):
                out.append(step)
    return out


def test_the_default_resets_only_at_the_finest_level_and_densifies_as_before(scene):
    config = MVGSConfig.default().with_budget(2000)
    assert config.coarse_opacity_reset is False and [s.factor for s in config.stages] == [2, 1]
    with_coarse = dataclasses.replace(config, coarse_opacity_reset=True)
    got = [ViewSchedule(scene, c) for c in (config, with_coarse)]
    plans = [[s.next() for _ in range(config.total_steps)] for s in got]
    resets = [[p.step for p in ps if p.reset_opacity] for ps in plans]
    assert resets[0] == expected_resets(config, coarse=False)
    assert resets[1] == expected_resets(config, coarse=True)
    coarse_steps = config.stages[0].steps
    # The rule does something here: the clock crosses reset periods while the 1/2 level trains.
    assert any(s <= coarse_steps for s in resets[1]) and not any(s <= coarse_steps for s in resets[0])
    assert [s for s in resets[1] if s > coarse_steps] == resets[0] and resets[0]
    # Nothing else of the plan changes: densification, clock and views are the same step by step.
    for a, b in zip(*plans):
        assert (a.clock, a.densify, a.factor, a.views) == (b.clock, b.densify, b.factor, b.views)


def test_finest_is_the_smallest_factor_whatever_the_resolution_scale(scene, tmp_path):
    # --resolution-scale 2 multiplies every factor: the finest level is then 2, and it still resets.
    ap = cli.common_args(argparse.ArgumentParser(), str(tmp_path / "out"))
    config = cli.config_from_args(ap.parse_args(["--preset", "default", "--steps", "1000", "--resolution-scale", "2"]))
    assert [s.factor for s in config.stages] == [4, 2]
    plans = list(ViewSchedule(scene, config))
    assert {p.factor for p in plans if p.reset_opacity} == {2}


@pytest.mark.parametrize("preset", ["baseline", "multiview", "paper", "compact", "default"])
def test_which_presets_reset_at_coarse_levels(preset):
    assert MVGSConfig.from_preset(preset).coarse_opacity_reset is (preset not in ("default", "compact"))


def test_the_cli_flag_and_bad_values(tmp_path):
    ap = cli.common_args(argparse.ArgumentParser(), str(tmp_path / "out"))
    on = cli.config_from_args(ap.parse_args(["--preset", "default", "--coarse-opacity-reset"]))
    off = cli.config_from_args(ap.parse_args(["--preset", "multiview", "--no-coarse-opacity-reset"]))
    plain = cli.config_from_args(ap.parse_args(["--preset", "default"]))
    assert (on.coarse_opacity_reset, off.coarse_opacity_reset, plain.coarse_opacity_reset) == (True, False, False)
    with pytest.raises(ValueError, match=r"coarse_opacity_reset must be a bool, got 'no'"):
        MVGSConfig.default(coarse_opacity_reset="no")


def test_a_config_written_before_the_field_reads_as_resetting_everywhere():
    # Checkpoints and metrics written before the field existed resume with the resets they ran with.
    d = MVGSConfig.default().to_dict()
    d.pop("coarse_opacity_reset")
    assert MVGSConfig.from_dict(d).coarse_opacity_reset is True
    assert MVGSConfig.from_dict(MVGSConfig.default().to_dict()) == MVGSConfig.default()


def test_a_default_run_through_both_levels_never_resets_at_the_coarse_one(scene):
    """The controller with the 3DGS adapter, a default run long enough to densify at both levels,
    hand over and reset: no reset while the 1/2 level trains, at least one after, and the
    Gaussians' opacities are capped by the reset value only then."""
    # resets 100 work apart (the floor of 10 densifications) so a 600-view run crosses one at each level
    config = MVGSConfig.default(min_densify_per_reset=10).with_budget(600)
    # 3DGS's reset of every opacity, so that a reset shows as the cap on all of them (the default
    # "inside" spares the far background: tests/test_reset_scope.py)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(config, seed=0, opacity_reset_scope="all"))
    trainer = MVGS(adapter, scene, config)
    infos, cap = [], adapter.config.opacity_reset_value
    for _ in range(trainer.total_steps):
        info = trainer.step()
        infos.append(info)
        if info.opacity_reset:
            assert float(torch.sigmoid(adapter.params["opacities"].detach()).max()) <= cap + 1e-6
    assert {i.factor for i in infos} == {2, 1}
    assert not [i.step for i in infos if i.factor == 2 and i.opacity_reset]
    assert [i.step for i in infos if i.factor == 1 and i.opacity_reset]
    assert any(i.densify is not None for i in infos if i.factor == 2)
