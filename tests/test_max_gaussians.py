"""The exact Gaussian budget (MVGSConfig.max_gaussians, issue 27): a run never holds more than N
primitives, through densification, opacity resets, pyramid hand-offs and a checkpoint resume;
a larger initial model is cut before the first render; growth follows the schedule
n0 + (N - n0) (1 - (1 - x)^2), written out here from its definition; an adapter that ignores the
cap stops the run."""

from __future__ import annotations

import math

import pytest
import torch

from mvgs_plugin import MVGS, MVGSConfig
from mvgs_plugin.config import Stage
from mvgs_plugin.cli import DensifyTally
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig, even_cut_order
from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig
from mvgs_plugin.protocol import DensifyReport
from mvgs_plugin.testing import synthetic_scene

STEPS = 300


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=8, n_test=2, size=16, n_points=80)


def make(scene):
    torch.manual_seed(0)
    return GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=STEPS, sh_degree_interval=30))


def config(budget, **kw):
    # default(): its pyramid stages, clocks on work; β unscaled so that 16 px views densify; resets
    # 10 densifications apart, so that a 300-step run resets
    kw = {"min_densify_per_reset": 10, **kw}
    return MVGSConfig.default(max_gaussians=budget, grad_threshold_width=None, **kw).with_total_steps(STEPS)


def schedule_cap(cfg, n0, budget, clock):
    """The budget's cap at a densification call, from its definition."""
    start = min(n0, budget)
    x = (clock - cfg.densify_from) / (cfg.densify_until - cfg.densify_every - cfg.densify_from)
    x = min(1.0, max(0.0, x))
    return math.floor(start + (budget - start) * (1 - (1 - x) ** 2))


def watch_renders(trainer):
    """Records the primitive count at every render call."""
    counts = []
    original = trainer.adapter.render

    def render(cams, bgs):
        counts.append(trainer.adapter.num_primitives())
        return original(cams, bgs)

    trainer.adapter.render = render
    return counts


def resumed_copy(trainer, scene, cfg, tmp_path):
    """A second trainer resumed from a checkpoint of `trainer` now, with its renders watched."""
    trainer.save_checkpoint(str(tmp_path / "half.pt"))
    resumed = MVGS(make(scene), scene, cfg)
    resumed.load_checkpoint(str(tmp_path / "half.pt"))
    return resumed, watch_renders(resumed)


def test_a_larger_initial_model_is_cut_before_the_first_render(scene):
    budget = 50
    trainer = MVGS(make(scene), scene, config(budget))
    # no view folded in yet: opacity x even_cut_order about the scene's centre (the object's and the
    # far background's shares, each spread; tests/test_initial_cut.py checks that order)
    scores = trainer.adapter.get_opacities().detach() * even_cut_order(trainer.adapter.params["means"],
                                                                        scene.center).float()
    want = sorted(torch.argsort(scores, descending=True)[:budget].tolist())
    means0 = trainer.adapter.params["means"].detach().clone()
    counts = watch_renders(trainer)
    tally = DensifyTally(trainer.adapter.num_primitives())  # metrics.json's "densification"
    loaded = trainer.adapter.num_primitives()
    assert tally.totals["peak_primitives"] == loaded > budget  # the points as loaded
    tally.add(trainer.step())
    assert counts[0] == budget
    assert tally.totals["peak_primitives"] == budget  # the most the run held: the loaded points are not counted
    assert tally.totals["budget_cut"] == loaded - budget  # ... and what the cut took is recorded
    kept = trainer.adapter.params["means"].detach()
    # the first step moved the means a little: match each kept row to its nearest initial one
    nearest = torch.cdist(kept.double(), means0.double()).argmin(1)
    assert sorted(nearest.tolist()) == want


