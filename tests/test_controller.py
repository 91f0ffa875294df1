"""The MVGS controller driving the 3DGS adapter: summed-gradient step, statistics, stages,
checkpoints, guards, the three-line wrap and the conformance suite."""

import contextlib
import dataclasses
import difflib
import importlib.util
import math
import re
import warnings
from pathlib import Path
import struct
import zipfile

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin import CRDConfig, MVADConfig, MVGS, MVGSConfig, Stage, ViewSchedule
from mvgs_plugin.schedule import NoDensificationWarning
from mvgs_plugin.losses import photometric_loss
from mvgs_plugin.camera import Camera
from mvgs_plugin.data import Scene
from mvgs_plugin.io import load_checked, save_checked
from mvgs_plugin.testing import check_adapter, synthetic_scene

F64 = torch.float64
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=6, n_test=2, size=16, n_points=80)


def make(scene, dtype=torch.float32, **cfg):
    torch.manual_seed(0)
    return GS3DAdapter.from_scene(scene, GS3DConfig(**cfg), dtype=dtype)


def grads_at_optimizer_step(trainer):
    """Runs one controller step and returns the gradients the optimizer saw."""
    seen = {}
    original = trainer.adapter.optimizer_step

    def spy():
        seen.update({k: v.clone() for k, v in trainer.adapter.named_gradients().items() if v is not None})
        original()

    trainer.adapter.optimizer_step = spy
    info = trainer.step()
    trainer.adapter.optimizer_step = original
    return seen, info


@pytest.mark.parametrize("chunk", [1, 3, None])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_accumulated_gradient_equals_summed_loss_in_one_graph(scene, reduction, chunk):
    # chunk None: the memory bound puts all 4 views in one call with one batched loss.
    config = MVGSConfig(stages=(Stage(1, 4, 10),), reduction=reduction, chunk_size=chunk, densify_from=100)
    trainer = MVGS(make(scene, F64), scene, config)
    grads, info = grads_at_optimizer_step(trainer)
    assert len(info.views) == 4

    ref = make(scene, F64)
    ref.set_step(1)
    cams = [scene.train_cameras[i] for i in info.views]
    out = ref.render(cams, torch.zeros(4, 3, dtype=F64))
    loss = sum(photometric_loss(img, scene.image(c).to(img)) for img, c in zip(out.images, cams))
    (loss if reduction == "sum" else loss / 4).backward()
    for name, g in ref.named_gradients().items():
        if g is None:
            continue
        err = float((grads[name] - g).abs().max() / g.abs().max().clamp_min(1e-300))
        assert err <= 1e-10, f"{name}: relative difference {err}"


def test_default_chunk_size_is_the_memory_bound(scene):
    from mvgs_plugin.schedule import ViewSchedule

    n, (h, w) = 100_000, (scene.train_cameras[0].height, scene.train_cameras[0].width)
    per_view = 128 * n + 640 * h * w  # bytes: the documented per-view working memory
    for views_fitting in (1, 2, 4):
        budget_mb = (views_fitting + 0.5) * per_view / 2**20
        schedule = ViewSchedule(scene, MVGSConfig(stages=(Stage(1, 6, 10),), chunk_memory_mb=budget_mb))
        schedule.primitive_count = n
        plan = schedule.next()
        assert [len(c) for c in plan.chunks] == [views_fitting] * (6 // views_fitting) + (
            [6 % views_fitting] if 6 % views_fitting else [])
    # A model of unknown size is assumed large (1M): small chunks rather than a memory blow-up.
    schedule = ViewSchedule(scene, MVGSConfig(stages=(Stage(1, 6, 10),), chunk_memory_mb=200))
    schedule.primitive_count = 10**6
    assert [len(c) for c in schedule.next().chunks] == [1] * 6
    with pytest.raises(ValueError, match="chunk_memory_mb"):
        MVGSConfig(chunk_memory_mb=0)
    with pytest.raises(ValueError, match="chunk_size must be a positive int"):
        MVGSConfig(chunk_size=0)


