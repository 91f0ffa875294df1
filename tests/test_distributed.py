"""Data-parallel MVGS over torch.distributed (gloo, 2 CPU processes on localhost).

The reference for every distributed run is the single-process controller run in this process on
the same config, seed and model. A distributed step sums the same per-view gradients in another
order, so in float64 the gradients the optimizer sees agree to rounding (1e-12 of each group's
largest entry) and so do the parameters (1e-9 relative: a few steps of Adam on top); ranks must
agree exactly."""

import datetime
import math
import os
import socket
import subprocess
import sys
import time
import traceback
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from mvgs_plugin.adapters.gs3d import STAT_NAMES, GS3DAdapter, GS3DConfig
from mvgs_plugin import MVGS, MVGSConfig, Stage
from mvgs_plugin.distributed import Collective, abort_on_error, backend_for, init_from_env, require_support, shard
from mvgs_plugin.cli import model_config
from mvgs_plugin.data import load_scene
from mvgs_plugin.io import load_checked
from mvgs_plugin.testing import check_adapter, check_distributed_support, synthetic_scene

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64


# ---- shared setup (the workers and the single-process reference build the same things) ---------
def make_scene():
    return synthetic_scene(n_train=6, n_test=2, size=16, n_points=80)


def make_trainer(config, dtype, distributed=None):
    torch.manual_seed(0)
    scene = make_scene()
    # Adam's eps: the 3DGS value 1e-15 turns gradients that are 0 in exact arithmetic but ±1e-19
    # after rounding (the rotation of an isotropic Gaussian) into full ±lr steps, so any change in
    # the order of a sum flips them by 2·lr. PyTorch's default 1e-8 keeps rounding noise at rounding
    # level, so parameters can be compared tightly; the gradients are compared as they are.
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(adam_eps=1e-8), dtype=dtype)
    adapter.collect_blend_stats()  # so the blend statistics are summed over the ranks and checked too
    trainer = MVGS(adapter, scene, config, distributed=distributed)
    trainer.seen_gradients = []
    original = adapter.optimizer_step

    def spy():  # the gradients each optimizer step applies (None right after a densification)
        trainer.seen_gradients.append({k: None if g is None else g.clone() for k, g in adapter.named_gradients().items()})
        original()

    adapter.optimizer_step = spy
    return trainer


# M = 5 over 2 ranks (3 + 2 views), chunks of 2 split between the ranks, random backgrounds,
# MVAD + CRD on, a low threshold so clone and split fire at the densification of steps 2 and 4.
SUMMED = MVGSConfig.multiview(stages=(Stage(2, 5, 2), Stage(1, 5, 2)), chunk_size=2, densify_from=1,
                            densify_every=2, densify_until=100, opacity_reset_every=1000, grad_threshold=1e-5,
                            background="random")
# The released code's variant: statistics from the last view only, mean reduction, and a stage with
# M = 1, so rank 1 renders nothing at steps 3-4 (no gradient, no statistics of its own).
LAST_MEAN = MVGSConfig.paper(stages=(Stage(2, 3, 2), Stage(1, 1, 2)), reduction="mean", densify_from=1,
                             densify_every=2, densify_until=100, opacity_reset_every=1000, grad_threshold=1e-5,
                             restart_per_stage=False, opacity_reset_at_handoff=False)
# float32, several densifications, an opacity reset at step 6 and a checkpoint at step 5 (between
# two densifications, so the statistics in it are partial on each rank).
LONG = MVGSConfig.multiview(stages=(Stage(2, 4, 3), Stage(1, 4, 5)), densify_from=1, densify_every=2,
                          densify_until=100, opacity_reset_every=6, grad_threshold=1e-5, background="random")
CUT = 5


def run(trainer, steps):
    infos = [trainer.step() for _ in range(steps)]
    return [(i.views, i.loss, i.num_primitives, None if i.densify is None else i.densify.after, i.threshold, i.boxes)
            for i in infos]


def snapshot(trainer):
    a = trainer.adapter
    return {"params": {k: v.detach().clone() for k, v in a.params.items()},
            "stats": {k: t.clone() for k, (t, _) in a.statistics().items()},
            "adam": {name: {k: v.clone() for k, v in a.optimizer.state[p].items()} for name, p in a.params.items()},
            "generator": a._generator.get_state()}


# ---- the worker processes -------------------------------------------------------------------
def scenario_equivalence(coll, out):
    result = {}
    for name, config in (("summed", SUMMED), ("last_mean", LAST_MEAN)):
        trainer = make_trainer(config, F64, coll)
        result[name] = {"steps": run(trainer, config.total_steps), "final": snapshot(trainer),
                        "grads": trainer.seen_gradients}
    return result


