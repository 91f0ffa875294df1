"""MVGSConfig.with_late_views and train_4dgs.py's --late-views: the work the pyramid's coarse
steps save, spent as M-view steps at the end, so that a run of N steps does N full-resolution
views of work. The work is recomputed here from the cost model's definition (a view at factor f
costs 0.1 + 0.9 / f of a full-resolution one), not through MVGSConfig.step_work."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from mvgs_plugin.cli import config_from_args
from mvgs_plugin.config import MVGSConfig, Stage

ROOT = Path(__file__).resolve().parents[1]


def _work(stages) -> float:
    finest = min(s.factor for s in stages)
    return sum(s.steps * s.views * (0.1 + 0.9 * finest / s.factor) for s in stages)


def _example(script: str):
    spec = importlib.util.spec_from_file_location(script[:-3] + "_late", ROOT / "examples" / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("views", [2, 3, 4])
@pytest.mark.parametrize("total", [600, 3000, 30_000])
def test_a_late_view_plan_does_the_work_of_its_steps(views, total):
    # The late stage spends the saving of the recipe's own warm-up, so the plan keeps its proportions
    # at every length (no warmup_work_cap, which would cut the warm-up at 30k and not the late steps).
    plain = MVGSConfig.default(warmup_work_cap=None).with_total_steps(total)
    late = MVGSConfig.default().with_late_views(views).with_total_steps(total)
    assert late.total_steps == total and late.warmup_work_cap is None
    # the pyramid alone saves what its coarse steps do not cost: 0.45 of a full view per step at 1/2
    coarse = plain.stages[:-1]
    saved = sum(s.steps * (1 - (0.1 + 0.9 / s.factor)) for s in coarse)
    assert saved > 0.15 * total and _work(plain.stages) == pytest.approx(total - saved, abs=1e-6)
    # every stage rounds to whole steps: the work is the step count within a few views
    assert abs(_work(late.stages) - total) <= views + 1, (late.stages, _work(late.stages))
    # the pyramid is kept; the last stage is split into one-view then M-view steps at full resolution
    n = len(coarse)
    assert late.stages[:n] == plain.stages[:n]
    assert [(s.factor, s.views) for s in late.stages[n:]] == [(1, 1), (1, views)]
    assert late.stages[n].steps + late.stages[n + 1].steps == plain.stages[n].steps


def test_late_views_keep_their_split_at_another_resolution_and_on_a_budget():
    base = MVGSConfig.default()
    scaled = MVGSConfig.default(stages=tuple(Stage(s.factor * 2, s.views, s.steps) for s in base.stages))
    assert [s.steps for s in scaled.with_late_views(2).stages] == [s.steps for s in base.with_late_views(2).stages]
    on_budget = base.with_late_views(2).with_budget(600)
    assert abs(_work(on_budget.stages) - 600) <= 3 and on_budget.stages[-1].views == 2
    # equal work: as many steps as a single-view full-resolution run of the same budget, within rounding
    assert abs(on_budget.total_steps - 600) <= 3


def test_late_views_change_nothing_without_a_cheaper_stage_or_with_one_view():
    assert MVGSConfig.baseline().with_late_views(2) == MVGSConfig.baseline()
    assert MVGSConfig.default().with_late_views(1) == MVGSConfig.default()


@pytest.mark.parametrize("bad", [0, -2, True, 2.0, "2"])
def test_a_bad_late_view_count_is_refused_naming_it(bad):
    with pytest.raises(ValueError, match=f"late views must be an int >= 1, got {bad!r}"):
        MVGSConfig.default().with_late_views(bad)


def test_late_views_refuse_a_plan_whose_last_stage_has_several_views():
    with pytest.raises(ValueError, match="views=8"):
        MVGSConfig.multiview().with_late_views(2)
    with pytest.raises(ValueError, match="one view per step"):
        MVGSConfig.default().with_views(2).with_late_views(2)


def test_late_views_refuse_restarting_clocks_a_budget_and_a_last_stage_too_short():
    with pytest.raises(ValueError, match="preset 'paper' has restart_per_stage=True"):
        MVGSConfig.paper().with_views(1).with_late_views(2)
    with pytest.raises(ValueError, match="already has budget=600.0"):
        MVGSConfig.default().with_budget(600).with_late_views(2)
    # 1000 steps at 1/4 save 1000 x (1 - 0.325) = 675 views of work; a last stage of 10 cannot take them
    with pytest.raises(ValueError, match="675 2-view steps, more than the last stage's 10 steps"):
        MVGSConfig.default(stages=(Stage(4, 1, 1000), Stage(1, 1, 10))).with_late_views(2)


@pytest.mark.parametrize("total", [3000, 4500, 10_000])
def test_every_schedule_keeps_its_share_of_the_work_on_either_clock(total):
    """Densification ends at half the run's work, resets come every tenth, size pruning starts
    at a tenth: the shares of 3DGS's 30k recipe (15000, 3000, 3000 of 30000), whether the run is
    asked for in steps or as a budget of the same work (lengths where with_total_steps' floors
    for short runs, a reset at most every 300, do not act)."""
    late = MVGSConfig.default().with_late_views(2)
    by_steps, by_budget = late.with_total_steps(total), late.with_budget(total)
    for config in (by_steps, by_budget):  # the same plan, to a step of rounding
        assert [(s.factor, s.views) for s in config.stages] == [(2, 1), (1, 1), (1, 2)]
        assert all(abs(a.steps - b.steps) <= 1 for a, b in zip(config.stages, by_steps.stages))
        assert abs(config.densify_until - total / 2) <= 1
        assert abs(config.opacity_reset_every - total / 10) <= 1
        assert abs(config.prune_large_after - total / 10) <= 1


def test_train_4dgs_late_views_default_and_overrides(tmp_path):
    example = _example("train_4dgs.py")
    data = ["--data", str(tmp_path), "--steps", "600"]

    def resolved(*flags):
        args = example.parse_args(data + list(flags))
        return args.late_views, config_from_args(args).stages

    views, stages = resolved()
    assert views == example.LATE_VIEWS == 2 and stages[-1].views == 2 and abs(_work(stages) - 600) <= 3
    assert resolved("--preset", "compact")[0] == 2
    for flags in (["--preset", "baseline"], ["--views", "2"], ["--stages", "4:1:100,1:1:500"], ["--late-views", "1"],
                  ["--budget", "600"]):
        views, stages = resolved(*flags)
        assert views == 1 and all(s.views == stages[-1].views for s in stages), flags
    assert resolved("--late-views", "1")[1] == MVGSConfig.default().with_total_steps(600).stages
    views, stages = resolved("--late-views", "3")
    assert views == 3 and stages[-1].views == 3 and abs(_work(stages) - 600) <= 4
    with pytest.raises(SystemExit):
        example.parse_args(data + ["--late-views", "0"])
    from mvgs_plugin.cli import UsageError  # one line from launch(), not a traceback

    with pytest.raises(UsageError, match="--late-views 2: late views need"):
        config_from_args(example.parse_args(data + ["--preset", "multiview", "--late-views", "2"]))


def test_train_3dgs_has_no_late_views(capsys):
    with pytest.raises(SystemExit):
        _example("train_3dgs.py").parse_args(["--late-views", "2"])
    assert "unrecognized arguments: --late-views 2" in capsys.readouterr().err


def test_on_a_forward_facing_rig_late_views_add_nothing(tmp_path):
    """for_scene drops the pyramid on a forward-facing rig, so there is no saving to spend: the
    4DGS example's config there is the single-view full-resolution plan of the baseline's length."""
    import argparse

    from mvgs_plugin import cli
    from test_forward_init import parallel_rig
    from test_forward_rig import Rig

    fwd = Rig(parallel_rig([-1.0, -0.5, 0.0, 0.5, 1.0]))
    ap = cli.late_views_arg(cli.common_args(argparse.ArgumentParser(), "out"), 2)
    args = cli.resolve_late_views(ap.parse_args(["--steps", "600"]), 2)
    assert args.late_views == 2
    config = config_from_args(args, fwd)
    assert [(s.factor, s.views) for s in config.stages] == [(1, 1)] and config.total_steps == 600
    assert abs(_work(config.stages) - 600) < 1e-9
    # and on a converging rig the same flags spend the pyramid's saving
    assert config_from_args(args).stages[-1].views == 2


def test_the_view_cap_of_a_small_rig_applies_to_the_late_stage():
    """--max-views-fraction caps every stage's views at that share of the training cameras, the
    late stage too (three cameras, 0.5: one view per step), and the run keeps its --steps."""
    import argparse

    from mvgs_plugin import cli
    from test_forward_rig import Rig, ring

    ap = cli.late_views_arg(cli.common_args(argparse.ArgumentParser(), "out"), 2)
    args = cli.resolve_late_views(ap.parse_args(["--steps", "600", "--max-views-fraction", "0.5"]), 2)
    config = config_from_args(args, Rig(ring(3)))
    assert all(s.views == 1 for s in config.stages) and config.total_steps == 600
    uncapped = config_from_args(cli.resolve_late_views(ap.parse_args(["--steps", "600"]), 2), Rig(ring(3)))
    assert uncapped.stages[-1].views == 2 and uncapped.total_steps == 600


def test_a_run_too_short_for_its_plan_is_a_usage_error_naming_the_flag(tmp_path):
    """--steps below the plan's stage count: a one-line usage error naming the flag (no
    traceback), and on train_4dgs.py the hint that --late-views 1 drops the late stage."""
    from mvgs_plugin.cli import UsageError

    example = _example("train_4dgs.py")
    data = ["--data", str(tmp_path)]
    with pytest.raises(UsageError, match=r"--steps 2: the stage plan has 3 stages, so the run needs at least 3 steps "
                                         r"\(--late-views 2 added a stage; --late-views 1 does not\)"):
        config_from_args(example.parse_args(data + ["--steps", "2"]))
    assert len(config_from_args(example.parse_args(data + ["--steps", "2", "--late-views", "1"])).stages) == 2
    with pytest.raises(UsageError, match=r"--steps 1: the stage plan has 2 stages, so the run needs at least 2") as err:
        config_from_args(_example("train_3dgs.py").parse_args(data + ["--steps", "1"]))
    assert "--late-views" not in str(err.value)
    with pytest.raises(UsageError, match=r"--budget 500: the paper preset restarts its schedules at every stage"):
        config_from_args(example.parse_args(data + ["--preset", "paper", "--budget", "500", "--late-views", "1"]))


def test_a_refused_resume_names_the_late_views_value_of_the_checkpoint(tmp_path):
    """A checkpoint of the plain default (--late-views 1; train_4dgs.py's default before 2 became
    it) refused under today's default: the error names the flag that resumes it. A checkpoint of
    another plan altogether gets no hint."""
    import torch

    from mvgs_plugin.cli import late_views_hint
    from mvgs_plugin.io import save_checked

    example = _example("train_4dgs.py")
    data = ["--data", str(tmp_path), "--steps", "600"]
    plain = MVGSConfig.default().with_total_steps(600)  # the plan --late-views 1 gives, written out
    cases = {"plain": plain, "other": MVGSConfig.default().with_total_steps(700)}
    for name, cfg in cases.items():
        save_checked({"config": cfg.to_dict(), "schedule": {}, "torch_rng": torch.get_rng_state(), "adapter": {}},
                     str(tmp_path / f"{name}.pt"))
    args = example.parse_args(data + ["--resume", str(tmp_path / "plain.pt")])
    current = config_from_args(args)
    assert late_views_hint(args, None, current) == (" (the checkpoint's stage plan is this command's with "
                                                    "--late-views 1: add it to resume)")
    assert late_views_hint(example.parse_args(data + ["--resume", str(tmp_path / "other.pt")]), None, current) == ""
    # a plan with no coarse saving (the baseline) is the same for every --late-views: a checkpoint of
    # that plan refused for another reason (its seed) gets no hint
    base = ["--preset", "baseline"]
    save_checked({"config": MVGSConfig.baseline(seed=1).with_total_steps(600).to_dict()}, str(tmp_path / "seed1.pt"))
    args = example.parse_args(data + base + ["--resume", str(tmp_path / "seed1.pt")])
    assert late_views_hint(args, None, config_from_args(args)) == ""
    # under --late-views 1 a checkpoint of today's default is named the other way round
    late = config_from_args(example.parse_args(data))
    save_checked({"config": late.to_dict()}, str(tmp_path / "late.pt"))
    args = example.parse_args(data + ["--late-views", "1", "--resume", str(tmp_path / "late.pt")])
    assert "--late-views 2" in late_views_hint(args, None, config_from_args(args))


def test_a_given_late_views_that_adds_nothing_says_so(tmp_path, capsys):
    """--preset baseline --late-views 2 has no coarse stage whose saving it could spend: the run is
    the baseline's, and a note on stderr says the flag changed nothing (it used to be silent). The
    same plan reached by the example's own default (no --late-views given) prints nothing."""
    example = _example("train_4dgs.py")
    data = ["--data", str(tmp_path), "--steps", "600"]
    given = config_from_args(example.parse_args(data + ["--preset", "baseline", "--late-views", "2"]))
    assert given.stages == MVGSConfig.baseline().with_total_steps(600).stages
    err = capsys.readouterr().err
    assert "--late-views 2 changes nothing here: the plan has no coarser stage" in err
    config_from_args(example.parse_args(data + ["--preset", "baseline"]))
    assert "late-views" not in capsys.readouterr().err
    spent = config_from_args(example.parse_args(data + ["--late-views", "2"]))
    assert spent.stages[-1].views == 2 and "changes nothing" not in capsys.readouterr().err