def test_chunks_do_not_change_the_step(scene):
    results = []
    for chunk in (1, 3):
        config = MVGSConfig(stages=(Stage(1, 5, 10),), chunk_size=chunk, densify_from=100)
        trainer = MVGS(make(scene, F64), scene, config)
        trainer.step()
        results.append(trainer.adapter.positions().clone())
    assert torch.allclose(results[0], results[1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("stats_from,expected", [("all", 4), ("last", 1)])
def test_statistics_from_all_or_last_view(scene, stats_from, expected):
    trainer = MVGS(make(scene), scene, MVGSConfig(stages=(Stage(1, 4, 10),), stats_from=stats_from, chunk_size=2))
    counted = []
    original = trainer.adapter.accumulate_stats
    trainer.adapter.accumulate_stats = lambda result: (counted.append(result.images.shape[0]), original(result))
    info = trainer.step()
    assert sum(counted) == expected
    if stats_from == "last":
        # The last view rendered alone: its statistics are its own.
        assert counted == [1]
    assert len(info.views) == 4


def test_stages_render_at_their_pyramid_level_and_carry_the_model(scene):
    config = MVGSConfig(stages=(Stage(4, 3, 2), Stage(2, 2, 2), Stage(1, 1, 2)), densify_from=100)
    trainer = MVGS(make(scene), scene, config)
    sizes = []
    original = trainer.adapter.render
    trainer.adapter.render = lambda cams, bgs: (sizes.append((len(cams), cams[0].width)), original(cams, bgs))[1]
    infos = [trainer.step() for _ in range(6)]
    assert [i.factor for i in infos] == [4, 4, 2, 2, 1, 1]
    # Default chunking: a small model's views fit the memory bound, so each step is one call.
    assert sizes == [(3, 4), (3, 4), (2, 8), (2, 8), (1, 16), (1, 16)]
    assert [len(i.views) for i in infos] == [3, 3, 2, 2, 1, 1]


def test_baseline_preset_is_plain_single_view_training(scene):
    """M = 1 and every MVGS feature off: the controller does exactly what the hand-written
    single-view loop of examples/three_line_wrap does."""
    steps = 20
    config = MVGSConfig.baseline().with_total_steps(steps)
    run = GS3DConfig.for_run(config)  # the example's model: its schedules on the run's clock
    trainer = MVGS(make(scene, position_lr_max_steps=run.position_lr_max_steps,
                        sh_degree_interval=run.sh_degree_interval), scene, config)  # make() seeds 0 as train() does
    trainer.fit(progress=False)
    single = _load_example("single_view")
    model = single.train(scene, steps)
    assert model.num_primitives() == trainer.adapter.num_primitives()
    assert torch.allclose(model.positions(), trainer.adapter.positions(), atol=1e-6)


def test_every_bundled_model_warns_when_its_schedules_are_on_another_clock_and_for_run_fits_them(scene):
    """3DGS, Scaffold-GS and 4DGS built with their configs' defaults (30k-step decays, 4DGS's
    3000 coarse steps) warn, naming the field and the fix, on a 40-step run; built with their
    for_run(config) they do not, and GS4DConfig.for_run splits the clock as train_4dgs.py does."""
    from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
    from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig

    timed = synthetic_scene(n_train=6, n_test=2, size=16, n_points=80, time=True)
    config = MVGSConfig.baseline().with_total_steps(40)
    for kind, cfg_type, field, on in ((GS3DAdapter, GS3DConfig, "position_lr_max_steps", scene),
                                      (ScaffoldAdapter, ScaffoldConfig, "lr_max_steps", scene),
                                      (GS4DAdapter, GS4DConfig, "coarse_steps + fine_steps (3000 + 20000)", timed)):
        with pytest.warns(UserWarning, match=re.escape(f"its config's {field}") + r".* this run's clock is 40; build its "
                          + re.escape(f"config with {cfg_type.__name__}.for_run(config)")):
            MVGS(kind.from_scene(on, cfg_type()), on, config)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            warnings.simplefilter("ignore", NoDensificationWarning)  # these runs are too short to densify
            MVGS(kind.from_scene(on, cfg_type.for_run(config)), on, config)
    spec = importlib.util.spec_from_file_location("train_4dgs_for_run", EXAMPLES / "train_4dgs.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    theirs = example.gs4d_config(config, example.parse_args(["--data", str(EXAMPLES / "scenes" / "tabletop")]))
    ours = GS4DConfig.for_run(config)
    assert (ours.coarse_steps, ours.fine_steps) == (theirs.coarse_steps, theirs.fine_steps) == (5, 35)
    assert ours.canonical.position_lr_max_steps == theirs.canonical.position_lr_max_steps == 40


def _load_example(name):
    spec = importlib.util.spec_from_file_location(f"wrap_{name}", EXAMPLES / "three_line_wrap" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_three_line_wrap(scene):
    a = (EXAMPLES / "three_line_wrap" / "single_view.py").read_text().splitlines()
    b = (EXAMPLES / "three_line_wrap" / "mvgs.py").read_text().splitlines()
    changed = [ln for ln in difflib.unified_diff(a, b, lineterm="", n=0) if ln[:1] in "+-" and ln[:3] not in ("+++", "---")]
    removed = sum(ln.startswith("-") for ln in changed)
    added = sum(ln.startswith("+") for ln in changed)
    assert max(removed, added) <= 3, changed
    assert max(removed, added) >= 1
    mvgs = _load_example("mvgs").train(scene, 12)
    single = _load_example("single_view").train(scene, 12)
    assert mvgs.num_primitives() > 0 and single.num_primitives() > 0
    assert not torch.equal(mvgs.positions()[: single.num_primitives()], single.positions()[: mvgs.num_primitives()])


EARLY_RESETS = {"min_densify_per_reset": 10}  # resets 10 densifications apart: a 300-step run then resets


@pytest.mark.parametrize("preset, config", [("baseline", EARLY_RESETS), ("paper", EARLY_RESETS), ("default", EARLY_RESETS),
                                            ("multiview", EARLY_RESETS),
                                            ("paper", {"max_gaussians": 60, "budget_initial_share": 0.5, **EARLY_RESETS})])
def test_three_line_wrap_is_the_controllers_run_with_every_preset(scene, preset, config):
    """The hand-written loop of examples/three_line_wrap/mvgs.py, 300 steps: the schedule (built
    here independently with the same config) asks for densifications, an opacity reset and
    pyramid hand-offs (with paper's opacity reset at each), and the loop ends with the model the
    controller trains from the same start: same count, same positions. So it runs every phase as
    the controller does, cross-ray densification included (its clones counted here; no warning:
    the loop records its loss maps and passes its model), a budget's first cut, and the default's
    cut of the faintest Gaussians."""
    import warnings

    steps = 300
    cfg = MVGSConfig.from_preset(preset, seed=0, **config).with_total_steps(steps)
    plans = list(ViewSchedule(scene, cfg))
    assert sum(p.densify for p in plans) >= 3 and sum(p.reset_opacity for p in plans) >= 1, preset
    if preset != "baseline":
        assert len({p.stage for p in plans}) >= 2  # a pyramid hand-off too
    if preset == "paper":
        assert sum(p.handoff_reset for p in plans) >= 1
    boxes, faint = [], []
    real_densify = GS3DAdapter.densify

    def counting(self, ctx):
        report = real_densify(self, ctx)
        boxes.append(report.from_boxes)
        faint.append(report.extra.get("faint", 0))
        return report

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        GS3DAdapter.densify = counting
        try:
            model = _load_example("mvgs").train(scene, steps, preset=preset, **config)
        finally:
            GS3DAdapter.densify = real_densify
    assert not [w for w in caught if "cross-ray" in str(w.message)], [str(w.message) for w in caught]
    if preset == "paper":
        assert sum(boxes) > 0  # cross-ray densification cloned
    # the default's cut of the faintest Gaussians, once after the window: the loop never asked for
    # blend statistics, densify_context(adapter=model) did
    assert sum(p.faint_cut for p in plans) == (preset == "default")
    assert (faint[-1] > 0) if preset == "default" else not any(faint), (preset, faint)
    run = GS3DConfig.for_run(cfg.for_scene(scene))  # the example's model: its schedules on the run's clock
    trainer = MVGS(make(scene, position_lr_max_steps=run.position_lr_max_steps,
                        sh_degree_interval=run.sh_degree_interval), scene, cfg)
    counts = watch_counts(trainer)
    trainer.fit(progress=False)
    if "max_gaussians" in config:
        assert counts[0] == 30 and max(counts) <= 60
    assert model.num_primitives() == trainer.adapter.num_primitives() != len(scene.points)
    torch.testing.assert_close(model.positions(), trainer.adapter.positions(), rtol=0, atol=1e-5)


def test_the_wrap_runs_the_steps_it_is_asked_for_on_a_forward_facing_rig(monkeypatch):
    """On a forward-facing rig for_scene() drops the pyramid; resolved before with_total_steps
    (as the examples do), a run asked for 40 steps runs 40, where resolving after would keep the
    recipe's work and run fewer."""
    from mvgs_plugin.data import load_nerf_synthetic

    forward = load_nerf_synthetic(EXAMPLES.parent / "tests" / "data" / "forward64")
    late = MVGSConfig.default().with_total_steps(40).for_scene(forward)
    assert len(late.stages) == 1 and late.stages[0].steps < 40  # the trap
    steps = []
    monkeypatch.setattr(GS3DAdapter, "set_step", lambda self, step: steps.append(step))
    _load_example("mvgs").train(forward, 40)
    assert len(steps) == 40


def test_densify_context_takes_the_models_size_from_the_model_or_says_it_guessed(scene):
    """CRD's clone cap is max_new x the model's size: from adapter= (and the clip bounds from its
    positions), from primitive_count=, or, given neither, the schedule's last count with one
    warning (a cap of 0, which a hand-written loop used to get, cloned nothing)."""
    import warnings

    cfg = MVGSConfig.multiview(seed=0, crd=CRDConfig(enabled=True)).with_total_steps(300)
    assert cfg.crd.max_new is not None  # CRDConfig's default cap (paper() has none)
    schedule = ViewSchedule(scene, cfg)
    plan = next(p for p in schedule if p.densify)
    maps = [torch.rand(c.height, c.width) for c in plan.cameras]
    model = make(scene)
    ctx = schedule.densify_context(plan, maps, adapter=model)
    assert ctx.max_new_from_boxes == math.ceil(cfg.crd.max_new * model.num_primitives()) > 0
    assert schedule.densify_context(plan, maps, primitive_count=7).max_new_from_boxes == math.ceil(cfg.crd.max_new * 7)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        guessed = [schedule.densify_context(plan, maps).max_new_from_boxes for _ in range(2)]
    assert guessed == [math.ceil(cfg.crd.max_new * len(scene.points))] * 2
    said = [str(w.message) for w in caught if "model's size" in str(w.message)]
    assert len(said) == 1 and "densify_context(plan, adapter=model)" in said[0]


def watch_counts(trainer):
    """The primitive count at every render call of `trainer`."""
    counts, original = [], trainer.adapter.render
    trainer.adapter.render = lambda cams, bgs: (counts.append(trainer.adapter.num_primitives()), original(cams, bgs))[1]
    return counts


def test_a_loop_that_does_not_record_loss_maps_skips_cross_ray_densification_with_one_warning(scene):
    """The single-view loop run with a CRD config (it never calls plan.record): it trains on,
    and cross-ray densification is skipped with one warning naming what it needs."""
    import warnings

    config = MVGSConfig.multiview(seed=0, crd=CRDConfig(enabled=True)).with_total_steps(200)
    schedule = ViewSchedule(scene, config)
    model = make(scene)
    densified = 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for plan in schedule:
            model.set_step(plan.clock)
            for cams, targets, backgrounds, collect in plan:
                out = model.render(cams, backgrounds)
                (plan.weight * sum(photometric_loss(i, t) for i, t in zip(out.images, targets))).backward()
                if collect:
                    model.accumulate_stats(out)
            with torch.no_grad():
                if plan.densify:
                    ctx = schedule.densify_context(plan)
                    assert ctx.boxes is None
                    model.densify(ctx)
                    densified += 1
            model.optimizer_step()
            model.zero_grad()
    said = [str(w.message) for w in caught if "cross-ray" in str(w.message)]
    assert densified >= 2 and len(said) == 1, said
    assert "plan.record(images, targets)" in said[0]


@pytest.mark.parametrize("preset,cut", [("multiview", 15), ("default", 15)])
def test_checkpoint_resume_matches_uninterrupted_training(scene, tmp_path, preset, cut):
    # multiview counts steps; default counts work (its clocks are in full-resolution views),
    # and its cut after step 15 is its hand-off from 1/2 to full resolution.
    # 3DGS's unscaled threshold: at 16 px the presets' (meant for 800 px) grows nothing
    config = MVGSConfig.from_preset(preset, background="random", densify_from=1, densify_every=4,
                                    densify_until=30_000, grad_threshold_width=None).with_total_steps(30).with_views(2)
    full = MVGS(make(scene), scene, config)
    torch.manual_seed(7)
    infos = []
    full.fit(progress=False, callback=infos.append)
    # the model grows on both sides of the cut
    grown = [i.step for i in infos if i.densify is not None and i.densify.after > i.densify.before]
    assert min(grown) <= cut < max(grown), grown

    first = MVGS(make(scene), scene, config)
    torch.manual_seed(7)
    first.fit(steps=cut, progress=False)
    path = tmp_path / "ckpt.pt"
    first.save_checkpoint(str(path))
    torch.manual_seed(12345)  # the checkpoint must restore the random state, whatever it is now
    resumed = MVGS(make(scene), scene, config)
    resumed.load_checkpoint(str(path))
    assert resumed.step_count == cut
    resumed.fit(progress=False)
    assert resumed.adapter.num_primitives() == full.adapter.num_primitives()
    assert torch.allclose(resumed.adapter.positions(), full.adapter.positions(), atol=1e-6)


@contextlib.contextmanager
def storages_tagged_cuda():
    """torch.save as a GPU run writes: every storage is recorded on cuda:0 (torch's own location
    registry, consulted first while this is open), so a plain torch.load of the file on a
    machine without CUDA fails as it would for a checkpoint from a GPU."""
    from torch import serialization

    def tag(obj):
        return "cuda:0"
    serialization.register_package(0, tag, lambda obj, location: None)
    try:
        yield
    finally:
        serialization._package_registry[:] = [e for e in serialization._package_registry if e[1] is not tag]


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA: a CUDA-tagged file opens there")
def test_a_checkpoint_written_on_a_gpu_resumes_on_the_cpu(scene, tmp_path):
    config = MVGSConfig.from_preset("default", densify_from=1, densify_every=4, densify_until=30_000,
                                    grad_threshold_width=None).with_total_steps(30)
    full = MVGS(make(scene), scene, config)
    torch.manual_seed(7)
    full.fit(progress=False)

    first = MVGS(make(scene), scene, config)
    torch.manual_seed(7)
    first.fit(steps=15, progress=False)
    path = tmp_path / "gpu.pt"
    with storages_tagged_cuda():
        first.save_checkpoint(str(path))
    with pytest.raises(RuntimeError, match="CUDA"):  # the file really says cuda:0
        torch.load(str(path), weights_only=True)
    resumed = MVGS(make(scene), scene, config)
    resumed.load_checkpoint(str(path))
    assert resumed.step_count == 15 and resumed.adapter.positions().device.type == "cpu"
    resumed.fit(progress=False)
    assert resumed.adapter.num_primitives() == full.adapter.num_primitives()
    assert torch.allclose(resumed.adapter.positions(), full.adapter.positions(), atol=1e-6)


def test_nan_gradient_stops_before_the_optimizer_step(scene, tmp_path):
    trainer = MVGS(make(scene), scene, MVGSConfig(stages=(Stage(1, 2, 10),), densify_from=100))
    trainer.step()
    path = tmp_path / "ckpt.pt"
    trainer.save_checkpoint(str(path))
    before = path.read_bytes()
    positions = trainer.adapter.positions().clone()
    original = trainer.adapter.render

    def poisoned(cams, bgs):
        out = original(cams, bgs)
        out.images = out.images * torch.where(torch.rand(()) >= 0, torch.tensor(float("nan")), torch.tensor(1.0))
        return out

    trainer.adapter.render = poisoned
    with pytest.raises(FloatingPointError, match=r"step 2: the loss is nan for views \['view_"):
        trainer.step()
    assert torch.equal(trainer.adapter.positions(), positions)
    assert path.read_bytes() == before


def test_nan_in_a_gradient_group_is_named(scene):
    trainer = MVGS(make(scene), scene, MVGSConfig(stages=(Stage(1, 2, 10),), densify_from=100))
    name = next(iter(trainer.adapter.named_gradients()))
    original = trainer.adapter.named_gradients

    def poisoned():
        grads = original()
        grads[name] = grads[name] * math.nan
        return grads

    trainer.adapter.named_gradients = poisoned
    with pytest.raises(FloatingPointError, match=rf"step 1: .* non-finite gradient entries in group '{name}'"):
        trainer.step()


def test_fit_evaluate_and_steps_exhausted(scene):
    trainer = MVGS(make(scene), scene, MVGSConfig.default().with_total_steps(8))
    trainer.fit(progress=False)
    result = trainer.evaluate()
    assert 0 < result.psnr < 100 and 0 < result.ssim <= 1 and len(result.per_view) == len(scene.test_cameras)
    with pytest.raises(RuntimeError, match="training is complete"):
        trainer.step()


def test_gs3d_adapter_passes_the_conformance_suite(scene):
    report = check_adapter(lambda s: make(s), scene)
    assert set(report.values()) == {"ok"} and len(report) >= 6


def test_conformance_suite_catches_a_broken_adapter(scene):
    class Misaligned(GS3DAdapter):
        """Names a gradient group that never receives a gradient."""

        def named_gradients(self):
            grads = super().named_gradients()
            grads.pop(next(iter(grads)))  # claims one group less ...
            grads["bogus"] = None  # ... and one that never gets a gradient
            return grads

    with pytest.raises(AssertionError, match="check_gradients_reach_every_group: group 'bogus' received no gradient"):
        check_adapter(lambda s: Misaligned.from_scene(s, GS3DConfig()), scene)


class Ascent(GS3DAdapter):
    def optimizer_step(self):  # climbs the gradient
        for p in self.params.values():
            if p.grad is not None:
                p.grad.neg_()
        super().optimizer_step()


class IgnoresCap(GS3DAdapter):
    def densify(self, ctx):
        return super().densify(dataclasses.replace(ctx, max_primitives=None))


class KeepsStats(GS3DAdapter):
    def densify(self, ctx):  # the statistics survive the call (rows added get zeros)
        old = {k: v.clone() for k, v in self.stats.items()}
        report = super().densify(ctx)
        n = min(len(old["denom"]), self.num_primitives())
        for k, v in old.items():
            self.stats[k][:n] = v[:n]
        return report


class NoBackground(GS3DAdapter):
    def render(self, cameras, backgrounds):
        return super().render(cameras, torch.zeros_like(backgrounds))


class StaleOptimizer(GS3DAdapter):
    def densify(self, ctx):  # the model's new tensors, but the optimizer left on others (as on those of before)
        report = super().densify(ctx)
        for group in self.optimizer.param_groups:
            group["params"] = [torch.nn.Parameter(p.detach().clone()) for p in group["params"]]
        return report


class NoZeroGrad(GS3DAdapter):
    def zero_grad(self):
        pass


class ForgetsStats(GS3DAdapter):
    def load_state_dict(self, state):  # a resume that starts the window's statistics over
        super().load_state_dict(state)
        for value in self.stats.values():
            value.zero_()


class Unseeded(GS3DAdapter):
    calls = 0

    @classmethod
    def from_scene(cls, scene, config=None, **kw):  # another random jitter at every call
        adapter = super().from_scene(scene, config, **kw)
        Unseeded.calls += 1
        gen = torch.Generator().manual_seed(Unseeded.calls)
        with torch.no_grad():
            means = adapter.params["means"]
            means.add_(0.01 * torch.randn(means.shape, generator=gen, dtype=means.dtype))
        return adapter


class StaleMoments(GS3DAdapter):
    def densify(self, ctx):  # the optimizer follows the new tensors, but keeps their Adam moments of before
        old = [{k: v.clone() for k, v in self.optimizer.state[g["params"][0]].items()}
               if g["params"][0] in self.optimizer.state else None for g in self.optimizer.param_groups]
        report = super().densify(ctx)
        for group, state in zip(self.optimizer.param_groups, old):
            if state is not None:
                self.optimizer.state[group["params"][0]] = state
        return report


class NoReset(GS3DAdapter):
    reset_opacity = None  # not written: the controller calls it first at the first opacity reset


class NaNWhenEmpty(GS3DAdapter):
    def render(self, cameras, backgrounds):  # normalised by the view's coverage: 0 / 0 where nothing is seen
        out = super().render(cameras, backgrounds)
        cover = out.alphas.sum(dim=(1, 2, 3), keepdim=True)
        return dataclasses.replace(out, images=out.images * (cover / cover))


class Raises(GS3DAdapter):
    def reset_opacity(self):
        raise NotImplementedError("never written")

    def state_dict(self):
        raise RuntimeError("cannot save")


@pytest.mark.parametrize("kind, message", [
    (Ascent, "check_optimizer_descends: 10 optimizer steps on the same 3 views did not lower their loss"),
    (IgnoresCap, r"check_the_cap_holds: densify with max_primitives=\d+ \(the model had \d+\) left \d+"),
    (KeepsStats, "check_stats_and_densify: a second densify right after the first .* must reset the statistics"),
    (NoBackground, r"check_background: an empty view rendered with background \[0.2"),
    (StaleOptimizer, "check_stats_and_densify: after densify, an optimizer step with gradients changed nothing"),
    (NoZeroGrad, "check_gradients_reach_every_group: zero_grad\\(\\) left a gradient in group"),
    (Raises, "check_state_dict_round_trip: the adapter raised RuntimeError: cannot save"),
    (Unseeded, r"check_make_adapter_is_deterministic: two calls of make_adapter built models that render "
               r"differently .*[(]seed its random initialisation"),
    (ForgetsStats, r"check_state_dict_round_trip: a densify right after load_state_dict went (\d+) -> \1 where the "
                   r"saved adapter went \1 -> \d+: state_dict must carry the densification statistics"),
    (StaleMoments, r"check_stats_and_densify: after a densify that went (\d+) -> \d+, the optimizer's 'exp_avg' of "
                   r"'means' has shape \[\1, 3\] where its parameter has \[\d+, 3\]: the optimizer's state \(e.g. "
                   r"Adam's exp_avg / exp_avg_sq\) must be cut and extended"),
    (NoReset, r"check_protocol_methods: make_adapter\(scene\) must implement the Adapter protocol .*: NoReset has no "
              r"reset_opacity \(a model without an opacity reset implements reset_opacity as a no-op"),
    (NaNWhenEmpty, r"check_background: a view with nothing in it .* rendered non-finite pixels"),
])
def test_the_conformance_suite_names_what_a_broken_adapter_breaks(scene, kind, message):
    """One deliberate fault per adapter (as an outside integrator's adapters had them); the
    suite fails on it with the check's name and what is wrong."""
    with pytest.raises(AssertionError, match=message):
        check_adapter(lambda s: make_kind(kind, s), scene)


def test_misuse_of_the_suite_and_the_controller_is_named_at_once(scene):
    """An adapter instance given to check_adapter, an adapter class, None, a path or a preset name
    given to MVGS, a views count of 0, a fit of 0 steps: each a TypeError / ValueError naming the
    value and what was expected, before any step (not an AttributeError at some step)."""
    adapter = make(scene)
    with pytest.raises(TypeError, match="check_adapter takes make_adapter, a function scene -> a fresh adapter, got "
                                        "GS3DAdapter"):
        check_adapter(adapter, scene)
    config = MVGSConfig.baseline().with_total_steps(10)
    for args, message in [((None, scene, config), "adapter must implement the Adapter protocol .*: NoneType has no "
                                                  "render, regularization"),
                          ((GS3DAdapter, scene, config), r"adapter must be an adapter instance, got the class "
                                                         r"GS3DAdapter \(build one, e.g. GS3DAdapter.from_scene"),
                          ((adapter, "my_scene", config), r"scene must be a mvgs_plugin.data.Scene .*got str \(a path: "
                                                          r"load it with mvgs_plugin.data.load_scene\)"),
                          ((adapter, scene, "default"), r"config must be an MVGSConfig or None, got str 'default' "
                                                        r"\(a preset by name: MVGSConfig.from_preset\('default'\)\)")]:
        with pytest.raises(TypeError, match=message):
            MVGS(*args)
    with pytest.raises(ValueError, match="views must be a positive int, got 0"):
        MVGSConfig.multiview().with_views(0)
    trainer = MVGS(adapter, scene, config)
    for steps in (0, -1, 2.5):
        with pytest.raises(ValueError, match=rf"steps must be None \(the rest of the run\) or an int >= 1, got {steps}"):
            trainer.fit(steps=steps, progress=False)
    assert trainer.step_count == 0
    result = trainer.evaluate()  # printed, it says its numbers, not every test image's pixels
    n = len(scene.test_cameras)
    lp = "None" if result.lpips is None else f"{result.lpips:.4f}"
    assert repr(result) == (f"EvalResult(psnr={result.psnr:.4f}, ssim={result.ssim:.4f}, lpips={lp}, per_view=[{n} views: "
                            "name, psnr, ssim, lpips, image])") and "tensor" not in repr(result)


def make_kind(kind, scene):
    torch.manual_seed(0)
    return kind.from_scene(scene, GS3DConfig())


@pytest.mark.parametrize("preset", ["multiview", "paper"])
def test_mvad_and_crd_reach_the_adapter(scene, preset):
    extra = {"crd": CRDConfig(enabled=True)} if preset == "multiview" else {}  # CRD with multiview()'s guards
    config = MVGSConfig.from_preset(preset, stages=(Stage(1, 6, 4),), densify_from=1, densify_every=2,
                                    restart_per_stage=False, opacity_reset_at_handoff=False, **extra)
    trainer = MVGS(make(scene), scene, config)
    seen = []
    original = trainer.adapter.densify
    trainer.adapter.densify = lambda ctx: (seen.append(ctx), original(ctx))[1]
    n_before = trainer.adapter.num_primitives()
    trainer.step()
    info = trainer.step()
    assert len(seen) == 1 and info.densify is not None
    ctx = seen[0]
    # Six views on a ring around the scene: some pair is far apart, so the threshold halves
    # (default() first scales β from 800 px images to the scene's width; paper() never does).
    width = scene.train_cameras[0].width
    beta = config.grad_threshold * (800 / width if preset == "multiview" else 1.0)
    assert ctx.grad_threshold == pytest.approx(beta / 2) == info.threshold and info.mvad_fired
    assert ctx.boxes is not None and ctx.boxes.dim() == 3 and ctx.boxes.shape[1:] == (2, 3)
    assert info.boxes == ctx.boxes.shape[0]
    if preset == "multiview":
        assert ctx.max_new_from_boxes == math.ceil(0.05 * n_before)
        pos = trainer.adapter.positions()
        assert (ctx.boxes[:, 0] >= pos.min(0).values.double() - 1e-3).all()  # clipped to the model's bounds
    else:
        assert ctx.max_new_from_boxes is None
    assert info.densify.from_boxes <= (ctx.max_new_from_boxes or 10**9)


def test_mvad_and_crd_off_in_the_baseline(scene):
    config = MVGSConfig.baseline(stages=(Stage(1, 1, 4),), densify_from=1, densify_every=2)
    trainer = MVGS(make(scene), scene, config)
    seen = []
    original = trainer.adapter.densify
    trainer.adapter.densify = lambda ctx: (seen.append(ctx), original(ctx))[1]
    trainer.step()
    trainer.step()
    assert seen[0].grad_threshold == config.grad_threshold and seen[0].boxes is None


def test_a_failed_checkpoint_write_keeps_the_previous_file(scene, tmp_path, monkeypatch):
    """save_atomic (used for checkpoints, anchors and deformation files) writes a temporary file
    and renames it: a crash mid-write leaves the old checkpoint loadable and no partial file."""
    import mvgs_plugin.io as io

    trainer = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(4))
    trainer.step()
    path = tmp_path / "ckpt.pt"
    trainer.save_checkpoint(str(path))
    before = path.read_bytes()
    trainer.step()

    def crash(obj, f):
        f.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(io.torch, "save", crash)
    with pytest.raises(OSError, match="disk full"):
        trainer.save_checkpoint(str(path))
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]
    monkeypatch.undo()
    fresh = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(4))
    fresh.load_checkpoint(str(path))
    assert fresh.step_count == 1


def test_a_failed_load_leaves_the_trainer_as_it_was(scene, tmp_path):
    """The schedule and RNG state load before the adapter's; when the adapter's part fails, the
    trainer must go on exactly as if no load had been tried."""
    config = MVGSConfig.baseline().with_total_steps(12)
    donor = MVGS(make(scene), scene, config)
    donor.fit(steps=5, progress=False)
    state = donor.state_dict()
    state["adapter"]["params"]["means"] = state["adapter"]["params"]["means"][:3]  # wrong row count
    torch.save(state, tmp_path / "bad.pt")

    torch.manual_seed(3)
    reference = MVGS(make(scene), scene, config)
    reference.fit(steps=2, progress=False)
    ref_state = torch.get_rng_state()
    reference.fit(progress=False)

    torch.manual_seed(3)
    trainer = MVGS(make(scene), scene, config)
    trainer.fit(steps=2, progress=False)
    torch.set_rng_state(ref_state)
    with pytest.raises(Exception):
        trainer.load_checkpoint(str(tmp_path / "bad.pt"))
    assert trainer.step_count == 2 and torch.equal(torch.get_rng_state(), ref_state)
    trainer.fit(progress=False)
    assert trainer.step_count == 12
    assert torch.equal(trainer.adapter.positions(), reference.adapter.positions())


def moved(scene, index, shift=0.5, name=None):
    """The scene with training view `index` moved by `shift` along x (or renamed), images kept."""
    cams = list(scene.train_cameras)
    c = cams[index]
    w2c = c.world_to_camera.clone()
    w2c[:3, 3] -= w2c[:3, :3] @ torch.tensor([shift, 0.0, 0.0], dtype=torch.float64)
    cams[index] = Camera(uid=c.uid, name=name or c.name, K=c.K, world_to_camera=w2c, width=c.width, height=c.height)
    images = {cam.uid: scene.image(cam) for cam in cams + list(scene.test_cameras)}
    return Scene(cams, list(scene.test_cameras), images, points=scene.points)


def test_a_checkpoint_of_other_training_views_is_refused_and_nothing_changes(scene, tmp_path):
    """A checkpoint resumed on another scene (same number of views) would train on silently: the
    schedule records each view's name, size and a digest of its camera, and a load on other views
    is refused naming the first that differs, with the trainer left as it was."""
    trainer = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(10))
    trainer.step()
    path = tmp_path / "a.pt"
    trainer.save_checkpoint(str(path))
    same = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(10))
    same.load_checkpoint(str(path))  # the same views load
    assert same.step_count == 1
    names = [c.name for c in scene.train_cameras]
    cases = [(moved(scene, 3), rf"view 3 \('{names[3]}'\): its intrinsics, pose or time differ"),
             (moved(scene, 3, shift=1e-3), rf"view 3 \('{names[3]}'\): its intrinsics, pose or time differ"),
             (moved(scene, 0, shift=0.0, name="other.png"), rf"view 0 \('other.png'\): its image is '{names[0]}' in the checkpoint"),
             (synthetic_scene(n_train=5, n_test=2, size=16, n_points=80), "made on 6 training views, this run has 5"),
             (synthetic_scene(n_train=6, n_test=2, size=20, n_points=80), "its size is 16x16 px in the checkpoint and 20x20")]
    for other, message in cases:
        fresh = MVGS(make(other), other, MVGSConfig.baseline().with_total_steps(10))
        before = {k: v.detach().clone() for k, v in fresh.adapter.params.items()}
        with pytest.raises(ValueError, match=message):
            fresh.load_checkpoint(str(path))
        assert fresh.step_count == 0
        for k, v in before.items():
            assert torch.equal(fresh.adapter.params[k], v), k
    # Another scene whose run also has another stage plan: the scene is the cause named
    other = synthetic_scene(n_train=5, n_test=2, size=16, n_points=80)
    fresh = MVGS(make(other), other, MVGSConfig.default().with_total_steps(60))
    assert fresh.config.stages != trainer.config.stages
    with pytest.raises(ValueError, match="made on 6 training views, this run has 5") as err:
        fresh.load_checkpoint(str(path))
    assert "stages" not in str(err.value)


