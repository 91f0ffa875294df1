"""bench_equal_compute's cross-scene summary: a run is compared with the reference run of its own
file, else with one of another file of the same scene and seed, and with the reference's best
so far (the best evaluation point of any of its runs within the row's CPU), checked here
against numbers worked out by hand."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_equal_compute as bench  # noqa: E402


def run(kind, budget, psnr, cpu, curve, gaussians=1000):
    return {"kind": kind, "budget": budget, "clock": "budget", "views": 1, "psnr": psnr, "ssim": 0.5,
            "gaussians": gaussians, "steps": int(budget), "work": budget, "cpu": cpu, "wall": cpu,
            "curve": [{"cpu": c, "step": 0, "work": 0, "psnr": p} for c, p in curve]}


def write(path, data, runs):
    path.write_text(json.dumps({"args": {"data": data, "seed": "0"}, "runs": runs}))
    return path


def rows_of(text):
    return [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines()[2:] if line]


def test_summary_pairs_across_files_and_against_the_best_so_far(tmp_path):
    # the baseline falls with more compute: 22 dB at 60 s (1k), 20 dB at 180 s (3k), whose curve
    # peaked at 23 dB at 120 s
    a = write(tmp_path / "a.json", "scenes/clutter", [
        run("baseline", 1000, 22.0, 60.0, [(30.0, 21.0), (60.0, 22.0)]),
        run("baseline", 3000, 20.0, 180.0, [(90.0, 21.5), (120.0, 23.0), (180.0, 20.0)]),
        run("default", 3000, 21.5, 150.0, [(150.0, 21.5)], gaussians=500)])
    # another file of the same scene: a candidate without a baseline of its own; and another scene
    b = write(tmp_path / "b.json", "scenes/clutter", [run("coarse-mv-budget", 3000, 22.5, 100.0, [(100.0, 22.5)], 300)])
    c = write(tmp_path / "c.json", "scenes/sparse", [run("coarse-mv-budget", 3000, 25.0, 100.0, [(100.0, 25.0)])])
    rows = {r[5]: r for r in rows_of(bench.summary([a, b, c]))}
    assert set(rows) == {"default", "coarse-mv-budget"}  # no baseline for sparse: no row
    # default at 150 s: 3k baseline 20.0 -> +1.50; best so far within 150 s is 23.0 -> -1.50
    assert rows["default"][7] == "+1.50" and rows["default"][9] == "-1.50" and rows["default"][10] == "0.50x"
    # the candidate at 100 s: best so far within 100 s is 22.0 (the 1k run's end) -> +0.50
    cand = rows["coarse-mv-budget"]
    assert cand[0] == "clutter" and cand[7] == "+2.50" and cand[9] == "+0.50" and cand[10] == "0.30x"
    # another reference kind
    ref = rows_of(bench.summary([a, b], reference="default"))
    assert {r[5] for r in ref} == {"baseline", "coarse-mv-budget"}
    assert bench.best_so_far(json.loads(a.read_text())["runs"], "baseline", 29.0) is None


def test_a_bench_run_starts_from_the_examples_init_with_its_background_shell():
    """bench_equal_compute builds its runs as train_3dgs.py does, so it must start from the same
    points: the scene's, plus the background shell the examples add (counted here from
    mvgs_plugin.data.init.background_shell itself), or the scene's alone with 0. A 10-step budget
    ends before densification starts, so the final count is the initial one."""
    import torch

    from mvgs_plugin.cli import BACKGROUND_POINTS, BUNDLED
    from mvgs_plugin.data import load_scene
    from mvgs_plugin.data.init import background_shell

    scene = load_scene(BUNDLED)
    shell, _, _ = background_shell(scene.train_cameras, scene.center, BACKGROUND_POINTS, scene.image)
    threads = torch.get_num_threads()
    try:
        plain = bench.train(None, "baseline", 10, 1, 1, 0, 4, background_points=0)
        shelled = bench.train(None, "baseline", 10, 1, 1, 0, 4)
    finally:
        torch.set_num_threads(threads)
    assert plain["gaussians"] == len(scene.points)
    assert shelled["gaussians"] == len(scene.points) + shell.shape[0] > len(scene.points)
    # every test view's PSNR is kept: their mean is the run's PSNR, and the median is theirs
    views = shelled["per_view_psnr"]
    assert len(views) == len(scene.test_cameras) and abs(sum(views) / len(views) - shelled["psnr"]) < 1e-9
    ordered = sorted(views)
    middle = len(ordered) // 2
    assert shelled["psnr_median"] == (ordered[middle] if len(ordered) % 2 else (ordered[middle - 1] + ordered[middle]) / 2)


def test_capped_run_kinds_take_the_budget_and_their_stage_plan(tmp_path):
    """The "-cap" kinds run the examples' CLI with --max-gaussians N: their config holds N and,
    for coarse-mv4-cap, 4 views per step at 1/4 resolution and 2 at 1/2; without N they stop."""
    import argparse

    from mvgs_plugin import cli

    def config(kind, n):
        ap = argparse.ArgumentParser()
        args = cli.common_args(ap, "out").parse_args(bench.run_argv(kind, 3000, 4, 0, 1, max_gaussians=n))
        return cli.config_from_args(args)

    mv = config("coarse-mv4-cap", 1234)
    assert mv.max_gaussians == 1234 and [(s.factor, s.views) for s in mv.stages] == [(4, 4), (2, 2), (1, 1)]
    assert mv.budget == 3000.0
    plain = config("default-cap", 99)
    assert plain.max_gaussians == 99 and all(s.views == 1 for s in plain.stages)
    assert config("coarse-mv4", None).max_gaussians is None
    with pytest.raises(ValueError, match="needs --max-gaussians"):
        bench.run_argv("default-cap", 3000, 4, 0, 1)
    with pytest.raises(SystemExit):
        bench.main(["--runs", "default-cap", "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit):  # a budget no run kind takes
        bench.main(["--runs", "default", "--max-gaussians", "10", "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_a_run_the_examples_refuse_ends_the_benchmark_with_its_error(tmp_path, capsys):
    """--resolution-scale 9 on the bundled 128 px scene is refused once a worker reads the scene:
    the benchmark ends with that message and exit code 2 (a multiprocessing Pool waited for ever
    for a worker that exited); bad values of its own flags are refused before any worker starts."""
    with pytest.raises(SystemExit) as err:
        bench.main(["--budgets", "40", "--runs", "baseline", "--processes", "1", "--points", "1",
                    "--resolution-scale", "9", "--out", str(tmp_path / "b")])
    assert err.value.code == 2
    assert "--resolution-scale 9 makes the 128x128 images 14x14" in capsys.readouterr().err
    for flag, value in (("--processes", "0"), ("--points", "0"), ("--data", str(tmp_path / "missing"))):
        with pytest.raises(SystemExit):
            bench.main(["--budgets", "40", flag, value, "--out", str(tmp_path / "c")])
        assert flag in capsys.readouterr().err


def test_the_spelled_out_plans_are_the_defaults_now_and_before(tmp_path):
    """default-half is today's default plan and default-quarter the one before 2026-11-27 (10 /
    20 / 70 % of the work at 1/4, 1/2 and full resolution), each worked out here from the view
    cost 0.1 + 0.9 / f: given one budget, the spelled-out kind and the plan it stands for make
    the same stages."""
    from mvgs_plugin import cli
    from mvgs_plugin.config import MVGSConfig

    def stages(kind, budget=3000):
        import argparse
        parser = argparse.ArgumentParser()
        parser.add_argument("--data", default=str(tmp_path))
        args = cli.common_args(parser, "out").parse_args(bench.run_argv(kind, budget, 1, 0, 1))
        return [(s.factor, s.views, s.steps) for s in cli.config_from_args(args).stages]

    assert stages("default-half") == stages("default")
    before = [(4, 1, 0.1), (2, 1, 0.2), (1, 1, 0.7)]
    assert stages("default-quarter") == [(f, m, round(3000 * w / (0.1 + 0.9 / f))) for f, m, w in before]
    now = [(f, m, round(3000 * w / (0.1 + 0.9 / f))) for f, m, w in ((2, 1, 0.3), (1, 1, 0.7))]
    assert stages("default") == now and MVGSConfig.default().with_budget(3000).stages[0].factor == 2


def test_the_reset_scope_kinds_reach_the_model_and_keep_their_presets():
    """baseline-reset-inside / default-reset-inside (and the plain kinds, since "inside" is the
    default) give the model opacity_reset_scope "inside", the -reset-all kinds 3DGS's "all";
    each stays its preset."""
    import importlib.util

    from mvgs_plugin import cli

    spec = importlib.util.spec_from_file_location("train_3dgs_bench", ROOT / "examples" / "train_3dgs.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    for kind, preset in (("baseline-reset-inside", "baseline"), ("default-reset-inside", "default"),
                         ("baseline", "baseline"), ("default", "default"),
                         ("baseline-reset-all", "baseline"), ("default-reset-all", "default")):
        args = example.parse_args(bench.run_argv(kind, 3000, 4, 0, 1))
        config = cli.config_from_args(args)
        model = cli.model_config(config, 0, opacity_reset_scope=args.opacity_reset_scope)
        assert config.preset == preset
        assert model.opacity_reset_scope == ("all" if kind.endswith("-all") else "inside")
        assert (len(config.stages) == 1) == (preset == "baseline")  # the default keeps its pyramid


def test_the_baseline_cap_kinds_order_growth_as_named():
    """baseline-cap runs the baseline at --max-gaussians N with GS3DConfig's growth order ("auto":
    the object first on a rig round the scene), baseline-score-cap by score alone; both need N."""
    import importlib.util

    from mvgs_plugin import cli
    from mvgs_plugin.adapters.gs3d import GS3DAdapter
    from mvgs_plugin.testing import synthetic_scene

    spec = importlib.util.spec_from_file_location("train_3dgs_bench_cap", ROOT / "examples" / "train_3dgs.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    around = synthetic_scene(n_train=8, n_test=2, size=16, n_points=80)
    for kind, order in (("baseline-cap", "inside-first"), ("baseline-score-cap", "score")):
        args = example.parse_args(bench.run_argv(kind, 3000, 4, 0, 1, max_gaussians=777))
        config = cli.config_from_args(args)
        assert config.preset == "baseline" and config.max_gaussians == 777 and len(config.stages) == 1
        model = cli.model_config(config, 0, budget_growth_order=args.budget_growth_order)
        assert GS3DAdapter.from_scene(around, model).config.budget_growth_order == order
        with pytest.raises(ValueError, match="needs --max-gaussians"):
            bench.run_argv(kind, 3000, 4, 0, 1)


def test_the_faint_kinds_ask_for_the_cut_and_keep_their_presets():
    """baseline-faint / default-faint: the baseline and the default with MVGSConfig.prune_faint
    0.01 (the default's own since 2026-11-30), default-no-faint the default without it, parsed as
    the benchmark's own runs parse them (the examples' flags and model flags)."""
    import argparse

    from mvgs_plugin import cli

    for kind, preset, share in (("baseline-faint", "baseline", 0.01), ("default-faint", "default", 0.01),
                                ("baseline", "baseline", 0.0), ("default", "default", 0.01),
                                ("default-no-faint", "default", 0.0)):
        parser = argparse.ArgumentParser()
        parser.add_argument("--data")
        args = cli.world_size_arg(cli.common_args(parser, "out/bench")).parse_args(bench.run_argv(kind, 3000, 4, 0, 1))
        config = cli.config_from_args(args)
        assert (config.preset, config.prune_faint) == (preset, share), kind


def test_the_tables_give_the_median_view_beside_the_mean(tmp_path):
    # a run whose mean falls on two bad views while its median view rises; a run saved before the
    # median was recorded gets an empty cell
    base = dict(run("baseline", 3000, 30.0, 100.0, [(100.0, 30.0)]), psnr_median=31.0)
    cand = dict(run("default", 3000, 29.5, 90.0, [(90.0, 29.5)]), psnr_median=31.4)
    old = run("compact", 3000, 29.0, 80.0, [(80.0, 29.0)])
    rows = {r[1]: r for r in rows_of(bench.table([base, cand, old], "tabletop").split("\n", 2)[2])}
    assert rows["baseline"][12] == "31.00" and rows["baseline"][13] == ""
    assert rows["default"][6] == "-0.50" and rows["default"][12] == "31.40" and rows["default"][13] == "+0.40"
    assert rows["compact"][12] == "" and rows["compact"][13] == ""
    summed = {r[5]: r for r in rows_of(bench.summary([write(tmp_path / "a.json", "scenes/tabletop", [base, cand, old])]))}
    assert summed["default"][7] == "-0.50" and summed["default"][13] == "+0.40" and summed["compact"][13] == ""


def test_summary_at_equal_cpu_interpolates_the_reference_and_pools_seeds(tmp_path):
    """The equal-CPU column: the reference's final PSNR, linear between the two runs whose CPU
    brackets the row's (30 dB at 100 s, 32 at 200 s, 33 at 300 s: 31.5 dB at 175 s, worked out by
    hand); a run cheaper than every reference run says by how much; the seed table averages."""
    base = [run("baseline", 1000, 30.0, 100.0, [(100.0, 30.0)]), run("baseline", 2000, 32.0, 200.0, [(200.0, 32.0)]),
            run("baseline", 3000, 33.0, 300.0, [(300.0, 33.0)])]
    s0 = tmp_path / "s0.json"
    s0.write_text(json.dumps({"args": {"data": "scenes/x", "seed": "0"}, "runs": base + [
        run("default", 3000, 32.0, 175.0, [(175.0, 32.0)], gaussians=500),   # 31.5 at 175 s -> +0.50
        run("default", 1000, 30.5, 80.0, [(80.0, 30.5)], gaussians=500)]}))  # below 100 s: at 0.80x
    s1 = tmp_path / "s1.json"
    s1.write_text(json.dumps({"args": {"data": "scenes/x", "seed": "1"}, "runs": base + [
        run("default", 3000, 32.2, 250.0, [(250.0, 32.2)], gaussians=250)]}))  # 32.5 at 250 s -> -0.30
    rows = {(r[1], r[3]): r for r in rows_of(bench.summary([s0, s1]))}
    assert rows[("0", "3000")][14] == "+0.50" and rows[("0", "3000")][7] == "-1.00"
    assert rows[("0", "1000")][14] == "at 0.80x"
    assert rows[("1", "3000")][14] == "-0.30" and rows[("1", "3000")][7] == "-0.80"
    assert bench.equal_cpu_psnr(base, "baseline", 350.0) is None and bench.equal_cpu_psnr(base[:1], "baseline", 100.0) is None
    pooled = {(r[2], r[3]): r for r in rows_of(bench.seed_summary([s0, s1]).split("\n", 2)[2])}
    # 3000: equal work -1.00 and -0.80 (mean -0.90), equal CPU +0.50 and -0.30 (mean +0.10), Gaussians 0.50x and 0.25x
    assert pooled[("3000", "default")][4:] == ["0 1", "-0.90 (-1.00 to -0.80)", "+0.10 (-0.30 to +0.50) (2)", "0.38x", "0.71x"]
    assert pooled[("1000", "default")][4:7] == ["0", "+0.50", ""]
