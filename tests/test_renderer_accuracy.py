"""Accuracy of reference_renderer.rasterization against the dense float64 reference.

Part 1 validates the dense reference itself (no renderer needed): projection against
gsplat's pure-PyTorch implementation, SH against gsplat's, the radius against an
eigen-decomposition, and the vectorised compositing against a literal per-pixel loop.
Part 2 compares every available backend of the renderer with the reference: images,
alphas, meta, gradients (float64), images in float32, and torch.autograd.gradcheck.
"""
from __future__ import annotations

import math
from functools import lru_cache

import pytest
import torch

try:  # tests/ may or may not be a package
    from tests import dense_reference as dr
except ImportError:  # pragma: no cover
    import dense_reference as dr


# ============================================================================ helpers
def _renderer():
    import mvgs_plugin.reference_renderer as reference_renderer  # an ImportError here is a test error, never a skip

    return reference_renderer


BACKENDS = dr.renderer_backends()
GRAD_KEYS = ("means", "quats", "scales", "opacities", "colors", "backgrounds")


def render(backend, scene, dtype=torch.float64, grad=False, **kw):
    """Run the renderer on ``scene`` cast to ``dtype``; returns (img, alpha, meta, inputs)."""
    assert not backend.startswith("renderer-unavailable"), backend
    inputs = {k: None if scene[k] is None else
              scene[k].detach().to(dtype).clone().requires_grad_(grad) for k in GRAD_KEYS}
    img, acc, meta = _renderer().rasterization(
        inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
        inputs["colors"], scene["viewmats"].to(dtype), scene["Ks"].to(dtype),
        scene["width"], scene["height"], sh_degree=scene["sh_degree"],
        backgrounds=inputs["backgrounds"], backend=backend, **kw)
    return img, acc, meta, inputs


def reference(scene, grad=False, **kw):
    inputs = {k: None if scene[k] is None else scene[k].detach().clone().requires_grad_(grad)
              for k in GRAD_KEYS}
    img, acc, metas = dr.dense_render_batch(
        inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
        inputs["colors"], scene["viewmats"], scene["Ks"], scene["width"], scene["height"],
        sh_degree=scene["sh_degree"], backgrounds=inputs["backgrounds"], **kw)
    return img, acc, metas, inputs


def loss_weights(shape_img, shape_acc, seed=1234):
    g = torch.Generator().manual_seed(seed)
    w_img = torch.rand(*shape_img, generator=g, dtype=torch.float64) * 2 - 1
    w_acc = torch.rand(*shape_acc, generator=g, dtype=torch.float64) * 2 - 1
    return w_img, w_acc


def weighted_loss(img, acc, seed=1234):
    w_img, w_acc = loss_weights(img.shape, acc.shape, seed)
    return (w_img.to(img.dtype) * img).sum() + 0.5 * (w_acc.to(acc.dtype) * acc).sum()


def assert_close_rel(actual, expected, rel, name):
    """max |a - e| <= rel * max |e| (with a tiny floor for an all-zero reference)."""
    assert actual is not None, f"{name}: no gradient"
    assert actual.shape == expected.shape, f"{name}: shape {tuple(actual.shape)} " \
                                           f"!= {tuple(expected.shape)}"
    actual = actual.detach().to(torch.float64)
    assert torch.isfinite(actual).all(), f"{name}: non-finite values"
    err = (actual - expected).abs().max().item()
    scale = expected.abs().max().item()
    assert err <= rel * scale + 1e-12, \
        f"{name}: max abs err {err:.3e} > {rel:g} * max|ref| ({scale:.3e})"