def scenario_long(coll, out):
    trainer = make_trainer(LONG, torch.float32, coll)
    run(trainer, CUT)
    trainer.save_checkpoint(str(out / "ckpt.pt"))
    steps = run(trainer, LONG.total_steps - CUT)
    return {"steps": steps, "final": snapshot(trainer)}


# The fault scenarios note when their failing step starts: the tests bound the time from there to
# the error (process start-up on a busy machine is not what they measure).
STEP_STARTED = [None]


def failing_step(trainer):
    STEP_STARTED[0] = time.monotonic()
    trainer.step()


def scenario_raise(coll, out):
    trainer = make_trainer(SUMMED, F64, coll)
    if coll.rank == 1:
        def broken(cams, bgs):
            raise ValueError("injected failure in rank 1's render")
        trainer.adapter.render = broken
    failing_step(trainer)


def scenario_die(coll, out):
    trainer = make_trainer(SUMMED, F64, coll)
    if coll.rank == 1:
        trainer.adapter.render = lambda cams, bgs: os._exit(3)  # killed without a word (OOM killer, segfault)
    failing_step(trainer)


def scenario_stall(coll, out):
    trainer = make_trainer(SUMMED, F64, coll)
    if coll.rank == 1:
        time.sleep(60)  # stuck (a hung driver, a deadlock); the test ends this process
    failing_step(trainer)


def scenario_training(coll, out):
    """The two successful scenarios in one launch (process start-up dominates their time)."""
    result = {"equivalence": scenario_equivalence(coll, out), "long": scenario_long(coll, out)}
    if coll.rank == 0:
        time.sleep(1.0)  # rank 0 still evaluating and writing after training, as in the examples
    result["closing_at"] = time.monotonic()  # CLOCK_MONOTONIC: one clock for every process on the machine
    return result


SCENARIOS = {f.__name__[len("scenario_"):]: f for f in
             (scenario_training, scenario_raise, scenario_die, scenario_stall)}


