"""Options of the equal-compute study (docs/equal_compute.md): Grendel-GS's optimizer rule for a
step of M views (MVGSConfig.views_scaling="sqrt", set_views_per_step), the sparse-view guard
(MVGSConfig.max_views_fraction) and the growth cap per stage (MVGSConfig.stage_growth). The
optimizer is checked against Adam written out by hand."""

from __future__ import annotations

import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
from mvgs_plugin.adapters.gsplat_strategy import MVGSStrategy
from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig
from mvgs_plugin import MVGS, MVGSConfig
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import synthetic_scene
from gsplat.strategy import DefaultStrategy  # the [dev] extra installs gsplat


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=10, n_test=1, size=16, n_points=30)


def hand_adam(grads, lr, b1, b2, eps):
    """Parameter change after Adam steps on the given gradients (torch's Adam, bias-corrected)."""
    m = v = torch.zeros_like(grads[0], dtype=torch.float64)
    delta = torch.zeros_like(m)
    for t, g in enumerate(grads, start=1):
        g = g.double()
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        delta = delta - lr * (m / (1 - b1 ** t)) / ((v / (1 - b2 ** t)).sqrt() + eps)
    return delta


@pytest.mark.parametrize("views", [1, 4, 9])
def test_an_m_view_step_uses_grendels_adam_hyperparameters(scene, views):
    cfg = GS3DConfig(adam_eps=1e-3)  # an eps large enough to matter in the comparison
    adapter = GS3DAdapter.from_scene(scene, cfg, dtype=torch.float64)  # no float32 rounding in the differences
    base = dict(adapter.learning_rates())
    adapter.set_views_per_step(views)
    g = torch.Generator().manual_seed(views)
    grads = [{n: 1e-3 * torch.randn(p.shape, generator=g, dtype=p.dtype) for n, p in adapter.params.items()}
             for _ in range(3)]
    before = {n: p.detach().clone() for n, p in adapter.params.items()}
    for step, gs in enumerate(grads, start=1):
        adapter.set_step(0)  # the step-0 learning rates every time: the means' decay out of the way
        for n, p in adapter.params.items():
            p.grad = gs[n].clone()
        adapter.optimizer_step()
        adapter.zero_grad()
    for n, p in adapter.params.items():
        want = hand_adam([gs[n] for gs in grads], base[n] * math.sqrt(views), 0.9 ** views, 0.999 ** views,
                         1e-3 / math.sqrt(views))
        torch.testing.assert_close((p.detach() - before[n]).double(), want, rtol=2e-4, atol=1e-9)


def test_other_adapters_scale_every_group(scene):
    timed = synthetic_scene(n_train=6, n_test=1, size=16, n_points=30, time=True)
    tiny = dict(resolution=(6, 5, 4, 5), multires=(1, 2), features=3, width=8)
    for adapter in (ScaffoldAdapter.from_scene(scene, ScaffoldConfig()),
                    GS4DAdapter.from_scene(timed, GS4DConfig(canonical=GS3DConfig(sh_degree=1), coarse_steps=2,
                                                             fine_steps=20, **tiny))):
        adapter.set_step(5)
        single = adapter.learning_rates()
        adapter.set_views_per_step(4)
        adapter.set_step(5)
        assert adapter.learning_rates() == pytest.approx({k: 2.0 * v for k, v in single.items()}, rel=1e-12)
        groups = list(adapter.optimizer.param_groups) + list(getattr(adapter, "field_optimizer",
                                                                     adapter.optimizer).param_groups)
        assert all(gr["betas"] == pytest.approx((0.9 ** 4, 0.999 ** 4)) for gr in groups)
        adapter.set_views_per_step(1)
        adapter.set_step(5)
        assert adapter.learning_rates() == single
        with pytest.raises(ValueError, match="views must be"):
            adapter.set_views_per_step(0)


def test_the_controller_scales_for_each_steps_views(scene):
    calls = []

    class Spy(GS3DAdapter):
        def set_views_per_step(self, views):
            calls.append(views)
            super().set_views_per_step(views)

    config = MVGSConfig.multiview(views_scaling="sqrt").with_views(4).with_total_steps(40)
    trainer = MVGS(Spy.from_scene(scene, GS3DConfig(position_lr_max_steps=40)), scene, config)
    infos = [trainer.step() for _ in range(40)]
    assert calls == [len(i.views) for i in infos] and len(set(calls)) > 1  # follows the stages
    lrs = trainer.adapter.learning_rates()
    assert lrs["sh0"] == pytest.approx(trainer.adapter.config.lr_sh0 * math.sqrt(calls[-1]))
    # off by default: never called, the single-view rates
    calls.clear()
    plain = MVGS(Spy.from_scene(scene), scene, MVGSConfig.multiview().with_views(4).with_total_steps(20))
    plain.fit()
    assert calls == [] and plain.adapter.learning_rates()["sh0"] == plain.adapter.config.lr_sh0


