"""Invariants of reference_renderer.rasterization that hold whatever the exact numbers are.

Permutation of the Gaussians, a rigid motion of scene and camera together (with the SH
coefficients rotated along), zero opacity, batch vs single cameras, and agreement between
every pair of available backends.
"""
from __future__ import annotations

import itertools

import pytest
import torch

try:  # tests/ may or may not be a package
    from tests import dense_reference as dr
except ImportError:  # pragma: no cover
    import dense_reference as dr

GRAD_KEYS = ("means", "quats", "scales", "opacities", "colors", "backgrounds")


def _renderer():
    import mvgs_plugin.reference_renderer as reference_renderer  # an ImportError here is a test error, never a skip

    return reference_renderer


BACKENDS = dr.renderer_backends()
# Every pair; with a single backend, the backend against itself (a determinism check).
BACKEND_PAIRS = list(itertools.combinations(BACKENDS, 2)) or [(BACKENDS[0], BACKENDS[0])]


def render(backend, scene, grad=False, seed=77, **overrides):
    """Render ``scene`` (float64); returns img, alpha, meta, inputs, and (when ``grad``)
    the gradients of a fixed random weighted loss, including d loss / d means2d."""
    assert not backend.startswith("renderer-unavailable"), backend
    s = dict(scene, **overrides)
    inputs = {k: s[k].detach().clone().requires_grad_(grad) if s[k] is not None else None
              for k in GRAD_KEYS}
    img, acc, meta = _renderer().rasterization(
        inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
        inputs["colors"], s["viewmats"], s["Ks"], s["width"], s["height"],
        sh_degree=s["sh_degree"], backgrounds=inputs["backgrounds"], backend=backend)
    grads = None
    if grad:
        meta["means2d"].retain_grad()
        g = torch.Generator().manual_seed(seed)
        w_img = torch.rand(img.shape, generator=g, dtype=img.dtype) * 2 - 1
        w_acc = torch.rand(acc.shape, generator=g, dtype=acc.dtype) * 2 - 1
        ((w_img * img).sum() + (w_acc * acc).sum()).backward()
        grads = {k: inputs[k].grad for k in GRAD_KEYS if inputs[k] is not None}
        grads["means2d"] = meta["means2d"].grad
    return img.detach(), acc.detach(), meta, grads


def assert_rel(actual, expected, rel, name):
    assert actual is not None and expected is not None, f"{name}: missing gradient"
    assert actual.shape == expected.shape, name
    assert torch.isfinite(actual).all() and torch.isfinite(expected).all(), name
    err = (actual - expected).abs().max().item()
    scale = expected.abs().max().item()
    assert err <= rel * scale + 1e-13, f"{name}: err {err:.3e} > {rel:g} * {scale:.3e}"


def scene(kind, **kw):
    base = {
        "rgb": dict(seed=21, n=30, width=32, height=32),
        "sh3": dict(seed=22, n=30, width=40, height=24, sh_degree=3),
        "sh2_3cam": dict(seed=23, n=25, width=40, height=24, sh_degree=2, n_cameras=3),
        "percam_3cam": dict(seed=24, n=25, width=32, height=32, n_cameras=3,
                            per_camera_colors=True),
    }[kind]
    return dr.random_scene(**dict(base, **kw))


def test_torch_backend_is_available():
    assert "torch" in BACKENDS, f"available_backends() = {BACKENDS}"


