"""GS3DAdapter: initialisation, schedules, statistics, densification, persistence, training.

Expected values are computed here from the 3DGS rules (brute force, closed forms, hand-placed
Gaussians), never recorded from the adapter.
"""

from __future__ import annotations

import io
import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import SH_C0, GS3DAdapter, GS3DConfig, knn_mean_sq_dist
from mvgs_plugin.camera import Camera
from mvgs_plugin.data.scene import PointCloud, Scene
from mvgs_plugin.protocol import Adapter, DensifyContext
from mvgs_plugin.reference_renderer import rasterization

W, H = 40, 32
BETA = 2e-4


def camera(uid, x=0.0, width=W, height=H):
    """Looks down +z from (x, 0, 0); focal 40 px."""
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[0, 3] = -x
    K = [[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]]
    return Camera(uid=uid, name=f"c{uid}", K=K, world_to_camera=w2c, width=width, height=height)


def cube_scene(points=None, n_cams=3):
    cams = [camera(i, x=0.3 * i) for i in range(n_cams)]
    images = {c.uid: torch.zeros(H, W, 3) for c in cams}
    return Scene(cams, [], images, points=points)


def adapter(n, *, means=None, scale=0.005, opacity=0.5, config=None, extent=1.0, dtype=torch.float32):
    """n Gaussians; key i (sh0 red channel = i) identifies each one and its copies."""
    g = torch.Generator().manual_seed(n)
    if means is None:
        means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 3 + torch.rand(n, 1, generator=g)], 1)
    scales = torch.as_tensor(scale, dtype=torch.float32).expand(n, 3).clone() if not torch.is_tensor(scale) \
        or scale.ndim < 2 else scale
    sh = torch.zeros(n, 1, 3)
    sh[:, 0, 0] = torch.arange(n, dtype=torch.float32)
    sh[:, 0, 1:] = torch.rand(n, 2, generator=g)
    opac = torch.as_tensor(opacity, dtype=torch.float32).expand(n).clone()
    return GS3DAdapter.from_tensors(means.to(dtype), sh=sh, scales=scales, opacities=opac,
                                    quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
                                    scene_extent=extent, config=config, dtype=dtype)


def keys(a):
    return a.params["sh0"].detach()[:, 0, 0].round().long().tolist()


def fill_adam_state(a, seed=0):
    """One Adam step with random gradients and lr 0 (moments filled, parameters unchanged)."""
    g = torch.Generator().manual_seed(seed)
    saved = [grp["lr"] for grp in a.optimizer.param_groups]
    for grp in a.optimizer.param_groups:
        grp["lr"] = 0.0
    for p in a.params.values():
        p.grad = torch.randn(p.shape, generator=g, dtype=p.dtype)
    a.optimizer_step()
    a.zero_grad()
    for grp, lr in zip(a.optimizer.param_groups, saved):
        grp["lr"] = lr


def moments(a):
    """name -> (exp_avg, exp_avg_sq, step) of every group."""
    out = {}
    for name, p in a.params.items():
        st = a.optimizer.state[p]
        out[name] = (st["exp_avg"].clone(), st["exp_avg_sq"].clone(), float(st["step"]))
    return out


def set_stats(a, accum, denom, radii=None):
    a.grad_accum = torch.tensor(accum, dtype=torch.float32)
    a.denom = torch.tensor(denom, dtype=torch.float32)
    a.max_radii2D = torch.zeros(len(accum)) if radii is None else torch.tensor(radii, dtype=torch.float32)


def ctx(**kw):
    base = dict(step=600, grad_threshold=BETA, scene_extent=1.0)
    base.update(kw)
    return DensifyContext(**base)


# ---- construction ----------------------------------------------------------------------------

def test_protocol_and_groups():
    a = adapter(4)
    assert isinstance(a, Adapter)
    assert [g["name"] for g in a.optimizer.param_groups] == ["means", "sh0", "shN", "scales", "quats", "opacities"]
    assert all(g["eps"] == 1e-15 for g in a.optimizer.param_groups)
    assert a.params["shN"].shape == (4, 15, 3)
    assert a.num_primitives() == 4 and a.positions().shape == (4, 3)


