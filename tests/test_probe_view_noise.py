"""benchmarks/probe_view_noise.py: its noise scale and per-step gains against an exact enumeration of
every M-view step on quadratic losses, its per-view gradients against a plain render loop, bad
input said by name."""

import itertools
import math
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import common  # noqa: E402
import probe_view_noise  # noqa: E402
from mvgs_plugin.io import load_checked  # noqa: E402
from mvgs_plugin.losses import ssim  # noqa: E402
from test_bench_step_parts import checkpoint, plain_render  # noqa: E402,F401  (the 60-step gsplat-loop checkpoint fixture)


def _quadratic(n=7, seed=0, spread=1.0):
    """n views' quadratic losses L_i = 1/2 (x - c_i)^T P^-1 (x - c_i) over two parameter groups, at x:
    the views' gradients P^-1 (x - c_i), the metric P (the step is x - eps P g) and x - c_i."""
    g = torch.Generator().manual_seed(seed)
    x = {"a": torch.randn(4, generator=g, dtype=torch.float64), "b": torch.randn(3, generator=g, dtype=torch.float64)}
    centre = {k: v + torch.randn(v.shape, generator=g, dtype=torch.float64) for k, v in x.items()}
    c = [{k: centre[k] + spread * torch.randn(v.shape, generator=g, dtype=torch.float64) for k, v in x.items()}
         for _ in range(n)]
    p = {k: 0.1 + torch.rand(v.shape, generator=g, dtype=torch.float64) for k, v in x.items()}
    grads = [{k: (x[k] - ci[k]) / p[k] for k in x} for ci in c]
    return grads, p


def _enumerated_gain(grads, p, m, weighted):
    """The best expected loss decrease of a step x - eps P mean(g over S), S every m-subset of the
    views (Euclidean: P = 1 and L_i = 1/2 |x - c_i|^2), as a share of the full-batch step's: the
    loss is quadratic, so its decrease is eps G^T P g_S - eps^2 / 2 g_S^T P g_S exactly."""
    n = len(grads)
    metric = {k: (p[k] if weighted else torch.ones_like(p[k])) for k in p}
    if not weighted:  # L_i = 1/2 |x - c_i|^2: gradients x - c_i
        grads = [{k: g[k] * p[k] for k in g} for g in grads]
    full = {k: sum(g[k] for g in grads) / n for k in metric}

    def dot(u, v):
        return float(sum((metric[k] * u[k] * v[k]).sum() for k in metric))
    lin = quad = 0.0
    subsets = list(itertools.combinations(range(n), m))
    for s in subsets:
        gs = {k: sum(grads[i][k] for i in s) / m for k in metric}
        lin += dot(full, gs) / len(subsets)
        quad += dot(gs, gs) / len(subsets)
    best = 0.5 * lin * lin / quad  # max over eps of eps lin - eps^2 quad / 2
    return best / (0.5 * dot(full, full))


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("spread", [0.3, 3.0])
def test_gain_per_step_is_the_enumerated_best_step(weighted, spread):
    grads, p = _quadratic(spread=spread)
    n = len(grads)
    s = probe_view_noise.Spread(p)
    for g in (grads if weighted else [{k: v[k] * p[k] for k in v} for v in grads]):
        s.add(g)
    b = s.noise_scale(["a", "b"], weighted=weighted)
    for m in range(1, n + 1):
        assert probe_view_noise.gain_per_step(b, m, n) == pytest.approx(_enumerated_gain(grads, p, m, weighted), rel=1e-9)