def test_the_budget_holds_through_every_phase_and_follows_its_schedule(scene, tmp_path):
    budget = 120
    cfg = config(budget, budget_swap=0.02)  # off by default: the swap runs here too
    trainer = MVGS(make(scene), scene, cfg)
    n0 = trainer.adapter.num_primitives()
    assert n0 == 80 < budget
    counts = watch_renders(trainer)
    seen = {"densify": 0, "reset": 0, "stages": set(), "grew": 0, "capped": 0, "swapped": 0}
    for _ in range(STEPS // 2):
        info = trainer.step()
        seen["stages"].add(info.stage)
        seen["reset"] += info.opacity_reset
        if info.densify is not None:
            seen["densify"] += 1
            seen["grew"] += info.densify.after > info.densify.before
            cap = schedule_cap(trainer.config, n0, budget, trainer.schedule.plan.locate(info.step).clock)
            assert info.densify.extra["cap"] == cap
            assert info.num_primitives <= cap
            seen["capped"] += info.densify.extra["dropped_by_max_gaussians"] > 0
            seen["swapped"] += info.densify.extra["swapped"]
    resumed, resumed_counts = resumed_copy(trainer, scene, cfg, tmp_path)
    for run in (trainer, resumed):
        while run.step_count < run.total_steps:
            info = run.step()
            seen["stages"].add(info.stage)
            seen["reset"] += info.opacity_reset and run is trainer
            if info.densify is not None and run is trainer:
                seen["densify"] += 1
                seen["capped"] += info.densify.extra["dropped_by_max_gaussians"] > 0
                seen["swapped"] += info.densify.extra["swapped"]
    assert max(counts + resumed_counts) <= budget
    assert seen["densify"] >= 5 and seen["reset"] >= 1 and seen["stages"] == set(range(len(trainer.config.stages)))
    assert seen["grew"] >= 1 and seen["capped"] >= 1  # it grew, and the schedule held it back
    assert seen["swapped"] >= 1  # and at the cap, rows made way for candidates (budget_swap 0.02)
    for name, p in trainer.adapter.params.items():  # the resumed run is the same run
        torch.testing.assert_close(resumed.adapter.params[name], p, rtol=0, atol=0)
    # without the budget the same run holds more than it
    free = MVGS(make(scene), scene, config(None)).fit(progress=False)
    assert free.adapter.num_primitives() > budget


def test_an_initial_share_leaves_room_that_growth_fills_by_the_schedule(scene, tmp_path):
    """budget_initial_share s: a model above floor(s N) is cut to it before the first render (the
    same order as a cut to N would rank), the schedule starts from that count and
    reaches N, growth fills the room, and a resumed run is not cut again (it is the same run)."""
    budget, share = 60, 0.5
    start = math.floor(share * budget)
    cfg = config(budget, budget_initial_share=share)
    assert cfg.initial_cap() == start == 30
    trainer = MVGS(make(scene), scene, cfg)
    assert trainer.adapter.num_primitives() == 80 > budget
    order = even_cut_order(trainer.adapter.params["means"], scene.center).float()
    want = sorted(torch.argsort(trainer.adapter.get_opacities().detach() * order, descending=True)[:start].tolist())
    means0 = trainer.adapter.params["means"].detach().clone()
    counts = watch_renders(trainer)
    caps = []
    for _ in range(STEPS // 2):
        info = trainer.step()
        if info.step == 1:  # the rows kept by the cut: the top `start` of that order
            kept = trainer.adapter.params["means"].detach()
            assert sorted(torch.cdist(kept.double(), means0.double()).argmin(1).tolist()) == want
        if info.densify is not None:
            clock = trainer.schedule.plan.locate(info.step).clock
            caps.append(info.densify.extra["cap"])
            assert info.densify.extra["cap"] == schedule_cap(trainer.config, start, budget, clock)
    assert counts[0] == start
    at_checkpoint = trainer.adapter.num_primitives()
    resumed, resumed_counts = resumed_copy(trainer, scene, cfg, tmp_path)
    for run in (trainer, resumed):
        while run.step_count < run.total_steps:
            info = run.step()
            if info.densify is not None and run is trainer:
                caps.append(info.densify.extra["cap"])
    assert resumed_counts[0] == at_checkpoint  # a resumed run is not cut to the share again
    assert max(counts + resumed_counts) <= budget
    assert caps[0] < budget and caps[-1] == budget  # the cap climbs from the cut to N
    assert max(counts) > start  # and growth used the room the cut left
    for name, p in trainer.adapter.params.items():
        torch.testing.assert_close(resumed.adapter.params[name], p, rtol=0, atol=0)


def test_scaffold_anchors_keep_the_budget(scene):
    budget = 40
    adapter = ScaffoldAdapter.from_scene(scene, ScaffoldConfig(voxel_size=0.05, lr_max_steps=STEPS, seed=0))
    assert adapter.num_primitives() > budget
    trainer = MVGS(adapter, scene, config(budget))
    counts = watch_renders(trainer)
    densified = 0
    for _ in range(STEPS):
        info = trainer.step()
        densified += info.densify is not None
    assert densified >= 5 and max(counts) <= budget and counts[0] == budget


def test_an_adapter_that_ignores_the_cap_stops_the_run(scene):
    class Careless(GS3DAdapter):
        def densify(self, ctx):
            return DensifyReport(before=self.num_primitives(), after=self.num_primitives())

    torch.manual_seed(0)
    adapter = Careless.from_scene(scene, GS3DConfig())
    trainer = MVGS(adapter, scene, config(50))
    with pytest.raises(RuntimeError, match="above the cap 50"):
        trainer.step()


def test_bad_budgets_are_refused():
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="max_gaussians"):
            MVGSConfig(max_gaussians=bad)
    with pytest.raises(ValueError, match="densify_rank"):
        MVGSConfig(densify_rank="loss")
    for bad in (-0.1, 1.0, True, "0.1", math.nan):
        with pytest.raises(ValueError, match="budget_swap"):
            MVGSConfig(budget_swap=bad)
    for bad in (0, -0.5, 1.5, True, "0.5", math.nan, math.inf):
        with pytest.raises(ValueError, match=r"budget_initial_share must be a share of max_gaussians in \(0, 1\]"):
            MVGSConfig(budget_initial_share=bad)


def test_pixels_per_gaussian_sets_the_budget_from_the_training_views(scene):
    # 8 training views of 16 x 16 px: 2048 pixels; at 64 pixels per Gaussian, 32 Gaussians
    assert len(scene.train_cameras) == 8 and {(c.width, c.height) for c in scene.train_cameras} == {(16, 16)}
    assert MVGSConfig.baseline(pixels_per_gaussian=64).for_scene(scene).max_gaussians == 32
    # counted at the finest stage's resolution: factor 2 renders 8 x 8 px views, 512 pixels
    coarse = MVGSConfig.baseline(pixels_per_gaussian=64, stages=(Stage(4, 1, 10), Stage(2, 1, 10)))
    assert coarse.for_scene(scene).max_gaussians == 8
    # an explicit budget wins; the rule is idempotent; one pixel count per Gaussian gives one
    assert MVGSConfig.baseline(pixels_per_gaussian=64, max_gaussians=7).for_scene(scene).max_gaussians == 7
    once = MVGSConfig.default(pixels_per_gaussian=64).for_scene(scene)
    assert once.for_scene(scene) == once
    assert MVGSConfig.baseline(pixels_per_gaussian=2048).for_scene(scene).max_gaussians == 1
    # a ratio that leaves no Gaussian is refused, naming the pixels (it was rounded up to 1 in silence)
    with pytest.raises(ValueError, match=r"pixels_per_gaussian=1e\+09 gives a budget of no Gaussian for the 2048 "
                                         r"training pixels; give at most 2048"):
        MVGSConfig.baseline(pixels_per_gaussian=1e9).for_scene(scene)
    # a run with it holds the same budget: the controller resolves the config for its scene
    trainer = MVGS(make(scene), scene, config(None, pixels_per_gaussian=64))
    counts = watch_renders(trainer)
    trainer.step()
    assert trainer.config.max_gaussians == 32 and counts[0] == 32


def test_pixels_per_gaussian_reaches_the_config_from_the_command_line(scene):
    from mvgs_plugin import cli

    import argparse

    ap = cli.common_args(argparse.ArgumentParser(), out="out")
    args = ap.parse_args(["--preset", "baseline", "--pixels-per-gaussian", "128", "--steps", "100"])
    assert cli.config_from_args(args, scene).max_gaussians == 16  # 2048 / 128
    for bad in ("0", "-3", "nan", "inf"):
        with pytest.raises(SystemExit):
            ap.parse_args(["--pixels-per-gaussian", bad])
    for bad in (0, -1.0, float("nan"), float("inf"), True, "64"):
        with pytest.raises(ValueError, match="pixels_per_gaussian"):
            MVGSConfig(pixels_per_gaussian=bad)
    # a ratio that leaves no Gaussian on this scene: one line naming the flag, as argparse's errors
    args = ap.parse_args(["--preset", "baseline", "--pixels-per-gaussian", "5000", "--steps", "100"])
    with pytest.raises(cli.UsageError, match="--pixels-per-gaussian 5000: .* no Gaussian for the 2048 training pixels"):
        cli.config_from_args(args, scene)


def test_scaffold_refuses_a_swap_its_anchors_cannot_make(capsys):
    from test_late_views import _example

    example = _example("train_scaffold.py")
    assert example.parse_args(["--max-gaussians", "50"]).budget_swap is None
    with pytest.raises(SystemExit):
        example.parse_args(["--max-gaussians", "50", "--budget-swap", "0.5"])
    assert "--budget-swap 0.5: Scaffold-GS anchors do not swap" in capsys.readouterr().err


def test_budget_swap_reaches_the_config_from_the_command_line(scene, capsys):
    from mvgs_plugin import cli

    import argparse

    ap = cli.common_args(argparse.ArgumentParser(), out="out")
    args = ap.parse_args(["--preset", "baseline", "--max-gaussians", "50", "--steps", "100"])
    assert cli.config_from_args(args, scene).budget_swap == 0.0  # off by default
    args = ap.parse_args(["--preset", "baseline", "--max-gaussians", "50", "--budget-swap", "0.3", "--steps", "100"])
    assert cli.config_from_args(args, scene).budget_swap == 0.3
    for bad in ("1", "-0.1", "nan", "x"):
        with pytest.raises(SystemExit):
            ap.parse_args(["--budget-swap", bad])
        assert "--budget-swap" in capsys.readouterr().err
    args = ap.parse_args(["--preset", "baseline", "--max-gaussians", "50", "--budget-initial-share", "0.25"])
    assert cli.config_from_args(args, scene).initial_cap() == 12
    for bad in ("0", "1.5", "nan"):
        with pytest.raises(SystemExit):
            ap.parse_args(["--budget-initial-share", bad])
        assert "--budget-initial-share" in capsys.readouterr().err


def test_a_budget_turns_size_pruning_off_unless_asked(scene):
    """ctx.prune_large after prune_large_after: on without a budget (3DGS), off with one, on with
    one and budget_size_pruning."""
    seen = {}
    for name, budget, kw in (("free", None, {}), ("budget", 500, {}), ("budget+size", 500, {"budget_size_pruning": True})):
        trainer = MVGS(make(scene), scene, config(budget, **kw))
        flags = []
        original = trainer.adapter.densify

        def spy(ctx, original=original, flags=flags, trainer=trainer):
            if not ctx.faint_share:  # the default's cut of the faintest after the window prunes nothing by size
                flags.append((trainer.schedule.plan.locate(trainer.step_count).clock, ctx.prune_large))
            return original(ctx)

        trainer.adapter.densify = spy
        trainer.fit(progress=False)
        after = [f for c, f in flags if c > trainer.config.prune_large_after]
        assert len(after) >= 3
        seen[name] = set(after)
    assert seen == {"free": {True}, "budget": {False}, "budget+size": {True}}
    with pytest.raises(ValueError, match="budget_size_pruning"):
        MVGSConfig(budget_size_pruning=1)


def test_budget_size_pruning_from_the_command_line(scene):
    from mvgs_plugin import cli

    import argparse

    ap = cli.common_args(argparse.ArgumentParser(), out="out")
    assert cli.config_from_args(ap.parse_args(["--max-gaussians", "50"]), scene).budget_size_pruning is False
    args = ap.parse_args(["--max-gaussians", "50", "--budget-size-pruning"])
    assert cli.config_from_args(args, scene).budget_size_pruning is True