def test_knn_init_matches_brute_force():
    g = torch.Generator().manual_seed(1)
    xyz = torch.randn(300, 3, generator=g) * torch.tensor([1.0, 0.3, 2.0]) + 50.0
    xyz[7] = xyz[3]  # a duplicate: its nearest distance is 0 -> the 1e-7 floor
    xyz[8] = xyz[3]
    xyz[9] = xyz[3]
    rgb = torch.rand(300, 3, generator=g)
    a = GS3DAdapter.from_scene(cube_scene(PointCloud(xyz, rgb)), GS3DConfig(knn_chunk=7))

    x = xyz.double()
    d2 = torch.cdist(x, x) ** 2
    d2.fill_diagonal_(float("inf"))
    mean3 = d2.sort(dim=1).values[:, :3].mean(1).clamp_min(1e-7)
    want = torch.log(torch.sqrt(mean3)).float()[:, None].expand(300, 3)
    torch.testing.assert_close(a.params["scales"].detach(), want, rtol=0, atol=2e-5)
    assert float(a.params["scales"].detach()[3, 0]) == pytest.approx(math.log(math.sqrt(1e-7)), abs=1e-5)
    torch.testing.assert_close(a.params["sh0"].detach()[:, 0], (rgb - 0.5) / SH_C0)
    assert a.params["shN"].abs().sum() == 0
    assert torch.equal(a.params["quats"].detach(), torch.tensor([1.0, 0, 0, 0]).expand(300, 4))
    torch.testing.assert_close(a.get_opacities().detach(), torch.full((300,), 0.1))
    assert a.scene_extent == pytest.approx(cube_scene().extent)


@pytest.mark.parametrize("chunk,window", [(32, 3), (256, 8)])
def test_knn_is_exact_on_clustered_points(chunk, window):
    """Tight clusters, a far outlier, duplicates, a line: the curve-ordered search must still
    find the true neighbours (compared with all pairwise distances)."""
    g = torch.Generator().manual_seed(2)
    x = torch.randn(800, 3, generator=g)
    x[:300] *= 1e-3  # a cluster inside the cloud
    x[300:450] = torch.linspace(-3, 3, 150)[:, None] * torch.tensor([1.0, 0.5, 0.0])  # a line
    x[700] = 100.0  # an outlier
    x[701:704] = x[10]  # duplicates
    want_d2 = torch.cdist(x.double(), x.double()) ** 2
    want_d2.fill_diagonal_(float("inf"))
    want = want_d2.sort(dim=1).values[:, :3].mean(1)
    got = knn_mean_sq_dist(x, k=3, chunk=chunk, window=window)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-15)
    assert float(got[701]) == 0.0  # three exact duplicates
    two = knn_mean_sq_dist(torch.tensor([[0.0, 0, 0], [3.0, 4.0, 0]]))
    assert two.tolist() == [25.0, 25.0]  # fewer than k others: the mean of those there are


def test_random_init_without_points():
    scene = cube_scene(None)
    # this rig's cameras all look one way: without a cube size the points go where they look
    # (tests/test_forward_init.py); random_init_half_size asks for the 3DGS cube
    ahead = GS3DAdapter.from_scene(scene, GS3DConfig(random_init=500))
    depth = torch.stack([c.project(ahead.positions().double())[1] for c in scene.train_cameras])
    assert ahead.num_primitives() == 500 and float(depth.max(0).values.min()) > 0  # in front of a camera
    a = GS3DAdapter.from_scene(scene, GS3DConfig(random_init=500, random_init_half_size=scene.extent))
    assert a.num_primitives() == 500
    off = (a.positions().double() - scene.center).abs()
    assert float(off.max()) <= scene.extent
    assert float(off.max()) > 0.9 * scene.extent  # fills the cube, not a corner of it
    rgb = a.params["sh0"].detach()[:, 0] * SH_C0 + 0.5
    assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1 and float(rgb.std()) > 0.2


def test_from_tensors_rejects_inactive_values():
    with pytest.raises(ValueError, match="opacities must be in"):
        GS3DAdapter.from_tensors(torch.zeros(2, 3), rgb=torch.zeros(2, 3), scales=torch.ones(2, 3),
                                 opacities=torch.tensor([0.5, 1.0]), scene_extent=1.0)
    with pytest.raises(ValueError, match="scales must be > 0"):
        GS3DAdapter.from_tensors(torch.zeros(2, 3), rgb=torch.zeros(2, 3), scales=-torch.ones(2, 3),
                                 opacities=torch.tensor([0.5, 0.5]), scene_extent=1.0)


# ---- schedules -------------------------------------------------------------------------------