# ---------------------------------------------------------------------------- permutation
@pytest.mark.parametrize("kind", ["rgb", "sh3"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_permuting_gaussians_changes_nothing(backend, kind):
    s = scene(kind)
    for c in range(s["viewmats"].shape[0]):  # distinct depths: order is unambiguous
        z = (s["means"] @ s["viewmats"][c, :3, :3].T + s["viewmats"][c, :3, 3])[:, 2]
        assert torch.sort(z).values.diff().min() > 1e-6
    perm = torch.randperm(s["means"].shape[0], generator=torch.Generator().manual_seed(3))
    sp = dict(s)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        sp[k] = s[k][perm]
    img, acc, meta, grads = render(backend, s, grad=True)
    img_p, acc_p, meta_p, grads_p = render(backend, sp, grad=True)
    assert (img_p - img).abs().max().item() <= 1e-12
    assert (acc_p - acc).abs().max().item() <= 1e-12
    assert torch.equal(meta_p["radii"], meta["radii"][:, perm])
    vis = meta["radii"][:, perm, 0] > 0
    assert vis.sum() > 10
    torch.testing.assert_close(meta_p["means2d"].detach()[vis],
                               meta["means2d"].detach()[:, perm][vis])
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert_rel(grads_p[k], grads[k][perm], 1e-10, f"permuted grad {k}")
    assert_rel(grads_p["means2d"], grads["means2d"][:, perm], 1e-10, "permuted grad means2d")
    assert_rel(grads_p["backgrounds"], grads["backgrounds"], 1e-10, "grad backgrounds")


# ---------------------------------------------------------------------------- rigid motion
def quat_multiply(p, q):
    """Hamilton product, w-x-y-z; R(p * q) = R(p) R(q)."""
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack([pw * qw - px * qx - py * qy - pz * qz,
                        pw * qx + px * qw + py * qz - pz * qy,
                        pw * qy - px * qz + py * qw + pz * qx,
                        pw * qz + px * qy - py * qx + pz * qw], -1)


def sh_rotation(rot, degree):
    """A with Y(rot d) = Y(d) A for the reference's real SH basis (fitted, then checked)."""
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    y, y_rot = dr.sh_basis(degree, d), dr.sh_basis(degree, d @ rot.T)
    a = torch.linalg.lstsq(y, y_rot).solution
    assert (y @ a - y_rot).abs().max() < 1e-10, "SH basis must be rotation-covariant"
    return a


@pytest.mark.parametrize("kind", ["rgb", "sh3"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_rigid_motion_of_scene_and_cameras_changes_nothing(backend, kind):
    s = scene(kind)
    qm = torch.tensor([0.8, -0.3, 0.45, 0.2], dtype=torch.float64)
    qm = qm / qm.norm()
    rot = dr.quat_to_rotmat(qm[None])[0]
    trans = torch.tensor([1.5, -0.7, 2.2], dtype=torch.float64)
    motion = torch.eye(4, dtype=torch.float64)
    motion[:3, :3], motion[:3, 3] = rot, trans

    moved = dict(s)
    moved["means"] = s["means"] @ rot.T + trans
    moved["quats"] = quat_multiply(qm.expand_as(s["quats"]), s["quats"])
    torch.testing.assert_close(dr.quat_to_rotmat(moved["quats"]),
                               rot @ dr.quat_to_rotmat(s["quats"]))
    moved["viewmats"] = s["viewmats"] @ torch.linalg.inv(motion)
    if s["sh_degree"] is not None:
        a_inv = torch.linalg.inv(sh_rotation(rot, s["sh_degree"]))
        moved["colors"] = torch.einsum("kj,njc->nkc", a_inv, s["colors"])
        assert (moved["colors"][:, 1:] - s["colors"][:, 1:]).abs().max() > 0.1

    img, acc, meta, _ = render(backend, s)
    img_m, acc_m, meta_m, _ = render(backend, moved)
    assert (img_m - img).abs().max().item() <= 1e-9
    assert (acc_m - acc).abs().max().item() <= 1e-9
    assert torch.equal(meta_m["radii"], meta["radii"])
    vis = meta["radii"][..., 0] > 0
    torch.testing.assert_close(meta_m["means2d"].detach()[vis], meta["means2d"].detach()[vis],
                               rtol=0, atol=1e-9)
    torch.testing.assert_close(meta_m["depths"].detach()[vis], meta["depths"].detach()[vis],
                               rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------- zero opacity
@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_opacity_gives_exactly_the_background(backend):
    s = scene("sh3")
    zero = torch.zeros_like(s["opacities"])
    img, acc, _, grads = render(backend, s, grad=True, opacities=zero)
    C, H, W = img.shape[:3]
    assert torch.equal(img, s["backgrounds"][:, None, None, :].expand(C, H, W, 3))
    assert torch.equal(acc, torch.zeros(C, H, W, 1, dtype=torch.float64))
    # Transmittance is 1 everywhere, so d loss / d background = sum of the image weights.
    g = torch.Generator().manual_seed(77)
    w_img = torch.rand((C, H, W, 3), generator=g, dtype=torch.float64) * 2 - 1
    torch.testing.assert_close(grads["backgrounds"], w_img.sum((1, 2)), rtol=1e-12, atol=1e-12)
    for k, v in grads.items():
        if k != "backgrounds":
            assert torch.isfinite(v).all() and v.abs().max() == 0, k

    img0, acc0, _, _ = render(backend, s, opacities=zero, backgrounds=None)
    assert torch.equal(img0, torch.zeros_like(img0)) and torch.equal(acc0, torch.zeros_like(acc0))


# ---------------------------------------------------------------------------- batching
@pytest.mark.parametrize("kind", ["sh2_3cam", "percam_3cam"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_batch_of_cameras_equals_single_camera_renders(backend, kind):
    s = scene(kind)
    img, acc, meta, grads = render(backend, s, grad=True)
    summed = {k: torch.zeros_like(v) for k, v in grads.items() if k != "means2d"}
    for c in range(3):
        single = dict(s, viewmats=s["viewmats"][c:c + 1], Ks=s["Ks"][c:c + 1],
                      backgrounds=s["backgrounds"][c:c + 1])
        if s["sh_degree"] is None and s["colors"].dim() == 3:
            single["colors"] = s["colors"][c:c + 1]
        img_c, acc_c, meta_c, _ = render(backend, single)
        assert (img_c[0] - img[c]).abs().max().item() <= 1e-12
        assert (acc_c[0] - acc[c]).abs().max().item() <= 1e-12
        assert meta_c["n_cameras"] == 1
        assert torch.equal(meta_c["radii"][0], meta["radii"][c])
        vis = meta["radii"][c, :, 0] > 0
        for key in ("means2d", "conics", "depths"):
            torch.testing.assert_close(meta_c[key].detach()[0][vis], meta[key].detach()[c][vis],
                                       rtol=1e-12, atol=1e-12)
        single_in = {k: single[k].detach().clone().requires_grad_(True) for k in GRAD_KEYS}
        img_c, acc_c, _ = _renderer().rasterization(
            single_in["means"], single_in["quats"], single_in["scales"],
            single_in["opacities"], single_in["colors"], single["viewmats"], single["Ks"],
            s["width"], s["height"], sh_degree=s["sh_degree"],
            backgrounds=single_in["backgrounds"], backend=backend)
        # The batch loss's weights (same seed as render()), sliced to camera c.
        g = torch.Generator().manual_seed(77)
        w_img = torch.rand(img.shape, generator=g, dtype=img.dtype) * 2 - 1
        w_acc = torch.rand(acc.shape, generator=g, dtype=acc.dtype) * 2 - 1
        ((w_img[c:c + 1] * img_c).sum() + (w_acc[c:c + 1] * acc_c).sum()).backward()
        for k in summed:
            if single_in[k].grad.shape == summed[k].shape:  # shared by all cameras
                summed[k] += single_in[k].grad
            else:  # per camera (backgrounds, per-camera colours)
                summed[k][c:c + 1] += single_in[k].grad
    for k in summed:
        assert_rel(grads[k], summed[k], 1e-10, f"batched grad {k}")


# ---------------------------------------------------------------------------- backends
@pytest.mark.parametrize("kind", ["rgb", "sh3", "percam_3cam"])
@pytest.mark.parametrize("pair", BACKEND_PAIRS, ids=lambda p: f"{p[0]}-vs-{p[1]}")
def test_backends_agree_float64(pair, kind):
    a, b = pair
    s = scene(kind)
    img_a, acc_a, meta_a, grads_a = render(a, s, grad=True)
    img_b, acc_b, meta_b, grads_b = render(b, s, grad=True)
    assert (img_a - img_b).abs().max().item() <= 1e-5
    assert (acc_a - acc_b).abs().max().item() <= 1e-5
    assert torch.equal(meta_a["radii"], meta_b["radii"])
    vis = meta_a["radii"][..., 0] > 0
    for key in ("means2d", "conics", "depths"):
        torch.testing.assert_close(meta_a[key].detach()[vis], meta_b[key].detach()[vis],
                                   rtol=1e-9, atol=1e-9)
    for k in grads_a:
        assert_rel(grads_b[k], grads_a[k], 1e-5, f"{a} vs {b}: grad {k}")
