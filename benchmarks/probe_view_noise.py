"""How much an optimizer step gains from a second, third, fourth view: the views' gradient noise scale.

Issue 27 asked for a recipe with several views per step that beats one view per step at equal
CPU; none of nine did (docs/equal_compute.md, "Multi-view steps"). This probe measures why from
the gradients themselves, on a model at any point of a run, without training.

At a gsplat-loop checkpoint it computes every training view's gradient g_i of the loop's loss
(0.8 L1 + 0.2 (1 - SSIM)), their mean G (the whole training set's gradient) and their spread
S^2 = sum_i |g_i - G|^2 / (n - 1), the views' agreement (their mean pairwise inner product over
their mean squared norm: 1 if every view asked for the same step, 0 if each moves what no other
moves), and the simple noise scale of McCandlish et al. (2018, "An Empirical Model of
Large-Batch Training"): B = S^2 / |G|^2, in two metrics: each
parameter group's own (Euclidean), and the whole model's in the metric of the Adam step the
loop takes next (each coordinate weighted by lr / (sqrt(v_hat) + eps), v_hat the checkpoint's
second moment moved one step on by a view's mean squared gradient: the step the loop would
actually take).

With an optimal step size on a locally quadratic loss (curvature taken as isotropic in that
metric), a step over M views drawn without replacement from n gains

    dL(M) = dL_max / (1 + B (1/M - 1/n))

(the mean of M of n vectors has covariance S^2 (1/M - 1/n)). A step costs M r + a: r the
render, loss and backward of a view, a what a step does once (Adam; both timed here, one thread:
the views' gradients as they are taken, Adam's step on the model; the strategy's statistics, also
once per step, are left out). Per unit of CPU an M-view step therefore gains, relative to a
one-view step,

    E(M) = (1 + B (1 - 1/n)) (r + a) / ((1 + B (1/M - 1/n)) (M r + a))

On a clock linear in views (a = 0) E(M) < 1 exactly when B < n, that is when the views'
agreement is above 0: extra views pay only when the views' gradients pull against each other;
a per-step share a > 0 lowers that threshold. The table prints B, E(2), E(4), E(4) with a = 0,
and the B at which E(4) = 1. It also prints what a four-view step may cost for any clock, a GPU's
or several cores' (where M views in one launch can cost less than M one-view steps): four-view
steps gain more per unit of that clock than one-view steps exactly when a four-view step costs
less than C(4) = dL(4) / dL(1) = (1 + B (1 - 1/n)) / (1 + B (1/4 - 1/n)) one-view steps
(4 E(4) on a linear clock; with the measured curvatures, scaled by their ratio too).

With --curvature-samples K the probe also checks the formula's assumption on the loss itself: the
second derivative of the loss over every training view along K random 4-view steps and K one-view
steps (the metric's step on the raw gradient, a central difference over one such step), each per
squared step length: equal where the curvature is isotropic; E(4) is scaled by their ratio
(printed only where both are positive: over one step the loss can be concave early on).

    python examples/gsplat_loop/simple_trainer_mvgs.py --data SCENE --steps 3000 --threads 1 --background-points 2000 --world-size-rule distance --opacity-reset-scope inside --preset baseline --grow-grad2d 0.00125 --save-steps 300 1000 2000 3000 --out out/b
    python benchmarks/probe_view_noise.py out/b/ckpt_300.pt out/b/ckpt_1000.pt out/b/ckpt_2000.pt out/b/ckpt_3000.pt --data SCENE --run-steps 3000 [--curvature-samples 8]

--run-steps is the run's --steps: the loop raises the SH degree on a schedule scaled to it, and
the gradients are taken at the degree the loop renders with at the checkpoint's step. --repeats
is the number of timed Adam steps.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Tuple

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import bench_step_parts  # noqa: E402
import common  # noqa: E402

Grads = Dict[str, torch.Tensor]


class Spread:
    """Per-coordinate sums of per-view gradients and of their squares, each group flattened
    (float64): the views' mean and spread in the Euclidean metric and in a diagonal metric per
    group (|x|^2_P = sum_j P_j x_j^2), given as `metric` or set later (.metric), once the
    views' own second moments are known."""

    def __init__(self, metric: Optional[Grads] = None):
        self.metric = metric
        self.n = 0
        self.sum: Grads = {}
        self.sumsq: Grads = {}

    def add(self, grads: Grads) -> None:
        for k, g in grads.items():
            g = g.detach().double().reshape(-1)
            if k in self.sum:
                self.sum[k] += g
                self.sumsq[k] += g * g
            else:
                self.sum[k], self.sumsq[k] = g.clone(), g * g
        self.n += 1

    def _terms(self, keys: Iterable[str], weighted: bool):
        """(|G|^2, S^2, sum_i |g_i|^2) over the groups `keys`."""
        n = self.n
        mean_sq = spread = total = 0.0
        for k in keys:
            w = self.metric[k] if weighted else 1.0
            mean = self.sum[k] / n
            m2 = float((w * mean * mean).sum())
            s2 = float((w * self.sumsq[k]).sum())
            mean_sq += m2
            total += s2
            spread += (s2 - n * m2) / (n - 1)
        return mean_sq, max(spread, 0.0), total

    def agreement(self, keys: Iterable[str], weighted: bool = False) -> float:
        """The views' mean pairwise inner product over their mean squared norm, sum_{i != j} g_i . g_j
        / ((n - 1) sum_i |g_i|^2): 1 when every view's gradient is the same, 0 when they are
        orthogonal (each view moves what no other moves), negative when they pull apart."""
        if self.n < 2:
            raise ValueError(f"an agreement needs at least 2 views' gradients, got {self.n}")
        n = self.n
        mean_sq, _, sq = self._terms(keys, weighted)
        return (n * n * mean_sq - sq) / ((n - 1) * sq)

    def noise_scale(self, keys: Iterable[str], weighted: bool = False) -> float:
        """B = S^2 / |G|^2 over the groups `keys` (inf when the mean gradient is zero)."""
        if self.n < 2:
            raise ValueError(f"a noise scale needs at least 2 views' gradients, got {self.n}")
        mean_sq, spread, _ = self._terms(keys, weighted)
        return spread / mean_sq if mean_sq > 0 else math.inf