def test_means_lr_is_log_linear():
    extent = 2.5
    a = adapter(3, extent=extent)
    want = {0: 1.6e-4 * extent, 15000: math.sqrt(1.6e-4 * 1.6e-6) * extent, 30000: 1.6e-6 * extent,
            45000: 1.6e-6 * extent, 7500: 1.6e-4 ** 0.75 * 1.6e-6 ** 0.25 * extent}
    for step, lr in want.items():
        a.set_step(step)
        assert a.learning_rates()["means"] == pytest.approx(lr, rel=1e-9), step
    assert a.learning_rates() | {"means": 0} == {"means": 0, "sh0": 2.5e-3, "shN": 2.5e-3 / 20,
                                                 "scales": 5e-3, "quats": 1e-3, "opacities": 0.05}


def test_sh_degree_schedule_reaches_the_rasterizer():
    seen = []

    def spy(*args, **kw):
        seen.append((kw["sh_degree"], kw["packed"], args[7], args[8]))
        return rasterization(*args, **kw)

    a = adapter(3, config=GS3DConfig(rasterize=spy))
    for step, degree in [(0, 0), (999, 0), (1000, 1), (2999, 2), (3000, 3), (12000, 3)]:
        a.set_step(step)
        assert a.active_sh_degree == degree
        a.render([camera(0)], torch.zeros(1, 3))
        assert seen[-1] == (degree, False, W, H)
    b = adapter(3, config=GS3DConfig(sh_degree=1))
    b.set_step(5000)
    assert b.active_sh_degree == 1


def test_render_checks_sizes_and_backgrounds():
    a = adapter(3)
    with pytest.raises(ValueError, match="one size"):
        a.render([camera(0), camera(1, width=W + 8)], torch.zeros(2, 3))
    with pytest.raises(ValueError, match="backgrounds must be"):
        a.render([camera(0)], torch.zeros(2, 3))
    out = a.render([camera(0), camera(1, x=0.2)], torch.ones(2, 3))
    assert out.images.shape == (2, H, W, 3) and out.alphas.shape == (2, H, W, 1)


# ---- statistics -------------------------------------------------------------------------------

def test_accumulate_stats_in_ndc_units():
    # Tiles are 16 px and a Gaussian counts as visible when its 3-sigma square touches a tile
    # of the 40x32 image (3 x 2 tiles). Camera 1 sits at x = 3. By geometry:
    # A (0,0,3): u = 20 in camera 0; u = -20 in camera 1 -> no tile.     visible in 0 only
    # B (0,0,-3): behind both.                                           never visible
    # C (3,0,3): u = 60 in camera 0 (first tile column past the grid);   visible in 1 only
    # D (1.5,0,3): u = 40 in camera 0 and u = 0 in camera 1, radius 4 px: visible in both
    means = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0], [3.0, 0.0, 3.0], [1.5, 0.0, 3.0]])
    a = adapter(4, means=means, scale=0.05)
    cams = [camera(0), camera(1, x=3.0)]
    visible = torch.tensor([[True, False, False, True], [False, False, True, True]])  # [C, N]
    weights = torch.tensor([[[3.0, -4.0], [1.0, 1.0], [5.0, 0.0], [0.5, 0.5]],
                            [[0.0, 2.0], [1.0, 1.0], [-1.0, 1.0], [2.0, -1.0]]])  # dL/dmeans2d [C,N,2]
    scale = torch.tensor([W / 2, H / 2])
    want = (weights * scale).norm(dim=-1) * visible  # [C, N]

    for chunk in range(2):  # two chunks accumulate
        out = a.render(cams, torch.zeros(2, 3))
        (out.aux["means2d"] * weights).sum().backward()
        a.accumulate_stats(out)
        a.zero_grad()
        assert torch.equal((out.aux["radii"] > 0).all(-1), visible)
    torch.testing.assert_close(a.grad_accum, 2 * want.sum(0))
    torch.testing.assert_close(a.denom, torch.tensor([2.0, 0.0, 2.0, 4.0]))
    radii = out.aux["radii"].max(-1).values.float()
    torch.testing.assert_close(a.max_radii2D, radii.max(0).values)
    assert float(a.max_radii2D[0]) > 0 and float(a.max_radii2D[1]) == 0
    torch.testing.assert_close(a.mean_grads(), torch.stack([want[0, 0], torch.tensor(0.0), want[1, 2],
                                                            want[:, 3].sum() / 2]))