def test_a_checkpoint_of_other_images_of_the_same_cameras_is_refused(scene, tmp_path):
    """Two renders of one rig (the generator's tabletop and reflective scenes share their cameras)
    have the same views: the checkpoint also records a digest of each training image, so a resume
    on the other images is refused naming the views that differ, and the trainer is left as it
    was. The digest is of the file's bytes: the same files pass, one changed pixel does not."""
    from PIL import Image

    cams, tests = list(scene.train_cameras), list(scene.test_cameras)
    data = tmp_path / "scene"
    data.mkdir()

    def on_disk(brighter=()):
        files = {}
        for cam in cams + tests:
            img = scene.image(cam).clone()
            if cam.uid in brighter:
                img[0, 0] = 1.0 - img[0, 0]  # one pixel of the view
            files[cam.uid] = data / f"{cam.uid}{'b' if cam.uid in brighter else ''}.png"
            Image.fromarray((img.numpy() * 255).round().astype("uint8")).save(files[cam.uid])
        return Scene(cams, tests, files, points=scene.points)

    first = on_disk()
    trainer = MVGS(make(first), first, MVGSConfig.baseline().with_total_steps(10))
    trainer.step()
    path = tmp_path / "a.pt"
    trainer.save_checkpoint(str(path))
    again = on_disk()  # the same files, read by another Scene
    resumed = MVGS(make(again), again, MVGSConfig.baseline().with_total_steps(10))
    resumed.load_checkpoint(str(path))
    assert resumed.step_count == 1

    other = on_disk(brighter={cams[2].uid, cams[4].uid})
    fresh = MVGS(make(other), other, MVGSConfig.baseline().with_total_steps(10))
    before = {k: v.detach().clone() for k, v in fresh.adapter.params.items()}
    with pytest.raises(ValueError, match=rf"other images of the same cameras: 2 of {len(cams)} training views' image "
                                         rf"files differ in content \(view 2 \('{cams[2].name}'\), 4 \('{cams[4].name}'\)\)"):
        fresh.load_checkpoint(str(path))
    assert fresh.step_count == 0
    assert all(torch.equal(fresh.adapter.params[k], v) for k, v in before.items())

    # Images given in memory are digested from their pixels: another tensor is another image
    in_memory = {c.uid: scene.image(c) for c in cams + tests}
    darker = {**in_memory, cams[1].uid: in_memory[cams[1].uid] * 0.5}
    trainer = MVGS(make(scene), Scene(cams, tests, in_memory, points=scene.points),
                   MVGSConfig.baseline().with_total_steps(10))
    trainer.step()
    trainer.save_checkpoint(str(path))
    fresh = MVGS(make(scene), Scene(cams, tests, darker, points=scene.points), MVGSConfig.baseline().with_total_steps(10))
    with pytest.raises(ValueError, match=rf"1 of {len(cams)} training views' image files differ in content \(view 1 "):
        fresh.load_checkpoint(str(path))

    # A checkpoint written before the digests were recorded loads without that check
    state = load_checked(path)
    state["schedule"].pop("images")
    old = tmp_path / "old.pt"
    save_checked(state, old)
    fresh = MVGS(make(scene), Scene(cams, tests, darker, points=scene.points), MVGSConfig.baseline().with_total_steps(10))
    fresh.load_checkpoint(str(old))
    assert fresh.step_count == 1


