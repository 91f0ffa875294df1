"""View sampler, stage plan and config presets."""

import collections

import pytest

from mvgs_plugin.config import MVGSConfig, Stage
from mvgs_plugin.sampler import ViewSampler
from mvgs_plugin.schedule import StagePlan


@pytest.mark.parametrize("n,m", [(10, 3), (7, 7), (12, 5), (5, 1), (48, 48)])
def test_no_repeats_in_a_step_and_every_view_once_per_epoch(n, m):
    s = ViewSampler(n, seed=3)
    steps = [s.sample(m) for _ in range(200)]
    assert all(len(set(v)) == m for v in steps)
    flat = [i for v in steps for i in v]
    # Over any whole number of epochs drawn, each view appears the same number of times, up to
    # the one epoch a straddling step shifts.
    counts = collections.Counter(flat)
    assert set(counts) == set(range(n))
    assert max(counts.values()) - min(counts.values()) <= 1
    # Within each window of n consecutive draws aligned to epochs, every view appears once when
    # m divides n (no straddling steps).
    if n % m == 0:
        for e in range(len(flat) // n):
            assert sorted(flat[e * n : (e + 1) * n]) == list(range(n))


def test_sampler_is_seeded_and_resumable():
    a, b = ViewSampler(9, seed=1), ViewSampler(9, seed=1)
    assert [a.sample(4) for _ in range(5)] == [b.sample(4) for _ in range(5)]
    state = a.state_dict()
    rest = [a.sample(4) for _ in range(7)]
    c = ViewSampler(9, seed=123)
    c.load_state_dict(state)
    assert [c.sample(4) for _ in range(7)] == rest
    assert [ViewSampler(9, seed=2).sample(4) for _ in range(3)] != [ViewSampler(9, seed=1).sample(4) for _ in range(3)]


def test_more_views_than_exist_is_capped():
    s = ViewSampler(4, seed=0)
    with pytest.warns(UserWarning, match="only 4 training views"):
        v = s.sample(10)
    assert sorted(v) == [0, 1, 2, 3]


@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_bad_view_counts(bad):
    with pytest.raises(ValueError, match="positive int"):
        ViewSampler(3).sample(bad)
    with pytest.raises(ValueError, match="positive int"):
        ViewSampler(bad)


def test_stage_plan_continuous_and_restarting():
    stages = (Stage(8, 4, 3), Stage(2, 2, 2), Stage(1, 1, 5))
    cont = StagePlan(stages, restart_per_stage=False)
    rest = StagePlan(stages, restart_per_stage=True)
    got = [(p.index, p.local_step, p.clock, p.first_in_stage) for p in map(cont.locate, range(1, 11))]
    assert [g[0] for g in got] == [0, 0, 0, 1, 1, 2, 2, 2, 2, 2]
    assert [g[2] for g in got] == list(range(1, 11))
    assert [rest.locate(s).clock for s in range(1, 11)] == [1, 2, 3, 1, 2, 1, 2, 3, 4, 5]
    assert [s for s in range(1, 11) if cont.locate(s).first_in_stage] == [1, 4, 6]
    with pytest.raises(ValueError, match=r"step must be in \[1, 10\]"):
        cont.locate(11)


def test_presets_follow_the_method_notes():
    base = MVGSConfig.baseline()
    assert base.stages == (Stage(1, 1, 30_000),) and base.stats_from == "all"
    paper = MVGSConfig.paper()
    assert [(s.factor, s.views, s.steps) for s in paper.stages] == [(8, 48, 3000), (4, 24, 3000), (2, 12, 3000), (1, 8, 30000)]
    assert paper.stats_from == "last" and paper.restart_per_stage and paper.opacity_reset_at_handoff
    ours = MVGSConfig.multiview()
    assert [s.factor for s in ours.stages] == [8, 4, 2, 1]
    assert ours.stats_from == "all" and not ours.restart_per_stage and not ours.opacity_reset_at_handoff
    assert MVGSConfig.from_dict(ours.to_dict()) == ours


def test_with_total_steps_keeps_proportions():
    c = MVGSConfig.multiview().with_total_steps(3900)
    assert c.total_steps == 3900
    assert [s.steps for s in c.stages] == [300, 300, 300, 3000]
    # continuous clock: 39k -> 3.9k is a factor 10
    assert (c.densify_from, c.densify_until, c.densify_every, c.opacity_reset_every) == (50, 1500, 10, 300)
    p = MVGSConfig.paper().with_total_steps(3900)
    # restarting clock: relative to the 30k final stage -> factor 0.1 as well
    assert (p.densify_from, p.densify_until, p.opacity_reset_every) == (50, 1500, 300)
    b = MVGSConfig.baseline().with_total_steps(3000)
    assert b.stages == (Stage(1, 1, 3000),) and b.densify_every == 10


def test_short_runs_let_the_model_settle_before_densifying():
    # 500 / 30k of a 120-step run is step 2: the floor waits 50 steps, but never later than
    # the recipe's own start.
    short = MVGSConfig.baseline().with_total_steps(120)
    assert (short.densify_from, short.densify_until, short.densify_every) == (50, 60, 10)
    assert MVGSConfig.baseline(densify_from=20).with_total_steps(120).densify_from == 20
    assert MVGSConfig.baseline().with_total_steps(60_000).densify_from == 1000


def test_with_views():
    c = MVGSConfig.multiview().with_views(4)
    assert [s.views for s in c.stages] == [24, 12, 6, 4]


@pytest.mark.parametrize("field,value,pattern", [
    ("reduction", "max", "reduction must be one of"),
    ("stats_from", "first", "stats_from must be one of"),
    ("chunk_size", 0, "chunk_size must be a positive int"),
    ("lambda_dssim", 1.5, "lambda_dssim must be in"),
    ("background", "green", "background must be"),
    ("background", (2.0, 0.0, 0.0), "background must be"),
    ("stages", (), "stages must be a non-empty"),
    ("densify_until", float("nan"), "densify_until must be an int >= 0"),
    ("densify_from", 2.5, "densify_from must be an int >= 0"),
    ("prune_large_after", -1, "prune_large_after must be an int >= 0"),
    ("seed", -1, "seed must be an int in 0..4294967295, got -1"),
])
def test_bad_config(field, value, pattern):
    with pytest.raises(ValueError, match=pattern):
        MVGSConfig(**{field: value})


def test_bad_stage():
    with pytest.raises(ValueError, match="Stage.views must be a positive int, got 0"):
        Stage(1, 0, 10)


def _rig(cameras, instants):
    """Times of a synchronized rig's views, camera by camera (view c * instants + k at time k)."""
    return [k / (instants - 1) for c in range(cameras) for k in range(instants)]


@pytest.mark.parametrize("cameras, m", [(8, 4), (8, 3), (5, 2), (4, 4)])
def test_instant_steps_hold_views_of_one_time_and_cover_every_view(cameras, m):
    instants = 6
    times = _rig(cameras, instants)
    s = ViewSampler(len(times), seed=3, times=times, time_spread="instant")
    steps = instants * -(-cameras // m)  # one epoch of visits
    seen = collections.Counter()
    for _ in range(steps):
        step = s.sample(m)
        assert len(step) == m and len(set(step)) == m  # M distinct views
        assert len({times[i] for i in step}) == 1  # all of one instant
        seen.update(step)
    assert set(seen) == set(range(len(times)))  # every view in an epoch
    assert max(seen.values()) <= 2  # a view repeats only to fill an instant's last visit
    if cameras % m == 0:
        assert set(seen.values()) == {1}


def test_instant_is_resumable_and_caps_m_to_an_instant():
    times = _rig(3, 4)
    a = ViewSampler(len(times), seed=5, times=times, time_spread="instant")
    for _ in range(5):
        a.sample(2)
    b = ViewSampler(len(times), seed=99, times=times, time_spread="instant")
    b.load_state_dict(a.state_dict())
    assert [a.sample(2) for _ in range(9)] == [b.sample(2) for _ in range(9)]
    with pytest.warns(UserWarning, match="an instant holds 3 views"):
        step = a.sample(5)
    assert len(step) == 3 and len({times[i] for i in step}) == 1


def test_instant_refuses_a_scene_without_shared_times():
    with pytest.raises(ValueError, match='"instant" needs views that share a time .* 10 distinct times'):
        ViewSampler(10, times=[k / 9 for k in range(10)], time_spread="instant")
    with pytest.raises(ValueError, match='"instant" needs one time per view'):
        ViewSampler(4, times=None, time_spread="instant")