# Scenes: name -> (random_scene kwargs, extra render kwargs); "tile_border" cases use
# dr.tile_border_scene instead (Gaussians visibly cut by the tile rule).
CASES = {
    "rgb_32x32": (dict(seed=1, n=40, width=32, height=32, color_range=(-0.3, 1.3)), {}),
    "rgb_percam_40x24": (dict(seed=2, n=30, width=40, height=24, per_camera_colors=True), {}),
    "sh0_nobg_40x24": (dict(seed=3, n=25, width=40, height=24, sh_degree=0, background=False),
                       {}),
    "sh1_K16_32x32": (dict(seed=4, n=32, width=32, height=32, sh_degree=1, sh_k=16), {}),
    "sh2_40x24": (dict(seed=5, n=36, width=40, height=24, sh_degree=2), {}),
    "sh3_32x32": (dict(seed=6, n=60, width=32, height=32, sh_degree=3), {}),
    "stack_sh3_40x24": (dict(seed=7, n=30, width=40, height=24, sh_degree=3,
                             opaque_stack=6), {}),
    "opaque_clamp_32x32": (dict(seed=9, n=24, width=32, height=32, opacity_range=(0.9, 1.0),
                                opaque_stack=3, stack_opacity=1.0), {}),
    "planes_eps_tile8_32x32": (dict(seed=8, n=40, width=32, height=32),
                               dict(near_plane=2.6, far_plane=5.0, eps2d=0.1, tile_size=8)),
    "tile_border_48x40": (dict(seed=41, tile_size=16), dict(tile_size=16)),
    "tile_border_t8_48x40": (dict(seed=42, tile_size=8), dict(tile_size=8)),
}


@lru_cache(maxsize=None)
def case(name):
    kw, render_kw = CASES[name]
    if name.startswith("tile_border"):
        return dr.tile_border_scene(**kw), render_kw
    return dr.random_scene(**kw), render_kw


@lru_cache(maxsize=None)
def reference_result(name):
    """Reference image/alpha/meta and gradients of weighted_loss for a case (float64)."""
    scene, render_kw = case(name)
    img, acc, metas, inputs = reference(scene, grad=True, **render_kw)
    for m in metas:
        m["means2d"].retain_grad()
    weighted_loss(img, acc).backward()
    grads = {k: inputs[k].grad.detach().clone() for k in GRAD_KEYS if inputs[k] is not None}
    grads["means2d"] = torch.stack([m["means2d"].grad for m in metas])
    metas = [{k: (v.detach() if torch.is_tensor(v) else v) for k, v in m.items()} for m in metas]
    return img.detach(), acc.detach(), metas, grads


# ============================================================================ part 1
# The reference against independent implementations.

def _literal_render(means2d, conics, opacities, colors, depths, radii, width, height,
                    background, tile_size=16):
    """The spec's per-pixel loop in plain Python floats (no tensors, no vectorisation).

    Returns image [H][W][3], transmittance [H][W], and counts of the pixels that stopped
    early and of the terms whose alpha hit the 0.999 clamp.
    """
    n = len(depths)
    order = sorted(range(n), key=lambda i: (depths[i], i))
    ntx = (width + tile_size - 1) // tile_size
    nty = (height + tile_size - 1) // tile_size
    rect = {}
    for i in range(n):
        r = radii[i]
        if r <= 0:
            continue
        u, v = means2d[i]
        rect[i] = (min(max(math.floor((u - r) / tile_size), 0), ntx),
                   min(max(math.floor((u + r + tile_size - 1) / tile_size), 0), ntx),
                   min(max(math.floor((v - r) / tile_size), 0), nty),
                   min(max(math.floor((v + r + tile_size - 1) / tile_size), 0), nty))
    image, trans, stopped, clamped = [], [], 0, 0
    for py in range(height):
        row, trow = [], []
        for px in range(width):
            t, col = 1.0, [0.0, 0.0, 0.0]
            tx, ty = px // tile_size, py // tile_size
            for i in order:
                if i not in rect:
                    continue
                x0, x1, y0, y1 = rect[i]
                if not (x0 <= tx < x1 and y0 <= ty < y1):
                    continue
                dx, dy = means2d[i][0] - (px + 0.5), means2d[i][1] - (py + 0.5)
                a, b, c = conics[i]
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                if sigma < 0:
                    continue
                alpha = min(0.999, opacities[i] * math.exp(-sigma))
                clamped += alpha == 0.999
                if alpha < 1.0 / 255.0:
                    continue
                test_t = t * (1.0 - alpha)
                if test_t < 1e-4:
                    stopped += 1
                    break
                for k in range(3):
                    col[k] += colors[i][k] * alpha * t
                t = test_t
            row.append([col[k] + t * background[k] for k in range(3)])
            trow.append(t)
        image.append(row)
        trans.append(trow)
    return image, trans, dict(stopped=stopped, clamped=clamped)