def test_a_checkpoint_of_another_length_is_refused_naming_both_plans(scene, tmp_path):
    trainer = MVGS(make(scene), scene, MVGSConfig.default().with_total_steps(30))
    trainer.step()
    trainer.save_checkpoint(str(tmp_path / "a.pt"))
    longer = MVGS(make(scene), scene, MVGSConfig.default().with_total_steps(60))
    assert [(st.factor, st.views) for st in trainer.config.stages] == [(2, 1), (1, 1)]
    saved = [st.steps for st in trainer.config.stages]
    here = [st.steps for st in longer.config.stages]
    with pytest.raises(ValueError) as err:
        longer.load_checkpoint(str(tmp_path / "a.pt"))
    assert (f"the checkpoint's plan: {saved[0]} steps of 1 view(s) at 1/2, {saved[1]} steps of 1 view(s) at 1/1; "
            f"this run's: {here[0]} steps of 1 view(s) at 1/2, {here[1]} steps of 1 view(s) at 1/1") in str(err.value)
    assert "(--steps / --budget)" in str(err.value) and longer.step_count == 0


def test_a_flipped_bit_in_a_checkpoint_is_refused(scene, tmp_path):
    trainer = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(10))
    trainer.step()
    good = tmp_path / "good.pt"
    trainer.save_checkpoint(str(good))
    data = good.read_bytes()
    with zipfile.ZipFile(good) as archive:  # where the pickled data (checksum, payload) lie in the file
        info = next(i for i in archive.infolist() if i.filename.endswith("data.pkl"))
        name_len, extra_len = struct.unpack("<HH", data[info.header_offset + 26:info.header_offset + 30])  # local header
        start = info.header_offset + 30 + name_len + extra_len
        assert data[start:start + info.compress_size] == archive.read(info.filename)
        pickled = (start, start + info.compress_size)
    state = {k: v.detach().clone() for k, v in trainer.adapter.params.items()}
    rng = torch.Generator().manual_seed(0)
    refused = 0
    for k in range(25):  # anywhere in the file: the zip structure, the header or the payload
        pos = int(torch.randint(len(data), (1,), generator=rng))
        flipped = bytearray(data)
        flipped[pos] ^= 1 << int(torch.randint(8, (1,), generator=rng))
        bad = tmp_path / f"flip{k}.pt"
        bad.write_bytes(bytes(flipped))
        try:
            trainer.load_checkpoint(str(bad))
        except ValueError as err:
            assert f"flip{k}.pt" in str(err)
            refused += 1
        else:
            # a byte no reader uses (torch's zip pads its records with "Z", and its reader skips the
            # small records' CRCs); never one of the pickled data, which the checksum covers: what loads
            # is the saved state
            assert not pickled[0] <= pos < pickled[1], (pos, data[pos:pos + 1])
            for name, value in state.items():
                assert torch.equal(trainer.adapter.params[name], value), name
        assert trainer.step_count == 1
    assert refused >= 20
    trainer.load_checkpoint(str(good))