def test_per_group_noise_scale_is_a_plain_mean_and_variance():
    grads, p = _quadratic(n=9, seed=3)
    s = probe_view_noise.Spread()
    for g in grads:
        s.add(g)
    stacked = torch.stack([g["a"] for g in grads])
    expected = float(stacked.var(0, unbiased=True).sum() / (stacked.mean(0) ** 2).sum())
    assert s.noise_scale(["a"]) == pytest.approx(expected, rel=1e-12)
    # the agreement: the mean over pairs of views of their inner product, over the mean squared norm
    flat = [torch.cat([g["a"], g["b"]]) for g in grads]
    pairs = [float(flat[i] @ flat[j]) for i in range(9) for j in range(9) if i != j]
    norms = [float(f @ f) for f in flat]
    assert s.agreement(["a", "b"]) == pytest.approx((sum(pairs) / len(pairs)) / (sum(norms) / 9), rel=1e-12)
    orthogonal = probe_view_noise.Spread()
    for i in range(5):
        orthogonal.add({"a": torch.eye(5)[i] * (i + 1)})
    assert orthogonal.agreement(["a"]) == pytest.approx(0.0, abs=1e-12)
    same = probe_view_noise.Spread()
    for _ in range(3):
        same.add({"a": torch.tensor([1.0, -2.0])})
    assert same.agreement(["a"]) == pytest.approx(1.0) and same.noise_scale(["a"]) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("share", [0.0, 0.2])
def test_efficiency_is_one_at_the_break_even_noise_scale(share):
    # scale the views' spread about their mean until B is the break-even value: the enumerated steps
    # then gain as much per unit of CPU with 4 views as with one
    n, m = 7, 4
    grads, p = _quadratic(n=n, seed=1)
    mean = {k: sum(g[k] for g in grads) / n for k in p}

    def scaled(f):
        return [{k: mean[k] + f * (g[k] - mean[k]) for k in g} for g in grads]

    def b_of(gs):
        s = probe_view_noise.Spread(p)
        for g in gs:
            s.add(g)
        return s.noise_scale(["a", "b"], weighted=True)
    target = probe_view_noise.break_even(m, n, share)
    if share == 0.0:
        assert target == pytest.approx(n)  # a clock linear in views: extra views pay only beyond B = n
    gs = scaled(math.sqrt(target / b_of(grads)))
    assert b_of(gs) == pytest.approx(target, rel=1e-9)
    per_cpu = [_enumerated_gain(gs, p, k, True) / (k * (1 - share) + share) for k in (1, m)]
    assert per_cpu[1] / per_cpu[0] == pytest.approx(1.0, rel=1e-9)
    assert probe_view_noise.efficiency(target, m, n, share) == pytest.approx(1.0, rel=1e-9)
    # below it the one-view steps gain more per unit of CPU
    low = scaled(0.5 * math.sqrt(target / b_of(grads)))
    assert _enumerated_gain(low, p, m, True) / (m * (1 - share) + share) < _enumerated_gain(low, p, 1, True)


@pytest.mark.parametrize("seed", [0, 2])
def test_four_view_steps_pay_exactly_below_the_printed_cost(seed):
    # on any clock: a 4-view step costing C(4) one-view steps gains, by enumeration of every subset,
    # exactly as much per unit of that clock as one-view steps; a little cheaper it gains more
    n, m = 7, 4
    grads, p = _quadratic(n=n, seed=seed)
    s = probe_view_noise.Spread(p)
    for g in grads:
        s.add(g)
    cost = probe_view_noise.pays_below(s.noise_scale(["a", "b"], weighted=True), m, n)
    one, four = (_enumerated_gain(grads, p, k, True) for k in (1, m))
    assert four / cost == pytest.approx(one, rel=1e-9)
    assert four / (0.95 * cost) > one and four / (1.05 * cost) < one
    assert 1.0 < cost < m  # more views never lose gain per step, and gain less than m times as much
    # on a clock linear in views it is m E(m)
    b = s.noise_scale(["a", "b"], weighted=True)
    assert cost == pytest.approx(m * probe_view_noise.efficiency(b, m, n, 0.0), rel=1e-12)


def _quadratic_loss(h, slope):
    """loss_at(step, t) of L(x) = slope . x + 1/2 x^T diag(h) x at x = t * step (one group 'a')."""
    def loss_at(step, t):
        x = t * step["a"] if "a" in step else torch.zeros_like(h)
        return float(slope @ x + 0.5 * (h * x * x).sum())
    return loss_at