@pytest.mark.parametrize("name", ["rgb_percam_40x24", "sh0_nobg_40x24", "stack_sh3_40x24",
                                  "opaque_clamp_32x32", "planes_eps_tile8_32x32",
                                  "tile_border_t8_48x40"])
def test_reference_compositing_matches_literal_loop(name):
    scene, render_kw = case(name)
    img, acc, metas, _ = reference_result(name)
    tile = render_kw.get("tile_size", 16)
    counts = dict(stopped=0, clamped=0)
    for c, m in enumerate(metas):
        colors = scene["colors"][c] if scene["colors"].dim() == 3 and scene["sh_degree"] is None \
            else scene["colors"]
        rgb = dr.gaussian_colors(scene["means"], colors, scene["viewmats"][c], scene["sh_degree"])
        image, trans, cnt = _literal_render(
            m["means2d"].tolist(), m["conics"].tolist(), scene["opacities"].tolist(),
            rgb.tolist(), m["depths"].tolist(), m["radii"].tolist(), scene["width"],
            scene["height"],
            [0.0] * 3 if scene["backgrounds"] is None else scene["backgrounds"][c].tolist(), tile)
        counts = {k: counts[k] + cnt[k] for k in counts}
        image = torch.tensor(image, dtype=torch.float64)
        alpha = 1.0 - torch.tensor(trans, dtype=torch.float64)[..., None]
        assert (image - img[c]).abs().max().item() < 1e-12
        assert (alpha - acc[c]).abs().max().item() < 1e-12
    # The scenes must keep exercising the rules they were built for.
    if name in ("stack_sh3_40x24", "opaque_clamp_32x32"):
        assert counts["stopped"] > 0, "scene must exercise the T < 1e-4 stop"
    if name == "opaque_clamp_32x32":
        assert counts["clamped"] > 0, "scene must exercise the 0.999 clamp"


