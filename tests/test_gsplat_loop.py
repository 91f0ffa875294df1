"""MVGSStrategy in gsplat's own loop shape (examples/gsplat_loop/).

Checked against independent computations: each view's statistic against one render and one
loss per view; chunked steps against one render call of all views (gradients and statistics);
the pyramid batch against the package's own pyramid images and scaled cameras; the threshold
against β · 800 / W halved by hand for spread cameras; the loop with step_post_backward before
the optimizer step against the loop with it after (the same model, bit for bit); every example
trained through densification, opacity resets and stage hand-offs and resumed from a checkpoint
to the same tensors. gsplat 1.5.3's DefaultStrategy is installed by the [dev] extra.
"""

import copy
import difflib
import json
import math
import re
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gsplat.strategy import DefaultStrategy, MCMCStrategy

from mvgs_plugin import CRDConfig, MVGSConfig
from mvgs_plugin.adapters.gs3d import beyond_far_line, even_cut_order
from mvgs_plugin.adapters.gsplat_strategy import MVGSStrategy, views_of
from mvgs_plugin.adapters import gsplat_strategy
from mvgs_plugin.data import load_scene
from mvgs_plugin.io import load_checked, save_checked
from mvgs_plugin.losses import ssim
from mvgs_plugin.schedule import ViewSchedule

ROOT = Path(__file__).resolve().parents[1]
LOOP = ROOT / "examples" / "gsplat_loop"
FORWARD = ROOT / "tests" / "data" / "forward64"
TABLETOP = ROOT / "examples" / "scenes" / "tabletop"
sys.path.insert(0, str(LOOP))

import common  # noqa: E402
import simple_trainer  # noqa: E402
import simple_trainer_chunked  # noqa: E402
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
        self.log = {"n_cameras": [], "grow": [], "grown": [], "prune": 0}

    def _update_state(self, params, state, info, packed=False):
        self.log["n_cameras"].append(int(info["n_cameras"]))
        return super()._update_state(params, state, info, packed)

    def _grow_gs(self, params, optimizers, state, step):
        self.log["grow"].append(self.grow_grad2d)
        n_dupli, n_split = super()._grow_gs(params, optimizers, state, step)
        self.log["grown"].append((step, n_dupli + n_split))
        return n_dupli, n_split


class SceneParser:
    """common.Parser's fields for an already loaded scene (no second read)."""

    def __init__(self, scene):
        self.points = scene.points.xyz.numpy()
        self.points_rgb = (scene.points.rgb.numpy() * 255).round().astype("uint8")


def fresh_model(scene, sh_degree=1):
    torch.manual_seed(0)
    cfg = common.Config(sh_degree=sh_degree)
    cfg.make_strategy()
    splats, optimizers = common.create_splats_with_optimizers(SceneParser(scene), cfg, scene.extent)
    return cfg, splats, optimizers


def render(splats, cfg, data, sh_degree=0):
    pixels = data["image"] / 255.0
    renders, _, info = common.rasterize_splats(splats, cfg, None, data["camtoworld"], data["K"], pixels.shape[2],
                                               pixels.shape[1], sh_degree=sh_degree, backgrounds=data["background"])
    return renders, pixels, info


def gsplat_loss(colors, pixels):
    return 0.8 * F.l1_loss(colors, pixels) + 0.2 * (1.0 - ssim(colors, pixels, padding="valid"))


def step_once(strategy, splats, optimizers, state, data_list, order="after", step=0):
    """One step of the gsplat loop over a list of batches (the step's chunks): render,
    pre-hook, the chunk's mean loss times its share of the step's views, backward per batch;
    then optimizer step and one post-hook per batch ("after", simple_trainer's order), or a
    post-hook right after each backward ("before")."""
    m = sum(d["image"].shape[0] for d in data_list)
    infos = []
    for data in data_list:
        colors, pixels, info = render(splats, common.Config(), data)
        strategy.step_pre_backward(splats, optimizers, state, step, info)
        (gsplat_loss(colors, pixels) * (len(pixels) / m)).backward()
        if order == "before":
            strategy.step_post_backward(splats, optimizers, state, step, info, renders=colors)
        infos.append((info, colors))
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    if order == "after":
        for info, colors in infos:
            strategy.step_post_backward(splats, optimizers, state, step, info, renders=colors)


def plain_step(strategy, splats, optimizers, state, cfg, batch, loss_fn, with_renders=True):
    """One unchunked step in gsplat's order with the loss `loss_fn(colors, pixels)`."""
    colors, pixels, info = render(splats, cfg, batch)
    strategy.step_pre_backward(splats, optimizers, state, 0, info)
    loss_fn(colors, pixels).backward()
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    strategy.step_post_backward(splats, optimizers, state, 0, info, renders=colors if with_renders else None)


# ---- the diff ------------------------------------------------------------------------------------
def changed_lines(a, b):
    ops = difflib.SequenceMatcher(None, a, b, autojunk=False).get_opcodes()
    return sum(max(i2 - i1, j2 - j1) for tag, i1, i2, j1, j2 in ops if tag != "equal")


def test_mvgs_loop_adds_four_lines_to_the_single_view_loop_and_to_gsplats_own():
    single = (LOOP / "simple_trainer.py").read_text().splitlines()
    mvgs = (LOOP / "simple_trainer_mvgs.py").read_text().splitlines()
    assert changed_lines(["a", "b", "c"], ["a", "x", "c", "d"]) == 2  # the counter itself
    n = changed_lines(single, mvgs)
    assert 1 <= n <= 5, n
    diff = [line for line in difflib.ndiff(single, mvgs) if line[:2] in ("+ ", "- ")]
    added = [line[2:].strip() for line in diff if line.startswith("+ ")]
    assert len(added) == len(diff) == 4  # added only: the loop's own lines are all kept
    assert any("MVGSStrategy(self.cfg.strategy, self.trainset" in line for line in added)
    assert any("self.cfg.strategy.loader(trainloader)" in line for line in added)
    # the patch of gsplat 1.5.3's examples/simple_trainer.py: zero-context hunks that only add,
    # at most five lines, and the same statements as in our port
    patch = (LOOP / "gsplat_1.5.3.patch").read_text().splitlines()
    hunks = [line for line in patch if line.startswith("@@")]
    plus = [line[1:].strip() for line in patch if line.startswith("+") and not line.startswith("+++")]
    minus = [line for line in patch if line.startswith("-") and not line.startswith("---")]
    assert hunks and all(re.fullmatch(r"@@ -\d+,0 \+\d+(,\d+)? @@.*", h) for h in hunks)
    assert not minus and len(plus) <= 5
    # the port passes its command line's size and reset rules (--world-size-rule, --opacity-reset-scope) on
    assert [p.replace("cfg.mvgs_preset", '"default"').replace(", **cfg.mvgs_rules", "") for p in added] == plus
    # docs/gsplat_loop.md (linked from the README) shows the added lines
    page = (ROOT / "docs" / "gsplat_loop.md").read_text()
    for line in added + plus:
        assert line in page, line


def test_the_wrapper_is_a_default_strategy_to_the_trainer(forward):
    s = DefaultStrategy(absgrad=True, verbose=True, grow_grad2d=3e-4)
    w = MVGSStrategy(s, forward, "multiview", steps=100)
    assert isinstance(w, DefaultStrategy)  # simple_trainer's isinstance dispatch takes it
    assert (w.absgrad, w.verbose, w.grow_grad2d) == (True, True, 3e-4)  # its field reads too
    with pytest.raises(TypeError, match="DefaultStrategy"):
        MVGSStrategy(MCMCStrategy(), forward)
    with pytest.raises(TypeError, match="already an MVGSStrategy"):
        MVGSStrategy(w, forward)
    with pytest.raises(ValueError, match="steps must be a positive int"):
        MVGSStrategy(s, forward, steps=0)


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
    assert strategy.strategy.log["n_cameras"] == [m] * len(batches)  # each chunk normalised as the step
    assert torch.equal(state["count"], expected_count)
    torch.testing.assert_close(state["grad2d"], expected_grad, rtol=1e-4, atol=1e-9)


def test_chunks_weighted_by_their_share_give_the_one_call_gradients(forward):
    """Each chunk's mean loss times len(chunk) / M: the parameter gradients of one render call
    over all M views (and, by the test above, its statistics)."""
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(DefaultStrategy(), forward, MVGSConfig.multiview(chunk_size=3), steps=300)
    whole = next(strategy.batches())
    m = whole["image"].shape[0]
    colors, pixels, _ = render(splats, cfg, whole)
    gsplat_loss(colors, pixels).backward()
    expected = {k: p.grad.clone() for k, p in splats.items()}
    for p in splats.values():
        p.grad = None
    parts = [(slice(s, min(s + 3, m)), (min(s + 3, m) - s) / m) for s in range(0, m, 3)]
    for part, weight in parts:
        one = {k: t[part] for k, t in whole.items()}
        colors, pixels, _ = render(splats, cfg, one)
        (gsplat_loss(colors, pixels) * weight).backward()
    for k, p in splats.items():
        torch.testing.assert_close(p.grad, expected[k], rtol=1e-4, atol=1e-9)
    # chunks() gives these slices and weights for the current step
    assert [(p.start, p.stop, w) for p, w in strategy.chunks()] == [(p.start, p.stop, w) for p, w in parts]


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
    # gsplat's defaults (refine from step 500) on a 300-step run: said, not a run that never densifies in silence
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        MVGSStrategy(DefaultStrategy(), forward, "default", steps=300)
    assert len(said) == 1, [str(w.message) for w in said]  # once: not again as the schedule's NoDensificationWarning
    assert str(said[0].message).startswith("the strategy's refine window starts at step 500, at or after the run's "
                                           "300 steps: this run never densifies")


def mvad_expected(scene, data, base, width):
    """β · 800 / W, halved when any two of the step's cameras, seen from the scene centre, are
    at least a chord of 1 apart on the unit sphere (MVAD's "any" rule, by hand)."""
    centres = data["camtoworld"][:, :3, 3].double()
    d = centres - scene.center
    d = d / d.norm(dim=-1, keepdim=True)
    far = (torch.cdist(d, d) >= 1.0).any()
    return base * 800.0 / width * (0.5 if far else 1.0), bool(far)


def small_clock(**kw):
    """A strategy that refines every 2 steps from step 2 and resets opacities every 4."""
    return Spy(refine_start_iter=1, refine_every=2, reset_every=4, refine_stop_iter=100, **kw)


def test_each_step_refines_once_with_the_schedules_threshold(tabletop):
    cfg, splats, optimizers = fresh_model(tabletop)
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.multiview(chunk_size=5, crd=CRDConfig()), steps=12)
    state = strategy.initialize_state(scene_scale=tabletop.extent)
    expected, halved, counts = [], [], []
    for step, batches in zip(range(6), strategy.batches(chunked=True)):
        plan = strategy.plan
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


