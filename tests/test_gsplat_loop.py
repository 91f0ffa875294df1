"""MVGS inside gsplat's own trainer shape: examples/gsplat_loop and adapters.gsplat_strategy.

What is checked, each against a computation of its own:
- the MVGS loop is the single-view loop with at most five changed lines (a diff);
- a batch of M views gives the strategy each view's single-view statistic (one render and one
  loss per view, by hand), and chunks of a step give the same statistics as one call;
- a step refines once however many chunks it has, never while gradients are unused, with the
  schedule's threshold (MVAD by hand) as grow_grad2d, and resets opacities on the schedule's
  clock (gsplat 1.5.3's DefaultStrategy alone never does);
- cross-ray boxes clone exactly the Gaussians a brute-force test finds inside them;
- both example loops train through densification, opacity resets and (MVGS) stage hand-offs,
  and a run resumed from a checkpoint ends where the uninterrupted one does.
"""

import difflib
import math
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from gsplat.strategy import DefaultStrategy, MCMCStrategy

from mvgs_plugin.adapters.gsplat_strategy import MVGSStrategy
from mvgs_plugin import CRDConfig, MVGSConfig
from mvgs_plugin.data import load_scene
from mvgs_plugin.losses import ssim

ROOT = Path(__file__).resolve().parents[1]
LOOP = ROOT / "examples" / "gsplat_loop"
FORWARD = ROOT / "tests" / "data" / "forward64"
TABLETOP = ROOT / "examples" / "scenes" / "tabletop"
sys.path.insert(0, str(LOOP))
import common  # noqa: E402
import simple_trainer  # noqa: E402
import simple_trainer_mvgs  # noqa: E402


@pytest.fixture(scope="module")
def forward():
    return load_scene(FORWARD)


@pytest.fixture(scope="module")
def tabletop():
    return load_scene(TABLETOP)