def test_accumulate_stats_needs_backward():
    a = adapter(3)
    out = a.render([camera(0)], torch.zeros(1, 3))
    with pytest.raises(RuntimeError, match="backward"):
        a.accumulate_stats(out)


# ---- densification ----------------------------------------------------------------------------

SMALL, LARGE = 0.005, 0.05


def densify_fixture(config=None):
    """16 hand-built Gaussians (extent 1, percent_dense 0.01 -> small <= 0.01 < large)."""
    scales = torch.full((16,), SMALL)
    scales[[4, 5, 6, 15]] = LARGE
    scales[11] = 0.2  # > 0.1 * extent: oversized in the world
    opac = torch.full((16,), 0.5)
    opac[[10, 15]] = 0.001  # below min_opacity 0.005
    a = adapter(16, scale=scales[:, None].expand(16, 3).clone(), opacity=opac, config=config)
    accum = [5e-4] * 7 + [1e-4] * 3 + [0.0, 0.0, 0.0, 1.0, 4.5e-4, 5e-4]
    denom = [1.0] * 10 + [1.0, 1.0, 1.0, 0.0, 3.0, 1.0]
    radii = [5.0] * 16
    radii[12] = 30.0  # > 20 px on screen
    set_stats(a, accum, denom, radii)
    fill_adam_state(a)
    return a


def snapshot(a):
    """key -> list of (attributes, moments) rows."""
    rows = {}
    m = {name: (a.optimizer.state[p]["exp_avg"], a.optimizer.state[p]["exp_avg_sq"]) for name, p in a.params.items()}
    for i, k in enumerate(keys(a)):
        attrs = {name: p.detach()[i].clone() for name, p in a.params.items()}
        mom = {name: (m[name][0][i].clone(), m[name][1][i].clone()) for name in a.params}
        rows.setdefault(k, []).append((attrs, mom))
    return rows


def is_zero(mom):
    return all(float(x.abs().sum()) == 0 and float(y.abs().sum()) == 0 for x, y in mom.values())


def same(d1, d2):
    return all(torch.equal(d1[k], d2[k]) for k in d1)


def same_mom(m1, m2):
    return all(torch.equal(m1[k][0], m2[k][0]) and torch.equal(m1[k][1], m2[k][1]) for k in m1)


@pytest.mark.parametrize("prune_large,screen,expect_pruned", [
    (False, None, {10, 15}), (True, None, {10, 11, 15}), (True, 20.0, {10, 11, 12, 15})])
def test_densify_clone_split_prune(prune_large, screen, expect_pruned):
    a = densify_fixture(GS3DConfig(max_screen_size=screen))
    before = snapshot(a)
    steps = {name: float(a.optimizer.state[p]["step"]) for name, p in a.params.items()}
    rep = a.densify(ctx(prune_large=prune_large))
    after = snapshot(a)

    cloned, split = {0, 1, 2, 3}, {4, 5, 6, 15}
    assert (rep.cloned, rep.split, rep.from_boxes) == (4, 4, 0)
    # pruned: 10 (and 11, 12 per the rule), and the two children of 15 (they copy its opacity)
    assert rep.pruned == len(expect_pruned - {15}) + 2
    assert rep.after == 16 + 4 + 4 - len(expect_pruned - {15}) - 2 == a.num_primitives()
    assert set(after) == set(range(16)) - expect_pruned
    for k in after:
        if k in cloned:  # original (with its moments) + exact copy (zero moments)
            (attrs, mom), = before[k]
            assert len(after[k]) == 2 and all(same(r[0], attrs) for r in after[k])
            assert sum(same_mom(r[1], mom) for r in after[k]) == 1
            assert sum(is_zero(r[1]) for r in after[k]) == 1
        elif k in split:  # two children, the parent gone
            (attrs, _), = before[k]
            assert len(after[k]) == 2
            for child, mom in after[k]:
                assert is_zero(mom)
                torch.testing.assert_close(child["scales"], attrs["scales"] - math.log(1.6))
                for name in ("sh0", "shN", "quats", "opacities"):
                    assert torch.equal(child[name], attrs[name])
                offset = (child["means"] - attrs["means"]).norm()
                assert 0 < float(offset) < 6 * LARGE * math.sqrt(3)
            assert not torch.equal(after[k][0][0]["means"], after[k][1][0]["means"])
        else:  # untouched survivors keep attributes and moments
            assert len(after[k]) == 1
            assert same(after[k][0][0], before[k][0][0]) and same_mom(after[k][0][1], before[k][0][1])
    for name, p in a.params.items():  # Adam's step counter survives the surgery
        assert float(a.optimizer.state[p]["step"]) == steps[name]
        assert p.grad is None and p.shape[0] == rep.after
    assert a.grad_accum.abs().sum() == 0 and a.denom.abs().sum() == 0 and a.max_radii2D.abs().sum() == 0
    fill_adam_state(a, seed=1)  # the optimizer still works on the new shapes
    assert all(float(a.optimizer.state[p]["step"]) == 2 for p in a.params.values())