def gain_per_step(b: float, m: int, n: int) -> float:
    """dL(M) / dL_max: the share of a full-batch step's gain an optimal step over m of n views
    (without replacement) makes, at noise scale b."""
    if not 1 <= m <= n:
        raise ValueError(f"views per step {m}: expected 1..{n} (the training views)")
    return 1.0 / (1.0 + b * (1.0 / m - 1.0 / n))


def efficiency(b: float, m: int, n: int, step_share: float = 0.0) -> float:
    """E(M): progress per unit of CPU of m-view steps over one-view steps; step_share = a / (r + a),
    the share of a one-view step's CPU spent once per step."""
    if not 0.0 <= step_share < 1.0:
        raise ValueError(f"step_share {step_share}: expected a share in [0, 1)")
    r, a = 1.0 - step_share, step_share
    return pays_below(b, m, n) * (r + a) / (m * r + a)


def pays_below(b: float, m: int, n: int) -> float:
    """C(m) = dL(m) / dL(1): m-view steps gain more per unit of any clock than one-view steps
    exactly when an m-view step costs less than C(m) one-view steps on it."""
    return gain_per_step(b, m, n) / gain_per_step(b, 1, n)


def break_even(m: int, n: int, step_share: float) -> float:
    """The noise scale B above which m-view steps gain more per unit of CPU than one-view steps
    (E(m) = 1), inf when no B reaches it."""
    r, a = 1.0 - step_share, step_share
    # (1 + B (1 - 1/n)) (r + a) = (1 + B (1/m - 1/n)) (m r + a), solved for B
    lhs = (1.0 - 1.0 / n) * (r + a) - (1.0 / m - 1.0 / n) * (m * r + a)
    rhs = (m * r + a) - (r + a)
    return rhs / lhs if lhs > 0 else math.inf


def adam_metric(saved: Dict, spread: Spread) -> Grads:
    """Per group, lr / (sqrt(v_hat) + eps) of the Adam step the loop takes next, v_hat the
    checkpoint's second moment after one more step with a view's mean squared gradient, bias-
    corrected (flattened; groups the optimizer never stepped are left out). One step on: a
    Gaussian densification has just made has v = 0 in the checkpoint, and lr / eps there is
    not its step (Adam's first step on it moves it about 3 lr)."""
    metric = {}
    for k in spread.sum:
        opt = saved["optimizers"][k]
        group = opt["param_groups"][0]
        state = opt["state"].get(0)
        if not state or "exp_avg_sq" not in state:
            continue
        t = float(state["step"]) + 1.0
        b2 = group["betas"][1]
        v = b2 * state["exp_avg_sq"].double().reshape(-1) + (1.0 - b2) * spread.sumsq[k] / spread.n
        metric[k] = group["lr"] / ((v / (1.0 - b2 ** t)).sqrt() + group["eps"])
    return metric


def view_loss(params: Dict[str, torch.Tensor], cfg, parser, d, degree: int) -> torch.Tensor:
    """The loop's loss on one training item d, rendered from params."""
    colors, _, _ = bench_step_parts.render_view(params, cfg, parser, d, degree)
    return bench_step_parts.loop_loss(colors, d, cfg)


