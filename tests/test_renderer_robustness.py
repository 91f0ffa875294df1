"""Hard cases (finite images and gradients, analytic values where they exist) and bad input
(clear errors naming the argument) for reference_renderer.rasterization."""

import math

import pytest
import torch

from mvgs_plugin.reference_renderer import available_backends, rasterization

BACKENDS = available_backends()
assert "torch" in BACKENDS, "the PyTorch backend must always be available"

F64 = torch.float64


def camera(width=32, height=32, f=32.0, cx=None, cy=None, dtype=F64):
    K = torch.tensor([[f, 0, width / 2 if cx is None else cx], [0, f, height / 2 if cy is None else cy], [0, 0, 1]],
                     dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], K[None]


def gaussians(means, scales, opacities=None, colors=None, quats=None, dtype=F64):
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = len(means)
    scales = torch.as_tensor(scales, dtype=dtype).expand(n, 3).clone()
    quats = torch.tensor([1.0, 0, 0, 0], dtype=dtype).repeat(n, 1) if quats is None else torch.as_tensor(quats, dtype=dtype)
    opac = torch.full((n,), 0.5, dtype=dtype) if opacities is None else torch.as_tensor(opacities, dtype=dtype).expand(n).clone()
    colors = torch.rand(n, 3, dtype=dtype, generator=torch.Generator().manual_seed(0)) if colors is None else torch.as_tensor(colors, dtype=dtype)
    return means, quats, scales, opac, colors


def pixel_center_point(px, py, z, width=32, height=32, f=32.0):
    """World point (camera at the origin) that projects exactly onto the centre of pixel (px, py)."""
    return [(px + 0.5 - width / 2) * z / f, (py + 0.5 - height / 2) * z / f, z]


def render_and_grad(g, viewmats, Ks, width, height, backend, bg=None, **kw):
    """Renders, backpropagates a weighted image + alpha loss; asserts everything is finite."""
    params = [t.clone().requires_grad_() for t in g]
    img, alpha, meta = rasterization(*params, viewmats, Ks, width, height, backgrounds=bg, backend=backend, **kw)
    meta["means2d"].retain_grad()
    w = torch.rand(img.shape, dtype=img.dtype, generator=torch.Generator().manual_seed(1))
    ((img * w).sum() + alpha.sum()).backward()
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    for name, p in zip(("means", "quats", "scales", "opacities", "colors"), params):
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert torch.isfinite(meta["means2d"].grad).all()
    return img.detach(), alpha.detach(), meta, params


