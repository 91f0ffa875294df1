"""GS4DAdapter (4DGS: canonical Gaussians + HexPlane deformation) and the time-stratified sampler.

Expected values come from independent computations: central finite differences, the 3DGS
adapter's render of the same Gaussians, renders of single views, closed forms of the regularisers
on hand-built planes, hand-placed Gaussians and boxes. Nothing is recorded from a previous run.
"""

from __future__ import annotations

import collections
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.adapters.gs4d import PLANES, GS4DAdapter, GS4DConfig, HexPlaneField
from mvgs_plugin import MVGS, MVGSConfig, Stage
from mvgs_plugin.camera import Camera
from mvgs_plugin.protocol import DensifyContext
from mvgs_plugin.sampler import ViewSampler
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import check_adapter, look_at, synthetic_scene

TINY = dict(resolution=(6, 5, 4, 5), multires=(1, 2), features=3, width=8)


def tiny_config(**kw) -> GS4DConfig:
    base = dict(canonical=GS3DConfig(sh_degree=1), coarse_steps=10, fine_steps=100, **TINY)
    return GS4DConfig(**{**base, **kw})


def gaussians(n=40, seed=0, dtype=torch.float32) -> GS3DAdapter:
    """n random Gaussians about the origin (inside the synthetic scene's view)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 1.2
    return GS3DAdapter.from_tensors(
        means.to(dtype), rgb=torch.rand(n, 3, generator=g), scales=0.05 + 0.1 * torch.rand(n, 3, generator=g),
        opacities=0.2 + 0.6 * torch.rand(n, generator=g), quats=torch.randn(n, 4, generator=g),
        scene_extent=2.0, config=GS3DConfig(sh_degree=1), dtype=dtype)


def randomize_field(field: HexPlaneField, seed=1, scale=1.0) -> None:
    """Non-trivial planes and weights (a fresh field is zero or independent of t): planes
    uniform in [0.5, 1.5] (products of six stay O(1)), weights and biases in [-scale, scale]."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in field.named_parameters():
            u = torch.rand(p.shape, generator=g, dtype=torch.float64).to(p)
            p.copy_(0.5 + u if name.startswith("planes") else (2 * u - 1) * scale)


def fine(adapter: GS4DAdapter) -> GS4DAdapter:
    adapter.set_step(adapter.gs4d_config.coarse_steps + 1)
    return adapter


def cam_at(uid, t, eye=(3.0, 0.4, 0.8), size=20):
    K = [[1.2 * size, 0, size / 2], [0, 1.2 * size, size / 2], [0, 0, 1]]
    return Camera(uid, f"c{uid}", K, look_at(eye), size, size, t)


# ---- conformance -------------------------------------------------------------------------------
def central_difference(loss, flat, i: int, eps: float) -> float:
    """(loss(x + eps e_i) - loss(x - eps e_i)) / 2 eps, with entry i of `flat` (a view into a
    parameter) perturbed in place and restored."""
    old = float(flat[i])
    with torch.no_grad():
        flat[i] = old + eps
        up = float(loss())
        flat[i] = old - eps
        down = float(loss())
        flat[i] = old
    return (up - down) / (2 * eps)


def test_passes_the_conformance_suite_with_time():
    scene = synthetic_scene(time=True)
    done = check_adapter(lambda s: GS4DAdapter.from_scene(s, tiny_config()), scene)
    assert all(v == "ok" for v in done.values())


# ---- gradients by finite differences -------------------------------------------------------------
def test_field_gradients_match_finite_differences():
    torch.manual_seed(0)
    field = HexPlaneField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.2, 0.8]]), **{**TINY, "zero_init_heads": False},
                          generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    randomize_field(field)
    xyz = (torch.rand(7, 3, dtype=torch.float64) - 0.5) * 1.6
    xyz.requires_grad_(True)
    t = 0.37
    w = [torch.randn(7, k, dtype=torch.float64) for k in (3, 3, 4)]

    def loss():
        return sum((o * wi).sum() for o, wi in zip(field(xyz, t), w))

    loss().backward()
    params = dict(field.named_parameters())
    params["xyz"] = xyz
    eps = 1e-6
    g = torch.Generator().manual_seed(3)
    checked = 0
    for name, p in params.items():
        flat, grad = p.data.view(-1), p.grad.view(-1)
        # entries with a gradient (a plane has many cells no point touches), plus one random one
        idx = set(torch.nonzero(grad).view(-1)[:2].tolist()) | {int(torch.randint(flat.numel(), (1,), generator=g))}
        for i in idx:
            fd = central_difference(loss, flat, i, eps)
            assert abs(fd - float(grad[i])) <= 1e-6 + 1e-5 * abs(fd), f"{name}[{i}]: autograd {float(grad[i])}, FD {fd}"
            checked += 1
    assert checked >= len(params) * 2