def test_a_checkpoint_of_another_config_is_refused_or_its_overrides_named(scene, tmp_path):
    """A baseline checkpoint loaded into a run of the same stages but another seed and MVAD: strict
    refuses, naming each differing field with both values, and loads nothing; strict=False keeps
    this run's values, warns naming them, and loads the state. Speed-only fields may differ."""
    import dataclasses

    saved_config = MVGSConfig.baseline().with_total_steps(10)
    trainer = MVGS(make(scene), scene, saved_config)
    trainer.step()
    path = tmp_path / "base.pt"
    trainer.save_checkpoint(str(path))

    other = dataclasses.replace(saved_config, seed=7, mvad=MVADConfig(enabled=True))
    fresh = MVGS(make(scene), scene, other)
    before = fresh.adapter.positions().clone()
    with pytest.raises(ValueError) as err:
        fresh.load_checkpoint(str(path))
    message = str(err.value)
    assert "base.pt" in message and "mvad.enabled: checkpoint False, this run True" in message
    assert "seed: checkpoint 0, this run 7" in message
    assert fresh.step_count == 0 and torch.equal(fresh.adapter.positions(), before)
    with pytest.warns(UserWarning, match=r"this run's values are kept: .*mvad.enabled: checkpoint False, this run True"):
        fresh.load_checkpoint(str(path), strict=False)
    assert fresh.step_count == 1 and fresh.config.seed == 7
    assert torch.equal(fresh.adapter.positions(), trainer.adapter.positions())

    faster = MVGS(make(scene), scene, dataclasses.replace(saved_config, chunk_size=1, divergence_factor=None))
    faster.load_checkpoint(str(path))  # runtime fields only: no error, no warning
    assert faster.step_count == 1


