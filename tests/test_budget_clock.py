"""The budget clock: a run given a budget of work (full-resolution view renders) instead of a
step count, with every schedule on that clock (MVGSConfig.with_budget, ViewSchedule)."""

import dataclasses
import math

import pytest

from mvgs_plugin.config import DEFAULT_SHARES, CRDConfig, MVGSConfig, Stage
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import synthetic_scene


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=8, n_test=1, size=16, n_points=20)


def plans(scene, config):
    schedule = ViewSchedule(scene, config)
    return [schedule.next() for _ in range(config.total_steps)], schedule


def test_baseline_on_a_budget_is_the_baseline_on_steps(scene):
    # A baseline step is one full-resolution view: budget B and B steps are the same run.
    for b in (300, 1000, 4321):
        on_budget, on_steps = MVGSConfig.baseline().with_budget(b), MVGSConfig.baseline().with_total_steps(b)
        assert dataclasses.replace(on_budget, budget=None) == on_steps
    config = MVGSConfig.baseline().with_budget(800)
    got, schedule = plans(scene, config)
    ref, _ = plans(scene, MVGSConfig.baseline().with_total_steps(800))
    for a, r in zip(got, ref):
        assert (a.clock, a.densify, a.reset_opacity) == (r.clock, r.densify, r.reset_opacity)
    assert sum(p.densify for p in got) > 10 and sum(p.reset_opacity for p in got) >= 1
    assert schedule.work_done == pytest.approx(800)


def test_stages_keep_their_share_of_the_work():
    a, b = 0.1, 0.9
    config = MVGSConfig.multiview().with_views(4).with_budget(3000)
    recipe = MVGSConfig.multiview().with_views(4)
    cost = lambda s: s.views * (a + b / s.factor)  # noqa: E731 - the documented view cost
    recipe_work = [s.steps * cost(s) for s in recipe.stages]
    for stage, w in zip(config.stages, recipe_work):
        share = stage.steps * cost(stage) / 3000
        assert share == pytest.approx(w / sum(recipe_work), abs=cost(stage) / 3000)
    assert config.total_work == pytest.approx(3000, abs=max(cost(s) for s in config.stages) * len(config.stages))
    # The clock-valued fields are the 30k-view recipe's, times budget / 30000.
    assert (config.densify_from, config.densify_until, config.densify_every, config.opacity_reset_every) == (
        50, 1500, 10, 300)
    assert config.clock_length == 3000


def test_triggers_fire_where_the_work_clock_crosses_their_period(scene):
    config = MVGSConfig.multiview(crd=CRDConfig()).with_views(4).with_budget(2000)
    got, schedule = plans(scene, config)
    # The work of each step from its stage, walked independently of the schedule.
    work, bounds = 0.0, []
    for stage in config.stages:
        for _ in range(stage.steps):
            step = stage.views * (0.1 + 0.9 / stage.factor)
            bounds.append((work, work + step))
            work += step
    for plan, (lo, hi) in zip(got, bounds):
        assert plan.clock == math.floor(hi + 1e-9)
        crossed = lambda k: math.floor(hi / k + 1e-9) > math.floor(lo / k + 1e-9)  # noqa: E731
        inside = plan.clock < config.densify_until
        assert plan.densify == (inside and plan.clock > config.densify_from and crossed(config.densify_every))
        assert plan.reset_opacity == (inside and crossed(config.opacity_reset_every))
    dens = [p for p in got if p.densify]
    # Coarse steps are cheap: the clock passes many periods' worth of views only at full resolution.
    assert len(dens) == pytest.approx((config.densify_until - config.densify_from) / config.densify_every, abs=2)
    # Each stage's step count is rounded: the end is within half a step's work per stage.
    assert got[-1].clock == pytest.approx(2000, abs=sum(s.views * (0.1 + 0.9 / s.factor) for s in config.stages) / 2)
    # work_done counts what was rendered (at most the 8 training views per step).
    capped = sum(s.steps * min(s.views, 8) * (0.1 + 0.9 / s.factor) for s in config.stages)
    assert schedule.work_done == pytest.approx(capped)


@pytest.mark.parametrize("bad", [0, -5, float("inf"), float("nan"), True])
def test_bad_budget_is_refused(bad):
    with pytest.raises(ValueError, match="budget"):
        MVGSConfig.default().with_budget(bad)