# ---- hook order --------------------------------------------------------------------------------------
def train_small(scene, order, steps=24, save_at=None, resume=None):
    """A gsplat-shaped loop on the package's batches, chunks of 3, refines every 2 steps and
    opacity resets every 4, through the multiview preset's pyramid hand-offs."""
    cfg, splats, optimizers = fresh_model(scene)
    strategy = MVGSStrategy(small_clock(), scene, MVGSConfig.multiview(chunk_size=3), steps=steps)
    state = strategy.initialize_state(scene_scale=scene.extent)
    it = strategy.batches(chunked=True)
    saved, refines, resets = None, 0, 0
    if resume is not None:
        for k, v in resume["splats"].items():
            splats[k] = torch.nn.Parameter(v.clone())
            optimizers[k].param_groups[0]["params"] = [splats[k]]
            optimizers[k].load_state_dict(resume["optimizers"][k])
        state.update({k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in resume["state"].items()})
        strategy.load_state_dict(resume["mvgs"], splats, optimizers, state)
        torch.set_rng_state(resume["rng"])  # gsplat's split samples from it
    for batches in it:
        plan = strategy.plan
        refines += plan.densify
        resets += plan.reset_opacity or plan.handoff_reset
        step_once(strategy, splats, optimizers, state, batches, order=order, step=plan.step - 1)
        if plan.step == save_at:
            saved = {"splats": {k: v.detach().clone() for k, v in splats.items()},
                     "optimizers": {k: copy.deepcopy(o.state_dict()) for k, o in optimizers.items()},
                     "state": {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in state.items()},
                     "mvgs": strategy.state_dict(), "rng": torch.get_rng_state()}
    return splats, strategy, saved, refines, resets


def test_post_backward_before_the_optimizer_step_trains_the_same_model(forward):
    after, s_after, _, refines, resets = train_small(forward, "after")
    before, s_before, saved, _, _ = train_small(forward, "before", save_at=12)
    assert refines >= 5 and resets >= 3 and len(s_after.config.stages) > 1  # refines, resets, hand-offs
    assert s_after.last_refine["after"] != s_after.last_refine["before"]
    assert len(after["means"]) != len(forward.points)
    for k in after.keys():
        assert torch.equal(after[k], before[k]), k
    # a checkpoint taken with a refine deferred to the next batch resumes to the same model
    assert saved["mvgs"]["pending"] is not None
    resumed, _, _, _, _ = train_small(forward, "before", resume=saved)
    for k in after.keys():
        assert torch.equal(resumed[k], before[k]), k


def test_a_deferred_refine_needs_the_optimizer_step_first(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.multiview(chunk_size=4), steps=12)
    state = strategy.initialize_state(scene_scale=forward.extent)
    it = strategy.batches(chunked=True)
    step_once(strategy, splats, optimizers, state, next(it), order="before")  # step 1: no refine
    for data in next(it):  # step 2 refines: post-hooks before any optimizer step, then no step at all
        colors, pixels, info = render(splats, cfg, data)
        strategy.step_pre_backward(splats, optimizers, state, 1, info)
        gsplat_loss(colors, pixels).backward()
        strategy.step_post_backward(splats, optimizers, state, 1, info)
    before = {k: v.detach().clone() for k, v in splats.items()}
    with pytest.raises(RuntimeError, match="waits for the gradients"):
        next(it)
    for k in before:  # nothing replaced, every gradient still there for the optimizer
        assert torch.equal(splats[k].detach(), before[k]) and splats[k].grad is not None, k


def test_call_counts_are_checked_at_the_first_step(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(DefaultStrategy(), forward, "multiview", steps=50)
    state = strategy.initialize_state()
    with pytest.raises(RuntimeError, match="before the step's batch was brought to its level"):
        strategy.step_post_backward(splats, optimizers, state, 0, {})
    it = strategy.batches()
    data = next(it)
    colors, pixels, info = render(splats, cfg, data)
    strategy.step_pre_backward(splats, optimizers, state, 0, info)
    gsplat_loss(colors, pixels).backward()
    with pytest.raises(RuntimeError, match="reported 0 of its"):
        next(it)
    strategy.step_post_backward(splats, optimizers, state, 0, info)
    with pytest.raises(RuntimeError, match="reported .* views for a step of"):
        strategy.step_post_backward(splats, optimizers, state, 0, info)
    next(it)  # the refused draw lost no plan: the schedule's second step comes next
    assert strategy.plan.step == 2


def test_opacity_resets_follow_the_schedule(forward):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.multiview(crd=CRDConfig()), steps=10)
    state = strategy.initialize_state(scene_scale=forward.extent)
    ceiling = 2 * strategy.strategy.prune_opa
    reset_steps = []
    for batch in strategy.batches():
        plan = strategy.plan
        step_once(strategy, splats, optimizers, state, [batch])
        top = float(torch.sigmoid(splats["opacities"].detach()).max())
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
    assert float(torch.sigmoid(splats["opacities"].detach()).min()) > 0.9


def test_verbose_lines_carry_the_loops_step(forward, capsys):
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(small_clock(verbose=True), forward, MVGSConfig.multiview(), steps=10)
    state = strategy.initialize_state(scene_scale=forward.extent)
    for batch in strategy.batches():
        step_once(strategy, splats, optimizers, state, [batch], step=1000 + strategy.plan.step)
    lines = capsys.readouterr().out.splitlines()
    steps = {int(m.group(1)) for m in (re.match(r"Step (\d+):", line) for line in lines) if m}
    assert any("duplicated" in line for line in lines) and any("opacities reset" in line for line in lines)
    assert steps and all(s > 1000 for s in steps)  # never the wrapper's internal 1 or 3


# ---- their data: a DataLoader on the user's Dataset ----------------------------------------------------
def test_at_level_matches_the_packages_pyramid(forward):
    parser = common.Parser(FORWARD)
    trainset = common.Dataset(parser, "train")
    config = MVGSConfig.multiview(chunk_size=3)
    strategy = MVGSStrategy(DefaultStrategy(), trainset, config, steps=40)
    reference = ViewSchedule(forward, config.for_scene(forward).with_total_steps(40))  # the package's own
    loader = torch.utils.data.DataLoader(trainset, batch_sampler=strategy.batch_sampler())
    factors = set()
    for step, data in zip(range(12), loader):
        pixels, Ks = strategy.at_level(data["image"] / 255.0, data["K"], data["image_id"])
        plan = reference.next()
        assert data["image_id"].tolist() == plan.views
        factors.add(plan.factor)
        torch.testing.assert_close(pixels, torch.stack(plan.images), atol=2e-6, rtol=0)
        torch.testing.assert_close(Ks.double(), torch.stack([c.K for c in plan.cameras]), atol=1e-4, rtol=1e-6)
        strategy.plan, strategy._reported = None, 0  # (no training here)
    assert len(factors) >= 3  # several pyramid levels crossed
    # a batch out of the sampler's order is refused, naming both
    it = iter(loader)
    data = next(it)
    with pytest.raises(ValueError, match="batches must arrive in the order"):
        strategy.at_level(data["image"], data["K"], data["image_id"].flip(0))


def loader_run(parser, workers, steps=30, stop_at=None, state=None):
    """The views, sizes and K of every step the MVGS loader gives (no training)."""
    trainset = common.Dataset(parser, "train")
    strategy = MVGSStrategy(DefaultStrategy(), trainset, MVGSConfig.multiview(chunk_size=3), steps=steps)
    if state is not None:
        strategy.load_state_dict(state)
    dl = torch.utils.data.DataLoader(trainset, batch_size=1, shuffle=True, num_workers=workers,
                                     persistent_workers=workers > 0)
    seen = []
    for data in strategy.loader(dl):
        seen.append((data["image_id"].tolist(), tuple(data["image"].shape), data["K"].clone()))
        strategy._reported = len(strategy.plan.views)  # (no training here)
        if stop_at is not None and len(seen) == stop_at:
            return seen, strategy.state_dict()
    return seen, None


def test_the_loader_keeps_its_workers_and_draws_the_schedule_in_order():
    parser = common.Parser(FORWARD)
    plain, _ = loader_run(parser, 0)
    assert len(plain) == 30
    workers, _ = loader_run(parser, 2)  # two worker processes loading ahead of the loop
    assert [(v, s) for v, s, _ in workers] == [(v, s) for v, s, _ in plain]
    assert all(torch.equal(a, b) for (_, _, a), (_, _, b) in zip(workers, plain))
    # a checkpoint taken while the workers have drawn ahead resumes at the next step
    head, state = loader_run(parser, 2, stop_at=11)
    tail, _ = loader_run(parser, 2, state=state)
    assert [(v, s) for v, s, _ in head + tail] == [(v, s) for v, s, _ in plain]


def test_views_of_reads_datasets_without_their_images(forward):
    parser = common.Parser(FORWARD)
    views = views_of(common.Dataset(parser, "train"))
    assert len(views.train_cameras) == len(forward.train_cameras)
    for a, b in zip(views.train_cameras, forward.train_cameras):
        assert torch.allclose(a.K, b.K, atol=1e-5) and torch.allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)
    assert abs(views.extent - forward.extent) < 1e-9

    class Items(torch.utils.data.Dataset):  # any Dataset of camera dicts
        def __len__(self):
            return 3

        def __getitem__(self, i):
            c = forward.train_cameras[i]
            return {"camtoworld": c.camera_to_world, "K": c.K, "image": torch.zeros(c.height, c.width, 3)}

    assert [c.width for c in views_of(Items()).train_cameras] == [64] * 3
    with pytest.raises(TypeError, match="not a dict with camtoworld"):
        views_of([1, 2])
    with pytest.raises(RuntimeError, match="loads its own images"):
        MVGSStrategy(DefaultStrategy(), Items(), steps=10).batches()


def test_a_multi_view_plan_on_images_of_several_sizes_is_refused_before_the_collate(forward):
    """A DataLoader stacks a step's images (torch's default collate), so M > 1 views of two sizes
    ended in torch's "stack expects each tensor to be equal size"; the sampler now refuses it,
    naming the sizes, and a one-view plan on the same views trains (one image per batch)."""
    cams = list(forward.train_cameras)
    small = [c.scaled(0.5) for c in cams[:3]]  # a second camera of another size

    class Items(torch.utils.data.Dataset):
        def __init__(self, cams):
            self.cams = cams

        def __len__(self):
            return len(self.cams)

        def __getitem__(self, i):
            c = self.cams[i]
            return {"camtoworld": c.camera_to_world, "K": c.K, "image": torch.zeros(c.height, c.width, 3)}

    mixed = Items(small + cams[3:])
    w, h = cams[0].width, cams[0].height
    strategy = MVGSStrategy(DefaultStrategy(), mixed, "multiview", steps=40)
    (w1, h1), (w2, h2) = sorted([(small[0].width, small[0].height), (w, h)])
    n1, n2 = (3, len(cams) - 3) if (w1, h1) == (small[0].width, small[0].height) else (len(cams) - 3, 3)
    with pytest.raises(ValueError, match=rf"up to {len(cams)} views per step.* 2 sizes: {w1}x{h1} \({n1} views\), "
                                         rf"{w2}x{h2} \({n2} views\)"):
        strategy.loader(torch.utils.data.DataLoader(mixed))
    one_view = MVGSStrategy(DefaultStrategy(), mixed, "default", steps=40)
    batch = next(iter(one_view.loader(torch.utils.data.DataLoader(mixed))))
    assert batch["image"].shape[0] == 1
    MVGSStrategy(DefaultStrategy(), Items(cams), "multiview", steps=40).batch_sampler()  # one size: fine