def test_render_gradients_through_the_deformation_match_finite_differences():
    a = fine(GS4DAdapter.from_canonical(gaussians(12, dtype=torch.float64), tiny_config(zero_init_heads=False)))
    randomize_field(a.field, scale=0.3)
    cam = cam_at(0, 0.6, size=16)
    target = torch.rand(16, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))

    def loss():
        return ((a.render([cam], torch.zeros(1, 3)).images[0] - target) ** 2).sum()

    loss().backward()
    # per group the entry with the largest gradient (a plane has many cells no point touches)
    checks = [a.field.heads["means"][3].bias, a.field.heads["scales"][3].weight, a.field.heads["quats"][1].weight,
              a.field.trunk.weight, a.field.planes[2], a.field.planes[9], a.params["means"], a.params["scales"]]
    for p in checks:
        i = int(p.grad.view(-1).abs().argmax())
        grad = float(p.grad.view(-1)[i])
        flat = p.data.view(-1)
        fd = central_difference(loss, flat, i, 1e-6)
        assert abs(fd) > 1e-8, "pick entries the loss depends on"
        assert abs(fd - grad) <= 1e-5 * max(1.0, abs(fd)), f"autograd {grad} vs FD {fd}"


# ---- zero field == the 3DGS adapter ----------------------------------------------------------------
def test_fresh_field_renders_exactly_as_the_3dgs_adapter_at_any_time():
    base = gaussians(30)
    a = fine(GS4DAdapter.from_canonical(base, tiny_config()))
    base.set_step(a._step)
    for t in (0.0, 0.3, 1.0):
        cams = [cam_at(0, t), cam_at(1, t, eye=(0.5, 3.0, 1.0))]
        assert torch.equal(a.render(cams, torch.ones(2, 3)).images, base.render(cams, torch.ones(2, 3)).images)


def test_field_that_vanishes_at_one_time_renders_as_3dgs_there_only():
    """Random planes and heads, zero biases, and every time plane zero on the grid row of
    t0 = 0.5: all features vanish at t0, so does the offset; elsewhere it does not."""
    base = gaussians(30)
    a = fine(GS4DAdapter.from_canonical(base, tiny_config(zero_init_heads=False)))
    randomize_field(a.field, scale=0.5)
    with torch.no_grad():
        for lin in [a.field.trunk] + [h[i] for h in a.field.heads.values() for i in (1, 3)]:
            lin.bias.zero_()
        for k in range(len(a.field.multires)):
            for p, (_, b) in enumerate(PLANES):
                if b == 3:
                    plane = a.field.planes[6 * k + p]
                    assert plane.shape[-2] == 5  # t = 0.5 -> 2t - 1 = 0 -> row 2 of 5
                    plane[..., 2, :] = 0.0
    base.set_step(a._step)
    at = lambda t: [cam_at(0, t), cam_at(1, t, eye=(0.5, 3.0, 1.0))]  # noqa: E731
    assert torch.equal(a.render(at(0.5), torch.ones(2, 3)).images, base.render(at(0.5), torch.ones(2, 3)).images)
    assert not torch.allclose(a.render(at(0.9), torch.ones(2, 3)).images, base.render(at(0.9), torch.ones(2, 3)).images)


def test_coarse_stage_ignores_the_field():
    base = gaussians(20)
    a = GS4DAdapter.from_canonical(base, tiny_config(zero_init_heads=False))
    randomize_field(a.field)
    a.set_step(a.gs4d_config.coarse_steps)
    base.set_step(a.gs4d_config.coarse_steps)
    cams = [cam_at(0, 0.2)]
    out = a.render(cams, torch.zeros(1, 3))
    assert torch.equal(out.images, base.render(cams, torch.zeros(1, 3)).images)
    out.images.sum().backward()
    assert all(p.grad is None for p in a.field.parameters())
    assert a.regularization(a.gs4d_config.coarse_steps) is None
    assert a.regularization(a.gs4d_config.coarse_steps + 1) is not None