@pytest.mark.parametrize("backend", BACKENDS)
class TestHardCases:
    def test_behind_camera_is_culled(self, backend):
        vm, K = camera()
        g = gaussians([[0, 0, -2.0], [0.1, 0, -0.005], [0, 0, 0.0]], 0.3)
        bg = torch.tensor([[0.2, 0.3, 0.4]], dtype=F64)
        img, alpha, meta, params = render_and_grad(g, vm, K, 32, 32, backend, bg)
        assert (meta["radii"] == 0).all()
        assert torch.equal(img, bg[:, None, None, :].expand_as(img))
        assert (alpha == 0).all()
        assert all((p.grad == 0).all() for p in params)

    def test_straddling_near_plane(self, backend):
        vm, K = camera()
        # Centre just in front of the near plane, extent reaching far behind the camera.
        g = gaussians([[0.0, 0.0, 0.02], [0.01, 0.0, 0.5]], [0.3, 0.3, 0.3])
        img, alpha, meta, _ = render_and_grad(g, vm, K, 32, 32, backend)
        assert (meta["radii"][0, :, 0] > 0).all()
        assert alpha.max() > 0.4

    def test_far_outside_and_straddling_border_jacobian_clamp(self, backend):
        vm, K = camera()
        # Far outside the frustum: x/z = 50 (limit is 0.5 + 0.15); a huge Gaussian whose centre is
        # outside but which reaches into the image; and one on the image border.
        g = gaussians([[100.0, 0, 2.0], [1.6, 0.0, 2.0], [1.0, 1.0, 2.0]], [[0.05] * 3, [1.0] * 3, [0.1] * 3])
        img, alpha, meta, params = render_and_grad(g, vm, K, 32, 32, backend)
        assert meta["radii"][0, 0, 0] == 0  # nothing to draw in any tile
        assert meta["radii"][0, 1, 0] > 0 and meta["radii"][0, 2, 0] > 0
        # The clamp: the 2D footprint of the x/z = 0.8 Gaussian is computed at x/z = 0.65, so its
        # conic equals that of the same Gaussian moved onto the frustum limit.
        limit = 0.5 + 0.3 * 0.5
        g2 = gaussians([[limit * 2.0, 0.0, 2.0]], [1.0, 1.0, 1.0])
        _, _, meta2 = rasterization(*g2, vm, K, 32, 32, backend=backend)
        assert torch.allclose(meta["conics"][0, 1], meta2["conics"][0, 0], rtol=1e-10)

    @pytest.mark.parametrize("ratio", [1e-6, 1e6])
    def test_needles_and_discs(self, backend, ratio):
        vm, K = camera()
        q = torch.nn.functional.normalize(torch.tensor([[0.9, 0.2, -0.3, 0.1], [0.3, 0.8, 0.1, -0.4]], dtype=F64), dim=-1)
        g = gaussians([[0.1, -0.1, 3.0], [-0.2, 0.2, 4.0]], [[0.5, 0.5 * ratio, 0.5], [0.5 * ratio, 0.5 * ratio, 0.5]], quats=q)
        img, alpha, meta, _ = render_and_grad(g, vm, K, 32, 32, backend)
        assert (meta["radii"][0, :, 0] > 0).all()

    def test_subpixel_gaussian_is_dilated_analytic(self, backend):
        vm, K = camera()
        # A point-like Gaussian exactly on the centre of pixel (10, 20): after the 0.3 px dilation
        # it is a 2D Gaussian of variance 0.3, so pixel (11, 20) sees alpha = o exp(-1 / 0.6).
        g = gaussians([pixel_center_point(10, 20, 3.0)], 1e-7, opacities=0.8, colors=[[1.0, 0.5, 0.25]])
        img, alpha, meta, _ = render_and_grad(g, vm, K, 32, 32, backend)
        assert meta["radii"][0, 0, 0] == math.ceil(3 * math.sqrt(0.3 + math.sqrt(0.1)))
        assert img[0, 20, 10].tolist() == pytest.approx([0.8, 0.4, 0.2], abs=1e-6)
        a = 0.8 * math.exp(-0.5 / 0.3)
        assert img[0, 20, 11, 0].item() == pytest.approx(a, rel=1e-5)
        assert alpha[0, 21, 11, 0].item() == pytest.approx(0.8 * math.exp(-0.5 * 2 / 0.3), rel=1e-5)
        # Two pixels away alpha would be 0.8 exp(-6.7) = 0.001 < 1/255: skipped, exactly 0.
        assert alpha[0, 22, 10, 0].item() == 0.0

    def test_gaussian_larger_than_image(self, backend):
        vm, K = camera()
        g = gaussians([pixel_center_point(15, 15, 4.0)], 100.0, opacities=0.6, colors=[[0.2, 0.9, 0.4]])
        img, alpha, meta, _ = render_and_grad(g, vm, K, 32, 32, backend)
        var = (32 * 100.0 / 4.0) ** 2 + 0.3  # (f s / z)^2 plus the dilation, pixels^2
        assert meta["radii"][0, 0, 0] == math.ceil(3 * math.sqrt(var + math.sqrt(0.1)))
        # Every pixel is evaluated: alpha = o exp(-d^2 / (2 var)) with d measured from pixel (15, 15).
        yy, xx = torch.meshgrid(torch.arange(32, dtype=F64), torch.arange(32, dtype=F64), indexing="ij")
        expected = 0.6 * torch.exp(-0.5 * ((xx - 15) ** 2 + (yy - 15) ** 2) / var)
        assert torch.allclose(alpha[0, ..., 0], expected, atol=1e-12)

    def test_opacity_zero_and_one(self, backend):
        vm, K = camera()
        bg = torch.tensor([[0.1, 0.2, 0.3]], dtype=F64)
        p = pixel_center_point(8, 8, 3.0)
        g = gaussians([p, [p[0], p[1], 5.0]], 1e-7, opacities=torch.tensor([1.0, 0.0]), colors=[[1.0, 0, 0], [0, 1.0, 0]])
        img, alpha, meta, params = render_and_grad(g, vm, K, 32, 32, backend, bg)
        # alpha is clamped at 0.999; the opacity-0 Gaussian contributes nothing.
        expected = 0.999 * torch.tensor([1.0, 0, 0], dtype=F64) + 0.001 * bg[0]
        assert torch.allclose(img[0, 8, 8], expected, atol=1e-12)
        # At the clamp alpha no longer depends on the opacity, and the opacity-0 Gaussian is
        # skipped (alpha < 1/255): this pixel passes no gradient to either opacity.
        opac = g[3].clone().requires_grad_()
        out = rasterization(g[0], g[1], g[2], opac, g[4], vm, K, 32, 32, backgrounds=bg, backend=backend)[0]
        (grad,) = torch.autograd.grad(out[0, 8, 8].sum(), opac)
        assert grad.tolist() == [0.0, 0.0]

    def test_ten_thousand_stacked_on_one_pixel(self, backend):
        vm, K = camera(16, 16, 16.0)
        n = 10_000
        z = torch.linspace(2.0, 6.0, n, dtype=F64)
        means = torch.stack([(4 + 0.5 - 8) * z / 16, (5 + 0.5 - 8) * z / 16, z], -1)
        colors = torch.rand(n, 3, dtype=F64, generator=torch.Generator().manual_seed(3))
        g = gaussians(means, 1e-7, opacities=0.5, colors=colors)
        bg = torch.tensor([[0.3, 0.6, 0.9]], dtype=F64)
        img, alpha, meta, _ = render_and_grad(g, vm, K, 16, 16, backend, bg)
        # alpha = 0.5 each: the pixel stops before the Gaussian that would take T below 1e-4,
        # i.e. the first 13 contribute (0.5^13 >= 1e-4 > 0.5^14).
        k = torch.arange(13, dtype=F64)
        expected = (colors[:13] * (0.5 ** (k + 1))[:, None]).sum(0) + bg[0] * 0.5**13
        assert torch.allclose(img[0, 5, 4], expected, atol=1e-12)
        assert alpha[0, 5, 4, 0].item() == pytest.approx(1 - 0.5**13, abs=1e-12)

    def test_unnormalised_quaternions(self, backend):
        vm, K = camera()
        q = torch.nn.functional.normalize(torch.randn(5, 4, dtype=F64, generator=torch.Generator().manual_seed(4)), dim=-1)
        means = torch.tensor([[0.2 * i - 0.4, 0.1 * i - 0.2, 3.0 + 0.3 * i] for i in range(5)], dtype=F64)
        g = gaussians(means, [0.3, 0.1, 0.05], quats=q)
        g_scaled = g[:1] + (q * torch.tensor([7.3, 0.01, 2.0, 1e3, 0.5], dtype=F64)[:, None],) + g[2:]
        a = rasterization(*g, vm, K, 32, 32, backend=backend)[0]
        b = rasterization(*g_scaled, vm, K, 32, 32, backend=backend)[0]
        assert torch.allclose(a, b, atol=1e-12)
        with pytest.raises(ValueError, match=r"quats.*row 2"):
            bad = q.clone()
            bad[2] = 0
            rasterization(g[0], bad, *g[2:], vm, K, 32, 32, backend=backend)

    def test_no_gaussians(self, backend):
        vm, K = camera(20, 12)
        e = torch.zeros(0, 3, dtype=F64)
        bg = torch.tensor([[0.5, 0.25, 1.0]], dtype=F64, requires_grad=True)
        img, alpha, meta = rasterization(e, torch.zeros(0, 4, dtype=F64), e, torch.zeros(0, dtype=F64), e, vm, K, 20, 12,
                                         backgrounds=bg, backend=backend)
        assert img.shape == (1, 12, 20, 3) and (alpha == 0).all()
        assert meta["means2d"].shape == (1, 0, 2) and meta["radii"].shape == (1, 0, 2)
        img.sum().backward()
        assert torch.allclose(bg.grad, torch.full((1, 3), 240.0, dtype=F64))

    @pytest.mark.parametrize("size", [(1, 1), (37, 5), (5, 37), (16, 17)])
    def test_tiny_and_non_square_images(self, backend, size):
        W, H = size
        vm, K = camera(W, H, f=float(max(W, H)))
        px, py = W // 2, H // 2
        g = gaussians([pixel_center_point(px, py, 3.0, W, H, float(max(W, H)))], 1e-7, opacities=0.7, colors=[[1.0, 1.0, 1.0]])
        img, alpha, _, _ = render_and_grad(g, vm, K, W, H, backend)
        assert img.shape == (1, H, W, 3)
        assert alpha[0, py, px, 0].item() == pytest.approx(0.7, abs=1e-12)

    def test_non_centred_principal_point_shifts_image(self, backend):
        # Moving the principal point by a whole tile moves the picture by exactly that many
        # pixels (the tile grid moves with it, so the tile rule selects the same pixels).
        gen = torch.Generator().manual_seed(5)
        means = torch.cat([torch.rand(30, 2, dtype=F64, generator=gen) * 1.0 - 0.5, 3 + torch.rand(30, 1, dtype=F64, generator=gen)], -1)
        g = gaussians(means, 0.06)
        vm, K1 = camera(64, 48, 40.0, cx=20.0, cy=18.0)
        _, K2 = camera(64, 48, 40.0, cx=36.0, cy=34.0)
        a = rasterization(*g, vm, K1, 64, 48, backend=backend)[0]
        b = rasterization(*g, vm, K2, 64, 48, backend=backend)[0]
        assert a[0, :, :48].abs().sum() > 1
        assert torch.allclose(b[0, 16:, 16:], a[0, :32, :48], atol=1e-12)