def _worker(rank, world, port, name, out, timeout):
    out = Path(out)
    with abort_on_error():  # as examples/train_3dgs.py does: an error ends the process at once
        try:
            torch.set_num_threads(1)
            dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world,
                                    timeout=datetime.timedelta(seconds=timeout))
            coll = Collective(timeout=timeout)
            result = SCENARIOS[name](coll, out)
            torch.save(result, out / f"rank{rank}.pt")
            coll.close()
            (out / f"rank{rank}.closed").write_text(str(time.monotonic()))
            # as the examples' launch() does: gloo's threads can abort the interpreter's teardown
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
        except BaseException as exc:
            if STEP_STARTED[0] is not None:
                (out / f"rank{rank}.elapsed").write_text(str(time.monotonic() - STEP_STARTED[0]))
            (out / f"rank{rank}.err").write_text(f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            raise


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(name, tmp_path, timeout=30.0, wait=90.0, world=2, until=None):
    """Runs a scenario on `world` spawned processes; returns (exit codes, seconds from the start of
    the failing step to each rank's error (None: no error), per-rank error text). Waits for the
    ranks in `until` (default: all) at most `wait` seconds, then terminates the processes still
    alive (their code: None)."""
    ctx = mp.start_processes(_worker, args=(world, free_port(), name, str(tmp_path), timeout), nprocs=world,
                             join=False, start_method="spawn")
    t0, ended = time.monotonic(), {}
    until = set(range(world) if until is None else until)
    while not until <= set(ended) and time.monotonic() - t0 < wait:
        for r, p in enumerate(ctx.processes):
            if r not in ended and p.exitcode is not None:
                ended[r] = time.monotonic() - t0
        time.sleep(0.05)
    codes = [p.exitcode for p in ctx.processes]
    for p in ctx.processes:
        if p.exitcode is None:
            p.terminate()  # only ever a process this test started
            p.join(5)
    read = lambda suffix, r: (tmp_path / f"rank{r}.{suffix}").read_text() \
        if (tmp_path / f"rank{r}.{suffix}").exists() else None  # noqa: E731
    elapsed = [None if read("elapsed", r) is None else float(read("elapsed", r)) for r in range(world)]
    return codes, elapsed, [read("err", r) or "" for r in range(world)]


def results(tmp_path, world=2):
    return [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in range(world)]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """Both ranks' results of scenario_training, and the folder holding rank 0's checkpoint."""
    folder = tmp_path_factory.mktemp("training")
    codes, _, errors = launch("training", folder)
    assert codes == [0, 0], errors
    return results(folder), folder


# ---- helpers of the comparisons --------------------------------------------------------------
def max_rel(a, b):
    scale = float(b.abs().max()) if b.numel() else 0.0
    return float((a - b).abs().max()) / max(scale, 1e-300) if a.numel() else 0.0


def assert_ranks_identical(per_rank):
    first = per_rank[0]["final"]
    for other in per_rank[1:]:
        o = other["final"]
        for k in first["params"]:
            assert torch.equal(first["params"][k], o["params"][k]), f"ranks differ in {k}"
            for key, v in first["adam"][k].items():
                assert torch.equal(v, o["adam"][k][key]), f"ranks differ in Adam's {key} of {k}"
        assert torch.equal(first["generator"], o["generator"]), "the adapters' generators diverged"
        assert [s[1:] for s in other["steps"]] == [s[1:] for s in per_rank[0]["steps"]]


# ---- tests ---------------------------------------------------------------------------------
@pytest.fixture(autouse=True)
def one_thread():
    """The single-process references run with one thread, as each worker does (tiny images: more
    threads only add contention on a busy 2-core machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_shard_splits_every_step_into_contiguous_balanced_blocks():
    for m in range(0, 12):
        for world in (1, 2, 3, 5):
            blocks = [shard(m, r, world) for r in range(world)]
            assert sum(blocks, []) == list(range(m))  # every view once, in order
            sizes = [len(b) for b in blocks]
            assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)
            if m:
                assert blocks[0][0] == 0  # rank 0 holds the first view (it adds the regulariser)
    with pytest.raises(ValueError, match="rank must be < world_size=2, got 2"):
        shard(4, 2, 2)
    with pytest.raises(ValueError, match=r"world_size must be a positive int, got 0"):
        shard(4, 0, 0)


def test_backend_choice_and_single_process_fallbacks(monkeypatch):
    assert backend_for("cpu") == "gloo" and backend_for("cuda:1") == "nccl"
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert init_from_env() is None  # not under torchrun: one process, nothing initialised
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert init_from_env() is None
    monkeypatch.setenv("WORLD_SIZE", "two")
    with pytest.raises(ValueError, match="WORLD_SIZE environment variable must be a positive int, got 'two'"):
        init_from_env()
    with pytest.raises(ValueError, match="timeout must be a finite number of seconds > 0, got -1"):
        init_from_env(timeout=-1)
    with pytest.raises(RuntimeError, match="torch.distributed is not initialised"):
        Collective()

    class NoStats:
        def gradient_parameters(self):
            return {}

    with pytest.raises(TypeError, match=r"NoStats cannot be trained over several processes: it lacks "
                                        r"\['statistics', 'load_statistics'\]"):
        require_support(NoStats())
    with pytest.raises(TypeError, match="distributed must be a mvgs_plugin.distributed.Collective or None, got str"):
        make_trainer(SUMMED, F64, distributed="gloo")


def test_distributed_steps_equal_single_process_steps(trained):
    per_rank = [r["equivalence"] for r in trained[0]]
    for name, config in (("summed", SUMMED), ("last_mean", LAST_MEAN)):
        ranks = [r[name] for r in per_rank]
        assert_ranks_identical(ranks)
        single = make_trainer(config, F64)
        steps = run(single, config.total_steps)
        ref = snapshot(single)
        got = ranks[0]
        for (v, loss, n, after, thr, boxes), (v1, loss1, n1, after1, thr1, boxes1) in zip(steps, got["steps"]):
            assert v1 == v and n1 == n and after1 == after and thr1 == thr and boxes1 == boxes
            assert math.isclose(loss1, loss, rel_tol=1e-12)  # the global loss, summed over ranks
        # Densification ran and changed the number of Gaussians: the comparison covers it.
        assert any(s[3] is not None for s in steps) and steps[-1][2] != 80
        for step, (mine, theirs) in enumerate(zip(single.seen_gradients, got["grads"]), 1):
            for k, g in mine.items():
                assert (g is None) == (theirs[k] is None), f"{name} step {step}: gradient of {k} present on one side"
                if g is not None:
                    err = max_rel(theirs[k], g)
                    assert err <= 1e-12, f"{name} step {step}: gradient of {k} differs by {err:.3g}"
        for k, p in ref["params"].items():
            err = max_rel(got["final"]["params"][k], p)
            assert err <= 1e-9, f"{name}: parameter {k} differs from the single-process run by {err:.3g}"
            for key, v in ref["adam"][k].items():
                err = max_rel(got["final"]["adam"][k][key], v)
                assert err <= 1e-9, f"{name}: Adam {key} of {k} differs by {err:.3g}"
        assert torch.equal(got["final"]["generator"], ref["generator"])


def test_ranks_stay_identical_and_rank0_checkpoint_resumes_in_one_process(trained):
    per_rank = [r["long"] for r in trained[0]]
    tmp_path = trained[1]
    assert_ranks_identical(per_rank)
    assert sum(s[3] is not None for s in per_rank[0]["steps"]) >= 1  # densified after the checkpoint too
    # The checkpoint rank 0 wrote holds the statistics summed over both ranks: it equals a single
    # process's state after the same steps (float32: one ulp-level sum order, 1e-5 relative) ...
    single = make_trainer(LONG, torch.float32)
    run(single, CUT)
    state = load_checked(str(tmp_path / "ckpt.pt"))
    assert state["schedule"]["step"] == CUT
    for k, t in single.adapter.statistics().items():
        assert t[0].abs().sum() > 0, "the checkpoint must fall between two densifications"
        assert max_rel(state["adapter"]["stats"][k], t[0]) <= 1e-5, k
    for k, p in single.adapter.params.items():
        assert max_rel(state["adapter"]["params"][k], p.detach()) <= 1e-5, k
    # ... and a single process resumes from it to the state the distributed run ended in.
    resumed = make_trainer(LONG, torch.float32)
    resumed.load_checkpoint(str(tmp_path / "ckpt.pt"))
    steps = run(resumed, LONG.total_steps - CUT)
    assert [s[2] for s in steps] == [s[2] for s in per_rank[0]["steps"]]
    for k, p in resumed.adapter.params.items():
        assert max_rel(per_rank[0]["final"]["params"][k], p.detach()) <= 1e-4, k


def test_ranks_leave_the_group_together(trained):
    """Collective.close() holds rank 1 until rank 0 (which works 1 s longer after training, as
    the examples' rank 0 evaluates and writes) reaches it too; only then do both tear down."""
    per_rank, folder = trained
    closed = [float((folder / f"rank{r}.closed").read_text()) for r in range(2)]
    assert per_rank[1]["closing_at"] + 0.9 <= per_rank[0]["closing_at"]  # rank 1 got there first
    assert closed[1] >= per_rank[0]["closing_at"], (closed, per_rank[0]["closing_at"])


def test_a_rank_that_raises_stops_every_rank_with_its_message(tmp_path):
    codes, seconds, errors = launch("raise", tmp_path, timeout=60.0)
    assert codes[0] not in (0, None) and codes[1] not in (0, None), (codes, errors)
    assert seconds[0] < 10  # no waiting for the 60 s timeout: the status exchange tells rank 0
    assert errors[1].startswith("ValueError: injected failure in rank 1's render")
    first = errors[0].splitlines()[0]
    assert first.startswith("DistributedError: rank 0/2 stops at step 1 because rank [1] failed"), first
    assert "rank 1: ValueError: injected failure in rank 1's render" in first


def test_a_rank_that_dies_stops_the_others(tmp_path):
    codes, seconds, errors = launch("die", tmp_path, timeout=60.0)
    assert codes[1] == 3 and codes[0] not in (0, None), (codes, errors)
    assert seconds[0] < 10  # gloo sees the closed connection at once, not after the 60 s timeout
    first = errors[0].splitlines()[0]
    assert first.startswith("DistributedError: rank 0/2: the status collective of step 1 failed: another rank "
                            "exited or did not answer within 60 s"), first


def test_a_stalled_rank_times_out(tmp_path):
    codes, seconds, errors = launch("stall", tmp_path, timeout=2.0, until=[0])
    assert codes[0] == 1, (codes, errors)  # rank 1 is still asleep: the test ends it
    first = errors[0].splitlines()[0]
    assert first.startswith("DistributedError: rank 0/2: the status collective of step 1 failed: another rank "
                            "exited or did not answer within 2 s"), first
    assert 2 <= seconds[0] < 12  # the 2 s timeout, plus slack for a busy machine


def test_train_3dgs_under_torchrun(tmp_path):
    """The example, unchanged, under torchrun with 2 processes: rank 0 alone writes, and its
    checkpoint loads in a single process."""
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-port", str(free_port()),
           str(ROOT / "examples" / "train_3dgs.py"), "--steps", "4", "--views", "2", "--resolution-scale", "8",
           "--threads", "1", "--no-progress", "--checkpoint", "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.count("test PSNR") == 1  # only rank 0 evaluates and reports
    import json

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["world_size"] == 2 and metrics["steps"] == 4
    state = load_checked(str(out / "checkpoint.pt"))
    example = _load_example()
    scene = load_scene(example.BUNDLED)
    config = MVGSConfig.from_dict(state["config"])
    trainer = MVGS(GS3DAdapter.from_scene(scene, model_config(config, 0)), scene, config)
    trainer.load_checkpoint(str(out / "checkpoint.pt"))
    assert trainer.step_count == 4 and trainer.adapter.num_primitives() == metrics["num_gaussians"]


def _load_example():
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_3dgs_dist", ROOT / "examples" / "train_3dgs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_conformance_suite_checks_the_distributed_methods():
    scene = make_scene()
    make = lambda s: GS3DAdapter.from_scene(s, GS3DConfig())  # noqa: E731
    assert check_adapter(make, scene)["check_distributed_support"] == "ok"

    class RadiiSummed(GS3DAdapter):
        """Declares the screen radius a sum: two ranks' radii would add up."""

        def statistics(self):
            stats = super().statistics()
            stats["max_radii2D"] = (stats["max_radii2D"][0], "sum")
            return stats

    with pytest.raises(AssertionError, match="statistic 'max_radii2D': the sum over two adapters that rendered "
                                             "disjoint views differs"):
        check_distributed_support(lambda s: RadiiSummed.from_scene(s, GS3DConfig()), scene)
    class OpacityUnnamed(GS3DAdapter):
        """Trains its opacities but names them neither to gradient_parameters() nor to
        named_gradients(): ranks would not sum their gradients, and each would step its own."""

        def gradient_parameters(self):
            return {k: v for k, v in super().gradient_parameters().items() if k != "opacities"}

        def named_gradients(self):
            return {k: v for k, v in super().named_gradients().items() if k != "opacities"}

    with pytest.raises(AssertionError, match=r"state_dict\(\)\['params'\]\['opacities'\] differs from one adapter "
                                             r"that rendered every view .*must name every trainable tensor"):
        check_distributed_support(lambda s: OpacityUnnamed.from_scene(s, GS3DConfig()), scene)
    with pytest.raises(ValueError, match=r"statistics\['denom'\] must be \[80\], got \[3\]"):
        make(scene).load_statistics({**{name: torch.zeros(80) for name in STAT_NAMES}, "denom": torch.zeros(3)})


def _torchrun(script: str, args: list, out: Path) -> dict:
    import json

    def launch():
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-port",
               str(free_port()), str(ROOT / "examples" / script), *args, "--threads", "1", "--no-progress",
               "--out", str(out)]
        return subprocess.run(cmd, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                              text=True, timeout=300)

    proc = launch()
    # About 1 run in 5-10 of the Scaffold-GS script (none of the others), a rank aborts in gloo's
    # teardown with this message and nothing else (SIGABRT; no thread of ours runs at --threads 1;
    # the pattern of pytorch/pytorch PR 179291). One rerun for exactly that signature only.
    if proc.returncode != 0 and "terminate called without an active exception" in proc.stderr:
        proc = launch()
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.count("test PSNR") == 1  # only rank 0 evaluates and reports
    return json.loads((out / "metrics.json").read_text())


def _single(script: str, args: list, out: Path) -> dict:
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"{Path(script).stem}_single", ROOT / "examples" / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main([*args, "--threads", "1", "--no-progress", "--out", str(out)])


@pytest.mark.parametrize("script", ["train_scaffold.py", "train_4dgs.py"])
def test_scaffold_and_4dgs_examples_under_torchrun_match_one_process(tmp_path, script):
    """The Scaffold-GS and 4DGS examples under torchrun (2 ranks, the 4 views of a step split
    2 + 2) train the model one process trains: same primitive count, same test PSNR up to the
    float rounding of the gradient all-reduce."""
    if script == "train_4dgs.py":
        from test_adapter_gs4d import _write_dnerf

        data = tmp_path / "scene"
        _write_dnerf(data, synthetic_scene(n_train=6, n_test=2, size=16, time=True))
        args = ["--data", str(data), "--steps", "6", "--views", "4", "--init-random", "30"]
    else:
        args = ["--steps", "4", "--views", "4", "--resolution-scale", "8", "--voxel-size", "0.2"]
    two = _torchrun(script, args, tmp_path / "two")
    one = _single(script, args, tmp_path / "one")
    assert two["world_size"] == 2 and one["world_size"] == 1 and two["steps"] == one["steps"]
    assert two["num_gaussians"] == one["num_gaussians"]
    assert abs(two["psnr"] - one["psnr"]) < 0.05, (two["psnr"], one["psnr"])
    assert two["psnr"] != 0 and set((tmp_path / "two" / "test").iterdir())
