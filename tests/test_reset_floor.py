"""MVGSConfig.min_densify_per_reset: a compressed schedule never resets opacities sooner than K
densification calls apart (3DGS's own ratio, K = 30: a reset every 3000 steps, a densification
every 100), so a short run's Gaussians have time to recover from one reset before the next."""

import argparse
import math

import pytest

from mvgs_plugin import cli
from mvgs_plugin.config import MVGSConfig
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import synthetic_scene


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=48, n_test=1, size=16, n_points=20)


def walked(scene, config):
    """(reset steps, densification steps) of the schedule, step by step."""
    schedule = ViewSchedule(scene, config)
    plans = [schedule.next() for _ in range(config.total_steps)]
    return [p.step for p in plans if p.reset_opacity], [p.step for p in plans if p.densify]


def test_the_3dgs_recipe_itself_is_untouched():
    # 30 densifications per reset is 3DGS's schedule (every 100 steps, reset every 3000): the
    # floor binds only when a run is compressed below 3000 steps per reset.
    full = MVGSConfig.baseline()
    assert full.min_densify_per_reset == 30
    assert full.opacity_reset_every == full.min_densify_per_reset * full.densify_every
    for n in (3000, 30_000, 60_000):
        c = full.with_total_steps(n)
        assert c.opacity_reset_every == round(3000 * n / 30_000)


@pytest.mark.parametrize("budget", [300, 700, 1000, 1500, 2000, 2999])
def test_a_short_baseline_resets_once_per_30_densifications(scene, budget):
    config = MVGSConfig.baseline().with_budget(budget)
    resets, densify = walked(scene, config)
    # Written out from the definition: densification every max(10, 100 B / 30k) steps from the
    # 50th, a reset at every multiple of 30 intervals while the window (B / 2) is open.
    every = max(10, round(100 * budget / 30_000))
    until = round(15_000 * budget / 30_000)
    assert resets == list(range(30 * every, until, 30 * every))
    assert densify == list(range(every * (50 // every + 1), until, every))
    for a, b in zip(resets, resets[1:]):
        assert sum(a < d <= b for d in densify) >= 30


@pytest.mark.parametrize("preset", ["baseline", "default", "multiview"])
@pytest.mark.parametrize("budget", [1000, 2500, 8000])
def test_no_two_resets_closer_than_k_densifications(scene, preset, budget):
    for k in (1, 10, 30):
        config = MVGSConfig.from_preset(preset, min_densify_per_reset=k).with_budget(budget)
        resets, densify = walked(scene, config)
        for a, b in zip(resets, resets[1:]):
            assert sum(a < d <= b for d in densify) >= k, (preset, budget, k, resets)


def test_the_old_floor_is_one_flag_away(scene):
    old = MVGSConfig.baseline(min_densify_per_reset=10).with_budget(1000)
    new = MVGSConfig.baseline().with_budget(1000)
    assert walked(scene, old)[0] == [100, 200, 300, 400]
    assert walked(scene, new)[0] == [300]
    assert walked(scene, old)[1] == walked(scene, new)[1]  # densification is unchanged


def test_the_cli_flag_and_bad_values(tmp_path):
    ap = cli.common_args(argparse.ArgumentParser(), str(tmp_path / "out"))
    c = cli.config_from_args(ap.parse_args(["--preset", "baseline", "--budget", "1000", "--min-densify-per-reset", "10"]))
    assert (c.min_densify_per_reset, c.opacity_reset_every) == (10, 100)
    c = cli.config_from_args(ap.parse_args(["--preset", "baseline", "--budget", "1000"]))
    assert (c.min_densify_per_reset, c.opacity_reset_every) == (30, 300)
    with pytest.raises(SystemExit):
        ap.parse_args(["--min-densify-per-reset", "0"])
    for bad in (0, -3, 2.5, True, "30"):
        with pytest.raises(ValueError, match="min_densify_per_reset"):
            MVGSConfig.baseline(min_densify_per_reset=bad)


def test_a_config_written_before_the_field_keeps_its_clocks():
    # Configs are stored with their clocks already compressed: one without the field reads the
    # same clocks back, whatever floor made them.
    d = MVGSConfig.baseline(min_densify_per_reset=10).with_budget(1000).to_dict()
    d.pop("min_densify_per_reset")
    back = MVGSConfig.from_dict(d)
    assert back.opacity_reset_every == 100
    assert MVGSConfig.from_dict(MVGSConfig.default().to_dict()) == MVGSConfig.default()


def test_resuming_an_old_short_run_names_the_floor():
    # A checkpoint of a 1k run made before the field: resuming it with today's floor is refused
    # by the config check, which names the field to set (--min-densify-per-reset 10).
    from mvgs_plugin.controller import config_differences

    old = MVGSConfig.baseline(min_densify_per_reset=10).with_budget(1000).to_dict()
    old.pop("min_densify_per_reset")
    differ = {name: (a, b) for name, a, b in config_differences(MVGSConfig.from_dict(old),
                                                                MVGSConfig.baseline().with_budget(1000))}
    assert differ == {"min_densify_per_reset": (10, 30), "opacity_reset_every": (100, 300)}