def test_views_scaling_is_refused_where_it_cannot_be_applied(scene):
    class NoScaling(GS3DAdapter):
        set_views_per_step = None

    config = MVGSConfig.multiview(views_scaling="sqrt")
    with pytest.raises(ValueError, match="set_views_per_step"):
        MVGS(NoScaling.from_scene(scene), scene, config)
    with pytest.raises(ValueError, match="your loop owns the optimizers"):
        MVGSStrategy(DefaultStrategy(), scene, config, steps=10)
    with pytest.raises(ValueError, match="views_scaling must be one of"):
        MVGSConfig(views_scaling="linear")


@pytest.mark.parametrize("fraction,cap", [(0.25, 2), (0.5, 5), (0.05, 1), (1.0, 10)])
def test_the_sparse_view_guard_caps_every_step_and_keeps_the_work(scene, fraction, cap):
    # 10 training views: the cap is floor(fraction x 10), at least 1.
    recipe = MVGSConfig.multiview(max_views_fraction=fraction)  # 48, 24, 12, 8 views
    got = recipe.for_scene(scene)
    assert [s.views for s in got.stages] == [min(v, cap) for v in (48, 24, 12, 8)]
    assert [s.steps for s in got.stages] == [s.steps for s in recipe.stages]  # clocks on steps: steps kept
    on_budget = MVGSConfig.multiview(max_views_fraction=fraction).with_budget(2000)
    capped = on_budget.for_scene(scene)
    for a, b in zip(on_budget.stages, capped.stages):
        # a stage's work is steps x views x (0.1 + 0.9 / f): kept up to rounding one step
        assert abs(b.steps * b.views - a.steps * a.views) <= b.views / 2 + 1e-9, (a, b)
    assert capped.for_scene(scene) == capped  # idempotent
    schedule = ViewSchedule(scene, on_budget)
    plans = [schedule.next() for _ in range(schedule.total_steps)]
    assert max(len(p.views) for p in plans) == cap
    assert schedule.work_done == pytest.approx(capped.total_work)


def test_the_guard_leaves_scenes_with_enough_views_alone(scene):
    config = MVGSConfig.multiview(max_views_fraction=1.0)
    dense = synthetic_scene(n_train=48, n_test=1, size=16, n_points=30)
    assert config.for_scene(dense) is config
    for bad in (0.0, -0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="max_views_fraction"):
            MVGSConfig(max_views_fraction=bad)


def test_stage_growth_caps_every_stage_at_a_multiple_of_its_starting_count(scene):
    growth = 1.3
    config = MVGSConfig.default(stage_growth=growth, grad_threshold_width=None).with_total_steps(300)
    trainer = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=300)), scene, config)
    count, stage, start, capped = trainer.adapter.num_primitives(), None, None, 0
    for _ in range(trainer.total_steps):
        info = trainer.step()
        if info.stage != stage:
            stage, start = info.stage, count  # the count when the stage began (before its first step)
        assert info.num_primitives <= math.floor(growth * start), (info.step, info.num_primitives, start)
        if info.densify is not None:
            capped += info.densify.extra["dropped_by_max_gaussians"] > 0
        count = info.num_primitives
    assert capped > 0 and stage == len(config.stages) - 1  # the cap bound, and every stage ran
    # the same run without it grows past the cap
    free = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=300)), scene,
                MVGSConfig.default(grad_threshold_width=None).with_total_steps(300)).fit()
    assert free.adapter.num_primitives() > math.floor(growth * len(scene.points))
    # the stage's starting count survives a checkpoint
    state = trainer.schedule.state_dict()
    other = ViewSchedule(scene, config)
    other.load_state_dict(state)
    assert other.stage_start_count == trainer.schedule.stage_start_count == start
    with pytest.raises(ValueError, match="stage_growth"):
        MVGSConfig(stage_growth=1.0)
    with pytest.raises(ValueError, match="no cap on"):
        MVGSStrategy(DefaultStrategy(), scene, MVGSConfig.default(stage_growth=2.0), steps=10)