# ---- per-view times, statistics -----------------------------------------------------------------
def test_each_view_of_a_chunk_renders_at_its_own_time_and_counts_once():
    a = fine(GS4DAdapter.from_canonical(gaussians(30), tiny_config(zero_init_heads=False)))
    randomize_field(a.field, scale=0.3)
    cams = [cam_at(0, 0.1), cam_at(1, 0.8, eye=(0.5, 3.0, 1.0)), cam_at(2, 0.1, eye=(-3.0, 0.2, 0.5))]
    joint = a.render(cams, torch.rand(3, 3, generator=torch.Generator().manual_seed(0)))
    bgs = torch.rand(3, 3, generator=torch.Generator().manual_seed(0))
    singles = [a.render([c], bgs[i:i + 1]) for i, c in enumerate(cams)]
    assert torch.allclose(joint.images, torch.cat([s.images for s in singles]), atol=1e-6)
    assert not torch.allclose(singles[0].images, a.render([cam_at(0, 0.8)], bgs[:1]).images)
    # statistics: the chunk equals the three views accumulated one by one
    joint.images.sum().backward()
    a.accumulate_stats(joint)
    stats_joint = (a.grad_accum.clone(), a.denom.clone(), a.max_radii2D.clone())
    a.zero_grad()
    a._reset_stats()
    for s in singles:
        s.images.sum().backward()
        a.accumulate_stats(s)
    for x, y in zip(stats_joint, (a.grad_accum, a.denom, a.max_radii2D)):
        assert torch.allclose(x, y, rtol=1e-5, atol=1e-9)
    assert a.denom.max() <= 3 and a.denom.sum() > 0


def test_bad_cameras_are_rejected_in_the_fine_stage():
    a = fine(GS4DAdapter.from_canonical(gaussians(5), tiny_config()))
    with pytest.raises(ValueError, match="has no time"):
        a.render([cam_at(0, None)], torch.zeros(1, 3))
    with pytest.raises(ValueError, match="one size"):
        a.render([cam_at(0, 0.1), cam_at(1, 0.2, size=10)], torch.zeros(2, 3))


# ---- schedules and regularisers ------------------------------------------------------------------
def test_learning_rates_of_the_field_decay_over_the_fine_stage():
    a = GS4DAdapter.from_canonical(gaussians(5), tiny_config(coarse_steps=10, fine_steps=100))
    e = a.scene_extent
    for step, frac in ((0, 0.0), (10, 0.0), (60, 0.5), (110, 1.0), (500, 1.0)):
        a.set_step(step)
        lr = a.learning_rates()
        # 4DGaussians' D-NeRF configs: 1.6e-3 -> 1.6e-5 and 1.6e-4 -> 1.6e-6, log-linear
        assert math.isclose(lr["planes"], e * 1.6e-3 * 0.01 ** frac, rel_tol=1e-9)
        assert math.isclose(lr["mlp"], e * 1.6e-4 * 0.01 ** frac, rel_tol=1e-9)
        assert a.deformation_active == (step > 10)