def test_curvature_is_isotropic_where_the_hessian_is_the_metrics_inverse():
    # H = 3 P^-1: along any step -P g the curvature per squared length g^T P g is 3, whatever the views
    grads, _ = _quadratic(n=6, seed=5)
    grads = [{"a": g["a"]} for g in grads]
    p = {"a": 0.2 + torch.rand(4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)}
    loss_at = _quadratic_loss(3.0 / p["a"], torch.randn(4, dtype=torch.float64))
    one, four = probe_view_noise.curvatures(grads, p, loss_at, 4, 5, torch.Generator().manual_seed(0))
    assert one == pytest.approx(3.0, rel=1e-9) and four == pytest.approx(3.0, rel=1e-9)


def test_curvature_ratio_on_an_anisotropic_quadratic():
    # four views e_i + c e_4 (coordinates 0-3 curved a, coordinate 4 curved b, P = 1): every single view
    # has curvature (a + b c^2) / (1 + c^2) per squared length, the mean of all four (a / 4 + b c^2) / (1 / 4 + c^2)
    a, b, c = 0.5, 4.0, 0.7
    grads = [{"a": torch.eye(5, dtype=torch.float64)[i] + c * torch.eye(5, dtype=torch.float64)[4]} for i in range(4)]
    h = torch.tensor([a, a, a, a, b], dtype=torch.float64)
    loss_at = _quadratic_loss(h, torch.linspace(-1, 1, 5, dtype=torch.float64))
    one, four = probe_view_noise.curvatures(grads, {"a": torch.ones(5, dtype=torch.float64)}, loss_at, 4, 3,
                                            torch.Generator().manual_seed(0), delta=0.5)
    assert one == pytest.approx((a + b * c * c) / (1 + c * c), rel=1e-9)
    assert four == pytest.approx((a / 4 + b * c * c) / (0.25 + c * c), rel=1e-9)


def test_adams_metric_is_the_next_steps_as_torch_takes_it():
    # a checkpoint after one Adam step in which coordinate 4 got no gradient (v = 0 there, as for a
    # Gaussian densification just made), then one view's gradient: the metric is lr / (sqrt(v_hat) + eps)
    # with v_hat what torch's Adam holds after stepping with that gradient, finite on coordinate 4
    p = torch.nn.Parameter(torch.zeros(5))
    opt = torch.optim.Adam([p], lr=0.01, eps=1e-15)
    p.grad = torch.tensor([0.3, -0.2, 0.1, 0.5, 0.0])
    opt.step()
    saved = {"optimizers": {"a": {k: v for k, v in opt.state_dict().items()}}}
    saved["optimizers"]["a"]["state"] = {0: {k: v.clone() for k, v in opt.state_dict()["state"][0].items()}}
    g = torch.tensor([0.1, 0.4, -0.3, 0.2, 0.7])
    s = probe_view_noise.Spread()
    s.add({"a": g})
    metric = probe_view_noise.adam_metric(saved, s)["a"]
    p.grad = g.clone()
    opt.step()
    state = opt.state[p]
    v_hat = state["exp_avg_sq"].double() / (1.0 - 0.999 ** float(state["step"]))
    assert torch.allclose(metric, 0.01 / (v_hat.sqrt() + 1e-15), rtol=1e-6)
    assert float(metric[4]) < 1.0  # not lr / eps


def test_bad_values_are_named():
    with pytest.raises(ValueError, match="views per step 5: expected 1..4"):
        probe_view_noise.gain_per_step(1.0, 5, 4)
    with pytest.raises(ValueError, match="step_share 1.0"):
        probe_view_noise.efficiency(1.0, 2, 4, 1.0)
    s = probe_view_noise.Spread()
    s.add({"a": torch.ones(2)})
    with pytest.raises(ValueError, match="at least 2 views' gradients, got 1"):
        s.noise_scale(["a"])