def test_threshold_is_inclusive_and_mean_is_per_visit():
    a = adapter(4)
    # means: exactly beta (cloned, >= as the original), just below, 0 for a never-seen one with
    # a stray sum, and beta * 3 / 4 although the sum alone is 3 beta
    set_stats(a, [BETA, 0.999 * BETA, 1.0, 3 * BETA], [1.0, 1.0, 0.0, 4.0])
    rep = a.densify(ctx())
    assert rep.cloned == 1 and sorted(keys(a)) == [0, 0, 1, 2, 3]


def test_split_samples_follow_the_rotated_scales():
    n = 400
    s = torch.tensor([0.3, 0.02, 0.05])
    q = torch.tensor([math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)])  # 45 deg about z
    a = GS3DAdapter.from_tensors(torch.zeros(n, 3), rgb=torch.rand(n, 3), scales=s.expand(n, 3),
                                 quats=q.expand(n, 4), opacities=torch.full((n,), 0.5), scene_extent=1.0)
    set_stats(a, [1.0] * n, [1.0] * n)
    rep = a.densify(ctx())
    assert rep.split == n and rep.after == 2 * n
    c, sn = math.cos(math.pi / 4), math.sin(math.pi / 4)
    R = torch.tensor([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    local = a.positions() @ R / s  # R^T d / s: standard normal if the offsets are R (s * n)
    assert local.mean(0).abs().max() < 0.15
    assert (local.std(0) - 1).abs().max() < 0.1
    torch.testing.assert_close(a.get_scales().detach(), (s / 1.6).expand(2 * n, 3))


def test_boxes_clone_strictly_inside_and_respect_cap():
    means = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0],
                          [0.0, 0.0, 0.99], [3.5, 3.5, 3.5], [3.5, 3.5, 4.0]])
    boxes = torch.tensor([[[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], [[3.0, 3.0, 3.0], [4.0, 4.0, 4.0]]],
                         dtype=torch.float64)
    inside = {0, 1, 4, 5}  # 2 sits on a face, 6 on a face of the second box, 3 outside
    # large ones too (no size test for boxes); every mean gradient below the threshold
    accum = [1e-5, 5e-5, 9e-5, 9e-5, 8e-5, 2e-5, 9e-5]

    a = adapter(7, means=means, scale=0.05)
    set_stats(a, accum, [1.0] * 7)
    rep = a.densify(ctx(boxes=boxes))
    assert (rep.from_boxes, rep.cloned, rep.split, rep.pruned) == (4, 0, 0, 0)
    got = keys(a)
    assert sorted(got) == sorted(list(range(7)) + list(inside))

    a = adapter(7, means=means, scale=0.05)
    set_stats(a, accum, [1.0] * 7)
    rep = a.densify(ctx(boxes=boxes, max_new_from_boxes=2))
    assert rep.from_boxes == 2 and rep.extra["dropped_by_box_cap"] == 2
    assert sorted(keys(a)) == sorted(list(range(7)) + [4, 1])  # the two largest gradients inside

    with pytest.raises(ValueError, match="min > max"):
        a.densify(ctx(boxes=boxes.flip(1)))


def test_max_gaussians_keeps_largest_gradients():
    scales = torch.full((10,), SMALL)
    scales[[2, 5, 8]] = LARGE
    a = adapter(10, scale=scales[:, None].expand(10, 3).clone(), config=GS3DConfig(max_gaussians=13))
    accum = [3e-4, 4e-4, 9e-4, 5e-4, 6e-4, 8e-4, 7e-4, 1e-4, 2e-3, 2.5e-4]
    set_stats(a, accum, [1.0] * 10)
    rep = a.densify(ctx())
    # candidates by gradient: 8 (split), 2 (split), 5 (split) fit; everything after is dropped
    assert (rep.split, rep.cloned, rep.after) == (3, 0, 13)
    assert rep.extra["dropped_by_max_gaussians"] == 6
    assert sorted(keys(a)) == sorted([0, 1, 3, 4, 6, 7, 9] + [2, 2, 5, 5, 8, 8])

    accum[5] = 1e-5  # now the third best is 6, a small one: cloned
    a = adapter(10, scale=scales[:, None].expand(10, 3).clone(), config=GS3DConfig(max_gaussians=13))
    set_stats(a, accum, [1.0] * 10)
    rep = a.densify(ctx())
    assert (rep.split, rep.cloned, rep.after) == (2, 1, 13)
    assert sorted(keys(a)) == sorted([0, 1, 3, 4, 5, 6, 6, 7, 9] + [2, 2, 8, 8])


def test_the_controllers_cap_is_the_same_ranking_and_the_lower_cap_wins():
    scales = torch.full((10,), SMALL)
    scales[[2, 5, 8]] = LARGE
    accum = [3e-4, 4e-4, 9e-4, 5e-4, 6e-4, 8e-4, 7e-4, 1e-4, 2e-3, 2.5e-4]
    for config, cap in ((GS3DConfig(), 13), (GS3DConfig(max_gaussians=13), 20), (GS3DConfig(max_gaussians=20), 13)):
        a = adapter(10, scale=scales[:, None].expand(10, 3).clone(), config=config)
        set_stats(a, accum, [1.0] * 10)
        rep = a.densify(ctx(max_primitives=cap))
        # as with max_gaussians=13 above: the splits of 8, 2 and 5 fit, the rest is dropped
        assert (rep.split, rep.cloned, rep.after) == (3, 0, 13)
        assert sorted(keys(a)) == sorted([0, 1, 3, 4, 6, 7, 9] + [2, 2, 5, 5, 8, 8])
    with pytest.raises(ValueError, match="max_primitives"):
        a.densify(ctx(max_primitives=-1))


def test_a_model_above_the_cap_sheds_its_lowest_keep_scores():
    """keep score = opacity x footprint summed over the window's views; the five largest stay,
    nothing grows, and rows the prune rules remove count towards the cut."""
    opac = torch.tensor([0.5, 0.9, 0.2, 0.7, 0.004, 0.6, 0.3, 0.8, 0.4, 0.55])
    a = adapter(10, opacity=opac)
    accum = [3e-4, 4e-4, 9e-4, 5e-4, 6e-4, 8e-4, 7e-4, 1e-4, 2e-3, 2.5e-4]
    set_stats(a, accum, [2.0] * 10)
    coverage = torch.tensor([0.1, 0.05, 0.9, 0.02, 5.0, 0.3, 0.2, 0.01, 0.15, 0.12])
    a.coverage_accum = coverage.clone()
    want = opac * coverage
    want[4] = -1  # pruned by opacity < 0.005 whatever its coverage
    rep = a.densify(ctx(max_primitives=5))
    assert rep.after == 5 and rep.cloned == rep.split == 0
    assert rep.extra["shed_to_cap"] == 4 and rep.pruned == 5
    assert sorted(keys(a)) == sorted(torch.argsort(want, descending=True)[:5].tolist())


def test_a_full_budget_swaps_its_lowest_keep_scores_for_the_best_candidates():
    """At its cap (room 0) with four clone candidates, swap_share S lets floor(S x cap) rows go:
    the lowest keep scores (opacity x coverage) among the six rows that are not candidates, hand-
    sorted here; that many of the best candidates (by gradient: the squared sums are 0, so the
    consistency is 1) are cloned; the count stays at the cap. S = 0 grows nothing."""
    opac = torch.tensor([0.5, 0.9, 0.2, 0.7, 0.3, 0.6, 0.3, 0.8, 0.4, 0.55])
    coverage = torch.tensor([0.1, 0.05, 0.9, 0.02, 0.4, 0.3, 0.2, 0.01, 0.15, 0.12])
    accum = [1e-4, 9e-4, 1e-4, 6e-4, 1e-4, 1e-4, 3e-4, 1e-4, 1e-4, 5e-4]  # candidates (>= 2e-4): 1, 3, 6, 9
    candidates = [1, 3, 9, 6]  # best first
    others = [i for i in range(10) if i not in candidates]
    by_keep = sorted(others, key=lambda i: float(opac[i] * coverage[i]))  # 7 (0.008), 0 (0.05), 8 (0.06), ...
    for share, swaps in ((0.0, 0), (0.3, 3), (0.9, 4)):
        a = adapter(10, opacity=opac)
        set_stats(a, accum, [1.0] * 10)
        a.coverage_accum = coverage.clone()
        rep = a.densify(ctx(max_primitives=10, swap_share=share))
        assert rep.after == 10 and rep.cloned == swaps and rep.split == 0
        assert rep.extra["swapped"] == swaps and rep.extra["shed_to_cap"] == 0 and rep.pruned == swaps
        assert rep.extra["dropped_by_max_gaussians"] == 4 - swaps
        want = [i for i in range(10) if i not in by_keep[:swaps]] + candidates[:swaps]
        assert sorted(keys(a)) == sorted(want)


def test_the_swap_counts_a_split_as_its_growth_and_never_takes_the_room_twice():
    """One split candidate (a large Gaussian: it grows by split_samples - 1 = 1) and room 1 left
    under the cap: its growth fits, so nothing is swapped whatever the share."""
    scales = torch.full((6,), SMALL)
    scales[2] = LARGE
    a = adapter(6, scale=scales[:, None].expand(6, 3).clone())
    set_stats(a, [1e-4, 1e-4, 9e-4, 1e-4, 1e-4, 1e-4], [1.0] * 6)
    a.coverage_accum = torch.full((6,), 0.5)
    rep = a.densify(ctx(max_primitives=7, swap_share=0.5))
    assert (rep.split, rep.after, rep.extra["swapped"]) == (1, 7, 0)


def test_consistency_and_scores_from_per_view_gradients():
    """consistency = (sum g)^2 / (n sum g^2) over a Gaussian's visits, computed here by hand from
    per-view gradient norms fed through accumulate_stats' statistics."""
    a = adapter(4)
    per_view = torch.tensor([[1e-3, 1e-3, 1e-3, 1e-3],   # the same in every view: 1
                             [4e-3, 0.0, 0.0, 0.0],      # one view of four: 1/4
                             [2e-3, 1e-3, 0.0, 0.0],     # (3e-3)^2 / (4 * 5e-6) = 0.45
                             [0.0, 0.0, 0.0, 0.0]])      # never pulled: 0
    a.grad_accum = per_view.sum(1)
    a.grad_sq_accum = per_view.square().sum(1)
    a.denom = torch.full((4,), 4.0)
    torch.testing.assert_close(a.consistency(), torch.tensor([1.0, 0.25, 0.45, 0.0]))
    mean = per_view.sum(1) / 4
    torch.testing.assert_close(a.densify_scores("gradient"), mean)
    torch.testing.assert_close(a.densify_scores("consistency"), mean * torch.tensor([1.0, 0.25, 0.45, 0.0]))
    with pytest.raises(ValueError, match="rank_by"):
        a.densify_scores("loss")


def test_consistency_ranks_growth_under_a_cap():
    """Two candidates with the same mean gradient, one from every view, one from a single view:
    under a cap of one new row the consistent one is cloned (by gradient alone: row order)."""
    for rank_by, winner in (("consistency", 1), ("gradient", 0)):
        a = adapter(2)
        a.grad_accum = torch.tensor([4e-3, 4e-3])
        a.grad_sq_accum = torch.tensor([16e-6, 4e-6])  # row 0: one view of four; row 1: 1e-3 in each
        a.denom = torch.tensor([4.0, 4.0])
        rep = a.densify(ctx(max_primitives=3, rank_by=rank_by))
        assert rep.cloned == 1 and rep.after == 3
        assert sorted(keys(a)) == sorted([0, 1, winner])


def test_reset_opacity():
    a = adapter(4, opacity=torch.tensor([0.5, 0.02, 0.005, 0.9]))
    fill_adam_state(a)
    before = moments(a)
    a.params["means"].grad = torch.ones_like(a.params["means"])
    a.reset_opacity()
    torch.testing.assert_close(a.get_opacities().detach(), torch.tensor([0.01, 0.01, 0.005, 0.01]))
    after = moments(a)
    assert after["opacities"][0].abs().sum() == 0 and after["opacities"][1].abs().sum() == 0
    assert after["opacities"][2] == before["opacities"][2]
    for name in ("means", "sh0", "shN", "scales", "quats"):
        assert torch.equal(after[name][0], before[name][0]) and torch.equal(after[name][1], before[name][1])
    assert a.params["means"].grad is not None  # only the opacity tensor was replaced


# ---- persistence ------------------------------------------------------------------------------

def train_step(a, cams, target):
    out = a.render(cams, torch.zeros(len(cams), 3))
    loss = (out.images - target).abs().sum()
    loss.backward()
    a.accumulate_stats(out)
    a.optimizer_step()
    a.zero_grad()
    return float(loss.detach())


def test_state_dict_round_trip_into_other_size():
    cams = [camera(0), camera(1, x=0.2)]
    target = torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(3))
    a = adapter(12, scale=0.05)
    a.set_step(1500)
    for _ in range(2):
        train_step(a, cams, target)
    a.densify(ctx(grad_threshold=0.0))  # every Gaussian grows: shapes change
    train_step(a, cams, target)
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)  # plain tensors and Python values only

    b = adapter(5, config=GS3DConfig(lr_sh0=0.5))
    b.load_state_dict(state)
    assert b.num_primitives() == a.num_primitives() == 24 and b.config.lr_sh0 == a.config.lr_sh0
    assert b.active_sh_degree == a.active_sh_degree == 1
    assert torch.equal(b.render(cams, torch.zeros(2, 3)).images, a.render(cams, torch.zeros(2, 3)).images)
    assert b.learning_rates() == a.learning_rates()
    for (na, sa), (nb, sb) in zip(moments(a).items(), moments(b).items()):
        assert na == nb and torch.equal(sa[0], sb[0]) and torch.equal(sa[1], sb[1]) and sa[2] == sb[2]
    for key in ("grad_accum", "denom", "max_radii2D"):
        assert torch.equal(getattr(a, key), getattr(b, key))
    # resuming continues exactly: one more step and a densification (random split samples)
    assert train_step(a, cams, target) == train_step(b, cams, target)
    a.densify(ctx(grad_threshold=0.0))
    b.densify(ctx(grad_threshold=0.0))
    for name in a.params:
        assert torch.equal(a.params[name], b.params[name]), name