def view_gradients(splats: Dict[str, torch.Tensor], cfg, parser, degree: int) -> Iterable[Grads]:
    """Each training view's gradient of the loop's loss, one view at a time."""
    params = {k: v.detach().clone().requires_grad_(True) for k, v in splats.items()}
    views = common.Dataset(parser, "train")
    for i in range(len(views)):
        loss = view_loss(params, cfg, parser, views[i], degree)
        grads = torch.autograd.grad(loss, list(params.values()), allow_unused=True)
        yield {k: g for k, g in zip(params, grads) if g is not None}


def curvatures(grads: List[Grads], metric: Grads, loss_at: Callable[[Grads, float], float], m: int,
               samples: int, generator: torch.Generator, delta: float = 1.0) -> Tuple[float, float]:
    """The model's assumption checked on the loss itself: (along one-view steps, along m-view
    steps) the loss's second derivative along d = -P mean(g over S) per squared length
    |mean g|^2_P (equal where the curvature is isotropic in the metric P, as the gain formula
    takes it; negative where the loss is concave over such a step).
    Each is a ratio of sums over `samples` random view sets (m of them without replacement),
    the second derivative a central difference of loss_at(d, t) at t = -delta, 0, +delta (t = 1
    is the step the metric's optimizer takes: lr / (sqrt(v_hat) + eps) on the raw gradient)."""
    n = len(grads)
    keys = [k for k in metric if k in grads[0]]
    at_zero = loss_at({}, 0.0)

    def per_length(views: int) -> float:
        curve = length = 0.0
        for _ in range(samples):
            pick = torch.randperm(n, generator=generator)[:views].tolist()
            mean = {k: sum(grads[i][k].double() for i in pick) / views for k in keys}
            step = {k: -(metric[k].view_as(mean[k]) * mean[k]) for k in keys}
            curve += (loss_at(step, delta) + loss_at(step, -delta) - 2.0 * at_zero) / delta ** 2
            length += float(sum((metric[k].view_as(mean[k]) * mean[k] ** 2).sum() for k in keys))
        return curve / length
    return per_length(1), per_length(m)


def full_loss(splats: Dict[str, torch.Tensor], cfg, parser, degree: int) -> Callable[[Grads, float], float]:
    """loss_at(step, t): the loop's loss averaged over every training view (float64 sum) with the
    parameters moved by t x step."""
    views = common.Dataset(parser, "train")

    def loss_at(step: Grads, t: float) -> float:
        params = {k: (v + t * step[k].to(v.dtype).view_as(v) if k in step else v) for k, v in splats.items()}
        total = 0.0
        with torch.no_grad():
            for i in range(len(views)):
                total += float(view_loss(params, cfg, parser, views[i], degree))
        return total / len(views)
    return loss_at