def test_budget_needs_a_continuous_clock():
    with pytest.raises(ValueError, match="restart_per_stage"):
        MVGSConfig.paper().with_budget(1000)
    with pytest.raises(ValueError, match="view_cost"):
        MVGSConfig(view_cost=(0.5, 0.6))


def test_budget_survives_the_config_round_trip():
    config = MVGSConfig.multiview().with_views(4).with_budget(1234)
    assert MVGSConfig.from_dict(config.to_dict()) == config


def test_stages_from_shares_gives_each_stage_its_share_of_the_work():
    from mvgs_plugin.config import stages_from_shares

    shares = ((8, 5, 0.05), (4, 3, 0.15), (2, 2, 0.3), (1, 1, 0.5))
    stages = stages_from_shares(shares, total_work=30_000)
    assert [(s.factor, s.views) for s in stages] == [(f, m) for f, m, _ in shares]
    for stage, (f, m, w) in zip(stages, shares):
        per_step = m * (0.1 + 0.9 / f)  # the documented view cost, finest factor 1
        assert stage.steps * per_step == pytest.approx(w * 30_000, abs=per_step / 2)
    # Factors are relative to the finest stage (a run at --resolution-scale 2 doubles them all).
    doubled = stages_from_shares(tuple((2 * f, m, w) for f, m, w in shares))
    assert [s.steps for s in doubled] == [s.steps for s in stages]
    for bad in ((), ((4, 1, 0.5), (1, 1, 0.6)), ((4, 1, 0.0), (1, 1, 1.0)), ((4, 1),)):
        with pytest.raises(ValueError, match="shares"):
            stages_from_shares(bad)


@pytest.mark.parametrize("budget", [1000, 3000, 3333, 10_000, 30_000])
def test_default_is_coarse_to_fine_with_one_view_and_a_warmup_of_30_percent_up_to_1000_views(budget):
    config = MVGSConfig.default().with_budget(budget)
    assert [(s.factor, s.views) for s in config.stages] == [(2, 1), (1, 1)]
    assert not config.mvad and not config.crd and config.grad_threshold_width == 800
    work = [s.steps * (0.1 + 0.9 / s.factor) for s in config.stages]
    # The 1/2 level gets 30 % of the budget, but never more than 1000 full-resolution views' work;
    # full resolution gets the rest, and the budget is spent (each to within a step's rounding).
    warmup = min(0.3 * budget, 1000.0)
    assert work[0] == pytest.approx(warmup, abs=0.55)
    assert sum(work) == pytest.approx(budget, abs=1.0)
    # Coarse steps are cheap: the run makes more optimizer steps than a baseline on the budget.
    assert config.total_steps == round(warmup / 0.55) + round(budget - warmup)
    # Densification ends at 50 % of the budget, after full resolution has begun.
    assert config.densify_until / budget == pytest.approx(0.5, abs=1e-3)
    assert work[0] < config.densify_until
    multiview = MVGSConfig.multiview().with_views(4)
    assert [(s.factor, s.views) for s in multiview.stages] == [(8, 24), (4, 12), (2, 6), (1, 4)]
    assert multiview.mvad and not multiview.crd  # CRD: paper() only (issue 27)
    assert MVGSConfig.from_preset("multiview") == MVGSConfig.multiview()