def test_regularisers_on_hand_built_planes():
    field = HexPlaneField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (4, 4, 4, 6), (1,), 2, 4, generator=torch.Generator())
    with torch.no_grad():
        for p, (a, b) in enumerate(PLANES):
            g = field.planes[p]
            rows = torch.arange(g.shape[-2], dtype=g.dtype)[:, None].expand(g.shape[-2:])
            cols = torch.arange(g.shape[-1], dtype=g.dtype)[None, :].expand(g.shape[-2:])
            if b == 3:  # time planes: 1 + 0.1 t^2 along time (rows), constant along space
                g.copy_((1 + 0.1 * rows ** 2).expand_as(g))
            else:  # space planes: 0.2 row + 0.3 col
                g.copy_((0.2 * rows + 0.3 * cols).expand_as(g))
    with torch.no_grad():
        r = field.regularizers()
    # TV: first differences 0.2 (rows) and 0.3 (cols) everywhere, 3 space planes
    assert math.isclose(float(r["tv"]), 3 * (0.2 ** 2 + 0.3 ** 2), rel_tol=1e-5)
    # time smoothness: second difference of 0.1 t^2 is 0.2, 3 time planes
    assert math.isclose(float(r["time_smoothness"]), 3 * 0.2 ** 2, rel_tol=1e-5)
    # l1: mean of 0.1 t^2 over t = 0..5 is 0.1 * 55 / 6
    assert math.isclose(float(r["l1_time"]), 3 * 0.1 * 55 / 6, rel_tol=1e-5)
    a = GS4DAdapter.from_canonical(gaussians(5), tiny_config(plane_tv_weight=2.0, time_smoothness_weight=3.0,
                                                             l1_time_planes_weight=5.0))
    with torch.no_grad():
        parts = a.field.regularizers()
    want = 2.0 * parts["tv"] + 3.0 * parts["time_smoothness"] + 5.0 * parts["l1_time"]
    assert torch.allclose(a.regularization(11), want)
    # a fresh field: time planes are 1 (no smoothness, no L1), space planes random (TV > 0)
    assert float(parts["time_smoothness"]) == 0.0 and float(parts["l1_time"]) == 0.0 and float(parts["tv"]) > 0


# ---- densification -------------------------------------------------------------------------------
def _with_offset(adapter: GS4DAdapter, offset) -> GS4DAdapter:
    """A field whose position offset is the constant `offset` (head weights 0, bias = offset)."""
    with torch.no_grad():
        adapter.field.heads["means"][3].bias.copy_(torch.tensor(offset))
    return adapter


def test_cross_ray_boxes_test_the_positions_at_the_views_times():
    means = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.5, 0.0]])
    base = GS3DAdapter.from_tensors(means, rgb=torch.rand(3, 3), scales=torch.full((3, 3), 0.001),
                                    opacities=torch.full((3,), 0.5), scene_extent=1.0, config=GS3DConfig(sh_degree=0))
    box = torch.tensor([[[0.4, -0.1, -0.1], [0.6, 0.1, 0.1]]], dtype=torch.float64)  # holds x = 0.5 only
    ctx = DensifyContext(step=1, grad_threshold=math.inf, scene_extent=1.0, boxes=box,
                         cameras=(cam_at(0, 0.2), cam_at(1, 0.7)))
    cfg = tiny_config(canonical=GS3DConfig(sh_degree=0), prune_min_count=0)
    # coarse stage: canonical positions, none inside
    a = _with_offset(GS4DAdapter.from_canonical(base, cfg), [0.5, 0.0, 0.0])
    assert a.densify(ctx).from_boxes == 0
    # fine stage: the first Gaussian moves to x = 0.5 at every time -> inside; the others are not
    a = fine(_with_offset(GS4DAdapter.from_canonical(base, cfg), [0.5, 0.0, 0.0]))
    rep = a.densify(ctx)
    assert rep.from_boxes == 1 and a.num_primitives() == 4
    assert torch.equal(a.params["means"][3], means[0])  # the clone is canonical, moves alike
    # no view times in the context: the canonical rule
    a = fine(_with_offset(GS4DAdapter.from_canonical(base, cfg), [0.5, 0.0, 0.0]))
    assert a.densify(DensifyContext(1, math.inf, 1.0, boxes=box)).from_boxes == 0


def test_original_caps_on_growth_and_pruning():
    base = gaussians(20)
    scene = synthetic_scene(time=True)

    def run(cfg):
        a = fine(GS4DAdapter.from_canonical(base, cfg))
        with torch.no_grad():
            a.params["opacities"][:5] = -10.0  # 5 transparent Gaussians
        for c in scene.train_cameras[:3]:
            out = a.render([c], torch.zeros(1, 3))
            out.images.sum().backward()
            a.accumulate_stats(out)
        with torch.no_grad():
            return a.densify(DensifyContext(step=20, grad_threshold=0.0, scene_extent=2.0))

    grown = run(tiny_config(growth_cap=None, prune_min_count=10_000))
    assert grown.after > grown.before and grown.pruned == 0  # below prune_min_count: no pruning
    capped = run(tiny_config(growth_cap=20, prune_min_count=10_000))
    assert capped.after == capped.before == 20 and capped.extra["growth_capped"]
    pruned = run(tiny_config(growth_cap=20, prune_min_count=0))
    assert pruned.pruned == 5 and pruned.after == 15


