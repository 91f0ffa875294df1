"""How much an optimizer step gains from a second, third, fourth view: the views' gradient noise scale.

Issue 27 asked for a recipe with several views per step that beats one view per step at equal
CPU; none of nine did (docs/equal_compute.md, "Multi-view steps"). This probe measures why from
the gradients themselves, on a model at any point of a run, without training.

At a gsplat-loop checkpoint it computes every training view's gradient g_i of the loop's loss
(0.8 L1 + 0.2 (1 - SSIM)), their mean G (the whole training set's gradient) and their spread
S^2 = sum_i |g_i - G|^2 / (n - 1), the views' agreement (their mean pairwise inner product over
their mean squared norm: 1 if every view asked for the same step, 0 if each moves what no other
moves), and the simple noise scale of McCandlish et al.
(2018, "An Empirical Model of Large-Batch Training"): B = S^2 / |G|^2, in two metrics: each
parameter group's own (Euclidean), and the whole model's in the metric of the Adam step the
loop takes there (each coordinate weighted by lr / (sqrt(v_hat) + eps) from the checkpoint's
optimizer state: the step the loop would actually take).

With an optimal step size on a locally quadratic loss (curvature taken as isotropic in that
metric), a step over M views drawn without replacement from n gains

    dL(M) = dL_max / (1 + B (1/M - 1/n))

(the mean of M of n vectors has covariance S^2 (1/M - 1/n)). A step costs M r + a: r the
render, loss and backward of a view, a what a step does once (Adam; both timed here, one
thread: the views' gradients as they are taken, Adam's step on the model; the strategy's
statistics, also once per step, are left out). Per unit of CPU an M-view step therefore gains, relative to a one-view
step,

    E(M) = (1 + B (1 - 1/n)) (r + a) / ((1 + B (1/M - 1/n)) (M r + a))

On a clock linear in views (a = 0) E(M) < 1 exactly when B < n: the extra views of a step pay
only when the views disagree so much that the step's noise, not its count, limits progress (the
critical batch of McCandlish et al. is B); a per-step share a > 0 lowers that threshold. The
table prints B, E(2), E(4), E(4) with a = 0, and the B at which E(4) = 1.

    python examples/gsplat_loop/simple_trainer.py --data SCENE --steps 3000 --threads 1 --save-steps 300 1000 2000 3000 --out out/g
    python benchmarks/probe_view_noise.py out/g/ckpt_300.pt out/g/ckpt_1000.pt ... --data SCENE --run-steps 3000

--repeats is the number of timed Adam steps. --run-steps is the run's --steps: the loop raises the SH degree on a schedule scaled to it, and
the gradients are taken at the degree the loop renders with at the checkpoint's step.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import bench_step_parts  # noqa: E402
import common  # noqa: E402
from mvgs_plugin.losses import ssim  # noqa: E402

Grads = Dict[str, torch.Tensor]


class Spread:
    """Running sums of per-view gradients, each group flattened (float64): their mean and spread,
    in the Euclidean metric and, given a diagonal metric per group, in that one (|x|^2_P =
    sum_j P_j x_j^2)."""

    def __init__(self, metric: Optional[Grads] = None):
        self.metric = metric
        self.n = 0
        self.sum: Grads = {}
        self.sq: Dict[str, float] = {}
        self.sq_p: Dict[str, float] = {}

    def add(self, grads: Grads) -> None:
        for k, g in grads.items():
            g = g.detach().double().reshape(-1)
            self.sum[k] = self.sum[k] + g if k in self.sum else g.clone()
            self.sq[k] = self.sq.get(k, 0.0) + float(g @ g)
            if self.metric is not None and k in self.metric:
                self.sq_p[k] = self.sq_p.get(k, 0.0) + float((self.metric[k] * g * g).sum())
        self.n += 1

    def _terms(self, keys: Iterable[str], weighted: bool):
        """(|G|^2, S^2) over the groups `keys`."""
        n = self.n
        mean_sq = spread = 0.0
        for k in keys:
            mean = self.sum[k] / n
            m2 = float((self.metric[k] * mean * mean).sum()) if weighted else float(mean @ mean)
            s2 = self.sq_p[k] if weighted else self.sq[k]
            mean_sq += m2
            spread += (s2 - n * m2) / (n - 1)
        return mean_sq, max(spread, 0.0)

    def agreement(self, keys: Iterable[str], weighted: bool = False) -> float:
        """The views' mean pairwise inner product over their mean squared norm, sum_{i != j} g_i . g_j
        / ((n - 1) sum_i |g_i|^2): 1 when every view's gradient is the same, 0 when they are
        orthogonal (each view moves what no other moves), negative when they pull apart."""
        if self.n < 2:
            raise ValueError(f"an agreement needs at least 2 views' gradients, got {self.n}")
        n = self.n
        mean_sq, _ = self._terms(keys, weighted)
        sq = sum((self.sq_p if weighted else self.sq)[k] for k in keys)
        return (n * n * mean_sq - sq) / ((n - 1) * sq)

    def noise_scale(self, keys: Iterable[str], weighted: bool = False) -> float:
        """B = S^2 / |G|^2 over the groups `keys` (inf when the mean gradient is zero)."""
        if self.n < 2:
            raise ValueError(f"a noise scale needs at least 2 views' gradients, got {self.n}")
        mean_sq, spread = self._terms(keys, weighted)
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
    return gain_per_step(b, m, n) / gain_per_step(b, 1, n) * (r + a) / (m * r + a)


def break_even(m: int, n: int, step_share: float) -> float:
    """The noise scale B above which m-view steps gain more per unit of CPU than one-view steps
    (E(m) = 1), inf when no B reaches it."""
    r, a = 1.0 - step_share, step_share
    # (1 + B (1 - 1/n)) (r + a) = (1 + B (1/m - 1/n)) (m r + a), solved for B
    lhs = (1.0 - 1.0 / n) * (r + a) - (1.0 / m - 1.0 / n) * (m * r + a)
    rhs = (m * r + a) - (r + a)
    return rhs / lhs if lhs > 0 else math.inf


def adam_metric(saved: Dict, names: Iterable[str]) -> Grads:
    """Per group, lr / (sqrt(v_hat) + eps) from the checkpoint's Adam states (flattened; groups
    the optimizer never stepped are left out)."""
    metric = {}
    for k in names:
        opt = saved["optimizers"][k]
        group = opt["param_groups"][0]
        state = opt["state"].get(0)
        if not state or "exp_avg_sq" not in state:
            continue
        t = float(state["step"])
        v_hat = state["exp_avg_sq"].double() / (1.0 - group["betas"][1] ** t)
        metric[k] = (group["lr"] / (v_hat.sqrt() + group["eps"])).reshape(-1)
    return metric


def view_gradients(splats: Dict[str, torch.Tensor], cfg, parser, degree: int) -> Iterable[Grads]:
    """Each training view's gradient of the loop's loss, one view at a time."""
    params = {k: v.detach().clone().requires_grad_(True) for k, v in splats.items()}
    views = common.Dataset(parser, "train")
    for i in range(len(views)):
        d = views[i]
        pixels = d["image"][None] / 255.0
        colors, _, _ = bench_step_parts.render_view(params, cfg, parser, d, degree)
        if "mask" in d:
            pixels = pixels * d["mask"][None, ..., None]
            colors = colors * d["mask"][None, ..., None]
        loss = (1.0 - cfg.ssim_lambda) * F.l1_loss(colors, pixels) + cfg.ssim_lambda * (
            1.0 - ssim(colors, pixels, padding="valid"))
        grads = torch.autograd.grad(loss, list(params.values()), allow_unused=True)
        yield {k: g for k, g in zip(params, grads) if g is not None}


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


def probe(ckpt: Path, parser, run_steps: int, repeats: int,
          gradients: Callable = view_gradients) -> Dict[str, float]:
    saved, splats, degree, cfg = bench_step_parts.load_model(ckpt)
    cfg.adjust_steps(run_steps)
    step = int(saved["step"])  # the 0-based index of the step the loop takes next
    in_use = min(step // cfg.sh_degree_interval, degree)
    spread = Spread(adam_metric(saved, splats))
    view_cpu = 0.0
    views = iter(gradients(splats, cfg, parser, in_use))
    while True:
        c0 = time.process_time()
        grads = next(views, None)
        if grads is None:
            break
        view_cpu += time.process_time() - c0
        spread.add(grads)
    groups = [k for k in splats if k in spread.sum and float(spread.sum[k].abs().sum()) > 0]
    step_cpu = adam_cpu(splats, repeats)
    share = step_cpu / (step_cpu + view_cpu / spread.n)
    n = spread.n
    b_adam = spread.noise_scale([k for k in groups if k in spread.metric], weighted=True)
    rho = spread.agreement([k for k in groups if k in spread.metric], weighted=True)
    row = {"checkpoint": str(ckpt), "step": step, "gaussians": len(splats["means"]), "views": n,
           "degree": in_use, "step_share": share, "b_adam": b_adam, "agreement": rho,
           "e2": efficiency(b_adam, 2, n, share), "e4": efficiency(b_adam, 4, n, share),
           "e4_linear": efficiency(b_adam, 4, n, 0.0), "break_even4": break_even(4, n, share)}
    row.update({"b_" + k: spread.noise_scale([k]) for k in groups})
    return row


GROUPS = ("means", "scales", "quats", "opacities", "sh0", "shN")


def table(rows: List[Dict[str, float]]) -> str:
    def f(v):
        return "-" if v is None else ("inf" if math.isinf(v) else f"{v:.2f}")
    lines = ["| checkpoint | step | Gaussians | views | SH degree | views' agreement | B, Adam's metric | "
             + " | ".join(f"B {g}" for g in GROUPS)
             + " | per-step share of CPU | E(2) | E(4) | E(4), clock linear in views | B where E(4) = 1 |",
             "|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(GROUPS) + "---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['checkpoint']} | {r['step']} | {r['gaussians']} | {r['views']} | {r['degree']} | "
                     f"{r['agreement']:.3f} | {f(r['b_adam'])} | " + " | ".join(f(r.get("b_" + g)) for g in GROUPS)
                     + f" | {r['step_share']:.1%} | {r['e2']:.2f} | {r['e4']:.2f} | {r['e4_linear']:.2f} | "
                     f"{f(r['break_even4'])} |")
    return "\n".join(lines) + "\n"


def _run_steps(ap):
    ap.add_argument("--run-steps", type=int, required=True,
                    help="the run's --steps (the loop's SH degree schedule is scaled to it)")


def _check(ap, args):
    if args.run_steps < 1:
        ap.error(f"--run-steps {args.run_steps}: expected the run's step count, at least 1")


def main(argv=None) -> str:
    args, parser = bench_step_parts.checkpoint_arguments(__doc__, argv, _run_steps, _check)
    rows = [probe(ckpt, parser, args.run_steps, args.repeats) for ckpt in args.checkpoints]
    text = (f"Scene: {args.data}; every training view's gradient of the loop's loss at each checkpoint; "
            "B = S^2 / |G|^2 (McCandlish et al. 2018's simple noise scale); E(M): progress per unit of CPU "
            "of M-view steps over one-view steps with an optimal step size (1 = as good; below 1 the extra "
            "views cost more than the steps they replace).\n\n" + table(rows))
    print(text)
    return text


if __name__ == "__main__":
    main()
