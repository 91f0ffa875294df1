"""The default on a forward-facing rig: no coarse warm-up (MVGSConfig.forward_rig, for_scene).

The rig measure is checked on analytic rigs; the resolved config against the baseline's own
schedule (built without for_scene), so a forward-facing scene gets exactly the baseline's run
on a budget and on steps; orbits and other presets are left alone."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin import MVGS, MVGSConfig, Stage
from mvgs_plugin.data import load_nerf_synthetic
from mvgs_plugin.data.init import CONVERGING_SPREAD, axis_spread, is_forward_facing
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import synthetic_scene
from test_forward_init import look, parallel_rig

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
CLOCKS = ("densify_from", "densify_until", "densify_every", "opacity_reset_every", "prune_large_after")


class Rig:
    """A stand-in scene: only its training cameras matter to for_scene."""

    def __init__(self, cameras):
        self.train_cameras = cameras


def ring(n=12, radius=3.0, height=0.0):
    return [look((radius * math.cos(2 * math.pi * k / n), radius * math.sin(2 * math.pi * k / n), height),
                 (0.0, 0.0, 0.0), uid=k) for k in range(n)]


def test_axis_spread_on_analytic_rigs():
    # Parallel axes: mean(d d^T) = z z^T, so I - z z^T has eigenvalues (0, 1, 1).
    assert axis_spread(parallel_rig([-1.0, 0.0, 1.0])) == pytest.approx(0.0, abs=1e-12)
    # A level ring looking at its centre: d = (cos t, sin t, 0) evenly, mean(d d^T) = diag(1/2, 1/2, 0),
    # I - mean = diag(1/2, 1/2, 1): smallest eigenvalue 1/2.
    assert axis_spread(ring(12)) == pytest.approx(0.5, abs=1e-9)
    # Two axes 2a apart (a = 10 degrees): mean(d d^T) has eigenvalues cos^2 a, sin^2 a, 0, so the
    # spread is 1 - cos^2 a = sin^2 a.
    a = math.radians(10.0)
    pair = [look((0.0, 0.0, 0.0), (math.sin(s * a), 0.0, math.cos(s * a)), uid=i) for i, s in enumerate((-1, 1))]
    assert axis_spread(pair) == pytest.approx(math.sin(a) ** 2, rel=1e-9)
    assert is_forward_facing(pair) == (math.sin(a) ** 2 < CONVERGING_SPREAD)
    assert is_forward_facing(parallel_rig([0.0, 1.0])) and not is_forward_facing(ring(12))
    with pytest.raises(ValueError, match="at least one camera"):
        axis_spread([])


@pytest.mark.parametrize("budget", [300, 1000, 3000])
def test_default_on_a_forward_rig_is_the_baseline_on_the_same_budget(budget):
    fwd = Rig(parallel_rig([-1.0, -0.5, 0.0, 0.5, 1.0]))
    want = MVGSConfig.baseline(grad_threshold_width=800.0).with_budget(budget)
    # on the recipe (as the examples call it), then on an already rescaled config (as MVGS does)
    for got in (MVGSConfig.default().for_scene(fwd).with_budget(budget),
                MVGSConfig.default().with_budget(budget).for_scene(fwd)):
        assert got.stages == want.stages
        assert {k: getattr(got, k) for k in CLOCKS} == {k: getattr(want, k) for k in CLOCKS}
        assert got.total_work == pytest.approx(budget) and got.clock_length == want.clock_length
        assert got.for_scene(fwd) == got  # idempotent


@pytest.mark.parametrize("steps", [600, 1000, 3000])
def test_default_resolved_on_the_recipe_keeps_the_step_count_and_the_baselines_clocks(steps):
    fwd = Rig(parallel_rig([-1.0, 0.0, 1.0]))
    got = MVGSConfig.default().for_scene(fwd).with_total_steps(steps)
    want = MVGSConfig.baseline().with_total_steps(steps)
    assert got.stages == (Stage(1, 1, steps),) == want.stages
    assert {k: getattr(got, k) for k in CLOCKS} == {k: getattr(want, k) for k in CLOCKS}
    assert got.clock_length == steps


def test_a_rescaled_steps_config_keeps_its_work_and_every_clock():
    fwd = Rig(parallel_rig([-1.0, 0.0, 1.0]))
    config = MVGSConfig.default().with_total_steps(1000)
    got = config.for_scene(fwd)
    # The coarse stages' work (steps x (0.1 + 0.9 / f)) moves to full resolution, one step per unit.
    coarse = sum(s.steps * (0.1 + 0.9 / s.factor) for s in config.stages if s.factor > 1)
    assert got.stages == (Stage(1, 1, config.stages[-1].steps + round(coarse)),)
    assert abs(got.total_work - config.total_work) <= 0.5
    assert {k: getattr(got, k) for k in CLOCKS} == {k: getattr(config, k) for k in CLOCKS}
    assert got.clock_length == config.clock_length


def test_a_rescaled_steps_config_on_a_forward_rig_warns_with_the_count_it_takes():
    """The API route the docs once showed (with_total_steps before the controller's for_scene)
    takes fewer steps on a forward rig: the schedule says how many and how to get N; resolved
    first, or on a budget, or on an orbit, it says nothing."""
    fwd, orbit = synthetic_scene(), synthetic_scene()
    fwd.train_cameras = parallel_rig([-1.0, 0.0, 1.0])
    config = MVGSConfig.default().with_total_steps(1000)
    coarse = sum(s.steps * (0.1 + 0.9 / s.factor) for s in config.stages if s.factor > 1)
    taken = config.stages[-1].steps + round(coarse)  # the work of the coarse stages, at one step per unit
    assert taken < 1000
    with pytest.warns(UserWarning, match=rf"this run takes {taken} steps, not the config's 1000; for 1000 steps "
                                         r"resolve the recipe first, config.for_scene\(scene\).with_total_steps\(N\)"):
        assert ViewSchedule(fwd, config, load_images=False).config.total_steps == taken
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for quiet in (MVGSConfig.default().for_scene(fwd).with_total_steps(1000), MVGSConfig.default().with_budget(1000)):
            ViewSchedule(fwd, quiet, load_images=False)
        ViewSchedule(orbit, config, load_images=False)


def test_orbits_other_presets_and_pyramid_keep_their_plans():
    orbit, fwd = Rig(ring(12)), Rig(parallel_rig([-1.0, 0.0, 1.0]))
    config = MVGSConfig.default().with_budget(1000)
    assert config.for_scene(orbit) is config
    kept = dataclasses.replace(config, forward_rig="pyramid")
    assert kept.for_scene(fwd) is kept
    for preset in ("multiview", "paper", "baseline"):
        c = MVGSConfig.from_preset(preset)
        assert c.forward_rig == "pyramid" and c.for_scene(fwd) is c
    # a forward rig's finest stages are kept when there are several (only coarser ones go)
    custom = MVGSConfig.default(stages=(Stage(2, 1, 100), Stage(1, 2, 50), Stage(1, 1, 200)))
    got = custom.for_scene(fwd)
    assert got.stages[:2] == (Stage(1, 2, 50), Stage(1, 1, 200 + round(100 * 0.55)))
    with pytest.raises(ValueError, match="forward_rig must be one of"):
        MVGSConfig(forward_rig="coarse")


def test_the_controller_and_view_schedule_run_the_forward_scene_as_the_baseline():
    scene = load_nerf_synthetic(FORWARD)
    assert is_forward_facing(scene.train_cameras)
    config = MVGSConfig.default().with_budget(200)
    # the baseline with the default's cut of the faintest after densification
    base = ViewSchedule(scene, MVGSConfig.baseline(grad_threshold_width=800.0, prune_faint=0.01).with_budget(200))
    own = ViewSchedule(scene, config)
    assert own.config.stages == base.config.stages
    for _ in range(base.total_steps):
        a, b = own.next(), base.next()
        assert (a.views, a.factor, a.densify, a.reset_opacity, a.clock, a.faint_cut) == (
            b.views, b.factor, b.densify, b.reset_opacity, b.clock, b.faint_cut)
    assert own.faint_done
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=200))
    trainer = MVGS(adapter, scene, config)
    assert trainer.config.stages == (Stage(1, 1, 200),) and trainer.total_steps == 200
    # an orbit keeps the pyramid
    orbit = synthetic_scene(n_train=8, n_test=1, size=16, n_points=20)
    assert not is_forward_facing(orbit.train_cameras)
    assert [s.factor for s in MVGS(GS3DAdapter.from_scene(orbit), orbit, config).config.stages] == [2, 1]


def test_a_resumed_forward_run_checks_its_resolved_config(tmp_path):
    scene = load_nerf_synthetic(FORWARD)
    config = MVGSConfig.default().with_budget(60)
    a = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=60)), scene, config)
    for _ in range(20):
        a.step()
    path = tmp_path / "ck.pt"
    a.save_checkpoint(str(path))
    b = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=60)), scene, config)
    b.load_checkpoint(str(path))
    for _ in range(5):
        a.step(), b.step()
    for k, v in a.adapter.params.items():
        assert torch.equal(v, b.adapter.params[k]), k