def adam_cpu(splats: Dict[str, torch.Tensor], repeats: int) -> float:
    """CPU seconds of the loop's optimizer step on these parameters (one Adam per group, every
    group with a gradient; the median of `repeats` steps after one that sets Adam's state up):
    the part of a step done once whatever its views."""
    params = {k: torch.nn.Parameter(v.detach().clone()) for k, v in splats.items()}
    optimizers = [torch.optim.Adam([p], lr=0.0, eps=1e-15) for p in params.values()]
    times = []
    for _ in range(repeats + 1):
        for p in params.values():
            p.grad = torch.ones_like(p)
        c0 = time.process_time()
        for opt in optimizers:
            opt.step()
        times.append(time.process_time() - c0)
    return sorted(times[1:])[len(times[1:]) // 2]


def probe(ckpt: Path, parser, run_steps: int, repeats: int, curvature_samples: int = 0) -> Dict[str, float]:
    """One checkpoint's row (see the module docstring): its views' agreement and noise scale, the
    gains of multi-view steps that follow, Adam's share of a step, and with curvature_samples > 0
    the loss's curvature along four-view and one-view steps."""
    saved, splats, degree, cfg = bench_step_parts.load_model(ckpt)
    cfg.adjust_steps(run_steps)
    step = int(saved["step"])  # the 0-based index of the step the loop takes next
    in_use = min(step // cfg.sh_degree_interval, degree)
    spread = Spread()
    view_cpu = 0.0
    kept: List[Grads] = []
    c0 = time.process_time()
    for grads in view_gradients(splats, cfg, parser, in_use):  # the CPU of a view's render, loss and backward
        view_cpu += time.process_time() - c0
        spread.add(grads)
        if curvature_samples:
            kept.append({k: g.detach().float().clone() for k, g in grads.items()})
        c0 = time.process_time()
    groups = [k for k in splats if k in spread.sum and float(spread.sum[k].abs().sum()) > 0]
    spread.metric = adam_metric(saved, spread)
    weighted = [k for k in groups if k in spread.metric]  # the groups Adam has stepped
    step_cpu = adam_cpu(splats, repeats)
    share = step_cpu / (step_cpu + view_cpu / spread.n)
    n = spread.n
    b_adam = spread.noise_scale(weighted, weighted=True)
    rho = spread.agreement(weighted, weighted=True)
    row = {"checkpoint": str(ckpt), "step": step, "gaussians": len(splats["means"]), "views": n,
           "degree": in_use, "step_share": share, "b_adam": b_adam, "agreement": rho,
           "e2": efficiency(b_adam, 2, n, share), "e4": efficiency(b_adam, 4, n, share),
           "e4_linear": efficiency(b_adam, 4, n, 0.0), "break_even4": break_even(4, n, share),
           "pays_below4": pays_below(b_adam, 4, n)}
    row.update({"b_" + k: spread.noise_scale([k]) for k in groups})
    if curvature_samples:
        one, four = curvatures(kept, {k: spread.metric[k] for k in weighted}, full_loss(splats, cfg, parser, in_use), 4, curvature_samples,
                               torch.Generator().manual_seed(0))
        row["curvature1"], row["curvature4"] = one, four
        if one > 0 and four > 0:  # the optimal step's gain scales as 1 / curvature
            row["e4_linear_curved"] = row["e4_linear"] * one / four
            row["pays_below4_curved"] = row["pays_below4"] * one / four
    return row


GROUPS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def table(rows: List[Dict[str, float]]) -> str:
    def f(v):
        return "-" if v is None else ("inf" if math.isinf(v) else f"{v:.2f}")

    def c(v):
        return "-" if v is None else f"{v:.3g}"
    lines = ["| checkpoint | step | Gaussians | views | SH degree | views' agreement | B, Adam's metric | "
             + " | ".join(f"B {g}" for g in GROUPS)
             + " | per-step share of CPU | E(2) | E(4) | E(4), clock linear in views | B where E(4) = 1 "
             "| curvature per squared length along 1-view / 4-view steps | E(4), linear clock, those curvatures "
             "| a 4-view step pays below this many one-view steps' cost, C(4) | C(4), those curvatures |",
             "|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(GROUPS) + "---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['checkpoint']} | {r['step']} | {r['gaussians']} | {r['views']} | {r['degree']} | "
                     f"{r['agreement']:.3f} | {f(r['b_adam'])} | " + " | ".join(f(r.get("b_" + g)) for g in GROUPS)
                     + f" | {r['step_share']:.1%} | {r['e2']:.2f} | {r['e4']:.2f} | {r['e4_linear']:.2f} | "
                     f"{f(r['break_even4'])} | {c(r.get('curvature1'))} / {c(r.get('curvature4'))} | {f(r.get('e4_linear_curved'))} | "
                     f"{f(r['pays_below4'])} | {f(r.get('pays_below4_curved'))} |")
    return "\n".join(lines) + "\n"


def _run_steps(ap):
    ap.add_argument("--run-steps", type=int, required=True,
                    help="the run's --steps (the loop's SH degree schedule is scaled to it)")
    ap.add_argument("--curvature-samples", type=int, default=0, metavar="K",
                    help="also measure the loss's curvature along K random 4-view and K one-view steps "
                         "(4 K renders of every training view; default: 0, not measured)")


def _check(ap, args):
    if args.run_steps < 1:
        ap.error(f"--run-steps {args.run_steps}: expected the run's step count, at least 1")
    if args.curvature_samples < 0:
        ap.error(f"--curvature-samples {args.curvature_samples}: expected 0 (off) or a number of view sets")


def main(argv=None) -> str:
    args, parser = bench_step_parts.checkpoint_arguments(__doc__, argv, _run_steps, _check)
    rows = [probe(ckpt, parser, args.run_steps, args.repeats, args.curvature_samples) for ckpt in args.checkpoints]
    text = (f"Scene: {args.data}; every training view's gradient of the loop's loss at each checkpoint; "
            "B = S^2 / |G|^2 (McCandlish et al. 2018's simple noise scale); E(M): progress per unit of CPU "
            "of M-view steps over one-view steps with an optimal step size (1 = as good; below 1 the extra "
            "views cost more than the steps they replace); C(4): the cost, in one-view steps, below which a "
            "4-view step pays on any clock.\n\n" + table(rows))
    print(text)
    return text


if __name__ == "__main__":
    main()