# ---- persistence and export ----------------------------------------------------------------------
def test_state_dict_round_trip_in_the_fine_stage(tmp_path):
    scene = synthetic_scene(time=True)
    a = fine(GS4DAdapter.from_scene(scene, tiny_config(zero_init_heads=False)))
    for _ in range(2):
        (a.render(scene.train_cameras[:2], torch.zeros(2, 3)).images.sum() + a.regularization(a._step)).backward()
        a.optimizer_step()
        a.zero_grad()
    state = a.state_dict()
    torch.save(state, tmp_path / "s.pt")
    b = GS4DAdapter.from_scene(synthetic_scene(time=True, seed=4), tiny_config())
    b.load_state_dict(torch.load(tmp_path / "s.pt", weights_only=False))
    assert b.deformation_active and b.learning_rates() == a.learning_rates()
    cams = scene.train_cameras[2:4]
    assert torch.equal(a.render(cams, torch.zeros(2, 3)).images, b.render(cams, torch.zeros(2, 3)).images)
    for m in (a, b):
        m.render(cams, torch.zeros(2, 3)).images.sum().backward()
        m.optimizer_step()
    for (k, p), q in zip(a.field.named_parameters(), b.field.parameters()):
        assert torch.equal(p, q), k
    with pytest.raises(ValueError, match="not 'mvgs-gs4d/1'"):
        b.load_state_dict({**state, "format": "mvgs-gs3d/1"})


def test_exports_canonical_baked_and_deformation(tmp_path):
    a = fine(GS4DAdapter.from_canonical(gaussians(25), tiny_config(zero_init_heads=False)))
    randomize_field(a.field, scale=0.2)
    cam = cam_at(0, 0.65)
    a.export_at_time(str(tmp_path / "t.ply"), 0.65)
    a.export(str(tmp_path / "t_cam.ply"), camera=cam)
    a.export(str(tmp_path / "canonical.ply"))
    a.save_deformation(str(tmp_path / "deformation.pt"))
    want = a.render([cam], torch.ones(1, 3)).images
    # the baked PLY, read by the 3DGS adapter, renders the scene at t = 0.65
    baked = GS3DAdapter.from_ply(tmp_path / "t.ply", scene_extent=2.0)
    baked.active_sh_degree = a.active_sh_degree
    assert torch.allclose(baked.render([cam], torch.ones(1, 3)).images, want, atol=1e-6)
    assert (tmp_path / "t.ply").read_bytes() == (tmp_path / "t_cam.ply").read_bytes()
    # canonical PLY + deformation file = the model: it renders each time as the trained one,
    # without being told the step the run ended at (a model built from files starts at step 0)
    b = GS4DAdapter.from_ply(tmp_path / "canonical.ply", scene_extent=2.0, config=a.gs4d_config)
    assert b.gs4d_config == a.gs4d_config and not b.deformation_active
    b.load_deformation(str(tmp_path / "deformation.pt"))
    assert b.deformation_active
    for t in (0.0, 0.65, 1.0):
        at = cam_at(0, t)
        assert torch.allclose(b.render([at], torch.ones(1, 3)).images, a.render([at], torch.ones(1, 3)).images,
                              atol=1e-6), t
    # a field saved in the coarse stage (not trained) leaves the Gaussians where they are
    coarse = GS4DAdapter.from_canonical(gaussians(25), tiny_config(zero_init_heads=False))
    randomize_field(coarse.field, scale=0.2)
    assert not coarse.deformation_active
    coarse.save_deformation(str(tmp_path / "coarse.pt"))
    c = GS4DAdapter.from_ply(tmp_path / "canonical.ply", scene_extent=2.0, config=a.gs4d_config)
    c.load_deformation(str(tmp_path / "coarse.pt"))
    assert not c.deformation_active
    static = GS3DAdapter.from_ply(tmp_path / "canonical.ply", scene_extent=2.0)
    static.active_sh_degree = c.active_sh_degree
    assert torch.allclose(c.render([cam], torch.ones(1, 3)).images, static.render([cam], torch.ones(1, 3)).images,
                          atol=1e-6)
    with pytest.raises(ValueError, match=r"t must be in \[0, 1\]"):
        a.export_at_time(str(tmp_path / "bad.ply"), 1.5)