# ---- their mistakes -------------------------------------------------------------------------------------
def run_loss(scene, loss_fn, steps):
    """The mistake warnings a multiview loop with `loss_fn` gets over `steps` steps."""
    cfg, splats, optimizers = fresh_model(scene)
    strategy = MVGSStrategy(DefaultStrategy(refine_start_iter=10**6), scene, MVGSConfig.multiview(), steps=steps)
    state = strategy.initialize_state(scene_scale=scene.extent)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        for batch in strategy.batches():
            plain_step(strategy, splats, optimizers, state, cfg, batch, loss_fn)
    return [str(w.message) for w in record if "average every term over the batch" in str(w.message).lower()]


def test_a_loss_on_one_view_is_said_once(forward):
    said = run_loss(forward, lambda c, p: F.l1_loss(c[0], p[0]), steps=12)
    assert len(said) == 1 and "reaches 1 of the" in said[0]


def test_an_ssim_term_on_colors_0_is_said_once(forward, tabletop):
    def habit(c, p):
        return 0.8 * F.l1_loss(c, p) + 0.2 * (1.0 - ssim(c[:1], p[:1], padding="valid"))

    said = run_loss(forward, habit, steps=80)
    assert len(said) == 1 and "position 0" in said[0]
    for scene in (forward, tabletop):  # an honest loss over the batch: nothing said
        assert run_loss(scene, gsplat_loss, steps=80) == []


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
        if strategy.plan.densify:
            found.append((strategy.last_refine["boxes"], strategy.last_refine["from_boxes"]))
    assert found and any(b > 0 for b, _ in found) and sum(c for _, c in found) > 0
    # without renders= the rule is skipped, once, with a warning
    cfg, splats, optimizers = fresh_model(tabletop)
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.multiview(crd=CRDConfig(enabled=True)), steps=12)
    state = strategy.initialize_state(scene_scale=tabletop.extent)
    with pytest.warns(UserWarning, match="cross-ray densification .* is skipped"):
        for _, batch in zip(range(4), strategy.batches()):
            plain_step(strategy, splats, optimizers, state, cfg, batch, gsplat_loss, with_renders=False)
    assert strategy.last_refine["boxes"] == 0


def test_a_parser_size_a_pixel_off_its_images_densifies_across_rays_at_the_renders_size(forward):
    """gsplat's Parser scales imsize_dict with a truncating int(), so it can say a pixel more or
    less than its images hold. The plan's cameras are the views as the loop rendered them (the
    batch's size and K), so cross-ray densification's loss maps fit them and boxes are found."""
    parser = common.Parser(FORWARD)
    parser.imsize_dict = {i: (w + 1, h - 1) for i, (w, h) in parser.imsize_dict.items()}
    trainset = common.Dataset(parser, "train")
    cfg, splats, optimizers = fresh_model(forward)
    config = MVGSConfig.multiview(crd=CRDConfig(enabled=True, max_new=1.0)).with_views(2)
    strategy = MVGSStrategy(small_clock(), trainset, config, steps=12)
    state = strategy.initialize_state(scene_scale=forward.extent)
    found = []
    for step, data in zip(range(6), strategy.loader(torch.utils.data.DataLoader(trainset))):
        pixels = data["image"] / 255.0
        h, w = pixels.shape[1:3]
        assert all((c.width, c.height) == (w, h) for c in strategy.plan.cameras)
        assert torch.allclose(torch.stack([c.K for c in strategy.plan.cameras]), data["K"].double())
        colors, _, info = common.rasterize_splats(splats, cfg, None, data["camtoworld"], data["K"], w, h, sh_degree=0)
        strategy.step_pre_backward(splats, optimizers, state, step, info)
        F.l1_loss(colors, pixels).backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(splats, optimizers, state, step, info, renders=colors)
        if strategy.plan.densify:
            found.append(strategy.last_refine["boxes"])
    assert found and max(found) > 0


# ---- the example loops end to end ---------------------------------------------------------------
def example_config(tmp_path, steps, preset, data=FORWARD, **kw):
    cfg = common.Config(data_dir=data, result_dir=tmp_path, mvgs_preset=preset, sh_degree=1, **kw)
    cfg.adjust_steps(steps)
    cfg.make_strategy(Spy)
    return cfg


@pytest.mark.parametrize("module,preset,kw", [
    pytest.param(simple_trainer, "single", {}, marks=pytest.mark.slow),
    (simple_trainer_mvgs, "default", {}),
    pytest.param(simple_trainer_mvgs, "multiview", {"num_workers": 2}, marks=pytest.mark.slow),
    # the chunked loop with 4 views at full resolution (multiview's 8 cost twice the time; 4 still
    # splits into chunks of 3 at every level)
    (simple_trainer_chunked, MVGSConfig.multiview().with_views(4), {"chunk_size": 3}),
])
def test_example_loop_trains_through_every_phase_and_resumes_exactly(tmp_path, forward, module, preset, kw):
    steps = 300  # densification every 10 steps from 50 to 150, an opacity reset at 100
    saves = [100, 120] if module is simple_trainer_chunked else [120]
    cfg = example_config(tmp_path / "a", steps, preset, save_steps=saves, **kw)
    assert (cfg.refine_start_iter, cfg.refine_stop_iter, cfg.refine_every, cfg.reset_every) == (50, 150, 10, 100)
    torch.manual_seed(0)
    runner = module.Runner(cfg)
    runner.train()
    splats, strategy = runner.splats, runner.cfg.strategy
    spy = strategy.strategy if isinstance(strategy, MVGSStrategy) else strategy
    assert len(spy.log["grow"]) >= 5  # densified
    assert len(splats["means"]) != len(forward.points)
    multiview = preset == "multiview" or isinstance(preset, MVGSConfig)
    if multiview:
        assert max(spy.log["n_cameras"]) > 1  # multi-view statistics reached gsplat's strategy
    if isinstance(strategy, MVGSStrategy):
        # multiview hands off between pyramid levels; the default trains this forward-facing rig at
        # full resolution only (MVGSConfig.forward_rig)
        assert (len(strategy.config.stages) > 1) == multiview
        assert strategy.schedule.step_count == steps
        assert strategy.last_refine is not None
    start = saves[0]
    if module is simple_trainer_chunked:  # the refine of step 100 waits in the checkpoint for the next batch
        data = load_checked(str(tmp_path / "a" / "ckpt_100.pt"))["data"]
        assert data["mvgs"]["pending"] is not None and data["mvgs"]["pending"]["densify"]
    resumed_cfg = example_config(tmp_path / "b", steps, preset, resume=tmp_path / "a" / f"ckpt_{start}.pt", **kw)
    torch.manual_seed(123)  # the checkpoint restores the RNG
    resumed = module.Runner(resumed_cfg)
    resumed.train()
    strategy = resumed.cfg.strategy
    spy = strategy.strategy if isinstance(strategy, MVGSStrategy) else strategy
    assert any(n > 0 for _, n in spy.log["grown"]), spy.log["grown"]  # the resumed part grew the model
    for k in splats.keys():
        assert torch.equal(resumed.splats[k], splats[k]), k


def test_example_cli_writes_metrics(tmp_path):
    out = tmp_path / "o"
    cfg = common.parse_config(["--data", str(FORWARD), "--steps", "60", "--out", str(out), "--threads", "1"])
    metrics = common.run(simple_trainer_mvgs.Runner, cfg)
    assert metrics["strategy"] == "MVGSStrategy" and metrics["preset"] == "default"
    # a forward-facing rig: the default trains at full resolution only, one unit of work per step
    assert metrics["work"] == 60 and metrics["steps"] == 60 and metrics["psnr"] > 10
    assert (out / "metrics.json").exists()
    with pytest.raises(SystemExit):
        common.parse_config(["--device", "cuda"] if not torch.cuda.is_available() else ["--steps", "1"])


def test_a_refused_resume_is_one_line_and_exit_2(tmp_path, capsys):
    """A checkpoint of another budget (or a damaged file) ends the example with one line naming
    --resume and exit code 2, as train_3dgs.py's refusals do, not a traceback."""
    base = ["--data", str(FORWARD), "--steps", "30", "--threads", "1"]
    cfg = common.parse_config(base + ["--out", str(tmp_path / "a"), "--max-gaussians", "400", "--save-steps", "10"])
    common.run(simple_trainer_mvgs.Runner, cfg)
    ckpt = tmp_path / "a" / "ckpt_10.pt"
    capsys.readouterr()
    cfg = common.parse_config(base + ["--out", str(tmp_path / "b"), "--max-gaussians", "300", "--resume", str(ckpt)])
    with pytest.raises(SystemExit) as err:
        common.run(simple_trainer_mvgs.Runner, cfg)
    lines = capsys.readouterr().err.strip().splitlines()
    assert err.value.code == 2 and len(lines) == 1
    assert f"error: --resume {ckpt}: " in lines[0] and "max_gaussians" in lines[0]
    bad = tmp_path / "bad.pt"
    bad.write_bytes(ckpt.read_bytes()[:200])
    foreign = tmp_path / "controller.pt"  # the keys of a controller's checkpoint (examples/train_3dgs.py)
    save_checked({"config": {}, "schedule": {}, "torch_rng": torch.get_rng_state(), "adapter": {}}, str(foreign))
    for name, flags, said in [
            ("c", ["--resume", str(bad)], f"error: --resume {bad}: not a checkpoint this loop wrote, or damaged ("),
            ("d", ["--resume", str(foreign)], f"error: --resume {foreign}: not a checkpoint of this loop: it has no "
                                              "['step', 'splats', 'optimizers', 'schedulers', 'strategy_state', 'data', "
                                              "'rng'] (it holds ['adapter', 'config', 'schedule', 'torch_rng'])"),
            ("e", ["--resume", str(ckpt), "--seed", "4"], f"error: --resume {ckpt}: the checkpoint was made with --seed 0 "
                                                          "(this command: 4); resume with the flags it was written with")]:
        cfg = common.parse_config(base + ["--out", str(tmp_path / name), "--max-gaussians", "400", *flags])
        with pytest.raises(SystemExit) as err:
            common.run(simple_trainer_mvgs.Runner, cfg)
        lines = capsys.readouterr().err.strip().splitlines()
        assert err.value.code == 2 and len(lines) == 1 and said in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "bad.pt", "controller.pt"]  # refused runs leave no folder
    cfg = common.parse_config(base + ["--out", str(tmp_path / "a"), "--max-gaussians", "400", "--resume", str(ckpt)])
    assert common.run(simple_trainer_mvgs.Runner, cfg)["seed"] == 0  # the same seed resumes, and says its seed