def test_a_killed_save_leaves_no_partial_after_the_next_save(scene, tmp_path):
    """A writer killed mid-save (SIGKILL: no cleanup runs) leaves its temporary file; the next
    save of the same path removes it. A partial whose writer is still running is kept."""
    import signal
    import subprocess
    import sys

    path = tmp_path / "ckpt.pt"
    killed = subprocess.run([sys.executable, "-c", (
        "import os, signal, tempfile, sys\n"
        "from mvgs_plugin.io import _partial_prefix\n"
        f"p = {str(path)!r}\n"
        "fd, tmp = tempfile.mkstemp(prefix=f'{_partial_prefix(p)}{os.getpid()}-', dir=os.path.dirname(p))\n"
        "os.write(fd, b'x' * 4096)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n")])
    assert killed.returncode == -signal.SIGKILL
    stale = [p.name for p in tmp_path.iterdir()]
    assert len(stale) == 1 and stale[0].startswith(".ckpt.pt.partial-")
    running = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        alive = tmp_path / f".ckpt.pt.partial-{running.pid}-abcd"
        alive.write_bytes(b"still being written")
        other = tmp_path / ".other.pt.partial-999999999-abcd"  # another target's: not ours to judge
        other.write_bytes(b"x")
        trainer = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(4))
        trainer.step()
        trainer.save_checkpoint(str(path))
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["ckpt.pt", alive.name, other.name])
    finally:
        running.kill()
        running.wait()