def test_from_tensors_and_from_ply_take_a_gs4d_config(tmp_path):
    """The inherited constructors take the 4DGS config (they read the SH degree from its
    canonical part): the canonical Gaussians are the activated inputs, the field the config's."""
    g = torch.Generator().manual_seed(5)
    n = 12
    means = torch.rand(n, 3, generator=g) - 0.5
    rgb, scales = torch.rand(n, 3, generator=g), 0.05 + 0.1 * torch.rand(n, 3, generator=g)
    opac = 0.2 + 0.6 * torch.rand(n, generator=g)
    config = tiny_config(features=4)
    a = GS4DAdapter.from_tensors(means, rgb=rgb, scales=scales, opacities=opac, scene_extent=2.0, config=config)
    assert a.gs4d_config == config and a.field.trunk.in_features == 4 * len(config.multires)
    assert torch.allclose(a.params["means"], means) and torch.allclose(a.get_scales(), scales, rtol=1e-6)
    assert torch.allclose(a.get_opacities(), opac, atol=1e-6)
    assert a.params["shN"].shape == (n, 3, 3)  # degree 1, as config.canonical says: 3 higher bands
    assert torch.allclose(a.params["sh0"][:, 0] * 0.28209479177387814 + 0.5, rgb, atol=1e-6)
    a.export(str(tmp_path / "c.ply"))
    b = GS4DAdapter.from_ply(tmp_path / "c.ply", scene_extent=2.0, config=config)
    assert b.gs4d_config == config and all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    with pytest.raises(ValueError, match="config must be a GS4DConfig, got dict"):
        GS4DAdapter.from_tensors(means, rgb=rgb, scales=scales, opacities=opac, scene_extent=2.0, config={})


def test_bad_configuration_names_the_value():
    with pytest.raises(ValueError, match="resolution must be"):
        GS4DConfig(resolution=(8, 8, 8))
    with pytest.raises(ValueError, match="bounds must be"):
        GS4DConfig(bounds=((0, 0, 0), (1, -1, 1)))
    with pytest.raises(ValueError, match="fine_steps must be a positive int, got 0"):
        GS4DConfig(fine_steps=0)
    with pytest.raises(ValueError, match="span no volume"):
        GS4DAdapter.from_canonical(GS3DAdapter.from_tensors(torch.zeros(3, 3), rgb=torch.rand(3, 3),
                                                            scales=torch.ones(3, 3) * 0.1,
                                                            opacities=torch.full((3,), 0.5), scene_extent=1.0))