def _model(checkpoint):
    """The 60-step checkpoint's splats (float32), the scene, a loop Config for 60 steps and the SH
    degree the loop renders with after them."""
    saved = load_checked(str(checkpoint))
    cfg = common.Config(sh_degree=3)
    cfg.adjust_steps(60)
    degree = min(int(saved["step"]) // cfg.sh_degree_interval, 3)
    return {k: v.float() for k, v in saved["splats"].items()}, common.Parser(FORWARD), cfg, degree


def test_the_views_gradients_are_those_of_a_plain_render_loop(checkpoint):
    splats, parser, cfg, degree = _model(checkpoint)
    probed = list(probe_view_noise.view_gradients(splats, cfg, parser, degree))
    views = common.Dataset(parser, "train")
    assert len(probed) == len(views) >= 2
    for i in (0, len(views) - 1):
        d = views[i]
        params = {k: v.clone().requires_grad_(True) for k, v in splats.items()}
        img, _, _ = plain_render(params, parser, d, degree)
        target = d["image"][None] / 255.0
        loss = 0.8 * F.l1_loss(img, target) + 0.2 * (1.0 - ssim(img, target, padding="valid"))
        loss.backward()
        for k, v in params.items():
            assert torch.allclose(probed[i][k], v.grad, rtol=1e-4, atol=1e-9), k


def test_the_row_reads_the_checkpoint_and_names_bad_input(checkpoint, capsys):
    text = probe_view_noise.main([str(checkpoint), "--data", str(FORWARD), "--run-steps", "60", "--repeats", "1"])
    row = [c.strip() for c in text.strip().splitlines()[-1].split("|")[1:-1]]
    saved = load_checked(str(checkpoint))
    assert int(row[1]) == saved["step"] and int(row[2]) == len(saved["splats"]["means"])
    b = float(row[6])
    views = int(row[3])
    assert -1.0 <= float(row[5]) <= 1.0
    assert b > 0 and float(row[16]) == pytest.approx(probe_view_noise.efficiency(b, 4, views, 0.0), abs=0.006)
    assert float(row[-2]) == pytest.approx(probe_view_noise.pays_below(b, 4, views), abs=0.006)
    assert row[-4:-2] == ["- / -", "-"] and row[-1] == "-"  # no curvature asked for
    with pytest.raises(SystemExit):
        probe_view_noise.main([str(checkpoint), "--data", str(FORWARD), "--run-steps", "0"])
    assert "--run-steps 0: expected the run's step count" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        probe_view_noise.main([str(checkpoint), "--data", str(FORWARD), "--run-steps", "60", "--curvature-samples", "-1"])
    assert "--curvature-samples -1" in capsys.readouterr().err


def test_the_curvature_check_reads_the_loss_over_every_view(checkpoint):
    # the probe's full loss at t = 0 is the mean of the loop's loss over the training views, computed
    # here through the renderer's own entry point; its curvature ratio is finite and positive
    splats, parser, cfg, degree = _model(checkpoint)
    loss_at = probe_view_noise.full_loss(splats, cfg, parser, degree)
    views = common.Dataset(parser, "train")
    losses = []
    with torch.no_grad():
        for i in range(len(views)):
            d = views[i]
            img, _, _ = plain_render(splats, parser, d, degree)
            target = d["image"][None] / 255.0
            losses.append(float(0.8 * F.l1_loss(img, target) + 0.2 * (1.0 - ssim(img, target, padding="valid"))))
    assert loss_at({}, 0.0) == pytest.approx(sum(losses) / len(losses), rel=1e-5)
    text = probe_view_noise.main([str(checkpoint), "--data", str(FORWARD), "--run-steps", "60", "--repeats", "1",
                                  "--curvature-samples", "2"])
    row = [c.strip() for c in text.strip().splitlines()[-1].split("|")[1:-1]]
    one, four = (float(x) for x in row[-4].split(" / "))
    assert math.isfinite(one) and math.isfinite(four)
    if one > 0 and four > 0:
        assert float(row[-3]) == pytest.approx(float(row[16]) * one / four, abs=0.02)
        assert float(row[-1]) == pytest.approx(float(row[-2]) * one / four, abs=0.02)
    else:
        assert row[-3] == row[-1] == "-"