@pytest.mark.parametrize("steps", [300, 1000, 7000])
def test_default_on_steps_keeps_its_clocks_at_the_same_fractions_of_the_work(scene, steps):
    """With --steps the default's clocks count work too: 3DGS's step-valued window (until step
    15000 of 30000) would otherwise close before the full-resolution stage opens (at 44 % of
    the default's steps), and the run would densify at full resolution for a few steps only."""
    config = MVGSConfig.default().with_total_steps(steps)
    assert config.total_steps == steps and config.counts_work and config.budget is None
    work_of = [s.steps * (0.1 + 0.9 / s.factor) for s in config.stages]
    total = sum(work_of)
    assert config.clock_length == round(total)
    full_res_from = sum(work_of[:-1])
    # The recipe's proportions (16364 steps at 1/2, 21000 at full: 30 % of the work at 1/2), with
    # the 1/2 level held to 1000 views' work (warmup_work_cap) once that is less.
    proportional = round(steps * 16364 / 37364) * 0.55
    assert full_res_from == pytest.approx(min(proportional, 1000.0), abs=0.55)
    if proportional < 1000:
        assert full_res_from / total == pytest.approx(0.3, abs=0.01)
    assert config.densify_until == max(1, round(15_000 * total / 30_000))
    got, schedule = plans(scene, config)
    full = [p for p in got if p.factor == 1]
    assert sum(p.densify for p in full) >= 1  # densification reaches full resolution
    assert got[-1].clock == pytest.approx(total, abs=1)
    # The same run as the default given that work as a budget, up to each stage's rounding.
    on_budget = MVGSConfig.default().with_budget(total)
    assert (on_budget.densify_from, on_budget.densify_until, on_budget.densify_every,
            on_budget.opacity_reset_every) == (config.densify_from, config.densify_until,
                                               config.densify_every, config.opacity_reset_every)
    assert all(abs(a.steps - b.steps) <= 1 for a, b in zip(on_budget.stages, config.stages))
    # The multi-view preset keeps counting steps (its equal-steps evidence is in steps).
    assert not MVGSConfig.multiview().with_total_steps(steps).counts_work
    with pytest.raises(ValueError, match="clock_unit"):
        MVGSConfig(clock_unit="views")
    with pytest.raises(ValueError, match="clock_unit"):
        MVGSConfig.paper(clock_unit="work")


def test_view_cost_flag_sets_the_clock_and_the_defaults_shares_of_its_work(tmp_path):
    """--view-cost A: a view at factor f costs A + (1 - A) / f. The default's stages keep their
    shares of the work (DEFAULT_SHARES: 30 % at 1/2, 70 % at full resolution) under that cost,
    recomputed here from the formula; a budget B is then B of that work; a bad A is a usage
    error naming it."""
    from mvgs_plugin.cli import config_from_args
    from test_late_views import _example

    example = _example("train_3dgs.py")
    a = 0.66
    cost = {f: a + (1 - a) / f for f, _, _ in DEFAULT_SHARES}
    shares = [w for _, _, w in DEFAULT_SHARES]
    assert math.isclose(sum(shares), 1.0) and [f for f, _, _ in DEFAULT_SHARES][-1] == 1
    recipe = MVGSConfig.default(view_cost=(a, 1 - a))
    assert recipe.view_cost == (a, 1 - a)
    assert [(s.factor, s.steps) for s in recipe.stages] == [
        (f, round(30_000 * w / cost[f])) for f, _, w in DEFAULT_SHARES]
    config = config_from_args(example.parse_args(["--data", str(tmp_path), "--view-cost", str(a), "--budget", "600"]))
    assert config.view_cost == (a, 1 - a) and config.budget == 600
    assert abs(sum(s.steps * cost[s.factor] for s in config.stages) - 600) <= 1.5
    work = [s.steps * cost[s.factor] / 600 for s in config.stages]
    assert len(work) == len(shares) and all(math.isclose(w, share, abs_tol=0.01) for w, share in zip(work, shares))
    # the baseline has one full-resolution stage: the cost model does not change its plan
    base = config_from_args(example.parse_args(["--data", str(tmp_path), "--view-cost", "0.9", "--preset", "baseline",
                                                "--budget", "600"]))
    assert [(s.factor, s.steps) for s in base.stages] == [(1, 600)]
    with pytest.raises(SystemExit):
        example.parse_args(["--data", str(tmp_path), "--view-cost", "1.5"])
    with pytest.raises(ValueError, match=r"view_cost must be \(a, b\) with a, b >= 0 and a \+ b = 1, got \(0.5, 0.6\)"):
        MVGSConfig.default(view_cost=(0.5, 0.6))