def test_bounds_come_from_the_initial_points_and_flat_clouds_get_a_box():
    flat = torch.tensor([[-2.0, -1.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    base = GS3DAdapter.from_tensors(flat, rgb=torch.rand(3, 3), scales=torch.ones(3, 3) * 0.1,
                                    opacities=torch.full((3,), 0.5), scene_extent=1.0)
    a = GS4DAdapter.from_canonical(base, tiny_config(canonical=GS3DConfig(sh_degree=0), min_bounds_fraction=0.1))
    lo, hi = a.field.bounds.tolist()
    assert lo == pytest.approx([-2.0, -1.0, -0.2]) and hi == pytest.approx([2.0, 1.0, 0.2])


def test_random_init_points_fill_the_box():
    scene = synthetic_scene(time=True)
    a = GS4DAdapter.from_scene(scene, tiny_config(init_random_points=50, init_box=((-1, -1, 0), (1, 1, 2))))
    extra = a.params["means"][len(scene.points):]
    assert extra.shape == (50, 3)
    assert bool(((extra >= torch.tensor([-1.0, -1, 0])) & (extra <= torch.tensor([1.0, 1, 2]))).all())


# ---- the time-stratified sampler -----------------------------------------------------------------
def test_stratified_sampler_takes_one_view_per_time_bin():
    times = [((7 * i) % 13) / 12 for i in range(13)]  # a shuffled set of times
    s = ViewSampler(13, seed=2, times=times, time_spread="stratified")
    by_time = sorted(range(13), key=lambda i: times[i])
    assert s.time_bins(4) == [by_time[0:3], by_time[3:6], by_time[6:9], by_time[9:13]]
    seen = collections.Counter()
    for _ in range(12):  # 12 steps: every bin of 3 (or 4) views runs through whole epochs
        picked = s.sample(4)
        assert [next(k for k, b in enumerate(s.time_bins(4)) if i in b) for i in picked] == [0, 1, 2, 3]
        seen.update(picked)
    assert all(seen[i] == 4 for b in s.time_bins(4)[:3] for i in b)  # bins of 3: each view 4 times
    assert all(seen[i] == 3 for i in s.time_bins(4)[3])  # the bin of 4: each view 3 times
    state = s.state_dict()
    rest = [s.sample(4) for _ in range(5)]
    r = ViewSampler(13, seed=9, times=times, time_spread="stratified")
    r.load_state_dict(state)
    assert [r.sample(4) for _ in range(5)] == rest
    with pytest.raises(ValueError, match="time_spread='stratified'"):
        ViewSampler(13, times=times).load_state_dict(state)


def test_stratified_sampler_errors_and_the_config_option():
    with pytest.raises(ValueError, match=r"view 1 has None"):
        ViewSampler(3, times=[0.0, None, 1.0], time_spread="stratified")
    with pytest.raises(ValueError, match="time_spread must be one of"):
        ViewSampler(3, time_spread="uniform")
    with pytest.raises(ValueError, match="time_spread must be one of"):
        MVGSConfig(time_spread="bins")
    scene = synthetic_scene(n_train=8, time=True)
    cfg = MVGSConfig(stages=(Stage(1, 4, 6),), time_spread="stratified", seed=1)
    times = sorted(c.time for c in scene.train_cameras)
    edges = [times[0], times[2], times[4], times[6]]  # bins of 2 by time
    for plan in ViewSchedule(scene, cfg):
        got = [c.time for c in plan.cameras]
        assert all(got[k] >= edges[k] for k in range(4)) and got == sorted(got)
    assert MVGSConfig.from_dict(cfg.to_dict()) == cfg


# ---- training ------------------------------------------------------------------------------------
def test_mvgs_trains_across_the_stage_switch_with_crd_and_mvad():
    scene = synthetic_scene(n_train=8, size=16, n_points=150, time=True)
    cfg = MVGSConfig.multiview(stages=(Stage(2, 3, 6), Stage(1, 3, 10)), time_spread="stratified",
                             densify_from=3, densify_until=16, densify_every=4, opacity_reset_every=100)
    a = GS4DAdapter.from_scene(scene, tiny_config(coarse_steps=6, fine_steps=10, prune_min_count=0))
    infos = []
    MVGS(a, scene, cfg).fit(progress=False, callback=infos.append)
    assert a.deformation_active and len(infos) == 16
    assert all(math.isfinite(i.loss) for i in infos)
    fine_densify = [i for i in infos if i.step > 6 and i.densify is not None]
    assert fine_densify and all(i.threshold is not None for i in fine_densify)  # MVAD ran
    assert any(h[3].weight.abs().sum() > 0 for h in a.field.heads.values())  # the field trained


def _write_dnerf(root: Path, scene) -> None:
    """A scene in the D-NeRF layout: PNGs and transforms with OpenGL camera-to-world and times."""
    from mvgs_plugin.reference_renderer.demo import save_png

    for split, cams in (("train", scene.train_cameras), ("test", scene.test_cameras)):
        (root / split).mkdir(parents=True)
        frames = []
        for i, c in enumerate(cams):
            save_png(str(root / split / f"r_{i:03d}.png"), scene.image(c).numpy())
            c2w = c.camera_to_world.numpy() @ np.diag([1.0, -1.0, -1.0, 1.0])
            frames.append({"file_path": f"{split}/r_{i:03d}", "time": c.time, "transform_matrix": c2w.tolist()})
        fov = 2 * math.atan(0.5 * cams[0].width / cams[0].fx)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))


def test_train_4dgs_example_writes_metrics_renders_plys_and_field(tmp_path):
    spec = importlib.util.spec_from_file_location(
        "train_4dgs", Path(__file__).resolve().parents[1] / "examples" / "train_4dgs.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    data = tmp_path / "scene"
    _write_dnerf(data, synthetic_scene(n_train=6, n_test=2, size=16, time=True))
    out = tmp_path / "out"
    m = example.main(["--data", str(data), "--preset", "default", "--steps", "6", "--views", "2",
                      "--out", str(out), "--no-progress", "--init-random", "30", "--export-times", "0.25"])
    saved = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "lpips", "train_seconds", "steps", "num_gaussians", "model_mb", "peak_memory_mb",
                "preset", "config"):
        assert key in saved, key
    assert saved == json.loads(json.dumps(m)) and saved["steps"] == 6
    assert saved["init"].endswith("; plus 30 --init-random points in the scene's own points' box widened to a cube")
    assert saved["config"]["time_spread"] == "stratified" and saved["model_config"]["coarse_steps"] == 1
    assert saved["config"]["prune_faint"] == 0.0  # 4DGS's recipe: the default preset's cut only when asked
    size = (out / "point_cloud.ply").stat().st_size + (out / "deformation.pt").stat().st_size
    assert math.isclose(saved["model_mb"], size / 2**20)
    assert (out / "point_cloud_t0.250.ply").exists() and len(list((out / "test").glob("*.png"))) == 2
    with pytest.raises(SystemExit):
        example.parse_args(["--data", str(data), "--coarse-fraction", "1.5"])


def test_initial_points_that_span_nothing_get_the_box_where_the_cameras_look():
    """One initial point (or one repeated), no shell: the deformation box used to be refused with a
    traceback asking for GS4DConfig.bounds, which no example exposes. It is now the box of the
    region random init uses (for this ring of cameras, the 3DGS cube: the cameras' centre +- the
    scene extent), with a warning; the adapter trains a step through the deformation."""
    from mvgs_plugin.data import PointCloud

    scene = synthetic_scene(time=True)
    scene.points = PointCloud(xyz=torch.tensor([[0.1, -0.2, 0.05]] * 3), rgb=torch.full((3, 3), 0.5))
    with pytest.warns(UserWarning, match=r"the 3 initial point\(s\) span no volume .* where the cameras look"):
        adapter = GS4DAdapter.from_scene(scene, tiny_config())
    c, e = scene.center.double(), float(scene.extent)
    box = adapter.field.bounds.double()
    # uniform samples of the cube c +- e: their box is within a few % of the cube's
    assert torch.allclose(box[0], c - e, atol=0.05 * e) and torch.allclose(box[1], c + e, atol=0.05 * e)
    adapter = fine(adapter)
    out = adapter.render([scene.train_cameras[0]], torch.zeros(1, 3))
    out.images.sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in adapter.field.parameters() if p.grad is not None)