def _args(**over):
    vm, K = camera()
    g = gaussians([[0, 0, 3.0], [0.2, 0.1, 4.0]], 0.2)
    args = dict(means=g[0], quats=g[1], scales=g[2], opacities=g[3], colors=g[4], viewmats=vm, Ks=K, width=32, height=32)
    args.update(over)
    return args


def _nan_at(t, idx):
    t = t.clone()
    t[idx] = float("nan")
    return t


BAD_INPUTS = [
    ("means", dict(means=torch.zeros(2, 2, dtype=F64)), ValueError, r"means must be \[N,3\], got \[2,2\]"),
    ("quats", dict(quats=torch.zeros(3, 4, dtype=F64)), ValueError, r"quats must be \[N,4\] with N=2, got \[3,4\]"),
    ("scales", dict(scales=torch.ones(2, 2, dtype=F64)), ValueError, r"scales must be \[N,3\] with N=2, got \[2,2\]"),
    ("opacities", dict(opacities=torch.ones(2, 1, dtype=F64)), ValueError, r"opacities must be \[N\] or \[C,N\]"),
    ("colors", dict(colors=torch.ones(3, 3, dtype=F64)), ValueError, r"colors must be \[N,D\] or \[C,N,D\].*got \[3,3\]"),
    ("viewmats", dict(viewmats=torch.eye(4, dtype=F64)), ValueError, r"viewmats must be \[C,4,4\], got \[4,4\]"),
    ("Ks", dict(Ks=torch.eye(3, dtype=F64)[None, :2]), ValueError, r"Ks must be \[C,3,3\] with C=1, got \[1,2,3\]"),
    ("nan means", dict(means=_nan_at(_args()["means"], (1, 2))), ValueError, r"means must be finite, got nan at index \[1, 2\]"),
    ("inf colors", dict(colors=_args()["colors"].index_fill(0, torch.tensor([0]), float("inf"))), ValueError, r"colors must be finite, got inf"),
    ("nan viewmats", dict(viewmats=_nan_at(camera()[0], (0, 0, 3))), ValueError, r"viewmats must be finite"),
    ("negative scale", dict(scales=torch.tensor([[0.1, -0.2, 0.1], [0.1, 0.1, 0.1]], dtype=F64)), ValueError, r"scales must be >= 0.*got -0.2 at index \[0, 1\]"),
    ("opacity > 1", dict(opacities=torch.tensor([0.5, 1.5], dtype=F64)), ValueError, r"opacities must be in \[0, 1\].*got 1.5 at index \[1\]"),
    ("opacity < 0", dict(opacities=torch.tensor([-0.1, 0.5], dtype=F64)), ValueError, r"opacities must be in \[0, 1\]"),
    ("dtype mismatch", dict(means=_args()["means"].float()), TypeError, r"quats has dtype torch.float64 but means has torch.float32"),
    ("int dtype", dict(means=torch.zeros(2, 3, dtype=torch.int64)), TypeError, r"means must be float32 or float64, got torch.int64"),
    ("not a tensor", dict(means=[[0, 0, 3.0]]), TypeError, r"means must be a torch.Tensor"),
    ("zero focal", dict(Ks=torch.tensor([[[0.0, 0, 16], [0, 32, 16], [0, 0, 1]]], dtype=F64)), ValueError, r"fx = Ks\[0,0,0\] must be > 0, got 0.0"),
    ("negative focal", dict(Ks=torch.tensor([[[32.0, 0, 16], [0, -32, 16], [0, 0, 1]]], dtype=F64)), ValueError, r"fy = Ks\[0,1,1\] must be > 0, got -32.0"),
    ("skew", dict(Ks=torch.tensor([[[32.0, 1, 16], [0, 32, 16], [0, 0, 1]]], dtype=F64)), ValueError, r"skew"),
    ("non-rigid viewmat", dict(viewmats=torch.diag(torch.tensor([2.0, 1, 1, 1], dtype=F64))[None]), ValueError, r"viewmats\[0\] must be a rigid"),
    ("projective viewmat", dict(viewmats=torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]], dtype=F64)), ValueError, r"last row must be \[0,0,0,1\]"),
    ("width", dict(width=0), ValueError, r"width must be a positive int, got 0"),
    ("height float", dict(height=32.0), ValueError, r"height must be a positive int, got 32.0"),
    ("near", dict(near_plane=0.0), ValueError, r"near_plane must be >= 1e-10"),
    ("far", dict(far_plane=0.001), ValueError, r"far_plane must be > near_plane"),
    ("eps2d", dict(eps2d=-0.1), ValueError, r"eps2d must be >= 0"),
    ("eps2d inf", dict(eps2d=float("inf")), ValueError, r"eps2d must be finite, got inf"),
    ("sh degree", dict(sh_degree=4, colors=torch.zeros(2, 25, 3, dtype=F64)), ValueError, r"sh_degree must be None or 0..3, got 4"),
    ("sh coeffs", dict(sh_degree=2, colors=torch.zeros(2, 4, 3, dtype=F64)), ValueError, r"K >= 9 for sh_degree=2.*got \[2,4,3\]"),
    ("backgrounds", dict(backgrounds=torch.zeros(2, 3, dtype=F64)), ValueError, r"backgrounds must be \[C,D\] with C=1, got \[2,3\]"),
    ("background channels", dict(backgrounds=torch.zeros(1, 5, dtype=F64)), ValueError, r"backgrounds must be \[C,3\]"),
    ("packed", dict(packed=True), ValueError, r"packed=True is not supported"),
    ("render mode", dict(render_mode="RGBD"), ValueError, r"render_mode must be one of"),
    ("camera model", dict(camera_model="fisheye"), ValueError, r"camera_model must be 'pinhole'"),
    ("backend", dict(backend="cuda"), ValueError, r"backend must be one of"),
]