def test_export_and_from_ply(tmp_path):
    a = adapter(9, scale=0.05)
    a.set_step(5000)
    with torch.no_grad():
        a.params["shN"].normal_(0, 0.1)
    path = tmp_path / "point_cloud.ply"
    a.export(str(path))
    b = GS3DAdapter.from_ply(path, scene_extent=1.0)
    assert b.active_sh_degree == 3
    cams = [camera(0)]
    for name in a.params:
        assert torch.equal(a.params[name], b.params[name]), name
    assert torch.equal(a.render(cams, torch.ones(1, 3)).images, b.render(cams, torch.ones(1, 3)).images)
    with pytest.raises(ValueError, match="SH degree 3"):
        GS3DAdapter.from_ply(path, 1.0, GS3DConfig(sh_degree=1))


# ---- training ---------------------------------------------------------------------------------

def test_short_training_lowers_loss_and_reaches_every_group():
    cams = [camera(0), camera(1, x=0.3), camera(2, x=-0.3)]
    truth = adapter(60, scale=0.06, opacity=0.8)
    truth.set_step(3000)
    with torch.no_grad():
        target = truth.render(cams, torch.zeros(3, 3)).images
    a = adapter(60, scale=0.06, opacity=0.8)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():  # perturb every attribute
        for p in a.params.values():
            p.add_(0.2 * torch.randn(p.shape, generator=g))
    a.set_step(3000)  # all SH bands active, so shN gets gradients too
    out = a.render(cams, torch.zeros(3, 3))
    (out.images - target).abs().sum().backward()
    grads = a.named_gradients()
    assert set(grads) == {"means", "sh0", "shN", "scales", "quats", "opacities"}
    for name, grad in grads.items():
        assert grad is not None and float(grad.abs().sum()) > 0, name
    a.zero_grad()
    losses = [train_step(a, cams, target) for _ in range(30)]
    assert losses[-1] < 0.8 * losses[0], losses


# ---- the controller's conformance checks ------------------------------------------------------

@pytest.mark.parametrize("check", ["check_render", "check_summed_equals_accumulated",
                                   "check_stats_and_densify", "check_state_dict_round_trip",
                                   "check_hard_cameras"])
def test_conformance(check):
    # check_gradients_reach_every_group is left out: at the 3DGS initialisation (isotropic
    # scales, identity rotations) the rotation gradient is exactly zero, as in the original;
    # test_short_training_lowers_loss_and_reaches_every_group covers gradients instead.
    testing = pytest.importorskip("mvgs_plugin.testing")
    getattr(testing, check)(lambda scene: GS3DAdapter.from_scene(scene), testing.synthetic_scene())