def test_a_flat_initial_cloud_gets_a_box_as_deep_as_where_the_cameras_look():
    """Ground-only points (z = 0, the generated moving scene's point file): the box along z spans
    the region where the cameras look (the 3DGS cube for this ring: centre +- extent), not a slab
    5 % as thick as it is wide, in which whatever moves above the ground would read the planes at
    its top face; x and y keep the points' extent. Said with a warning naming the axis."""
    from mvgs_plugin.data import PointCloud

    scene = synthetic_scene(time=True)
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(200, 2, generator=g, dtype=torch.float64) * 2 - 1
    scene.points = PointCloud(xyz=torch.cat([xy, torch.zeros(200, 1, dtype=torch.float64)], 1).float(),
                              rgb=torch.full((200, 3), 0.5))
    with pytest.warns(UserWarning, match=r"the initial points are flat along z .* the deformation box spans the region"):
        adapter = GS4DAdapter.from_scene(scene, tiny_config())
    box = adapter.field.bounds.double()
    c, e = scene.center.double(), float(scene.extent)
    assert torch.allclose(box[:, :2], torch.stack([xy.min(0).values, xy.max(0).values]), atol=1e-6)
    assert float(box[0, 2]) <= float(c[2] - 0.9 * e) and float(box[1, 2]) >= float(c[2] + 0.9 * e)
    flat = GS4DAdapter.from_scene(scene, tiny_config(bounds=((-1, -1, -0.05), (1, 1, 0.05))))  # given: kept
    assert torch.allclose(flat.field.bounds.double(), torch.tensor([[-1, -1, -0.05], [1, 1, 0.05]], dtype=torch.float64))