@pytest.mark.parametrize("case,over,exc,pattern", BAD_INPUTS, ids=[c[0] for c in BAD_INPUTS])
def test_bad_input_is_rejected_with_a_clear_message(case, over, exc, pattern):
    with pytest.raises(exc, match=pattern):
        rasterization(**_args(**over))


def test_scale_whose_square_overflows_is_rejected():
    args = _args()
    args = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in args.items()}
    args["scales"] = torch.full((2, 3), 1e30)
    with pytest.raises(ValueError, match=r"scales must be <= .*float32"):
        rasterization(**args)


@pytest.mark.parametrize("backend", ["cpp", "torch"])
def test_a_non_finite_gradient_to_a_learnt_background_is_named(backend):
    """A NaN in the loss at a pixel no Gaussian covers reaches only the background's gradient:
    it is named there on both backends; with a background that is not learnt nothing
    non-finite flows, so nothing is raised."""
    bg = torch.tensor([[0.1, 0.2, 0.3]], dtype=F64, requires_grad=True)
    img, _, _ = rasterization(**_args(backgrounds=bg, backend=backend))
    target = torch.rand_like(img)
    target[0, 0, 0, 0] = float("nan")  # a corner pixel: the two Gaussians at the centre do not reach it
    with pytest.raises(FloatingPointError, match="non-finite gradient w.r.t. backgrounds"):
        ((img - target) ** 2).mean().backward()
    means = _args()["means"].clone().requires_grad_(True)
    img, _, _ = rasterization(**_args(means=means, backgrounds=bg.detach(), backend=backend))
    ((img - target) ** 2).mean().backward()
    assert torch.isfinite(means.grad).all()


