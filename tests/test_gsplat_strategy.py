"""Drop-in proof: gsplat's own DefaultStrategy densifies a model rendered by our rasterizer.

gsplat's strategy reads meta["means2d"].grad, meta["radii"], width, height and n_cameras exactly
as it does with gsplat's CUDA rasterizer. The expected growth is computed here independently,
from the 3DGS rules (mean NDC gradient over visible views > threshold: clone if small, split if
large; prune low opacity), and compared with what the strategy did to the parameters.
"""

import math

import pytest
import torch

from gsplat.strategy import DefaultStrategy  # the [dev] extra installs gsplat==1.5.3

from mvgs_plugin.reference_renderer import _cpp, available_backends, rasterization

W, H = 48, 40


def make_params(seed=0):
    g = torch.Generator().manual_seed(seed)
    n = 40
    means = torch.cat([torch.rand(n, 2, generator=g) * 1.6 - 0.8, 3 + torch.rand(n, 1, generator=g)], -1)
    log_scales = torch.full((n, 3), math.log(0.005))
    log_scales[:12] = math.log(0.2)  # large ones (> 0.01 * scene_scale): split, not cloned
    logit_opac = torch.full((n,), 1.0)
    logit_opac[30:34] = -6.0  # sigmoid(-6) = 0.0025 < 0.005: pruned
    params = {
        "means": means,
        "scales": log_scales,
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        "opacities": logit_opac,
        "sh0": torch.rand(n, 1, 3, generator=g),
        "shN": torch.zeros(n, 3, 3),
    }
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in params.items()})
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    return params, optimizers


def cameras():
    viewmats = torch.eye(4).repeat(2, 1, 1)
    viewmats[1, 0, 3] = 0.2  # second camera shifted sideways
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]])
    return viewmats, K.expand(2, 3, 3).clone()


def render(params, backend):
    viewmats, Ks = cameras()
    colors = torch.cat([params["sh0"], params["shN"]], 1)
    return rasterization(
        params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
        colors, viewmats, Ks, W, H, sh_degree=1, backend=backend, packed=False,
    )


def run_steps(strategy, params, optimizers, state, steps, backend, record=None):
    target = torch.rand(2, H, W, 3, generator=torch.Generator().manual_seed(9))
    for step in range(steps):
        img, _, info = render(params, backend)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        (img - target).abs().mean().backward()
        if record is not None:
            record.append((info["means2d"].grad.clone(), info["radii"].clone(),
                           {k: p.detach().clone() for k, p in params.items()}))
        strategy.step_post_backward(params, optimizers, state, step, info, packed=False)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)


def mean_ndc_grad(record):
    """Mean over visible views of |d loss / d means2d| in NDC units (x W/2, y H/2, per camera count)."""
    total = torch.zeros(record[0][0].shape[1])
    count = torch.zeros_like(total)
    for grad, radii, _ in record:
        C = grad.shape[0]
        scaled = grad * torch.tensor([W / 2 * C, H / 2 * C])
        visible = (radii > 0).all(-1)
        total += (scaled.norm(dim=-1) * visible).sum(0)
        count += visible.sum(0)
    return total / count.clamp_min(1)


@pytest.mark.parametrize("backend", available_backends())
def test_default_strategy_grows_splits_and_prunes_as_expected(backend):
    # Dry run without refinement to learn the gradients, then pick a threshold between them.
    params, optimizers = make_params()
    probe = DefaultStrategy(refine_start_iter=10_000)
    record = []
    run_steps(probe, params, optimizers, probe.initialize_state(scene_scale=1.0), 2, backend, record)
    avg = mean_ndc_grad(record)
    visible = avg > 0
    # halfway between the two middle gradients: no Gaussian sits on the threshold, where the
    # strategy's own float sums and this test's could round to different sides
    middle = avg[visible].sort().values
    k = middle.numel() // 2
    threshold = float(0.5 * (middle[k - 1] + middle[k]))

    # The real run: refine at step 1 (after two accumulated steps).
    params, optimizers = make_params()
    strategy = DefaultStrategy(refine_start_iter=0, refine_every=1, reset_every=10_000, grow_grad2d=threshold)
    state = strategy.initialize_state(scene_scale=1.0)
    strategy.check_sanity(params, optimizers)
    record = []
    run_steps(strategy, params, optimizers, state, 2, backend, record)

    before = record[-1][2]  # parameters when the refinement ran
    n0 = before["means"].shape[0]
    high = mean_ndc_grad(record) > threshold
    small = torch.exp(before["scales"]).max(-1).values <= 0.01
    dupli, split = high & small, high & ~small
    low = torch.sigmoid(before["opacities"]) < 0.005
    assert dupli.any() and split.any() and (~high).any() and low.any(), "test scene must exercise every rule"
    # Clones keep their source; a split Gaussian becomes two; low-opacity ones (and their
    # copies) are pruned.
    kept = (~split & ~low).sum() + (dupli & ~low).sum() + 2 * (split & ~low).sum()
    assert params["means"].shape[0] == int(kept)
    assert all(p.shape[0] == int(kept) for p in params.values())
    # Split children have scale / 1.6 of their parent (log scale - log 1.6).
    parent_scales = before["scales"][split & ~low]
    child_scales = params["scales"].detach()[-2 * len(parent_scales):]
    expected = (parent_scales - math.log(1.6)).repeat(2, 1)
    assert torch.allclose(child_scales, expected, atol=1e-5)
    # Nothing with low opacity survives.
    assert (torch.sigmoid(params["opacities"]) >= 0.005).all()
    assert n0 == 40 and int(kept) != n0


@pytest.mark.parametrize("backend", available_backends())
def test_strategy_statistics_match_meta(backend):
    params, optimizers = make_params()
    strategy = DefaultStrategy(refine_start_iter=10_000)
    state = strategy.initialize_state(scene_scale=1.0)
    record = []
    run_steps(strategy, params, optimizers, state, 3, backend, record)
    count = sum((r[1] > 0).all(-1).sum(0) for r in record).float()
    assert torch.equal(state["count"], count)
    expected = mean_ndc_grad(record) * count.clamp_min(1)
    assert torch.allclose(state["grad2d"], expected, rtol=1e-5, atol=1e-12)
    assert (state["grad2d"] > 0).sum() > 20


def test_absgrad_is_sum_of_absolute_pixel_gradients():
    """meta['means2d'].absgrad (compiled backend) bounds |grad| and equals it for one pixel."""
    assert "cpp" in available_backends(), f"compiled backend unavailable: {_cpp.build_error()}"
    params, _ = make_params()
    viewmats, Ks = cameras()
    colors = torch.cat([params["sh0"], params["shN"]], 1)
    img, _, meta = rasterization(params["means"], params["quats"], torch.exp(params["scales"]),
                                 torch.sigmoid(params["opacities"]), colors, viewmats, Ks, W, H, sh_degree=1,
                                 absgrad=True, backend="cpp")
    meta["means2d"].retain_grad()
    img[0, 20, 24].sum().backward(retain_graph=True)
    # A single pixel: the sum of absolute values equals the absolute value of the sum.
    assert torch.allclose(meta["means2d"].absgrad, meta["means2d"].grad.abs(), atol=1e-7)
    meta["means2d"].grad = None
    w = torch.randn(img.shape, generator=torch.Generator().manual_seed(2))
    (img * w).sum().backward()
    assert (meta["means2d"].absgrad >= meta["means2d"].grad.abs() - 1e-6).all()
    assert (meta["means2d"].absgrad > meta["means2d"].grad.abs() + 1e-6).any()