@pytest.mark.parametrize("name", ["rgb_32x32", "sh2_40x24", "planes_eps_tile8_32x32"])
def test_reference_projection_matches_gsplat_torch_impl(name):
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    scene, render_kw = case(name)
    near = render_kw.get("near_plane", 0.01)
    far = render_kw.get("far_plane", 1e10)
    eps2d = render_kw.get("eps2d", 0.3)
    covars, _ = _quat_scale_to_covar_preci(scene["quats"], scene["scales"],
                                           compute_preci=False)
    g_radii, g_means2d, g_depths, g_conics, _ = _fully_fused_projection(
        scene["means"], covars, scene["viewmats"], scene["Ks"], scene["width"],
        scene["height"], eps2d=eps2d, near_plane=near, far_plane=far)
    _, _, metas, _ = reference_result(name)
    for c, m in enumerate(metas):
        in_depth = (g_depths[c] > near) & (g_depths[c] < far)
        assert torch.equal(m["visible"] & ~in_depth, torch.zeros_like(in_depth))
        vis = m["visible"]
        assert vis.sum() >= 5 and (~vis).sum() >= 2, "scene must have visible and culled ones"
        torch.testing.assert_close(m["depths"], g_depths[c], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(m["means2d"][vis], g_means2d[c][vis], rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(m["conics"][vis], g_conics[c][vis], rtol=1e-10, atol=1e-12)
        # gsplat's radius is per axis (3.33 sigma); only the culling by depth is shared.
        assert torch.equal(g_radii[c][~in_depth], torch.zeros_like(g_radii[c][~in_depth]))


def test_reference_radius_is_three_sigma_of_largest_eigenvalue():
    _, _, metas, _ = reference_result("sh3_32x32")
    checked = 0
    for m in metas:
        cov = m["cov2d"]
        a, c = cov[:, 0, 0], cov[:, 1, 1]
        mid = 0.5 * (a + c)
        lam = torch.linalg.eigvalsh(0.5 * (cov + cov.transpose(-1, -2)))[:, -1]
        far_from_floor = (mid * mid - m["det"]) > 0.1  # where the 0.1 floor is inactive
        sel = m["visible"] & far_from_floor
        assert torch.equal(m["radii"][sel], torch.ceil(3 * lam[sel].sqrt()).long())
        checked += int(sel.sum())
    assert checked >= 20


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_reference_sh_matches_gsplat_torch_impl(degree):
    from gsplat.cuda._torch_impl import _spherical_harmonics

    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(500, 3, generator=g, dtype=torch.float64) * 3.0
    coeffs = torch.randn(500, 16, 3, generator=g, dtype=torch.float64)
    ours = dr.sh_colors(coeffs, dirs, degree)
    theirs = torch.clamp_min(_spherical_harmonics(degree, dirs, coeffs) + 0.5, 0.0)
    torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)
    assert (ours == 0).any() and (ours > 0).any()


def test_reference_quaternion_convention():
    # w-x-y-z: a 90 degree turn about z maps x to y; scaling the quaternion changes nothing.
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]],
                     dtype=torch.float64)
    rot = dr.quat_to_rotmat(3.0 * q)[0]
    torch.testing.assert_close(rot @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                               torch.tensor([0.0, 1.0, 0], dtype=torch.float64))
    from gsplat.cuda._torch_impl import _quat_to_rotmat

    qs = torch.randn(100, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    torch.testing.assert_close(dr.quat_to_rotmat(qs), _quat_to_rotmat(qs), rtol=0, atol=1e-13)


def test_reference_gradients_finite_with_culled_gaussians():
    _, _, metas, grads = reference_result("planes_eps_tile8_32x32")
    assert any((~m["visible"]).any() for m in metas)
    for k, v in grads.items():
        assert torch.isfinite(v).all(), k


# ============================================================================ part 2
def test_torch_backend_is_available():
    assert "torch" in BACKENDS, f"available_backends() = {BACKENDS}"


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("backend", BACKENDS)
def test_images_and_meta_match_reference_float64(backend, name):
    scene, render_kw = case(name)
    ref_img, ref_acc, metas, _ = reference_result(name)
    img, acc, meta, _ = render(backend, scene, **render_kw)
    C, N = scene["viewmats"].shape[0], scene["means"].shape[0]
    H, W = scene["height"], scene["width"]
    assert img.shape == (C, H, W, 3) and acc.shape == (C, H, W, 1)
    assert img.dtype == torch.float64 and acc.dtype == torch.float64
    assert (img.detach() - ref_img).abs().max().item() <= 1e-5
    assert (acc.detach() - ref_acc).abs().max().item() <= 1e-5

    assert meta["width"] == W and meta["height"] == H and meta["n_cameras"] == C
    assert meta["gaussian_ids"] is None
    radii = meta["radii"]
    assert radii.shape == (C, N, 2) and radii.dtype == torch.int32
    ref_radii = torch.stack([m["radii"] for m in metas])
    assert torch.equal(radii[..., 0].long(), ref_radii), \
        f"radii differ at {torch.nonzero(radii[..., 0].long() != ref_radii).tolist()}"
    assert torch.equal(radii[..., 1], radii[..., 0])
    vis = ref_radii > 0
    for key, shape in (("means2d", (C, N, 2)), ("conics", (C, N, 3)), ("depths", (C, N))):
        assert meta[key].shape == shape, (key, meta[key].shape)
        ref = torch.stack([m[key] for m in metas])
        torch.testing.assert_close(meta[key].detach()[vis], ref[vis], rtol=1e-9, atol=1e-9,
                                   msg=lambda s, key=key: f"meta {key}: {s}")


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("backend", BACKENDS)
def test_images_match_reference_float32(backend, name):
    scene, render_kw = case(name)
    ref_img, ref_acc, metas, _ = reference_result(name)
    img, acc, meta, _ = render(backend, scene, dtype=torch.float32, **render_kw)
    assert img.dtype == torch.float32 and acc.dtype == torch.float32
    assert (img.double() - ref_img).abs().max().item() <= 1e-4
    assert (acc.double() - ref_acc).abs().max().item() <= 1e-4
    ref_radii = torch.stack([m["radii"] for m in metas])
    assert torch.equal(meta["radii"][..., 0].long(), ref_radii)


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_reference_float64(backend, name):
    scene, render_kw = case(name)
    _, _, _, ref_grads = reference_result(name)
    img, acc, meta, inputs = render(backend, scene, grad=True, **render_kw)
    meta["means2d"].retain_grad()
    weighted_loss(img, acc).backward()
    assert set(ref_grads) == {k for k in GRAD_KEYS if scene[k] is not None} | {"means2d"}
    for k in ref_grads:
        if k != "means2d":
            assert_close_rel(inputs[k].grad, ref_grads[k], 1e-4, f"d loss / d {k}")
    assert_close_rel(meta["means2d"].grad, ref_grads["means2d"], 1e-4, "d loss / d means2d")


@pytest.mark.parametrize("name", ["rgb_32x32", "sh3_32x32", "stack_sh3_40x24"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_float32_close_to_reference(backend, name):
    # float32 is not held to 1e-4; this only catches gross float32-only backward errors.
    scene, render_kw = case(name)
    _, _, _, ref_grads = reference_result(name)
    img, acc, meta, inputs = render(backend, scene, dtype=torch.float32, grad=True, **render_kw)
    weighted_loss(img, acc).backward()
    for k in ref_grads:
        if k == "means2d":
            continue
        assert inputs[k].grad.dtype == torch.float32
        assert_close_rel(inputs[k].grad, ref_grads[k], 2e-3, f"float32 d loss / d {k}")


# ---------------------------------------------------------------------------- gradcheck
def smooth_scene(seed, n, width, height, n_cameras, sh_degree=None):
    """Few, large, depth-separated Gaussians: every covered pixel sees alpha well above
    1/255 and below 0.999, transmittance stays far above 1e-4, means stay inside the
    Jacobian clamp, SH colours stay above 0 — so the image is smooth in all inputs."""
    g = torch.Generator().manual_seed(seed)

    def uni(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)

    s = dr.random_scene(seed, n, width, height, n_cameras=n_cameras, sh_degree=sh_degree,
                        extra_culled=False)
    k0, v0 = s["Ks"][0], s["viewmats"][0]
    z = 2.0 + 0.6 * torch.arange(n, dtype=torch.float64)[torch.randperm(n, generator=g)]
    u = uni(0.3 * width, 0.7 * width, n)
    v = uni(0.3 * height, 0.7 * height, n)
    cam = torch.stack([(u - k0[0, 2]) / k0[0, 0] * z, (v - k0[1, 2]) / k0[1, 1] * z, z], -1)
    s["means"] = (cam - v0[:3, 3]) @ v0[:3, :3]
    s["scales"] = z[:, None] * uni(0.25, 0.45, n, 3)
    s["opacities"] = uni(0.3, 0.7, n)
    if sh_degree is None:
        s["colors"] = uni(0.2, 0.8, n, 3)
    else:
        s["colors"][:, 1:, :] *= 0.3
        s["colors"][:, 0, :] = uni(0.3, 1.2, n, 3)
    return s


def assert_away_from_thresholds(scene):
    """Checks, with the reference, that no discontinuity is within reach of gradcheck."""
    W, H, T = scene["width"], scene["height"], 16
    for c in range(scene["viewmats"].shape[0]):
        m = dr.project(scene["means"], scene["quats"], scene["scales"], scene["viewmats"][c],
                       scene["Ks"][c], W, H)
        assert m["visible"].all()
        # Tile rectangles and radius not near a rounding boundary; every tile covered.
        u, v, r = m["means2d"][:, 0], m["means2d"][:, 1], m["radii"].double()
        for q in ((u - r) / T, (u + r + T - 1) / T, (v - r) / T, (v + r + T - 1) / T):
            assert ((q - q.round()).abs() > 1e-4).all()
        mid = 0.5 * (m["cov2d"][:, 0, 0] + m["cov2d"][:, 1, 1])
        s3 = 3 * torch.sqrt(mid + torch.sqrt(torch.clamp_min(mid * mid - m["det"], 0.1)))
        assert ((s3 - s3.round()).abs() > 1e-4).all()
        assert ((m["tiles"][:, 0] == 0) & (m["tiles"][:, 1] == (W + T - 1) // T)).all()
        assert ((m["tiles"][:, 2] == 0) & (m["tiles"][:, 3] == (H + T - 1) // T)).all()
        # Means inside the x/z, y/z clamp range with margin.
        K = scene["Ks"][c]
        x, y, z = m["means_cam"].unbind(-1)
        assert ((x / z > -K[0, 2] / K[0, 0] + 0.05) & (x / z < (W - K[0, 2]) / K[0, 0] - 0.05)).all()
        assert ((y / z > -K[1, 2] / K[1, 1] + 0.05) & (y / z < (H - K[1, 2]) / K[1, 1] - 0.05)).all()
        # Alpha at every pixel comfortably inside (1/255, 0.999); final T far above 1e-4.
        py, px = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
        d = m["means2d"][None, None] - torch.stack([px, py], -1)[:, :, None].double() - 0.5
        con = m["conics"]
        sig = 0.5 * (con[:, 0] * d[..., 0] ** 2 + con[:, 2] * d[..., 1] ** 2) \
            + con[:, 1] * d[..., 0] * d[..., 1]
        alpha = scene["opacities"] * torch.exp(-sig)
        assert alpha.min() > 1.5 / 255 and alpha.max() < 0.95
        assert torch.prod(1 - alpha, -1).min() > 1e-3
        if scene["sh_degree"] is not None:
            rgb = dr.sh_colors(scene["colors"], scene["means"] - dr.camera_centre(
                scene["viewmats"][c]), scene["sh_degree"])
            assert rgb.min() > 0.05


# name -> (smooth_scene kwargs, fast_mode). Full gradcheck costs two renders per scalar
# input (~380 renders for the 2-camera SH-3 scene, too slow for the pure-torch backend on
# a busy 2-core machine), so that one uses gradcheck's fast mode (random projections of
# the Jacobian); the two smaller scenes get the full element-wise check.
GRADCHECK_CASES = {
    "rgb_16x16_n4_1cam": (dict(seed=11, n=4, width=16, height=16, n_cameras=1), False),
    "sh2_24x20_n3_1cam": (dict(seed=12, n=3, width=24, height=20, n_cameras=1, sh_degree=2),
                          False),
    "sh3_32x32_n6_2cam": (dict(seed=13, n=6, width=32, height=32, n_cameras=2, sh_degree=3),
                          True),
}


@pytest.mark.parametrize("name", list(GRADCHECK_CASES))
@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_float64(backend, name):
    assert not backend.startswith("renderer-unavailable"), backend
    kw, fast = GRADCHECK_CASES[name]
    scene = smooth_scene(**kw)
    assert_away_from_thresholds(scene)
    rr = _renderer()
    C, H, W = scene["viewmats"].shape[0], scene["height"], scene["width"]
    g = torch.Generator().manual_seed(99)
    proj_img = torch.randn(4, C, H, W, 3, generator=g, dtype=torch.float64)
    proj_acc = torch.randn(2, C, H, W, 1, generator=g, dtype=torch.float64)

    def f(means, quats, scales, opacities, colors):
        img, acc, _ = rr.rasterization(
            means, quats, scales, opacities, colors, scene["viewmats"], scene["Ks"], W, H,
            sh_degree=scene["sh_degree"], backgrounds=scene["backgrounds"], backend=backend)
        return torch.cat([(proj_img * img).flatten(1).sum(1), (proj_acc * acc).flatten(1).sum(1)])

    args = tuple(scene[k].detach().clone().requires_grad_(True)
                 for k in ("means", "quats", "scales", "opacities", "colors"))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=fast)


def test_reference_itself_passes_gradcheck():
    scene = smooth_scene(seed=14, n=3, width=24, height=20, n_cameras=1, sh_degree=2)
    assert_away_from_thresholds(scene)
    g = torch.Generator().manual_seed(5)
    w = torch.randn(3, 20, 24, 4, generator=g, dtype=torch.float64)

    def f(means, quats, scales, opacities, colors):
        out = []
        for c in range(1):
            img, acc = dr.dense_render(means, quats, scales, opacities, colors,
                                       scene["viewmats"][c], scene["Ks"][c], 24, 20,
                                       sh_degree=2, background=scene["backgrounds"][c])
            out.append((w * torch.cat([img, acc], -1)).flatten(1).sum(1))
        return torch.cat(out)

    args = tuple(scene[k].detach().clone().requires_grad_(True)
                 for k in ("means", "quats", "scales", "opacities", "colors"))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4)


def tie_scene(order):
    """Two pairs of overlapping Gaussians with exactly equal camera depths (identity
    camera), listed in ``order``; front-to-back order within a pair is by index."""
    means = torch.tensor([[0.0, 0.0, 3.0], [0.15, 0.05, 3.0],
                          [-0.3, 0.2, 4.0], [-0.25, 0.25, 4.0]], dtype=torch.float64)
    colors = torch.tensor([[1.0, 0.1, 0.1], [0.1, 0.1, 1.0],
                           [0.1, 1.0, 0.1], [0.9, 0.9, 0.1]], dtype=torch.float64)
    g = torch.Generator().manual_seed(17)
    s = dict(means=means, quats=torch.randn(4, 4, generator=g, dtype=torch.float64),
             scales=torch.full((4, 3), 0.25, dtype=torch.float64) * torch.tensor([1.0, 0.7, 1.3]),
             opacities=torch.tensor([0.8, 0.7, 0.75, 0.85], dtype=torch.float64), colors=colors,
             viewmats=torch.eye(4, dtype=torch.float64)[None],
             Ks=dr.intrinsics(30.0, 31.0, 16.3, 15.7)[None], width=32, height=32,
             sh_degree=None, backgrounds=torch.tensor([[0.2, 0.3, 0.4]], dtype=torch.float64))
    for k in ("means", "quats", "scales", "opacities", "colors"):
        s[k] = s[k][list(order)]
    return s


@pytest.mark.parametrize("backend", BACKENDS)
def test_equal_depths_are_ordered_by_index(backend):
    images = []
    for order in ((0, 1, 2, 3), (1, 0, 3, 2)):
        s = tie_scene(order)
        ref_img, ref_acc, metas, _ = reference(s)
        # The reference against the literal loop (which sorts by (depth, index)).
        m = metas[0]
        lit, _, _ = _literal_render(m["means2d"].tolist(), m["conics"].tolist(),
                                    s["opacities"].tolist(), s["colors"].tolist(),
                                    m["depths"].tolist(), m["radii"].tolist(), 32, 32,
                                    s["backgrounds"][0].tolist())
        assert (torch.tensor(lit, dtype=torch.float64) - ref_img[0]).abs().max() < 1e-12
        img, acc, _, _ = render(backend, s)
        assert (img - ref_img).abs().max().item() <= 1e-5
        assert (acc - ref_acc).abs().max().item() <= 1e-12 + 1e-5
        images.append(ref_img)
    assert (images[0] - images[1]).abs().max() > 1e-2, "the tie order must matter here"