def test_step_timing_splits_the_adapter_loss_and_controller_time(scene, monkeypatch):
    """Time spent in the adapter's statistics, densification and optimizer step, and in the
    loss, is not counted as the controller's own (StepInfo.controller_seconds)."""
    import time as _time

    adapter = make(scene)
    pause = 0.05

    def slow(fn):
        def wrapped(*a, **k):
            _time.sleep(pause)
            return fn(*a, **k)
        return wrapped

    for name in ("accumulate_stats", "densify", "optimizer_step"):
        monkeypatch.setattr(adapter, name, slow(getattr(adapter, name)))
    import mvgs_plugin.controller as controller

    monkeypatch.setattr(controller, "photometric_loss", slow(controller.photometric_loss))
    config = MVGSConfig(stages=(Stage(1, 2, 2),), densify_from=1, densify_every=2, chunk_size=1)
    trainer = MVGS(adapter, scene, config)
    trainer.step()
    info = trainer.step()  # densifies: 2 x statistics + densify + optimizer, 2 x loss
    assert info.densify is not None
    assert info.adapter_seconds >= 4 * pause and info.loss_seconds >= 2 * pause
    parts = info.render_seconds + info.backward_seconds + info.loss_seconds + info.adapter_seconds
    assert parts <= info.seconds
    assert info.controller_seconds == pytest.approx(info.seconds - parts, abs=1e-12)
    assert info.controller_seconds < pause  # none of the sleeps landed in the controller's share