def test_a_resume_refused_for_another_model_gets_no_late_views_hint(tmp_path, capsys):
    """The hint is for a checkpoint of this model refused for its stage plan alone: one written by
    another script (here a 3DGS model) whose plan happens to be the one --late-views 1 gives is
    refused as another model, and adding --late-views 1 would not resume it, so it is not said."""
    import torch

    from mvgs_plugin.data import load_scene
    from mvgs_plugin.io import save_checked
    from test_example_resume import _dnerf

    example = _example("train_4dgs.py")
    data = ["--data", str(_dnerf(tmp_path / "moving")), "--steps", "600", "--threads", "1", "--no-progress",
            "--out", str(tmp_path / "out")]
    scene = load_scene(tmp_path / "moving", init=None)
    plain = config_from_args(example.parse_args(data + ["--late-views", "1"]), scene)
    assert plain.stages != config_from_args(example.parse_args(data), scene).stages
    checkpoint = tmp_path / "gs3d.pt"
    save_checked({"config": plain.to_dict(), "schedule": {}, "torch_rng": torch.get_rng_state(),
                  "adapter": {"format": "mvgs-gs3d/1"}}, str(checkpoint))
    with pytest.raises(SystemExit) as err:
        example.main(data + ["--resume", str(checkpoint)])
    said = capsys.readouterr().err
    assert err.value.code == 2 and "the checkpoint holds a 'mvgs-gs3d/1' model and this run trains a 'mvgs-gs4d/1'" in said
    assert "--late-views" not in said, said