class Spy(DefaultStrategy):
    """DefaultStrategy that records what reaches it (its behaviour unchanged)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.log = {"n_cameras": [], "grow": [], "prune": 0}

    def _update_state(self, params, state, info, packed=False):
        self.log["n_cameras"].append(int(info["n_cameras"]))
        return super()._update_state(params, state, info, packed)

    def _grow_gs(self, params, optimizers, state, step):
        self.log["grow"].append(self.grow_grad2d)
        return super()._grow_gs(params, optimizers, state, step)


def fresh_model(scene, sh_degree=1):
    torch.manual_seed(0)
    cfg = common.Config(sh_degree=sh_degree)
    splats, optimizers = common.create_splats_with_optimizers(scene, cfg, scene.extent)
    return cfg, splats, optimizers


def render(splats, cfg, data, sh_degree=0):
    pixels = data["image"] / 255.0
    renders, _, info = common.rasterize_splats(splats, cfg, data["camtoworld"], data["K"], pixels.shape[2],
                                               pixels.shape[1], sh_degree=sh_degree, backgrounds=data["background"])
    return renders, pixels, info


def gsplat_loss(colors, pixels):
    return 0.8 * F.l1_loss(colors, pixels) + 0.2 * (1.0 - ssim(colors, pixels, padding="valid"))


def step_once(strategy, splats, optimizers, state, data_list, order="after"):
    """One step of the gsplat loop over a list of batches: render, pre-hook, loss, backward per
    batch; then optimizer step and one post-hook per batch ("after", simple_trainer's order),
    or a post-hook right after each backward ("before")."""
    infos = []
    for data in data_list:
        colors, pixels, info = render(splats, common.Config(), data)
        strategy.step_pre_backward(splats, optimizers, state, 0, info)
        gsplat_loss(colors, pixels).backward()
        if order == "before":
            strategy.step_post_backward(splats, optimizers, state, 0, info, renders=colors)
        infos.append((info, colors))
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    if order == "after":
        for info, colors in infos:
            strategy.step_post_backward(splats, optimizers, state, 0, info, renders=colors)


# ---- the diff ------------------------------------------------------------------------------------
def changed_lines(a, b):
    ops = difflib.SequenceMatcher(None, a, b, autojunk=False).get_opcodes()
    return sum(max(i2 - i1, j2 - j1) for tag, i1, i2, j1, j2 in ops if tag != "equal")


def test_mvgs_loop_changes_at_most_five_lines_of_the_single_view_loop():
    single = (LOOP / "simple_trainer.py").read_text().splitlines()
    mvgs = (LOOP / "simple_trainer_mvgs.py").read_text().splitlines()
    assert changed_lines(["a", "b", "c"], ["a", "x", "c", "d"]) == 2  # the counter itself
    n = changed_lines(single, mvgs)
    assert 1 <= n <= 5, n
    added = [line.strip() for line in difflib.ndiff(single, mvgs) if line.startswith("+ ")]
    assert any("MVGSStrategy(DefaultStrategy(" in line for line in added)
    assert any("strategy.batches()" in line for line in added)
    # docs/gsplat_loop.md (linked from the README) shows the same diff
    page = (ROOT / "docs" / "gsplat_loop.md").read_text()
    for line in added:
        assert line.strip("+ ") in page, line


# ---- statistics ------------------------------------------------------------------------------------
def per_view_statistics(splats, cfg, data):
    """The screen-space statistic of every view rendered alone with its own loss: sum over views
    of |d loss_v / d means2d| in NDC, and the number of views each Gaussian is visible in."""
    grad2d = torch.zeros(len(splats["means"]))
    count = torch.zeros_like(grad2d)
    for v in range(data["image"].shape[0]):
        one = {k: t[v:v + 1] for k, t in data.items()}
        colors, pixels, info = render(splats, cfg, one)
        info["means2d"].retain_grad()
        gsplat_loss(colors, pixels).backward()
        g = info["means2d"].grad[0] * torch.tensor([pixels.shape[2] / 2.0, pixels.shape[1] / 2.0])
        visible = (info["radii"][0] > 0).all(-1)
        grad2d += torch.where(visible, g.norm(dim=-1), torch.zeros_like(grad2d))
        count += visible.float()
        for p in splats.values():
            p.grad = None
    return grad2d, count


@pytest.mark.parametrize("chunked", [False, True])
def test_a_batch_of_views_gives_each_view_its_single_view_statistic(forward, chunked):
    cfg, splats, optimizers = fresh_model(forward)
    config = MVGSConfig.multiview(chunk_size=3)
    strategy = MVGSStrategy(Spy(), forward, config, steps=300)
    state = strategy.initialize_state(scene_scale=forward.extent)
    step = next(strategy.batches(chunked=chunked))
    batches = step if chunked else [step]
    m = sum(b["image"].shape[0] for b in batches)
    assert m == min(config.stages[0].views, len(forward.train_cameras)) and m > 3
    assert len(batches) == (math.ceil(m / 3) if chunked else 1)
    whole = {k: torch.cat([b[k] for b in batches]) for k in batches[0]}
    expected_grad, expected_count = per_view_statistics(splats, cfg, whole)
    assert expected_count.sum() > 0
    step_once(strategy, splats, optimizers, state, batches)
    assert strategy.strategy.log["n_cameras"] == [b["image"].shape[0] for b in batches]
    assert torch.equal(state["count"], expected_count)
    torch.testing.assert_close(state["grad2d"], expected_grad, rtol=1e-4, atol=1e-9)


# ---- refinement ------------------------------------------------------------------------------------
def small_clock(**kw):
    """A strategy that refines every 2 steps from step 2 and resets opacities every 4."""
    return Spy(refine_start_iter=1, refine_every=2, reset_every=4, refine_stop_iter=100, **kw)


def test_the_strategy_clock_becomes_the_schedule_clock(forward):
    s = DefaultStrategy(refine_start_iter=60, refine_stop_iter=150, refine_every=10, reset_every=100,
                        grow_grad2d=3e-4)
    steps = MVGSStrategy(s, forward, "multiview", steps=300).config  # counts steps
    assert (steps.densify_from, steps.densify_until, steps.densify_every, steps.opacity_reset_every,
            steps.prune_large_after, steps.grad_threshold) == (60, 150, 10, 100, 100, 3e-4)
    # counts work: fractions of the run kept (the pyramid kept: on this forward rig the default
    # would train at full resolution only, where work and steps coincide)
    work = MVGSStrategy(s, forward, MVGSConfig.default(forward_rig="pyramid"), steps=300).config
    r = work.clock_length / 300
    assert work.counts_work and r < 1
    assert (work.densify_from, work.densify_until, work.densify_every, work.opacity_reset_every) == (
        round(60 * r), round(150 * r), round(10 * r), round(100 * r))
    kept = MVGSStrategy(s, forward, "multiview", steps=300, clock="config").config
    assert kept == MVGSConfig.multiview().with_total_steps(300)


def mvad_expected(scene, data, base, width):
    """β · 800 / W, halved when any two of the step's cameras, seen from the scene centre, are
    at least a chord of 1 apart on the unit sphere (MVAD's "any" rule, by hand)."""
    centres = data["camtoworld"][:, :3, 3].double()
    d = centres - scene.center
    d = d / d.norm(dim=-1, keepdim=True)
    far = (torch.cdist(d, d) >= 1.0).any()
    return base * 800.0 / width * (0.5 if far else 1.0), bool(far)


def test_each_step_refines_once_with_the_schedules_threshold(tabletop):
    cfg, splats, optimizers = fresh_model(tabletop)
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.multiview(chunk_size=5, crd=CRDConfig()), steps=12)
    state = strategy.initialize_state(scene_scale=tabletop.extent)
    expected, halved, counts = [], [], []
    for step, batches in zip(range(6), strategy.batches(chunked=True)):
        plan = strategy._plan
        assert len(batches) > 1  # several chunks per step
        n0 = len(splats["means"])
        step_once(strategy, splats, optimizers, state, batches)
        if plan.densify:
            whole = {k: torch.cat([b[k] for b in batches]) for k in batches[0]}
            beta, far = mvad_expected(tabletop, whole, 2e-4, whole["image"].shape[2])
            expected.append(beta)
            halved.append(far)
        else:
            assert len(splats["means"]) == n0  # no refine between densification steps
        counts.append(len(strategy.strategy.log["grow"]))
    assert expected and counts[-1] == len(expected)  # one refine per densification step, not per chunk
    assert strategy.strategy.log["grow"] == pytest.approx(expected, rel=1e-12)
    assert any(halved)  # the tabletop's orbit spreads a step's cameras: MVAD halves β


def test_a_refine_never_drops_unused_gradients(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.multiview(chunk_size=4, crd=CRDConfig()), steps=12)
    state = strategy.initialize_state(scene_scale=forward.extent)
    it = strategy.batches(chunked=True)
    step_once(strategy, splats, optimizers, state, next(it), order="before")  # step 1: no refine: fine
    before = {k: v.detach().clone() for k, v in splats.items()}
    with pytest.raises(RuntimeError, match="would drop the gradients"):
        step_once(strategy, splats, optimizers, state, next(it), order="before")  # step 2 refines
    for k in before:  # nothing replaced, every gradient still there for the optimizer
        assert torch.equal(splats[k].detach(), before[k]) and splats[k].grad is not None, k


def test_call_counts_are_checked(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(DefaultStrategy(), forward, "multiview", steps=50)
    state = strategy.initialize_state()
    with pytest.raises(RuntimeError, match="draw the step's batch"):
        strategy.step_post_backward(splats, optimizers, state, 0, {})
    it = strategy.batches()
    data = next(it)
    colors, pixels, info = render(splats, cfg, data)
    strategy.step_pre_backward(splats, optimizers, state, 0, info)
    gsplat_loss(colors, pixels).backward()
    with pytest.raises(RuntimeError, match="called 0 times for 1 batch"):
        next(it)
    strategy.step_post_backward(splats, optimizers, state, 0, info)
    with pytest.raises(RuntimeError, match="called 2 times for 1 batch"):
        strategy.step_post_backward(splats, optimizers, state, 0, info)
    with pytest.raises(TypeError, match="DefaultStrategy"):
        MVGSStrategy(MCMCStrategy(), forward)


def test_opacity_resets_follow_the_schedule(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.multiview(crd=CRDConfig()), steps=10)
    state = strategy.initialize_state(scene_scale=forward.extent)
    ceiling = 2 * strategy.strategy.prune_opa
    reset_steps = []
    for batch in strategy.batches():
        plan = strategy._plan
        step_once(strategy, splats, optimizers, state, [batch])
        top = float(torch.sigmoid(splats["opacities"]).max())
        if plan.reset_opacity:
            reset_steps.append(plan.step)
            assert top <= ceiling + 1e-7
        else:
            assert top > ceiling
    assert reset_steps == [4, 8]
    # gsplat 1.5.3's DefaultStrategy on its own never resets (its condition is always false)
    s = DefaultStrategy(reset_every=4, refine_start_iter=10**9)
    state = s.initialize_state()
    info = {"width": 1, "height": 1, "n_cameras": 1, "radii": torch.zeros(1, len(splats["means"]), 2),
            "gaussian_ids": None, "means2d": torch.zeros(1, len(splats["means"]), 2, requires_grad=True)}
    info["means2d"].grad = torch.zeros_like(info["means2d"])
    with torch.no_grad():
        splats["opacities"].fill_(3.0)
    s.step_post_backward(splats, optimizers, state, 4, info)
    assert float(torch.sigmoid(splats["opacities"]).min()) > 0.9


# ---- cross-ray densification ------------------------------------------------------------------------
def test_box_clone_copies_exactly_the_gaussians_inside(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(DefaultStrategy(), forward, "multiview", steps=50)
    state = strategy.initialize_state()
    n = len(splats["means"])
    state["grad2d"] = torch.rand(n, generator=torch.Generator().manual_seed(1))
    state["count"] = torch.ones(n)
    means = splats["means"].detach().clone()
    lo, hi = means.min(0).values, means.max(0).values
    mid = (lo + hi) / 2
    boxes = torch.stack([torch.stack([lo - 1, mid]), torch.stack([mid + (hi - mid) / 2, hi + 1])]).double()
    inside = [i for i in range(n) if any(all(boxes[b, 0, k] < means[i, k] < boxes[b, 1, k] for k in range(3))
                                         for b in range(2))]
    assert 0 < len(inside) < n
    for name, opt in optimizers.items():  # give the optimizer moments to check they start at zero
        splats[name].grad = torch.ones_like(splats[name])
        opt.step()
        opt.zero_grad(set_to_none=True)
    old = {k: v.detach().clone() for k, v in splats.items()}
    cap = len(inside) // 2
    added = strategy._clone_in_boxes(splats, optimizers, state, boxes, cap)
    best = sorted(inside, key=lambda i: -float(state["grad2d"][i]))[:cap]
    assert added == cap and len(splats["means"]) == n + cap
    for k in splats.keys():
        assert torch.equal(splats[k].detach()[:n], old[k])
        assert torch.equal(splats[k].detach()[n:], old[k][sorted(best)])
        moments = optimizers[k].state[splats[k]]["exp_avg"]
        assert torch.equal(moments[n:], torch.zeros_like(moments[n:]))
    assert torch.equal(state["grad2d"][n:], torch.zeros(cap)) and torch.equal(state["count"][n:], torch.zeros(cap))


def test_cross_ray_boxes_reach_the_strategy_through_renders(tabletop):
    cfg, splats, optimizers = fresh_model(tabletop)
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.multiview(crd=CRDConfig(enabled=True, max_new=1.0)), steps=12)
    state = strategy.initialize_state(scene_scale=tabletop.extent)
    found = []
    for _, batch in zip(range(6), strategy.batches()):
        step_once(strategy, splats, optimizers, state, [batch])
        if strategy._plan.densify:
            found.append((strategy.last_refine["boxes"], strategy.last_refine["from_boxes"]))
    assert found and any(b > 0 for b, _ in found) and sum(c for _, c in found) > 0
    # without renders= the rule is skipped, once, with a warning
    cfg, splats, optimizers = fresh_model(tabletop)
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.multiview(), steps=12)
    state = strategy.initialize_state(scene_scale=tabletop.extent)
    with pytest.warns(UserWarning, match="cross-ray densification .* is skipped"):
        for _, batch in zip(range(4), strategy.batches()):
            colors, pixels, info = render(splats, cfg, batch)
            strategy.step_pre_backward(splats, optimizers, state, 0, info)
            gsplat_loss(colors, pixels).backward()
            for opt in optimizers.values():
                opt.step()
                opt.zero_grad(set_to_none=True)
            strategy.step_post_backward(splats, optimizers, state, 0, info)
    assert strategy.last_refine["boxes"] == 0


# ---- the example loops end to end ---------------------------------------------------------------
def example_config(tmp_path, steps, preset, **kw):
    cfg = common.Config(data_dir=FORWARD, result_dir=tmp_path, preset=preset, sh_degree=1, **kw)
    cfg.adjust_steps(steps)
    return cfg


@pytest.mark.parametrize("module,preset", [pytest.param(simple_trainer, "single", marks=pytest.mark.slow),
                                           (simple_trainer_mvgs, "default"),
                                           pytest.param(simple_trainer_mvgs, "multiview", marks=pytest.mark.slow)])
def test_example_loop_trains_through_every_phase_and_resumes_exactly(tmp_path, monkeypatch, forward, module, preset):
    monkeypatch.setattr(module, "DefaultStrategy", Spy)
    steps = 300  # densification every 10 steps from 50 to 150, an opacity reset at 100
    cfg = example_config(tmp_path / "a", steps, preset, save_steps=[120])
    assert (cfg.refine_start_iter, cfg.refine_stop_iter, cfg.refine_every, cfg.reset_every) == (50, 150, 10, 100)
    torch.manual_seed(0)
    splats, strategy = module.train(cfg, forward)
    spy = strategy.strategy if isinstance(strategy, MVGSStrategy) else strategy
    assert len(spy.log["grow"]) >= 5  # densified
    assert len(splats["means"]) != len(forward.points)
    if preset == "multiview":
        assert max(spy.log["n_cameras"]) > 1  # multi-view statistics reached gsplat's strategy
    if isinstance(strategy, MVGSStrategy):
        # multiview hands off between pyramid levels; the default trains this forward-facing rig at
        # full resolution only (MVGSConfig.forward_rig)
        assert (len(strategy.config.stages) > 1) == (preset == "multiview")
        assert strategy.schedule.step_count == steps
        assert strategy.last_refine is not None
    resumed_cfg = example_config(tmp_path / "b", steps, preset, resume=tmp_path / "a" / "ckpt_120.pt")
    torch.manual_seed(123)  # the checkpoint restores the RNG
    resumed, _ = module.train(resumed_cfg, forward)
    for k in splats.keys():
        assert torch.equal(resumed[k], splats[k]), k


def test_example_cli_writes_metrics(tmp_path):
    out = tmp_path / "o"
    cfg = common.parse_config(["--data", str(FORWARD), "--steps", "60", "--out", str(out), "--threads", "1"])
    metrics = common.run(simple_trainer_mvgs.train, cfg)
    assert metrics["strategy"] == "MVGSStrategy" and metrics["preset"] == "default"
    # a forward-facing rig: the default trains at full resolution only, one unit of work per step
    assert metrics["work"] == 60 and metrics["steps"] == 60 and metrics["psnr"] > 10
    assert (out / "metrics.json").exists()
    with pytest.raises(SystemExit):
        common.parse_config(["--device", "cuda"] if not torch.cuda.is_available() else ["--steps", "1"])