class _RunsCodeOnLoad:
    """Unpickling this calls open(marker, "w"): what a crafted checkpoint could do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_checkpoint_that_would_run_code_is_refused_without_side_effect(scene, tmp_path):
    trainer = MVGS(make(scene), scene, MVGSConfig.baseline().with_total_steps(10))
    trainer.step()
    good = tmp_path / "good.pt"
    trainer.save_checkpoint(str(good))
    from mvgs_plugin.io import load_checked

    state = load_checked(str(good))  # what save_checkpoint writes is weights-only loadable
    marker = tmp_path / "pwned"
    state["adapter"]["payload"] = _RunsCodeOnLoad(marker)
    bad = tmp_path / "bad.pt"
    torch.save(state, bad)
    with pytest.raises(ValueError, match=r"cannot load checkpoint .*bad\.pt"):
        trainer.load_checkpoint(str(bad))
    assert not marker.exists()  # nothing ran
    torch.save({"config": {}}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match=r"missing \['adapter', 'schedule', 'torch_rng'\]"):
        trainer.load_checkpoint(str(tmp_path / "foreign.pt"))
    (tmp_path / "truncated.pt").write_bytes(good.read_bytes()[:100])
    with pytest.raises(ValueError, match="truncated.pt"):
        trainer.load_checkpoint(str(tmp_path / "truncated.pt"))
    trainer.load_checkpoint(str(good))
    assert trainer.step_count == 1


def test_an_adapter_on_another_clock_is_named_and_for_run_puts_it_on_the_runs(scene):
    # The README's Python route: a 300-unit budget with the model's 30k-step schedules would keep
    # the means' rate near its start; the controller says so, and GS3DConfig.for_run fixes it.
    config = MVGSConfig.default().with_budget(300)
    with pytest.warns(UserWarning, match=r"over 30000 steps .* clock is 300.*GS3DConfig\.for_run"):
        MVGS(GS3DAdapter.from_scene(scene), scene, config)
    model = GS3DConfig.for_run(config, seed=3)
    assert (model.position_lr_max_steps, model.sh_degree_interval, model.seed) == (300, 10, 3)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        trainer = MVGS(GS3DAdapter.from_scene(scene, model), scene, config)
    adapter = trainer.adapter
    # at the end of the clock the means' rate is 3DGS's final one (1.6e-6 x extent), at its start
    # the initial one, and the SH degree is full: written out, not read from the schedule code
    assert adapter.means_lr(300) == pytest.approx(1.6e-6 * adapter.scene_extent, rel=1e-9)
    assert adapter.means_lr(0) == pytest.approx(1.6e-4 * adapter.scene_extent, rel=1e-9)
    adapter.set_step(300)
    assert adapter.active_sh_degree == 3
    # a step-clock run: the clock is its steps
    assert GS3DConfig.for_run(MVGSConfig.baseline().with_total_steps(3000)).position_lr_max_steps == 3000


def test_a_stage_asking_for_more_views_than_the_scene_has_is_said_and_renders_them_all(scene):
    n = len(scene.train_cameras)
    config = MVGSConfig.baseline().with_total_steps(20)
    config = dataclasses.replace(config, stages=(Stage(factor=2, views=n + 3, steps=4), Stage(factor=1, views=2, steps=16)))
    with pytest.warns(UserWarning, match=rf"stage 0 \({n + 3} views at 1/2\) asks for more views .* {n} training views"):
        schedule = ViewSchedule(scene, config)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once, when the schedule is built: not again at the first draw
        warnings.simplefilter("ignore", NoDensificationWarning)  # these runs are too short to densify
        plan = schedule.next()
    assert sorted(plan.views) == list(range(n))  # every view once, not n + 3 draws
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.simplefilter("ignore", NoDensificationWarning)  # these runs are too short to densify
        ViewSchedule(scene, dataclasses.replace(config, stages=(Stage(factor=1, views=n, steps=20),)))


def test_a_view_schedule_says_when_its_run_densifies_at_no_step_and_names_wrong_arguments(scene):
    """A hand-written loop on ViewSchedule is told, as the CLI tells its user, when the run is too
    short to densify (the window's first call is judged by the schedule's own clock, stepped
    through here); a preset name is taken, other arguments are named."""
    def calls(schedule):
        return sum(plan.densify for plan in schedule)

    with pytest.warns(NoDensificationWarning, match=r"densifies at no step: its densification window, after 50 and before \d+ "):
        short = ViewSchedule(scene, MVGSConfig.default().for_scene(scene).with_total_steps(100), load_images=False)
    assert calls(short) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", NoDensificationWarning)
        longer = ViewSchedule(scene, MVGSConfig.default().for_scene(scene).with_total_steps(400), load_images=False)
    assert calls(longer) > 0
    with pytest.raises(TypeError, match=r"scene must be a mvgs_plugin.data.Scene .* got list"):
        ViewSchedule(scene.train_cameras, MVGSConfig.default())
    with pytest.raises(TypeError, match=r"config must be an MVGSConfig or a preset name, got int"):
        ViewSchedule(scene, 3)
    assert ViewSchedule(scene, "baseline", load_images=False).config.grad_threshold_width is None


def test_plan_record_refuses_loss_maps_that_are_not_the_plans_views(scene):
    """Recorded maps of another size (or too many) used to be accepted and gave cross-ray boxes
    from the wrong pixels; now they are refused naming the view and both sizes."""
    config = MVGSConfig.paper().for_scene(scene).with_total_steps(300)
    schedule = ViewSchedule(scene, config, load_images=False)
    plan = next(p for p in schedule if p.wants_maps)
    cam = plan.cameras[0]
    with pytest.raises(ValueError, match=rf"view 0 \({re.escape(repr(cam.name))}\) gave a 9x7 loss map, its camera at "
                                         rf"this level is {cam.width}x{cam.height}"):
        plan.record([torch.rand(7, 9, 3)], [torch.rand(7, 9, 3)])
    right = [torch.rand(c.height, c.width, 3) for c in plan.cameras]
    plan.record(right, right)
    assert len(plan.recorded) == len(plan.cameras)
    with pytest.raises(ValueError, match=rf"view {len(plan.cameras) + 1} recorded, but this step has {len(plan.cameras)}"):
        plan.record(right[:1], right[:1])


def test_a_schedule_state_from_another_plan_is_refused(scene):
    """A 300-step default state loaded into a multiview schedule continued at its step with
    8-view plans, and into a 100-step one with nothing left: both refused, nothing changed."""
    a = ViewSchedule(scene, MVGSConfig.default().for_scene(scene).with_total_steps(300), load_images=False)
    for _ in range(121):
        a.next()
    state = a.state_dict()
    b = ViewSchedule(scene, MVGSConfig.multiview().for_scene(scene).with_total_steps(300), load_images=False)
    with pytest.raises(ValueError, match=r"another stage plan \(factor, views, steps\)"):
        b.load_state_dict(state)
    assert b.step_count == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoDensificationWarning)
        c = ViewSchedule(scene, MVGSConfig.default().for_scene(scene).with_total_steps(100), load_images=False)
    with pytest.raises(ValueError, match="another stage plan"):
        c.load_state_dict(state)
    same = ViewSchedule(scene, MVGSConfig.default().for_scene(scene).with_total_steps(300), load_images=False)
    same.load_state_dict(state)
    assert same.step_count == 121 and [v.name for v in same.next().cameras] == [v.name for v in a.next().cameras]


def test_random_backgrounds_evaluate_on_the_scenes_own(scene):
    """Training on a random colour a step has no colour to evaluate on: the test renders use the
    one the scene's images were composited on (white here), not black. A model that covers
    nothing renders that colour: a white test view is matched exactly (PSNR inf)."""
    from mvgs_plugin.data import Scene

    white = {c.uid: torch.ones(c.height, c.width, 3) for c in scene.cameras}
    on_white = Scene(scene.train_cameras, scene.test_cameras, white, points=scene.points, background=(1.0, 1.0, 1.0))
    tiny = GS3DAdapter.from_tensors(torch.tensor([[0.0, 0.0, 0.0]]), scales=torch.full((1, 3), 1e-4),
                                    opacities=torch.tensor([1e-3]), rgb=torch.zeros(1, 3), scene_extent=1.0)
    for bg in ("random", "auto"):
        trainer = MVGS(tiny, on_white, MVGSConfig.baseline(background=bg).with_total_steps(10))
        assert trainer.schedule.background_value() == (1.0, 1.0, 1.0)
        assert trainer.evaluate().psnr > 60.0, bg
    black = MVGS(tiny, on_white, MVGSConfig.baseline(background="black").with_total_steps(10))
    assert black.evaluate().psnr < 1.0  # what "random" evaluated on before


def test_a_checkpoint_from_before_the_warmup_cap_resumes_when_its_plan_is_the_same(scene, tmp_path):
    """warmup_work_cap only shapes the plan once a run's length is set; the plan itself (stages)
    is what a resume compares. A default run saved before the field (its config reads None) with
    the plan today's default makes resumes; one whose plan the cap changed is refused, naming the
    flag that gives the checkpoint's plan back."""
    old = MVGSConfig.default(warmup_work_cap=None, densify_from=1, densify_every=4, densify_until=30_000,
                             grad_threshold_width=None)
    short, long = old.with_budget(30), old.with_budget(4000)  # the cap binds from 3334 up
    path = tmp_path / "old.pt"
    first = MVGS(make(scene), scene, short)
    first.fit(steps=5, progress=False)
    first.save_checkpoint(str(path))
    today = MVGSConfig.default(densify_from=1, densify_every=4, densify_until=30_000,
                               grad_threshold_width=None).with_budget(30)
    assert today.stages == short.stages and today.warmup_work_cap == 1000
    resumed = MVGS(make(scene), scene, today)
    resumed.load_checkpoint(str(path))
    assert resumed.step_count == 5
    # a plan the cap changed: 30 % of a budget of 4000 at 1/2 was 2,182 steps there, 1,818 today
    assert long.stages != dataclasses.replace(old, warmup_work_cap=1000.0).with_budget(4000).stages
    first = MVGS(make(scene), scene, long)
    first.step()
    first.save_checkpoint(str(path))
    capped = dataclasses.replace(old, warmup_work_cap=1000.0).with_budget(4000)
    with pytest.raises(ValueError, match="--warmup-work-cap 0"):
        MVGS(make(scene), scene, capped).load_checkpoint(str(path))