def test_a_flag_the_loop_does_not_read_is_refused_by_name(tmp_path, capsys):
    """--preset, --max-gaussians, --pixels-per-gaussian mean nothing to gsplat's single-view loop
    and --chunk-size only to the chunked one: a run given one it would ignore stops with one
    line naming it (exit 2, no folder left), where it used to train without them."""
    base = ["--data", str(FORWARD), "--steps", "2", "--threads", "1"]
    cases = [(simple_trainer, ["--preset", "default"], "--preset"),
             (simple_trainer, ["--max-gaussians", "300"], "--max-gaussians"),
             (simple_trainer, ["--pixels-per-gaussian", "50", "--chunk-size", "2"], "--pixels-per-gaussian --chunk-size"),
             (simple_trainer_mvgs, ["--chunk-size", "2"], "--chunk-size"),
             (simple_trainer, ["--world-size-rule", "distance", "--opacity-reset-scope", "inside"],
              "--world-size-rule --opacity-reset-scope")]
    for k, (module, flags, named) in enumerate(cases):
        cfg = common.parse_config(base + ["--out", str(tmp_path / f"r{k}"), *flags])
        with pytest.raises(SystemExit) as err:
            common.run(module.Runner, cfg)
        lines = capsys.readouterr().err.strip().splitlines()
        assert err.value.code == 2 and len(lines) == 1 and f"error: {named}: not read by this loop" in lines[0], lines
    assert list(tmp_path.iterdir()) == []
    # the flags each loop reads still run: the chunked loop with its chunk size, the MVGS loop with
    # a budget, the single-view loop with neither
    for module, flags in [(simple_trainer_chunked, ["--chunk-size", "2", "--preset", "multiview"]),
                          (simple_trainer_mvgs, ["--max-gaussians", "300"]), (simple_trainer, [])]:
        cfg = common.parse_config(base[:-4] + ["--steps", "8", "--threads", "1", "--out", str(tmp_path / module.__name__),
                                               *flags])
        assert common.run(module.Runner, cfg)["steps"] == 8


def test_the_example_cli_takes_a_budget_from_the_data(tmp_path, forward):
    """--pixels-per-gaussian P: the strategy resolves max_gaussians = training pixels / P for the
    loop's own training set, and the runner's model is cut to it before training."""
    from mvgs_plugin.camera import scaled_size

    pixels = sum(math.prod(scaled_size(c.width, c.height, 1)) for c in forward.train_cameras)
    p = pixels / 150.0  # a budget of 150 Gaussians, below the scene's points
    cfg = common.parse_config(["--data", str(FORWARD), "--steps", "20", "--out", str(tmp_path / "o"),
                               "--pixels-per-gaussian", repr(p), "--threads", "1"])
    runner = simple_trainer_mvgs.Runner(cfg)
    assert len(forward.points) > 150
    assert runner.cfg.strategy.config.max_gaussians == 150 and len(runner.splats["means"]) == 150
    with pytest.raises(SystemExit):
        common.parse_config(["--data", str(FORWARD), "--pixels-per-gaussian", "0"])


def test_the_example_cli_counts_the_budgets_views_and_rigs_as_the_package_cli_does(tmp_path, forward):
    """--budget-views V: V mean views' pixels / P, whatever the rig's count (0: every view, even
    for compact, whose preset counts 48); --budget-rigs round: no budget on this forward-facing
    rig. Checked against the pixels counted here."""
    from mvgs_plugin.camera import scaled_size

    n = len(forward.train_cameras)
    pixels = sum(math.prod(scaled_size(c.width, c.height, 1)) for c in forward.train_cameras)
    p = pixels / 600.0  # every view: 600 Gaussians

    def budget(*flags):
        cfg = common.parse_config(["--data", str(FORWARD), "--steps", "20", "--out", str(tmp_path / "o"),
                                   "--pixels-per-gaussian", repr(p), "--threads", "1", *flags])
        return simple_trainer_mvgs.Runner(cfg).cfg.strategy.config.max_gaussians

    assert budget() == 600
    assert budget("--budget-views", "3") == round(600 * 3 / n)
    assert budget("--budget-views", "0", "--preset", "compact", "--budget-rigs", "all") == 600
    assert budget("--budget-rigs", "round") is None  # a forward-facing rig: not budgeted
    with pytest.raises(SystemExit):
        common.parse_config(["--data", str(FORWARD), "--budget-views", "-1"])
    cfg = common.parse_config(["--data", str(FORWARD), "--steps", "8", "--out", str(tmp_path / "s"), "--budget-views", "4"])
    assert common.unread_flags(simple_trainer.Runner(cfg), cfg) == ["--budget-views"]  # gsplat's own loop reads none


def test_the_budget_holds_in_the_example_loop_through_every_phase_and_resume(tmp_path, forward, monkeypatch):
    """MVGSConfig.max_gaussians through MVGSStrategy: the model is cut to the budget at
    check_sanity (before any render), every refine ends at or under the schedule's cap (so no
    render sees more), growth is ranked into the room left, and a resumed run is the same run."""
    steps, budget = 300, 150
    n_points = len(forward.points)
    assert n_points > budget
    mvgs = MVGSConfig.default(max_gaussians=budget, budget_swap=0.02)
    cfg = example_config(tmp_path / "a", steps, mvgs, save_steps=[120])
    torch.manual_seed(0)
    runner = simple_trainer_mvgs.Runner(cfg)
    assert len(runner.splats["means"]) == budget  # cut before training
    strategy = runner.cfg.strategy
    refines = []
    original = strategy._refine

    def spy(params, optimizers, state, plan, step):
        original(params, optimizers, state, plan, step)
        refines.append(dict(strategy.last_refine))

    strategy._refine = spy
    resets = []
    real_reset = gsplat_strategy.reset_opa
    monkeypatch.setattr(gsplat_strategy, "reset_opa", lambda **kw: (resets.append(1), real_reset(**kw)))
    runner.train()
    assert len(refines) >= 5 and any(r["after"] > r["before"] - 1 for r in refines)
    for r in refines:
        assert r["cap"] is not None and r["after"] <= r["cap"] <= budget
    assert any(r["dropped_by_max_gaussians"] > 0 for r in refines)  # the ranking bound
    assert any(r["swapped"] > 0 for r in refines)  # budget_swap 0.02: a full budget swapped
    assert resets  # opacities were reset
    resumed_cfg = example_config(tmp_path / "b", steps, mvgs, resume=tmp_path / "a" / "ckpt_120.pt")
    torch.manual_seed(123)
    resumed = simple_trainer_mvgs.Runner(resumed_cfg)
    resumed.train()
    for k in runner.splats.keys():
        assert torch.equal(resumed.splats[k], runner.splats[k]), k


def test_the_faint_cut_in_the_example_loop_through_every_phase_and_resume(tmp_path, forward):
    """MVGSConfig.prune_faint through MVGSStrategy (--prune-faint): the loop's renders report blend
    statistics (strategy.rasterize_kwargs), the strategy keeps collecting them after the refine
    window, and at one step, twice the training views after it closed, removes the rows that a
    ranking written here names (least weight per blended pixel first, among the rows seen, while
    the removed weight stays within S); a resumed run makes the same cut."""
    steps, share = 300, 0.05  # refines every 10 steps from 50 to 150, a reset at 100
    cfg = example_config(tmp_path / "a", steps, "default", save_steps=[120], prune_faint=share)
    torch.manual_seed(0)
    runner = simple_trainer_mvgs.Runner(cfg)
    strategy = runner.cfg.strategy
    assert strategy.rasterize_kwargs == {"blend_stats": True} and strategy.config.prune_faint == share
    cuts = []
    original = strategy._faint_cut

    def spy(params, optimizers, state, plan, step):
        w, p, seen = (state[k].clone() for k in ("mvgs_blend_weight", "mvgs_blend_pixels", "mvgs_blend_seen"))
        means = params["means"].detach().clone()
        original(params, optimizers, state, plan, step)
        cuts.append((plan.step, w, p, seen, means, params["means"].detach().clone()))

    strategy._faint_cut = spy
    runner.train()
    n_train = len(runner.trainset)
    assert [c[0] for c in cuts] == [150 + 2 * n_train - 1]  # one cut; the window's last collected step is 149
    _, w, p, seen, before, after = cuts[0]
    # the statistics are those of the views since the window's last refine (step 140 or later): a
    # pixel's weights add up to its alpha <= 1, so at most one view's pixels per step since then
    h, w_px = runner.trainset[0]["image"].shape[:2]
    assert 0 < float(w.double().sum()) <= (cuts[0][0] - 140) * h * w_px
    order = sorted((i for i in range(len(w)) if seen[i] > 0),
                   key=lambda i: (float(w[i]) / float(p[i]) if p[i] > 0 else 0.0, i))
    total, acc, removed = float(w.double().sum()), 0.0, set()
    for i in order:
        acc += float(w[i])
        if acc > share * total:
            break
        removed.add(i)
    assert 0 < len(removed) < len(before) // 2
    kept = [i for i in range(len(before)) if i not in removed]
    assert torch.equal(after, before[kept]) and strategy.faint_removed == len(removed)
    resumed_cfg = example_config(tmp_path / "b", steps, "default", resume=tmp_path / "a" / "ckpt_120.pt",
                                 prune_faint=share)
    torch.manual_seed(123)
    resumed = simple_trainer_mvgs.Runner(resumed_cfg)
    resumed.train()
    assert resumed.cfg.strategy.faint_removed == len(removed)
    for k in runner.splats.keys():
        assert torch.equal(resumed.splats[k], runner.splats[k]), k


def test_a_loop_that_does_not_ask_for_blend_statistics_is_told_at_its_first_step(tmp_path, monkeypatch):
    cfg = example_config(tmp_path / "a", 300, "default", prune_faint=0.01)
    runner = simple_trainer_mvgs.Runner(cfg)
    monkeypatch.setattr(MVGSStrategy, "rasterize_kwargs", property(lambda self: {}))  # a loop that passes nothing
    with pytest.raises(ValueError, match=r"step 0: config.prune_faint=0.01 needs the blend statistics of every render "
                                         r"call: pass \*\*strategy.rasterize_kwargs \(blend_stats=True\)"):
        runner.train()