def test_device_mismatch_is_rejected():
    args = _args(colors=torch.zeros(2, 3, dtype=F64, device="meta"))
    with pytest.raises(TypeError, match=r"colors is on meta but means is on cpu"):
        rasterization(**args)


def test_absgrad_needs_compiled_backend():
    with pytest.raises(ValueError, match="absgrad=True needs backend 'cpp'"):
        rasterization(**_args(absgrad=True, backend="torch"))


def test_every_keyword_of_gsplat_rasterization_is_accepted_at_its_default():
    """A call written for gsplat 1.5.3 (the installed dev dependency) runs unchanged: every
    keyword of gsplat.rasterization exists here, its default is accepted (packed aside: gsplat
    defaults to packed=True, which is refused with the alternative named), and a value asking
    for what this renderer does not do is refused naming the option."""
    import inspect

    import gsplat  # a dev dependency (pyproject.toml [dev]); its rasterization is pure Python to import
    from gsplat.rendering import rasterization as gsplat_rasterization

    theirs = inspect.signature(gsplat_rasterization).parameters
    ours = inspect.signature(rasterization).parameters
    assert set(theirs) <= set(ours), sorted(set(theirs) - set(ours))
    args = _args()
    defaults = {k: p.default for k, p in theirs.items() if p.default is not inspect.Parameter.empty and k != "packed"}
    defaults = {k: v for k, v in defaults.items() if k not in args}
    img, _, _ = rasterization(**args, **defaults, packed=False)
    ref, _, _ = rasterization(**args)
    assert torch.equal(img, ref)
    with pytest.raises(ValueError, match="packed=True is not supported: pass packed=False"):
        rasterization(**args, packed=theirs["packed"].default)
    for name, value in (("sparse_grad", True), ("distributed", True), ("segmented", True), ("with_ut", True),
                        ("with_eval3d", True), ("covars", torch.eye(3, dtype=F64)[None]),
                        ("radial_coeffs", torch.zeros(1, 6, dtype=F64)), ("viewmats_rs", torch.eye(4, dtype=F64)[None]),
                        ("channel_chunk", 0)):
        with pytest.raises(ValueError, match=name):
            rasterization(**args, **{name: value})
    assert gsplat.__version__ == "1.5.3"