@pytest.mark.parametrize("views", [2, 4])
def test_views_per_step_keep_the_default_clocks_at_their_shares_of_the_work(views):
    """default().with_views(M) makes every step M views: the clocks, which count work, stretch
    with it, so densification still ends at half the run's work, resets come every tenth and
    size pruning starts at a tenth (3DGS's 15000, 3000, 3000 of 30000), whether the length is
    given in steps (before or after with_views) or as a budget (a length where the floor on
    resets, 30 densification intervals, does not act)."""
    for config in (MVGSConfig.default().with_views(views).with_total_steps(6000),
                   MVGSConfig.default().with_total_steps(6000).with_views(views),
                   MVGSConfig.default().with_views(views).with_budget(6000)):
        assert all(s.views == views for s in config.stages)
        work = sum(s.steps * s.views * (0.1 + 0.9 / s.factor) for s in config.stages)
        # (a clock rounded to whole work before M views multiply it is off by up to M / 2)
        assert config.densify_until == pytest.approx(work / 2, abs=views)
        assert config.opacity_reset_every == pytest.approx(work / 10, abs=views)
        assert config.prune_large_after == pytest.approx(work / 10, abs=views)
    # the multi-view preset counts steps: its clocks are steps whatever M is
    steps = MVGSConfig.multiview().with_total_steps(6000)
    assert steps.with_views(views).densify_until == steps.densify_until


def test_the_warmup_cap_keeps_coarse_stages_in_proportion_and_a_step_count_as_given():
    # Three levels at 1/4, 1/2, 1: per-step work 0.325, 0.55 and 1 (a + b / f, view_cost (0.1, 0.9)).
    plan = (Stage(4, 1, 4000), Stage(2, 2, 3000), Stage(1, 1, 20_000))
    cost = {4: 0.325, 2: 0.55, 1: 1.0}
    config = MVGSConfig(stages=plan, clock_unit="work", warmup_work_cap=600.0)
    coarse = [s.steps * s.views * cost[s.factor] for s in plan[:2]]  # 1300 and 3300 of 24600
    budget = 24_600 * 3  # the coarse levels would get 3900 + 9900 of it: capped to 600 in all
    run = config.with_budget(budget)
    got = [s.steps * s.views * cost[s.factor] for s in run.stages]
    assert sum(got[:2]) == pytest.approx(600, abs=2 * 1.1)
    assert got[0] / got[1] == pytest.approx(coarse[0] / coarse[1], rel=0.01)  # each keeps its share of the cap
    assert sum(got) == pytest.approx(budget, abs=2.0)  # full resolution takes the work they gave up
    # A step count stays a step count: the finest stage takes the steps the coarse ones gave up.
    steps = config.with_total_steps(30_000)
    assert steps.total_steps == 30_000
    assert sum(s.steps * s.views * cost[s.factor] for s in steps.stages[:2]) == pytest.approx(600, abs=2 * 1.1)
    # Below the cap, or without one, the plan is the proportional one.
    small = config.with_budget(2000)
    assert small.stages == dataclasses.replace(config, warmup_work_cap=None).with_budget(2000).stages
    uncapped = dataclasses.replace(config, warmup_work_cap=None).with_budget(budget)
    assert [s.steps * s.views * cost[s.factor] for s in uncapped.stages][:2] == pytest.approx(
        [3 * c for c in coarse], abs=1.1)
    # A plan with no coarser stage has nothing to cap.
    flat = MVGSConfig(stages=(Stage(1, 1, 30_000),), warmup_work_cap=1.0)
    assert flat.with_budget(10_000).stages == (Stage(1, 1, 10_000),)
    for bad in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="warmup_work_cap"):
            MVGSConfig(warmup_work_cap=bad)


def test_the_cli_runs_a_given_stage_plan_uncapped_unless_asked():
    import argparse

    from mvgs_plugin.cli import common_args, config_from_args

    def config(*argv):
        ap = argparse.ArgumentParser()
        common_args(ap, "out")
        return config_from_args(ap.parse_args(list(argv)))

    assert config("--budget", "10000").stages == (Stage(2, 1, 1818), Stage(1, 1, 9000))
    assert config("--budget", "10000", "--warmup-work-cap", "0").stages == (Stage(2, 1, 5455), Stage(1, 1, 7000))
    given = ("--budget", "10000", "--stages", "2:1:16364,1:1:21000")
    assert config(*given).stages == (Stage(2, 1, 5455), Stage(1, 1, 7000))
    assert config(*given, "--warmup-work-cap", "550").stages == (Stage(2, 1, 1000), Stage(1, 1, 9450))