def test_keep_scores_and_the_cut_at_check_sanity(forward):
    cfg, splats, optimizers = fresh_model(forward)
    n = len(splats["means"])
    # no view folded in yet: opacity x even_cut_order of the means about the rig's centre
    # (tests/test_initial_cut.py checks that order against grid blocks and group shares)
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.default(max_gaussians=n // 2), steps=12)
    assert strategy.scene_center is not None
    want = torch.sigmoid(splats["opacities"].detach()) * even_cut_order(splats["means"], strategy.scene_center).float()
    kept = set(torch.argsort(want, descending=True)[:n // 2].tolist())
    ref = {tuple(splats["means"][i].tolist()) for i in kept}
    strategy.check_sanity(splats, optimizers)
    assert {tuple(m) for m in splats["means"].detach().tolist()} == ref
    assert all(len(opt.param_groups[0]["params"][0]) == n // 2 for opt in optimizers.values())


def test_the_cut_at_check_sanity_resizes_the_kept_gaussians_with_the_trainers_own_factor(forward):
    """A cut before the first step re-sizes what it keeps to the spacing of the kept means,
    keeping the trainer's initial factor (init_scale): log-scales = log(init_scale x root mean
    squared distance to the 3 nearest kept means), by a dense pairwise reference."""
    torch.manual_seed(0)
    cfg = common.Config(sh_degree=1, init_scale=0.5)
    cfg.make_strategy()
    splats, optimizers = common.create_splats_with_optimizers(SceneParser(forward), cfg, forward.extent)
    n = len(splats["means"])
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.default(max_gaussians=n // 4), steps=12)
    strategy.check_sanity(splats, optimizers)
    p = splats["means"].detach().double()
    d2 = torch.cdist(p, p).square()
    d2.fill_diagonal_(math.inf)
    want = torch.log(0.5 * d2.topk(3, dim=1, largest=False).values.mean(dim=1).sqrt())
    assert len(p) == n // 4
    for col in range(3):
        assert torch.allclose(splats["scales"].detach()[:, col].double(), want, atol=1e-4)


def test_the_cut_at_check_sanity_keeps_the_initial_share(forward):
    """budget_initial_share 0.5: check_sanity cuts to floor(0.5 N), the same top keep scores, and
    the budget's growth schedule starts from that count (its first cap is not N)."""
    cfg, splats, optimizers = fresh_model(forward)
    n = len(splats["means"])
    budget = n // 2
    mvgs = MVGSConfig.default(max_gaussians=budget, budget_initial_share=0.5)
    strategy = MVGSStrategy(small_clock(), forward, mvgs, steps=12)
    want = torch.sigmoid(splats["opacities"].detach()) * even_cut_order(splats["means"], strategy.scene_center).float()
    kept = set(torch.argsort(want, descending=True)[:budget // 2].tolist())
    ref = {tuple(splats["means"][i].tolist()) for i in kept}
    strategy.check_sanity(splats, optimizers)
    assert {tuple(m) for m in splats["means"].detach().tolist()} == ref
    sched = strategy.schedule
    sched.next()
    assert sched.initial_count == budget // 2
    assert sched.budget_cap(sched.config.densify_from) == budget // 2
    assert sched.budget_cap(sched.config.densify_until) == budget


def test_the_first_cut_holds_with_plans_drawn_ahead_and_a_model_below_the_share(forward):
    """check_sanity after a DataLoader drew plans (none started) still cuts to the initial share
    and the schedule grows from the cut count; a model already below the share is not cut, and
    the schedule grows from the model's own count (not from the views' point count)."""
    cfg, splats, optimizers = fresh_model(forward)
    n = len(splats["means"])
    mvgs = MVGSConfig.default(max_gaussians=n // 2, budget_initial_share=0.5)
    strategy = MVGSStrategy(small_clock(), forward, mvgs, steps=12)
    ahead = iter(strategy.batch_sampler())
    next(ahead), next(ahead)  # two plans drawn by a prefetching loader, not started
    strategy.check_sanity(splats, optimizers)
    assert len(splats["means"]) == (n // 2) // 2
    sched = strategy.schedule
    assert sched.initial_count == (n // 2) // 2 and sched.budget_cap(sched.config.densify_from) == (n // 2) // 2
    cfg, splats, optimizers = fresh_model(forward)
    keep = {k: v.detach().clone() for k, v in splats.items()}
    mvgs = MVGSConfig.default(max_gaussians=4 * n, budget_initial_share=0.5)
    strategy = MVGSStrategy(small_clock(), forward, mvgs, steps=12)
    strategy.check_sanity(splats, optimizers)
    assert all(torch.equal(splats[k], v) for k, v in keep.items())
    strategy.schedule.next()
    assert strategy.schedule.initial_count == n
    assert strategy.schedule.budget_cap(strategy.schedule.config.densify_from) == n


def test_the_swap_removes_the_lowest_keep_scores_that_are_not_candidates(forward):
    """MVGSStrategy._swap_out on a hand-made window: candidates (mean grad2d > threshold) beyond
    the room make up to floor(share x cap) rows go, the lowest opacity x coverage among the
    others that the refine's prune does not remove anyway (sorted here by hand); the state shrinks
    with the model."""
    cfg, splats, optimizers = fresh_model(forward)
    n = len(splats["means"])
    g = torch.Generator().manual_seed(1)
    grad2d = torch.rand(n, generator=g)
    count = torch.ones(n)
    coverage = torch.rand(n, generator=g)
    state = {"grad2d": grad2d.clone(), "count": count.clone(), "radii": torch.zeros(n), "mvgs_coverage": coverage.clone()}
    threshold = float(torch.quantile(grad2d, 0.8))
    cand = grad2d > threshold
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.default(max_gaussians=n), steps=12)
    keep = torch.sigmoid(splats["opacities"].detach()) * coverage
    by_keep = sorted([i for i in range(n) if not cand[i]], key=lambda i: float(keep[i]))
    doomed = torch.zeros(n, dtype=torch.bool)
    doomed[by_keep[:5]] = True  # the five the swap would take first: the prune takes them
    others = by_keep[5:]
    for share, room in ((0.05, 0), (0.5, 3)):
        sp = {k: torch.nn.Parameter(v.detach().clone()) for k, v in splats.items()}
        opts = {k: torch.optim.Adam([sp[k]], lr=1e-3) for k in sp}
        st = {k: v.clone() for k, v in state.items()}
        want = min(int(cand.sum()) - room, math.floor(share * n))
        gone = set(others[:want])
        swapped, kept_mask = strategy._swap_out(sp, opts, st, cand, torch.ones(n, dtype=torch.long), doomed, room, n, share)
        assert swapped == want > 0
        kept = [i for i in range(n) if i not in gone]
        assert torch.equal(kept_mask, torch.tensor([i not in gone for i in range(n)]))
        assert torch.equal(sp["means"].detach(), splats["means"].detach()[kept])
        assert torch.equal(st["grad2d"], grad2d[kept]) and len(st["mvgs_coverage"]) == n - want
    swapped, kept_mask = strategy._swap_out(splats, optimizers, dict(state), cand, torch.ones(n, dtype=torch.long), doomed,
                                            int(cand.sum()), n, 0.5)
    assert swapped == 0 and bool(kept_mask.all())  # room enough


# budget_growth_order in the wrap, on the rows of the adapter's test (test_budget_growth_order.py):
# the farthest (8) sets far_distance, so the far line is at 6 and rows 4-7 are beyond it; every
# row is a growth candidate and the far rows pull hardest, as a textured background does.
from test_budget_growth_order import BETA, DISTANCES as ROW_DISTANCES, GRADS as ROW_GRADS, expected_clones  # noqa: E402


def rows_at_distances(center):
    n = len(ROW_DISTANCES)
    g = torch.Generator().manual_seed(0)
    direction = F.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    means = (center + torch.tensor(ROW_DISTANCES, dtype=torch.float64)[:, None] * direction).float()
    splats = torch.nn.ParameterDict({"means": means, "scales": torch.full((n, 3), -5.0), "quats": F.normalize(torch.randn(n, 4, generator=g), dim=1),
                                     "opacities": torch.zeros(n), "sh0": torch.zeros(n, 1, 3), "shN": torch.zeros(n, 3, 3)})
    optimizers = {k: torch.optim.Adam([splats[k]], lr=1e-3) for k in splats}
    return splats, optimizers


@pytest.mark.parametrize("order,room", [("auto", 2), ("auto", 4), ("auto", 5), ("inside-first", 7), ("score", 3), ("score", 5)])
def test_the_wraps_growth_order_fills_the_room_as_ranked_by_hand(tabletop, order, room):
    """MVGSStrategy(budget_growth_order=...) on a rig round the scene ("auto": inside-first):
    the candidates kept are the first `room` of the rows sorted here by (beyond 3/4 of the
    farthest initial distance, -gradient), or by -gradient alone with "score"; the far line is
    taken at check_sanity, from the model before any cut."""
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(max_gaussians=100), steps=12,
                            budget_growth_order=order)
    resolved = "inside-first" if order == "auto" else order
    assert strategy.budget_growth_order == resolved
    center = torch.as_tensor(tabletop.center, dtype=torch.float64)
    splats, optimizers = rows_at_distances(center)
    strategy.check_sanity(splats, optimizers)
    assert strategy.far_distance == pytest.approx(max(ROW_DISTANCES), rel=1e-6)
    state = {"grad2d": torch.tensor(ROW_GRADS), "count": torch.ones(len(ROW_GRADS))}
    assert strategy._rank_growth(state, BETA, room, splats["means"]) == len(ROW_GRADS) - room
    assert sorted(torch.nonzero(state["grad2d"]).squeeze(1).tolist()) == sorted(expected_clones(room, resolved))
    if resolved == "inside-first" and room <= 4:  # every far row outscores the inside ones, and none grew
        assert all(ROW_DISTANCES[i] < 6.0 for i in torch.nonzero(state["grad2d"]).squeeze(1).tolist())
    state = {"grad2d": torch.tensor(ROW_GRADS), "count": torch.ones(len(ROW_GRADS))}  # room for all: nothing falls
    assert strategy._rank_growth(state, BETA, len(ROW_GRADS), splats["means"]) == 0


def test_the_wraps_growth_order_follows_the_rig_and_the_checkpoint(forward, tabletop):
    """"auto" ranks by score on a forward-facing rig; a checkpoint keeps the order and far line
    it grew with, one saved before the order existed resumes by score, and an order given that
    differs from the checkpoint's is refused by name."""
    assert MVGSStrategy(small_clock(), forward, "default", steps=12).budget_growth_order == "score"
    with pytest.raises(ValueError, match="budget_growth_order must be one of"):
        MVGSStrategy(small_clock(), tabletop, "default", steps=12, budget_growth_order="far-first")
    a = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(max_gaussians=100), steps=12)
    splats, optimizers = rows_at_distances(torch.as_tensor(tabletop.center, dtype=torch.float64))
    a.check_sanity(splats, optimizers)
    saved = a.state_dict()
    assert saved["growth"] == {"order": "inside-first", "far_distance": a.far_distance}
    b = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(max_gaussians=100), steps=12)
    b.load_state_dict(saved)
    assert (b.budget_growth_order, b.far_distance) == ("inside-first", a.far_distance)
    old = {k: v for k, v in saved.items() if k != "growth"}
    b.load_state_dict(old)
    assert (b.budget_growth_order, b.far_distance) == ("score", None)
    c = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(max_gaussians=100), steps=12, budget_growth_order="score")
    with pytest.raises(ValueError, match="grew with budget_growth_order='inside-first'"):
        c.load_state_dict(saved)


def test_inside_first_holds_the_budget_through_a_tabletop_run_and_resumes_exactly(tmp_path, tabletop):
    """The MVGS loop on a rig round the scene under a budget: "auto" is inside-first; at every
    refine where candidates fell, no candidate beyond the far line grew while one inside fell
    (checked on the ranking's own inputs, by distance here), the count never exceeds the budget,
    and a run resumed from a checkpoint is the same run."""
    steps, budget = 240, 400
    mvgs = MVGSConfig.default(max_gaussians=budget)
    cfg = example_config(tmp_path / "a", steps, mvgs, data=TABLETOP, save_steps=[100])
    torch.manual_seed(0)
    runner = simple_trainer_mvgs.Runner(cfg)
    strategy = runner.cfg.strategy
    assert strategy.budget_growth_order == "inside-first" and strategy.far_distance is not None
    line = 0.75 * strategy.far_distance
    center = strategy.scene_center
    checked, refines = [], []
    rank, refine = strategy._rank_growth, strategy._refine

    def rank_spy(state, threshold, room, means=None, grow=None, cost=None):
        cand = state["grad2d"] / state["count"].clamp_min(1) > threshold if grow is None else grow.clone()
        dropped = rank(state, threshold, room, means, grow, cost)
        if dropped:
            far = torch.linalg.vector_norm(means.detach().double() - center, dim=1) >= line
            kept = state["grad2d"] > 0
            fell = cand & ~kept
            checked.append((bool((cand & far).any()), bool((cand & ~far).any())))
            assert not ((kept & cand & far).any() and (fell & ~far).any())
        return dropped

    def refine_spy(params, optimizers, state, plan, step):
        refine(params, optimizers, state, plan, step)
        refines.append(dict(strategy.last_refine))

    strategy._rank_growth, strategy._refine = rank_spy, refine_spy
    runner.train()
    assert checked and any(far and inside for far, inside in checked)  # both kinds competed for the room
    assert refines and all(r["after"] <= budget for r in refines)
    resumed_cfg = example_config(tmp_path / "b", steps, mvgs, data=TABLETOP, resume=tmp_path / "a" / "ckpt_100.pt")
    torch.manual_seed(123)
    resumed = simple_trainer_mvgs.Runner(resumed_cfg)
    resumed.train()
    for k in runner.splats.keys():
        assert torch.equal(resumed.splats[k], runner.splats[k]), k


def test_the_parser_reads_gsplats_data_factor_as_the_images_folder(tmp_path):
    """Parser(factor=2) reads a COLMAP scene's images_2/ (gsplat's convention): every K is the
    full-size model's with each row times its axis's size ratio (pycolmap's model, read here
    directly); a NeRF-style scene has no such folder and is refused naming it."""
    import numpy as np
    import pycolmap
    from PIL import Image

    from test_data_colmap import H, W, write_model

    info = write_model(tmp_path / "s")
    for f in (tmp_path / "s" / "images").rglob("*.png"):
        out = tmp_path / "s" / "images_2" / f.parent.name / f.name
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.open(f).resize((27, 20)).save(out)  # one factor, 40 x 30 / 1.48
    parser = common.Parser(tmp_path / "s", factor=2)
    rec = pycolmap.Reconstruction(str(info["model_dir"]))
    for i, cam in enumerate(parser.cameras):
        model = rec.cameras[rec.images[cam.uid].camera_id]
        full = model.calibration_matrix()
        want = np.diag([27 / W, 20 / H, 1.0]) @ full
        assert parser.imsize_dict[i] == (27, 20) and np.allclose(parser.Ks_dict[i], want, atol=1e-5)
    with pytest.raises(ValueError, match="images='images_2': a NeRF-style scene takes a downscaled copy of nerfstudio's images/"):
        common.Parser(ROOT / "examples" / "scenes" / "tabletop", factor=2)


def test_a_data_factor_without_its_folder_is_one_line_naming_the_flag(tmp_path):
    import subprocess

    r = subprocess.run([sys.executable, str(LOOP / "simple_trainer_mvgs.py"), "--data-factor", "2", "--steps", "10",
                        "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-800:]
    assert "simple_trainer_mvgs.py: error: --data-factor 2: images='images_2': a NeRF-style scene takes a downscaled copy" in r.stderr
    assert not (tmp_path / "o").exists()


def test_save_steps_beyond_the_run_are_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as err:
        common.parse_config(["--steps", "60", "--save-steps", "60", "100", "--out", str(tmp_path / "o")])
    assert err.value.code == 2
    assert "--save-steps 100: beyond the run's --steps 60" in capsys.readouterr().err
    assert common.parse_config(["--steps", "60", "--save-steps", "60", "--out", str(tmp_path / "o")]).save_steps == [60]


def _masked_forward(root: Path, occluded: bool) -> Path:
    """forward64 with masks hiding a 16 x 16 block of every training view, at a place drawn per
    view; with `occluded`, the block is painted magenta in the images."""
    import json as json_module

    import skimage.io

    shutil.copytree(FORWARD, root)
    meta = json_module.loads((root / "transforms_train.json").read_text())
    rng = np.random.default_rng(9)
    (root / "masks").mkdir()
    for k, frame in enumerate(meta["frames"]):
        file = root / (frame["file_path"] if frame["file_path"].endswith(".png") else frame["file_path"] + ".png")
        img = skimage.io.imread(file)
        y, x = rng.integers(0, img.shape[0] - 16), rng.integers(0, img.shape[1] - 16)
        m = np.full(img.shape[:2], 255, np.uint8)
        m[y:y + 16, x:x + 16] = 0
        skimage.io.imsave(root / f"masks/m{k:03d}.png", m, check_contrast=False)
        frame["mask_path"] = f"masks/m{k:03d}.png"
        if occluded:
            img[y:y + 16, x:x + 16, :3] = (255, 0, 255)
            skimage.io.imsave(file, img, check_contrast=False)
    (root / "transforms_train.json").write_text(json_module.dumps(meta))
    return root


def test_the_port_reads_masks_as_gsplat_does(tmp_path):
    """The CPU port on forward64 with masks (the default trains this rig at full resolution), 300
    steps through densification and an opacity reset: the training views occluded where the masks
    hide them end on the same model as the clean views with the same masks; a Dataset item carries
    the mask as gsplat's do."""
    runs = {}
    for name, occluded in (("clean", False), ("occluded", True)):
        data = _masked_forward(tmp_path / name, occluded)
        cfg = common.Config(data_dir=data, result_dir=tmp_path / f"out_{name}", mvgs_preset="default", sh_degree=1)
        cfg.adjust_steps(300)
        cfg.make_strategy(Spy)
        torch.manual_seed(0)
        runner = simple_trainer_mvgs.Runner(cfg)
        item = runner.trainset[0]
        assert item["mask"].dtype == torch.bool and item["mask"].shape == item["image"].shape[:2]
        assert 0 < int((~item["mask"]).sum()) == 16 * 16
        runner.train()
        assert len(runner.cfg.strategy.strategy.log["grow"]) >= 5
        runs[name] = runner.splats
    for k in runs["clean"].keys():
        assert torch.equal(runs["clean"][k], runs["occluded"][k]), k


def test_at_level_makes_a_masked_views_levels_as_the_package_does(tmp_path):
    """With masks, the loader's batches at every pyramid level match the package's own plans: the
    image the weighted mean of the kept pixels (no colour from a hidden one), the mask the
    package's weights above 1/2."""
    data_dir = _masked_forward(tmp_path / "s", occluded=True)
    scene = load_scene(data_dir)
    parser = common.Parser(data_dir)
    trainset = common.Dataset(parser, "train")
    config = MVGSConfig.multiview(chunk_size=3)
    strategy = MVGSStrategy(DefaultStrategy(), trainset, config, steps=40)
    reference = ViewSchedule(scene, config.for_scene(scene).with_total_steps(40))
    loader = torch.utils.data.DataLoader(trainset, batch_sampler=strategy.batch_sampler())
    factors = set()
    for step, data in zip(range(12), loader):
        out = strategy.at_level_dict(data)
        plan = reference.next()
        factors.add(plan.factor)
        torch.testing.assert_close(out["image"] / 255.0, torch.stack(plan.images), atol=2e-5, rtol=0)
        assert torch.equal(out["mask"], torch.stack(plan.masks)[..., 0] > 0.5)
        strategy.plan, strategy._reported = None, 0  # (no training here)
    assert len(factors) >= 3 and any(f > 1 for f in factors)


def test_a_batched_dataloader_and_a_threshold_the_config_clock_drops_are_said(forward):
    """gsplat's --batch_size B (Adam tuned for B views a step) cannot silently become one view a
    step: refused naming B. clock='config' keeps the config's threshold: a strategy whose
    grow_grad2d differs (absgrad's 8e-4) is told so, with the value it would have had."""
    s = DefaultStrategy(absgrad=True, grow_grad2d=8e-4)
    with pytest.warns(UserWarning, match=r"clock='config' uses the config's densification threshold \(0.0002\), not the "
                                         r"strategy's grow_grad2d=0.0008 \(absgrad statistics are larger\)"):
        MVGSStrategy(s, forward, "baseline", steps=1000, clock="config")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        MVGSStrategy(DefaultStrategy(), forward, "baseline", steps=1000, clock="config")  # the same β: nothing said
    w = MVGSStrategy(DefaultStrategy(refine_start_iter=10, refine_stop_iter=60, refine_every=10, reset_every=30),
                     forward, "baseline", steps=100)
    data = list(range(len(forward.train_cameras)))
    with pytest.raises(ValueError, match=r"the DataLoader batches 4 views a step, .*batch_size=1"):
        w.loader(torch.utils.data.DataLoader(data, batch_size=4))
    first = next(iter(w.loader(torch.utils.data.DataLoader(data, batch_size=1)).dataloader))  # one batch
    assert len(first) == 1  # the schedule's one view a step (the baseline)


# ---- a refine under the cap, as gsplat's own refine decides it ---------------------------------------
def refine_on(splats, optimizers, strategy, make_state, prune_large=False):
    """Draw steps until one densifies with size pruning on or off as `prune_large` asks, build
    its window with make_state(n, threshold) and run the strategy's refine on it. Returns (the
    context's cap, threshold, prune_large, the state before the refine)."""
    n = len(splats["means"])
    means = splats["means"].detach()
    while True:
        plan = strategy.schedule.next()
        if plan.densify:
            ctx = strategy.schedule.densify_context(plan, None, n, torch.stack([means.amin(0), means.amax(0)]).double())
            if ctx.prune_large == prune_large:
                break
    state = make_state(n, float(ctx.grad_threshold))
    before = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in state.items()}
    strategy._refine(splats, optimizers, state, plan, 0)
    assert strategy.last_refine["cap"] == ctx.max_primitives and strategy.last_refine["threshold"] == float(ctx.grad_threshold)
    return ctx.max_primitives, float(ctx.grad_threshold), ctx.prune_large, before


@pytest.mark.parametrize("scale2d,size_pruning", [(False, False), (True, False), (True, True)])
def test_a_capped_refine_grows_the_best_candidates_into_the_room_its_prune_leaves(forward, scale2d, size_pruning):
    """A refine under a binding cap, on a hand-made window: rows the strategy's prune removes
    (opacity under prune_opa; with screen-size refinement, a screen radius above prune_scale2d,
    which their copies inherit) are not grown from and leave their room; the room goes to the
    candidates (mean grad2d above the threshold, or a screen radius above grow_scale2d) with the
    largest mean gradient; a candidate that falls is not split by its screen radius either, so
    nothing is shed after the fact. The expected rows are worked out here with plain tensors from
    gsplat's rules."""
    cfg, splats, optimizers = fresh_model(forward)
    n0 = len(splats["means"])
    inner = DefaultStrategy(refine_start_iter=1, refine_every=2, reset_every=4, refine_stop_iter=100,
                            refine_scale2d_stop_iter=10**6 if scale2d else 0)
    # size_pruning: a budget that keeps gsplat's size rules (off by default under a budget), at a
    # refine after the first reset, where they apply
    strategy = MVGSStrategy(inner, forward, MVGSConfig.default(max_gaussians=n0 + 60, budget_size_pruning=size_pruning),
                            steps=12)
    state0 = strategy.initialize_state(scene_scale=forward.extent)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        splats["opacities"][torch.randperm(n0, generator=g)[:40]] = -10.0  # under prune_opa
        # half small enough to be duplicated, half split, none too large in the world (nor its children)
        size = torch.where(torch.rand(n0, generator=g) < 0.5, 0.005, 0.03) * forward.extent
        splats["scales"].copy_(torch.log(size)[:, None].expand(-1, 3))
    orig = {k: v.detach().clone() for k, v in splats.items()}

    def make_state(n, threshold):
        grad2d = threshold * 2.0 * torch.rand(n, generator=g)  # about half above the threshold
        radii = 0.2 * torch.rand(n, generator=g)  # screen radius / max(W, H): some above 0.05 and 0.15
        return {**state0, "grad2d": grad2d, "count": torch.ones(n), "radii": radii}

    cap, threshold, prune_large, st = refine_on(splats, optimizers, strategy, make_state, prune_large=size_pruning)
    n = n0  # the rows before the refine
    mean = st["grad2d"] / st["count"]
    grow = mean > threshold
    if scale2d:
        grow = grow | (st["radii"] > inner.grow_scale2d)
    scales = torch.exp(orig["scales"]).max(-1).values
    assert not bool((scales > inner.prune_scale3d * forward.extent).any())  # no row too large in the world
    doomed = torch.sigmoid(orig["opacities"]) < inner.prune_opa
    if scale2d and prune_large:
        doomed = doomed | (st["radii"] > inner.prune_scale2d)
    cand = grow & ~doomed
    large = scales > inner.grow_scale3d * forward.extent
    # a row adds one (duplicated, or split in two in its place); a small row with a large gradient
    # whose screen radius is also above grow_scale2d is both duplicated and split: it adds two
    adds = [1 + int(scale2d and bool(mean[i] > threshold) and not bool(large[i]) and bool(st["radii"][i] > inner.grow_scale2d))
            for i in range(n)]
    room = cap - (n - int(doomed.sum()))
    assert 0 < room < sum(adds[i] for i in range(n) if cand[i]) and int(doomed.sum()) >= 40  # the cap binds; the prune frees room
    grown, used = torch.zeros(n, dtype=torch.bool), 0
    for i in sorted(torch.nonzero(cand).flatten().tolist(), key=lambda i: -float(mean[i])):
        if used + adds[i] > room:
            break
        grown[i], used = True, used + adds[i]
    split_parents = grown & (large | (st["radii"] > inner.grow_scale2d if scale2d else torch.zeros(n, dtype=torch.bool)))
    survivors = ~doomed & ~split_parents  # a split removes its parent
    assert len(splats["means"]) == n - int(doomed.sum()) + used and 0 <= room - used < max(adds)
    assert strategy.last_refine["shed_to_cap"] == 0
    assert strategy.last_refine["dropped_by_max_gaussians"] == int(cand.sum()) - int(grown.sum())
    k = int(survivors.sum())
    assert torch.equal(splats["means"].detach()[:k], orig["means"][survivors])  # the originals, in order
    copies = grown & ~large & (mean > threshold)  # duplicated: their copies follow the originals
    assert torch.equal(splats["means"].detach()[k:k + int(copies.sum())], orig["means"][copies])


def test_box_clones_rank_by_the_windows_gradient_and_skip_what_the_prune_removes(forward):
    """Under a cap the candidates that fell have their grad2d zeroed before the boxes' clones are
    chosen: the clones are ranked by the window's gradient as it was (passed in), and a row the
    refine's prune removes is not copied (its copy would go with it)."""
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(DefaultStrategy(), forward, "multiview", steps=50)
    state = strategy.initialize_state()
    n = len(splats["means"])
    g = torch.Generator().manual_seed(4)
    window = torch.rand(n, generator=g)
    state["grad2d"], state["count"] = torch.where(torch.rand(n, generator=g) < 0.5, 0.0, window), torch.ones(n)
    doomed = torch.rand(n, generator=g) < 0.2
    means = splats["means"].detach().clone()
    lo, hi = means.min(0).values, means.max(0).values
    boxes = torch.stack([torch.stack([lo - 1, (lo + hi) / 2]), torch.stack([(lo + hi) / 2, hi + 1])]).double()
    inside = [i for i in range(n) if any(all(boxes[b, 0, k] < means[i, k] < boxes[b, 1, k] for k in range(3)) for b in range(2))]
    allowed = [i for i in inside if not doomed[i]]
    cap = len(allowed) // 3
    best = sorted(sorted(allowed, key=lambda i: -float(window[i]))[:cap])
    added = strategy._clone_in_boxes(splats, optimizers, state, boxes, cap, window, doomed)
    assert added == cap > 0 and torch.equal(splats["means"].detach()[n:], means[best])
    assert not set(best) & set(torch.nonzero(doomed).flatten().tolist())


def test_a_second_check_sanity_keeps_the_far_line_of_the_model_before_the_cut(tabletop):
    """The far line of budget_growth_order is the initial model's farthest mean, taken before the
    budget's first cut; a trainer that calls check_sanity again before the first step does not
    move it to the cut model's."""
    cfg, splats, optimizers = fresh_model(tabletop)
    n = len(splats["means"])
    center = torch.as_tensor(tabletop.center, dtype=torch.float64)
    far = float(torch.linalg.vector_norm(splats["means"].detach().double() - center, dim=1).max())
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(max_gaussians=n // 4), steps=12)
    strategy.check_sanity(splats, optimizers)
    assert len(splats["means"]) == n // 4
    strategy.check_sanity(splats, optimizers)
    assert len(splats["means"]) == n // 4 and strategy.far_distance == pytest.approx(far, rel=1e-9)
    assert float(torch.linalg.vector_norm(splats["means"].detach().double() - center, dim=1).max()) < far  # the cut moved it


def test_a_resumed_strategy_sizes_its_chunks_by_the_checkpoints_model(forward):
    """The schedule sizes a step's chunks (chunk_size None: a memory bound) by the model's count; a
    strategy resumed from a checkpoint takes the checkpoint's model size, not that of the fresh
    model its check_sanity saw before the checkpoint replaced it."""
    _, _, saved, _, _ = train_small(forward, "after", save_at=12)
    n = len(saved["splats"]["means"])
    cfg, splats, optimizers = fresh_model(forward)
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.multiview(chunk_size=3), steps=24)
    strategy.check_sanity(splats, optimizers)
    assert strategy.schedule.primitive_count == len(splats["means"]) != n
    strategy.load_state_dict(saved["mvgs"])
    assert strategy.schedule.primitive_count == n


def test_a_model_above_the_budget_after_the_first_step_is_refused_by_check_sanity(forward):
    """Before the first step check_sanity cuts to the budget; after it, the rows' statistics are in
    a state check_sanity is not given, so a model above max_gaussians is a ValueError naming both
    counts, and the model is left as it was."""
    cfg, splats, optimizers = fresh_model(forward)
    n = len(splats["means"])
    strategy = MVGSStrategy(small_clock(), forward, MVGSConfig.multiview(chunk_size=3, max_gaussians=n - 100), steps=24)
    state = strategy.initialize_state(scene_scale=forward.extent)
    strategy.check_sanity(splats, optimizers)
    assert len(splats["means"]) == n - 100
    step_once(strategy, splats, optimizers, state, next(iter(strategy.batches(chunked=True))))
    bigger, opts = fresh_model(forward)[1:]
    with pytest.raises(ValueError, match=rf"holds {n} Gaussians, above max_gaussians={n - 100}"):
        strategy.check_sanity(bigger, opts)
    assert len(bigger["means"]) == n
    strategy.check_sanity(splats, optimizers)  # the run's own model, within the budget: nothing to say


# ---- the far background's rules in the wrap (world_size_rule, opacity_reset_scope) --------------
# Rows of rows_at_distances (distances 0.5 ... 8 from the scene centre) with linear scales chosen
# here; with scene_scale 1 and prune_scale3d 0.1 the extent rule's limit is 0.1 everywhere and the
# distance rule's 0.1 x max(1, d): 0.1, 0.1, 0.3, 0.55, 0.65, 0.7, 0.75, 0.8.
ROW_SIZES = [0.05, 0.2, 0.25, 0.5, 0.7, 0.6, 0.9, 0.7]


@pytest.mark.parametrize("rule", ["extent", "distance"])
def test_the_wraps_size_rule_prunes_the_rows_a_limit_worked_by_hand_prunes(tabletop, rule):
    """At a refine with size pruning, MVGSStrategy(world_size_rule=...) removes exactly the rows
    whose largest scale is above the limit computed here by hand (no row grows: no gradient),
    keeps the others in order, counts the rows only the extent rule would have removed, and the
    budget's _fate marks the same rows as doomed."""
    center = torch.as_tensor(tabletop.center, dtype=torch.float64)
    splats, optimizers = rows_at_distances(center)
    with torch.no_grad():
        splats["scales"].copy_(torch.log(torch.tensor(ROW_SIZES))[:, None].expand(-1, 3))
        splats["scales"][:, 1:] -= 1.0  # anisotropic: the largest axis decides
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(), steps=12, world_size_rule=rule)
    assert (strategy.world_size_rule, strategy.opacity_reset_scope) == (rule, "all")
    state0 = strategy.initialize_state(scene_scale=1.0)
    limit = [0.1 * (max(1.0, d) if rule == "distance" else 1.0) for d in ROW_DISTANCES]
    too_big = [size > lim for size, lim in zip(ROW_SIZES, limit)]
    extent_too_big = [size > 0.1 for size in ROW_SIZES]
    n = len(ROW_SIZES)
    zero = {**state0, "grad2d": torch.zeros(n), "count": torch.ones(n)}
    grow, cost, doomed = strategy._fate(splats, dict(zero), 1e-3, prune_large=True, scale2d=False)
    assert doomed.tolist() == too_big and not bool(grow.any())
    orig = splats["means"].detach().clone()
    refine_on(splats, optimizers, strategy, lambda n, t: dict(zero), prune_large=True)
    kept = [i for i in range(n) if not too_big[i]]
    assert torch.equal(splats["means"].detach(), orig[kept])
    by_hand = sum(e and not t for e, t in zip(extent_too_big, too_big))
    assert strategy.last_refine["kept_by_distance"] == strategy.kept_by_distance == by_hand
    assert by_hand == (4 if rule == "distance" else 0)
    for name, opt in optimizers.items():  # the optimizers hold the pruned parameters
        assert opt.param_groups[0]["params"][0] is splats[name] and len(splats[name]) == len(kept)
    with pytest.raises(ValueError, match="world_size_rule must be one of 'extent', 'distance', got 'far'"):
        MVGSStrategy(small_clock(), tabletop, "default", steps=12, world_size_rule="far")


@pytest.mark.parametrize("scope", ["all", "inside"])
def test_a_reset_inside_spares_exactly_the_rows_beyond_the_far_line(tabletop, scope):
    """A reset of MVGSStrategy(opacity_reset_scope="inside"): every opacity capped at 2 x prune_opa
    but the rows at 3/4 of the initial model's farthest distance or beyond (rows 4-7 of
    rows_at_distances: 6.5 ... 8 against a line at 6), which keep theirs to the bit; the opacities'
    Adam moments zeroed for every row, as gsplat's reset_opa; "all" caps every row."""
    center = torch.as_tensor(tabletop.center, dtype=torch.float64)
    splats, optimizers = rows_at_distances(center)
    strategy = MVGSStrategy(small_clock(), tabletop, MVGSConfig.default(), steps=12, opacity_reset_scope=scope)
    strategy.check_sanity(splats, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    with torch.no_grad():
        splats["opacities"].copy_(torch.logit(torch.linspace(0.3, 0.95, len(ROW_DISTANCES))))
    splats["opacities"].grad = torch.linspace(-1, 1, len(ROW_DISTANCES))
    optimizers["opacities"].step()  # moments to zero
    optimizers["opacities"].zero_grad(set_to_none=True)
    before = splats["opacities"].detach().clone()
    plan = strategy.schedule.next()
    strategy._apply({"plan": plan, "densify": False, "reset": True, "step": 0, "params": splats,
                     "optimizers": optimizers, "state": state})
    ceiling = 2 * strategy.strategy.prune_opa
    spared = [scope == "inside" and d >= 0.75 * max(ROW_DISTANCES) for d in ROW_DISTANCES]
    assert sum(spared) == (4 if scope == "inside" else 0) and strategy.spared_by_reset == sum(spared)
    after = splats["opacities"].detach()
    for i, keep in enumerate(spared):
        if keep:
            assert after[i] == before[i]
        else:
            assert float(torch.sigmoid(after[i])) == pytest.approx(ceiling, rel=1e-5)
    opt = optimizers["opacities"]
    assert opt.param_groups[0]["params"][0] is splats["opacities"]
    moments = opt.state[splats["opacities"]]
    assert not bool(moments["exp_avg"].any()) and not bool(moments["exp_avg_sq"].any())


def test_the_loops_far_background_flags_reach_the_model_and_the_strategy(tmp_path, forward, tabletop):
    """--background-points N adds load_scene's shell to the port's Parser (and so to the initial
    splats) on a rig round the scene and nothing on a forward-facing one; --world-size-rule and
    --opacity-reset-scope reach MVGSStrategy; a checkpoint made with other rules is refused."""
    shell = load_scene(TABLETOP, background_points=2000)
    argv = ["--data", str(TABLETOP), "--steps", "300", "--threads", "1", "--background-points", "2000",
            "--world-size-rule", "distance", "--opacity-reset-scope", "inside", "--out", str(tmp_path / "a")]
    cfg = common.parse_config(argv)
    assert (cfg.background_points, cfg.mvgs_rules) == (2000, {"world_size_rule": "distance", "opacity_reset_scope": "inside",
                                                              "prune_faint": None})
    faint = common.parse_config(argv[:-1] + [str(tmp_path / "f"), "--prune-faint", "0.01"])
    assert faint.mvgs_rules["prune_faint"] == 0.01  # and MVGSStrategy's config takes it (below: the default, 0)
    runner = simple_trainer_mvgs.Runner(cfg)
    assert len(shell.points.xyz) > len(tabletop.points.xyz)
    assert torch.equal(runner.splats["means"].detach(), shell.points.xyz.float())
    s = runner.cfg.strategy
    assert (s.world_size_rule, s.opacity_reset_scope) == ("distance", "inside")
    assert s.config.prune_faint == 0.0 and s.rasterize_kwargs == {}
    faint.make_strategy(DefaultStrategy)
    assert MVGSStrategy(faint.strategy, tabletop, "default", steps=300, **faint.mvgs_rules).config.prune_faint == 0.01
    assert s.far_distance == pytest.approx(float((shell.points.xyz.double() - torch.as_tensor(tabletop.center)).norm(dim=1).max()))
    assert s.far_distance > 1.5 * float((tabletop.points.xyz.double() - torch.as_tensor(tabletop.center)).norm(dim=1).max())
    plain = simple_trainer.Runner(common.parse_config(argv[:6] + ["--background-points", "2000", "--out", str(tmp_path / "b")]))
    assert len(plain.splats["means"]) == len(shell.points.xyz)  # the single-view loop reads the shell too
    fwd = simple_trainer_mvgs.Runner(common.parse_config(["--data", str(FORWARD), "--steps", "300", "--background-points",
                                                          "2000", "--out", str(tmp_path / "c")]))
    assert len(fwd.splats["means"]) == len(forward.points.xyz)  # no shell on a forward-facing rig
    other = MVGSStrategy(small_clock(), tabletop, "default", steps=12)
    mine = MVGSStrategy(small_clock(), tabletop, "default", steps=12, world_size_rule="distance")
    with pytest.raises(ValueError, match="world_size_rule='extent' .this strategy: 'distance'."):
        mine.load_state_dict(other.state_dict())


def test_the_loop_with_the_far_background_rules_trains_through_every_phase_and_resumes(tmp_path, tabletop):
    """simple_trainer_mvgs.py on the bundled 360-degree rig with the shell and both rules, 300
    steps: densification (every 10 steps from 50 to 150), a size prune by distance that keeps
    shell rows the extent rule would have removed, an opacity reset at 100 that spares the far
    background, the pyramid's hand-off, a checkpoint at 120 and a resume to the same tensors."""
    rules = dict(background_points=2000, world_size_rule="distance", opacity_reset_scope="inside")
    cfg = example_config(tmp_path / "a", 300, "default", data=TABLETOP, save_steps=[120], **rules)
    torch.manual_seed(0)
    runner = simple_trainer_mvgs.Runner(cfg)
    runner.train()
    strategy = runner.cfg.strategy
    assert len(strategy.strategy.log["grow"]) >= 5 and len(strategy.config.stages) > 1
    assert strategy.kept_by_distance > 0 and strategy.spared_by_reset > 0
    far = beyond_far_line(runner.splats["means"].detach(), strategy.scene_center, strategy.far_distance)
    assert int(far.sum()) > 0  # the far background is still there at the end
    resumed_cfg = example_config(tmp_path / "b", 300, "default", data=TABLETOP, resume=tmp_path / "a" / "ckpt_120.pt",
                                 **rules)
    torch.manual_seed(123)
    resumed = simple_trainer_mvgs.Runner(resumed_cfg)
    resumed.train()
    assert resumed.cfg.strategy.kept_by_distance == strategy.kept_by_distance
    assert resumed.cfg.strategy.spared_by_reset == strategy.spared_by_reset
    for k in runner.splats.keys():
        assert torch.equal(resumed.splats[k], runner.splats[k]), k


def test_the_benchmark_table_budgets_a_share_of_the_gsplat_loops_baseline(tmp_path, forward):
    """bench_gsplat_loop.py --gsplat-budget F: the port's baseline (its --grow-grad2d 2e-4 x 800 / W)
    and default without a budget, then each with F x the baseline's count, every run with the
    far-background rules (--package-rules); each row is its run's metrics.json."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_gsplat_loop

    text = bench_gsplat_loop.main(["--gsplat-budget", "0.25", "--steps", "80", "--presets", "default", "--data",
                                   str(FORWARD), "--out", str(tmp_path), "--parallel", "2", "--package-rules"])
    free = json.loads((tmp_path / "gsplat_baseline" / "metrics.json").read_text())
    n = round(0.25 * free["num_gaussians"])
    width = forward.train_cameras[0].width
    rows = [line.split("|")[1:-1] for line in text.splitlines() if line.startswith(("| baseline", "| default"))]
    assert [r[0].strip() for r in rows] == ["baseline", "baseline", "default", "default"]
    for kind, r in zip(["", "_budget"] * 2, rows):
        m = json.loads((tmp_path / f"gsplat_{r[0].strip()}{kind}" / "metrics.json").read_text())
        assert m["preset"] == r[0].strip() and m["max_gaussians"] == (n if kind else None)
        assert r[1].strip() == (str(n) if kind else "-")
        assert float(r[2]) == pytest.approx(m["psnr"], abs=0.006)
        assert float(r[3]) == pytest.approx(m["psnr"] - free["psnr"], abs=0.011)
        assert int(r[4]) == m["num_gaussians"] and int(r[5]) == m["most_held"]
        assert (m["background_points"], m["world_size_rule"], m["opacity_reset_scope"]) == (2000, "distance", "inside")
        assert m["grow_grad2d"] == pytest.approx(2e-4 * 800 / width if m["preset"] == "baseline" else 2e-4, rel=1e-5)
        if kind:
            assert m["most_held"] <= n < free["num_gaussians"]
