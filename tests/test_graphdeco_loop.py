"""The graphdeco-shaped recipe (examples/graphdeco_loop): a GaussianModel with the original 3DGS
interface trained by a train.py-shaped loop with MVGS.

Checked against computations of their own: the render's viewspace gradient is the rasterizer's
pixel gradient in NDC units; densify_and_prune grows and prunes the counts the 3DGS rules give
by hand; the loop densifies, resets and hands over stages on the schedule's clock, clones from
cross-ray boxes, and resumes from a checkpoint to the same tensors as an uninterrupted run; under a
Gaussian budget the rows that grow are those of a ranking worked out row by row, and a run never
holds more than the budget nor more than its growth schedule, worked out by hand, allows.
"""

import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from mvgs_plugin import CRDConfig
from mvgs_plugin.camera import stack_cameras
from mvgs_plugin.data import load_scene
from mvgs_plugin.reference_renderer import rasterization

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples" / "graphdeco_loop"))
import gaussian_model  # noqa: E402
import train_mvgs  # noqa: E402

FORWARD = ROOT / "tests" / "data" / "forward64"


@pytest.fixture(scope="module")
def scene():
    return load_scene(FORWARD)


def model(scene, steps=100):
    torch.manual_seed(0)
    g = gaussian_model.GaussianModel(sh_degree=1)
    g.create_from_pcd(scene.points.xyz, scene.points.rgb, scene.extent)
    g.training_setup(steps)
    return g


def test_viewspace_gradient_is_the_pixel_gradient_in_ndc(scene):
    g = model(scene)
    cam = scene.train_cameras[3]
    bg = torch.zeros(3)
    target = scene.image(cam)
    pkg = gaussian_model.render(cam, g, bg)
    ((pkg["render"].permute(1, 2, 0) - target) ** 2).mean().backward()
    viewmats, Ks = stack_cameras([cam])
    img, _, meta = rasterization(g.get_xyz, g.get_rotation, g.get_scaling, g.get_opacity.squeeze(-1),
                                 g.get_features, viewmats, Ks, cam.width, cam.height, sh_degree=0,
                                 backgrounds=bg[None])
    meta["means2d"].retain_grad()
    ((img[0] - target) ** 2).mean().backward()
    expected = meta["means2d"].grad[0] * torch.tensor([cam.width / 2.0, cam.height / 2.0])
    torch.testing.assert_close(pkg["viewspace_points"].grad[:, :2], expected)
    assert torch.equal(pkg["viewspace_points"].grad[:, 2], torch.zeros(len(expected)))
    assert expected.abs().sum() > 0
    visible = (meta["radii"][0] > 0).all(-1)
    assert torch.equal(pkg["visibility_filter"], visible)


def test_densify_and_prune_follows_the_3dgs_rules(scene):
    g = model(scene)
    n = g.get_xyz.shape[0]
    gen = torch.Generator().manual_seed(2)
    g.xyz_gradient_accum = torch.rand(n, 1, generator=gen) * 4e-4
    g.denom = torch.ones(n, 1)
    g.denom[:10] = 0  # never seen: 0 / 0, which the rules read as 0
    g.xyz_gradient_accum[:10] = 0
    with torch.no_grad():
        g._opacity[-20:] = -8.0  # sigmoid < 0.005: pruned
        g._scaling[: n // 2] = math.log(1e-3)  # small (<= 0.01 extent): cloned, the rest split
    extent, beta = scene.extent, 2e-4
    grad = (g.xyz_gradient_accum / g.denom).nan_to_num(0.0).squeeze(-1)
    grad[:10] = 0
    small = g.get_scaling.max(dim=1).values <= 0.01 * extent
    clone = int(((grad >= beta) & small).sum())
    split = int(((grad >= beta) & ~small).sum())
    low = g.get_opacity.squeeze(-1) < 0.005
    # pruned after growth: low-opacity originals that were not split, plus clones of low-opacity ones,
    # plus the 2 children of every low-opacity split parent
    pruned = int((low & ~((grad >= beta) & ~small)).sum()) + int((low & (grad >= beta) & small).sum()) \
        + 2 * int((low & (grad >= beta) & ~small).sum())
    assert clone > 0 and split > 0
    g.densify_and_prune(beta, 0.005, extent, None)
    assert g.get_xyz.shape[0] == n + clone + split - pruned
    for name, group in zip(["xyz"], g.optimizer.param_groups):
        assert group["params"][0] is g._xyz
    assert g.xyz_gradient_accum.shape == (g.get_xyz.shape[0], 1) and float(g.xyz_gradient_accum.abs().sum()) == 0


@pytest.mark.parametrize("preset,views", [("default", None), pytest.param("multiview", 4, marks=pytest.mark.slow)])
def test_loop_trains_through_every_phase_and_resumes_exactly(tmp_path, scene, preset, views):
    steps = 300
    extra = {"crd": CRDConfig(enabled=True)} if preset == "multiview" else {}  # CRD is on in paper() only
    extra["min_densify_per_reset"] = 10  # resets 10 densifications apart: a 300-step run then resets
    # the checkpoint falls inside the densification window (steps 60-110 here) and before the opacity
    # reset at 100, so the resumed part densifies from restored statistics and resets too
    full, log = train_mvgs.training(scene, steps, preset, checkpoint_iterations=(85,), out=tmp_path, views=views,
                                    **extra)
    cfg = train_mvgs.MVGSConfig.from_preset(preset, **extra).with_total_steps(steps)
    assert len(cfg.stages) > 1  # pyramid hand-offs happen
    assert len(log["densify"]) >= 3 and log["reset"], log
    assert full.get_xyz.shape[0] != len(scene.points)
    if preset == "multiview":
        assert log["from_boxes"] > 0  # cross-ray boxes reached the graphdeco model
    resumed, log2 = train_mvgs.training(scene, steps, preset, start_checkpoint=tmp_path / "chkpnt85.pth",
                                        out=tmp_path / "b", views=views, **extra)
    assert log2["densify"] == [s for s in log["densify"] if s > 85] and len(log2["densify"]) >= 2
    assert log2["reset"] == [s for s in log["reset"] if s > 85] != []
    for a, b in zip(full.capture()[1:7], resumed.capture()[1:7]):
        assert torch.equal(a, b)
    assert math.isfinite(train_mvgs.evaluate(resumed, scene))


def budget_ctx(scene, cap, beta=2e-4, rank_by="consistency", prune_large=False):
    """The fields of a DensifyContext limit_growth and clone_in_boxes read."""
    return SimpleNamespace(max_primitives=cap, grad_threshold=beta, scene_extent=scene.extent,
                           scene_center=scene.center, prune_large=prune_large, rank_by=rank_by,
                           boxes=None, max_new_from_boxes=None)


def visits_of(n, seed):
    """Per row, a list of per-visit screen-space gradient norms (0 to 5 visits, some rows with
    one large visit and some with many even ones), and the sums a graphdeco model keeps of them."""
    gen = torch.Generator().manual_seed(seed)
    lists = []
    for i in range(n):
        k = int(torch.randint(0, 6, (1,), generator=gen))
        g = (torch.rand(k, generator=gen, dtype=torch.float64) * 6e-4).tolist()
        if i % 7 == 0 and k:  # one view holds it all
            g = [0.0] * (k - 1) + [sum(g)]
        lists.append(g)
    accum = torch.tensor([sum(g) for g in lists], dtype=torch.float32)[:, None]
    denom = torch.tensor([len(g) for g in lists], dtype=torch.float32)[:, None]
    sq = torch.tensor([sum(x * x for x in g) for g in lists], dtype=torch.float32)
    return lists, accum, denom, sq


def hand_ranked(lists, eligible, room, beta, far=None):
    """The rows that may grow, worked out one row at a time: mean gradient >= beta, score =
    mean x (sum g)^2 / (n sum g^2), best first (far rows after all others), as many as `room`."""
    rows = []
    for i, g in enumerate(lists):
        if not g or not eligible[i]:
            continue
        s, n = sum(g), len(g)
        mean = float(torch.tensor(s / n, dtype=torch.float32))  # the model's float32 mean
        if mean < beta:
            continue
        sq = sum(x * x for x in g)
        score = mean * min(1.0, s * s / (n * sq)) if sq > 0 else 0.0
        rows.append((bool(far[i]) if far is not None else False, -score, i))
    return {i for _, _, i in sorted(rows)[:room]}


@pytest.mark.parametrize("rank_by", ["consistency", "gradient"])
def test_limit_growth_keeps_the_best_scored_candidates_that_fit_the_budget(scene, rank_by):
    g = model(scene)
    n = g.get_xyz.shape[0]
    lists, g.xyz_gradient_accum, g.denom, sq = visits_of(n, seed=3)
    with torch.no_grad():
        g._opacity[-40:] = -8.0  # pruned by densify_and_prune: they leave room and grow nothing
        g._scaling[: n // 2] = math.log(1e-3)  # clones; the rest split
    kept_rows = n - 40
    cap = kept_rows + 150
    ctx = budget_ctx(scene, cap, rank_by=rank_by)
    eligible = [i < n - 40 for i in range(n)]
    if rank_by == "gradient":  # the mean alone: the hand ranking with every visit list made even
        lists = [[sum(v) / len(v)] * len(v) if v else v for v in lists]
    expected = hand_ranked(lists, eligible, 150, 2e-4)
    candidates = sum(1 for i, v in enumerate(lists) if v and eligible[i] and sum(v) / len(v) >= 2e-4)
    assert candidates > 300  # the budget binds: half of them at most may grow
    dropped = train_mvgs.limit_growth(g, sq, ctx, far_distance=None, inside_first=False)
    grows = set((g.xyz_gradient_accum.squeeze(-1) / g.denom.squeeze(-1).clamp_min(1) >= 2e-4).nonzero().squeeze(1)
                .tolist()) - set(range(n - 40, n))
    assert grows == expected and dropped == candidates - 150
    g.densify_and_prune(2e-4, train_mvgs.MIN_OPACITY, scene.extent, None)
    assert g.get_xyz.shape[0] == cap  # each clone or split adds one row; the pruned rows freed theirs


def test_limit_growth_grows_the_far_background_last(scene):
    g = model(scene)
    n = g.get_xyz.shape[0]
    lists, g.xyz_gradient_accum, g.denom, sq = visits_of(n, seed=4)
    xyz = g.get_xyz.detach()
    d = torch.linalg.vector_norm(xyz.double() - scene.center, dim=1)
    far_distance = float(d.max())
    far = (d >= 0.75 * far_distance).tolist()
    assert 0 < sum(far) < n
    expected = hand_ranked(lists, [True] * n, 200, 2e-4, far=far)
    ctx = budget_ctx(scene, n + 200)
    train_mvgs.limit_growth(g, sq, ctx, far_distance=far_distance, inside_first=True)
    grows = set((g.xyz_gradient_accum.squeeze(-1) / g.denom.squeeze(-1).clamp_min(1) >= 2e-4).nonzero().squeeze(1)
                .tolist())
    assert grows == expected
    inside = [i for i in range(n) if not far[i] and lists[i] and sum(lists[i]) / len(lists[i]) >= 2e-4]
    assert len(inside) >= 200 and not any(far[i] for i in grows)  # every place went inside the far line


def test_the_loop_refuses_a_cut_of_the_faintest_it_has_not(scene):
    """The default preset's prune_faint is dropped (densify_and_prune has no such cut: its plan's
    step would run as one more densification after the window); asked for by name, refused."""
    with pytest.raises(ValueError, match=r"prune_faint=0.01: this loop's densify_and_prune has no cut"):
        train_mvgs.training(scene, 200, preset="default", prune_faint=0.01)


def test_without_a_budget_limit_growth_changes_nothing(scene):
    g = model(scene)
    n = g.get_xyz.shape[0]
    _, g.xyz_gradient_accum, g.denom, sq = visits_of(n, seed=5)
    before = g.xyz_gradient_accum.clone()
    assert train_mvgs.limit_growth(g, sq, budget_ctx(scene, None), None, False) == 0
    assert torch.equal(g.xyz_gradient_accum, before)


def test_a_budget_holds_through_every_phase_and_resumes_exactly(tmp_path, scene):
    steps, n_budget = 300, 800
    # half the budget for the initial points (cut from 2653), growth to the budget after: both
    # halves of the rule run; the pyramid kept on this forward rig, so a stage hands over too; a
    # lower threshold than the default's, so that the candidates outnumber the room
    extra = {"min_densify_per_reset": 10, "max_gaussians": n_budget, "budget_initial_share": 0.5,
             "forward_rig": "pyramid", "grad_threshold": 1e-4}
    full, log = train_mvgs.training(scene, steps, "default", checkpoint_iterations=(85,), out=tmp_path, **extra)
    cfg = train_mvgs.MVGSConfig.from_preset("default", **extra).with_total_steps(steps).for_scene(scene)
    assert len(cfg.stages) > 1 and len(log["densify"]) >= 3 and log["reset"], log
    counts = log["counts"]
    assert counts[0] == n_budget // 2  # the cut, before the first step
    assert max(counts) <= n_budget and log["dropped_by_budget"] > 0  # the budget bound
    n0, lo, hi = n_budget // 2, cfg.densify_from, cfg.densify_until - cfg.densify_every
    for step in log["densify"]:  # the growth schedule, worked out by hand: n0 + (N - n0)(1 - (1 - x)^2)
        x = min(1.0, max(0.0, (log["clocks"][step - 1] - lo) / (hi - lo)))
        assert counts[step - 1] <= n0 + (n_budget - n0) * (1 - (1 - x) ** 2) + 1e-9
    assert counts[-1] >= 0.9 * n_budget  # it grew to the budget
    resumed, log2 = train_mvgs.training(scene, steps, "default", start_checkpoint=tmp_path / "chkpnt85.pth",
                                        out=tmp_path / "b", **extra)
    assert log2["densify"] == [s for s in log["densify"] if s > 85] and len(log2["densify"]) >= 2
    assert max(log2["counts"]) <= n_budget
    for a, b in zip(full.capture()[1:7], resumed.capture()[1:7]):
        assert torch.equal(a, b)
    assert math.isfinite(train_mvgs.evaluate(resumed, scene))


def test_the_benchmark_table_budgets_a_share_of_the_baselines_count(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_gsplat_loop

    text = bench_gsplat_loop.main(["--graphdeco-budget", "0.25", "--steps", "80", "--presets", "default",
                                   "--data", str(FORWARD), "--out", str(tmp_path), "--parallel", "2",
                                   "--threshold-width", "800", "--package-rules", "--opacity-lr", "0.05"])
    free = json.loads((tmp_path / "graphdeco_baseline" / "metrics.json").read_text())
    n = round(0.25 * free["num_gaussians"])
    rows = [line.split("|")[1:-1] for line in text.splitlines() if line.startswith("| baseline") or line.startswith("| default")]
    assert [r[0].strip() for r in rows] == ["baseline", "baseline", "default", "default"]
    for kind, r in zip(["", "_budget"] * 2, rows):
        m = json.loads((tmp_path / f"graphdeco_{r[0].strip()}{kind}" / "metrics.json").read_text())
        assert r[1].strip() == (str(n) if kind else "-") and m["max_gaussians"] == (n if kind else None)
        assert float(r[2]) == pytest.approx(m["psnr"], abs=0.006)
        assert float(r[3]) == pytest.approx(m["psnr"] - free["psnr"], abs=0.011)
        assert int(r[4]) == m["num_gaussians"] and int(r[5]) == m["most_held"] and m["threshold_width"] == 800
        assert (m["background_points"], m["world_size_rule"], m["opacity_reset_scope"]) == (2000, "distance", "inside")
        assert m["opacity_lr"] == 0.05
        if kind:
            assert m["most_held"] <= n < free["num_gaussians"]


def test_background_points_reach_the_loops_initial_model(tmp_path):
    """--background-points N gives the loop the scene's points plus the far background's shell, as
    load_scene draws it for that rig: on the bundled 360° rig the model starts with every one of
    them (two steps: no densification yet), on the forward-facing rig with none."""
    import subprocess

    bundled = ROOT / "examples" / "scenes" / "tabletop"
    for data, n in ((bundled, 300), (FORWARD, 300), (bundled, 0)):
        out = tmp_path / f"{data.name}_{n}"
        subprocess.run([sys.executable, str(ROOT / "examples" / "graphdeco_loop" / "train_mvgs.py"), "--data", str(data),
                        "--steps", "2", "--threads", "1", "--background-points", str(n), "--out", str(out)],
                       check=True, capture_output=True, text=True)
        m = json.loads((out / "metrics.json").read_text())
        plain = len(load_scene(data).points)
        expected = len(load_scene(data, background_points=n).points)
        assert m["background_points"] == n and m["densify_calls"] == 0
        assert m["num_gaussians"] == expected
        assert (expected > plain) == (data == bundled and n > 0)


def test_the_command_line_resumes_a_checkpoint_and_reports_the_budget_it_ran(tmp_path):
    """--checkpoint-iterations / --start-checkpoint (train.py's flags): a run of 240 steps on the
    64 px forward scene (four densifications, an opacity reset at 50), checkpointed at 120 and
    resumed from it in a new process, ends with the model the uninterrupted run ends with; and
    metrics.json gives compact's budget from the data (the forward rig's pixels / 213, which the
    flag does not say) and the preset's threshold width."""
    import subprocess

    def run(out, *flags):
        subprocess.run([sys.executable, str(ROOT / "examples" / "graphdeco_loop" / "train_mvgs.py"), "--data", str(FORWARD),
                        "--steps", "240", "--threads", "1", "--out", str(out), *flags], check=True, capture_output=True, text=True)
        return json.loads((out / "metrics.json").read_text())

    whole = run(tmp_path / "whole", "--checkpoint-iterations", "120")
    assert (tmp_path / "whole" / "chkpnt120.pth").is_file() and whole["densify_calls"] > 0 and whole["resets"]
    resumed = run(tmp_path / "resumed", "--start-checkpoint", str(tmp_path / "whole" / "chkpnt120.pth"))
    assert resumed["psnr"] == whole["psnr"] and resumed["num_gaussians"] == whole["num_gaussians"]
    assert resumed["densify_calls"] < whole["densify_calls"]  # it did only the second half
    # compact on the bundled 360-degree rig (none on a forward one): 48 views of 128 x 128 pixels / 213
    out = tmp_path / "compact"
    subprocess.run([sys.executable, str(ROOT / "examples" / "graphdeco_loop" / "train_mvgs.py"), "--preset", "compact",
                    "--steps", "2", "--threads", "1", "--out", str(out)], check=True, capture_output=True, text=True)
    compact = json.loads((out / "metrics.json").read_text())
    assert compact["max_gaussians"] == 48 * 128 * 128 // 213 and compact["threshold_width"] == 800.0
    bad = subprocess.run([sys.executable, str(ROOT / "examples" / "graphdeco_loop" / "train_mvgs.py"),
                          "--start-checkpoint", str(tmp_path / "none.pth")], capture_output=True, text=True)
    assert bad.returncode == 2 and "--start-checkpoint" in bad.stderr and "no such file" in bad.stderr


def rules_ctx(scene, prune_large=True):
    return SimpleNamespace(grad_threshold=2e-4, scene_extent=scene.extent, scene_center=scene.center,
                           prune_large=prune_large, max_primitives=None, boxes=None, max_new_from_boxes=None)


def placed(scene, rows):
    """A model on `scene` whose first len(rows) Gaussians sit at distance d from the scene centre
    (along +x) with largest scale s, rows = [(d, s), ...] in units of the extent; no gradients."""
    g = model(scene)
    e, c = scene.extent, scene.center.float()
    with torch.no_grad():
        for i, (d, s) in enumerate(rows):
            g._xyz[i] = c + torch.tensor([d * e, 0.0, 0.0])
            g._scaling[i] = torch.tensor([math.log(s * e), math.log(1e-3 * e), math.log(1e-3 * e)])
        g._opacity[:] = 0.0  # sigmoid 0.5: none pruned by opacity
    g.xyz_gradient_accum = torch.zeros(g.get_xyz.shape[0], 1)
    g.denom = torch.ones(g.get_xyz.shape[0], 1)
    return g


def test_the_size_rules_by_extent_and_by_distance(scene):
    """too_large against limits worked out by hand: 0.1 x extent everywhere (3DGS), or 0.1 x
    max(extent, d); densify_and_prune with each rule removes exactly those rows."""
    rows = [(0.2, 0.05), (0.2, 0.2), (3.0, 0.2), (3.0, 0.35), (10.0, 0.9), (10.0, 1.1), (0.9, 0.09), (0.9, 0.11)]
    by_extent = [s > 0.1 for _, s in rows]
    by_distance = [s > 0.1 * max(1.0, d) for d, s in rows]
    assert by_extent != by_distance
    for rule, expected in (("extent", by_extent), ("distance", by_distance)):
        g = placed(scene, rows)
        mask = train_mvgs.too_large(g, rules_ctx(scene), rule)
        assert mask[:len(rows)].tolist() == expected, rule
        n, rest = g.get_xyz.shape[0], int(mask[len(rows):].sum())
        kept_xyz = g.get_xyz.detach()[~mask].clone()
        # the scene's own points: the rows the extent rule prunes and the distance rule keeps, one by one
        e, c = scene.extent, scene.center
        spared = sum(1 for x, s in zip(g.get_xyz.detach().double()[len(rows):], g.get_scaling.detach().double()[len(rows):])
                     if 0.1 * e < float(s.max()) <= 0.1 * max(e, float(torch.dist(x, c))))
        kept = train_mvgs.densify_and_prune(g, rules_ctx(scene), rule)
        assert g.get_xyz.shape[0] == n - sum(expected) - rest
        torch.testing.assert_close(g.get_xyz.detach(), kept_xyz)
        assert kept == (sum(a and not b for a, b in zip(by_extent, by_distance)) + spared if rule == "distance" else 0)
        # before the first reset (prune_large False) neither rule prunes by size
        g = placed(scene, rows)
        train_mvgs.densify_and_prune(g, rules_ctx(scene, prune_large=False), rule)
        assert g.get_xyz.shape[0] == n


def test_a_reset_inside_spares_the_far_background(scene):
    """reset_opacity "inside": rows at 3/4 of far_distance or more from the centre keep their
    opacity, every other row is capped at 0.01, the opacity group's Adam moments are zeroed; "all"
    caps every row, as the model's own reset."""
    g = placed(scene, [(1.0, 0.01), (2.9, 0.01), (3.1, 0.01), (4.0, 0.01)])
    far_distance = 4.0 * scene.extent
    with torch.no_grad():
        g._opacity[:4] = torch.tensor([[2.0], [1.0], [0.5], [-1.0]])
        g._opacity[4:] = -7.0  # sigmoid ~ 0.0009: below the cap already
    g._opacity.grad = torch.ones_like(g._opacity)
    g.optimizer.step()
    before = torch.sigmoid(g._opacity.detach()).squeeze(-1)
    d = torch.linalg.vector_norm(g.get_xyz.detach().double() - scene.center, dim=1)
    spared_by_hand = d >= 0.75 * far_distance
    assert spared_by_hand[:4].tolist() == [False, False, True, True]
    n = train_mvgs.reset_opacity(g, "inside", scene.center, far_distance)
    after = g.get_opacity.detach().squeeze(-1)
    assert n == int(spared_by_hand.sum())
    torch.testing.assert_close(after[spared_by_hand], before[spared_by_hand])
    torch.testing.assert_close(after[~spared_by_hand], before[~spared_by_hand].clamp_max(0.01))
    state = g.optimizer.state[g._opacity]
    assert float(state["exp_avg"].abs().sum()) == 0 and float(state["exp_avg_sq"].abs().sum()) == 0
    assert train_mvgs.reset_opacity(g, "all", scene.center, far_distance) == 0
    assert float(g.get_opacity.detach().max()) <= 0.01 + 1e-6


def test_the_loop_with_the_package_rules_through_every_phase_and_a_resume(tmp_path):
    """The bundled 360° scene with a background shell, the distance size rule and resets that
    spare the far background: a 300-step run densifies, prunes large Gaussians, resets (sparing
    the shell), hands over a pyramid stage, and resumes from a checkpoint inside the window to the
    same tensors."""
    from mvgs_plugin.config import Stage

    scene = load_scene(ROOT / "examples" / "scenes" / "tabletop", background_points=2000)
    half = tuple(Stage(st.factor * 2, st.views, st.steps) for st in train_mvgs.MVGSConfig.from_preset("default").stages)
    steps, extra = 300, {"min_densify_per_reset": 10, "world_size_rule": "distance", "reset_scope": "inside",
                         "stages": half, "opacity_lr": 0.05}  # at 64 px, as --resolution-scale 2
    full, log = train_mvgs.training(scene, steps, "default", checkpoint_iterations=(85,), out=tmp_path, **extra)
    assert len(half) > 1
    assert len(log["densify"]) >= 3 and log["reset"] and log["spared_by_reset"] > 0, log
    assert log["kept_by_distance"] > 0
    resumed, log2 = train_mvgs.training(scene, steps, "default", start_checkpoint=tmp_path / "chkpnt85.pth",
                                        out=tmp_path / "b", **extra)
    assert log2["reset"] == [s for s in log["reset"] if s > 85] != []
    for a, b in zip(full.capture()[1:7], resumed.capture()[1:7]):
        assert torch.equal(a, b)
    for g in (full, resumed):  # --opacity-lr reaches Adam, and a resume keeps it
        lrs = {group["name"]: group["lr"] for group in g.optimizer.param_groups}
        assert lrs["opacity"] == 0.05 and lrs["f_dc"] == 2.5e-3
    assert math.isfinite(train_mvgs.evaluate(resumed, scene))
    with pytest.raises(ValueError, match=r"opacity_lr must be a finite number > 0, got -0\.1"):
        train_mvgs.training(scene, steps, "default", opacity_lr=-0.1)
    with pytest.raises(ValueError, match="world_size_rule"):
        train_mvgs.training(scene, steps, "default", world_size_rule="far")


def graphdeco_ssim(img1, img2):
    """3DGS's SSIM as its utils/loss_utils.py computes it, written out here: [3, H, W] images, an
    11-tap Gaussian window (sigma 1.5) applied as one 2D kernel per channel with zero padding of
    5 pixels, C1 = 0.01^2, C2 = 0.03^2, the map's mean."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-x * x / (2 * 1.5 ** 2))
    g = g / g.sum()
    window = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11).to(img1.dtype)
    conv = lambda t: torch.nn.functional.conv2d(t[None], window, padding=5, groups=3)[0]  # noqa: E731
    mu1, mu2 = conv(img1), conv(img2)
    s11, s22, s12 = conv(img1 * img1) - mu1 ** 2, conv(img2 * img2) - mu2 ** 2, conv(img1 * img2) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))).mean()


@pytest.mark.filterwarnings("ignore:this run densifies at no step")
def test_the_loops_loss_is_3dgs_with_its_zero_padded_ssim(scene, monkeypatch):
    """Every view's SSIM term is 3DGS's (zero padding at the border, where scikit-image's "valid"
    SSIM leaves out 5 pixels a side): the values the loop's SSIM gave, against the formula written
    out above on the same images."""
    seen = []

    def recording_ssim(img1, img2, **kw):
        value = train_mvgs_ssim(img1, img2, **kw)
        seen.append((img1.detach().clone(), img2.detach().clone(), value.detach()))
        return value

    train_mvgs_ssim = train_mvgs.ssim
    monkeypatch.setattr(train_mvgs, "ssim", recording_ssim)
    train_mvgs.training(scene, 3, "baseline")
    assert len(seen) == 3
    for img1, img2, value in seen:
        expected = graphdeco_ssim(img1.permute(2, 0, 1).double(), img2.permute(2, 0, 1).double())
        valid = train_mvgs_ssim(img1.double(), img2.double(), padding="valid")
        assert abs(float(value) - float(expected)) < 1e-5
        assert abs(float(valid) - float(expected)) > 1e-3  # the border matters on these images



@pytest.mark.parametrize("background", [(1.0, 1.0, 1.0), (0.0, 0.0, 0.0)])
def test_a_white_background_resets_once_more_where_densification_starts(background):
    """3DGS's train.py with -w resets opacities at iteration == densify_from_iter too: the loop on
    a white scene does the same at the step its clock reaches densify_from, and on another
    background resets only where the schedule does (every opacity_reset_every steps inside the
    window: none in a 200-step run, whose window ends at 100)."""
    scene = load_scene(FORWARD, background=background)
    steps = 200
    cfg = train_mvgs.MVGSConfig.from_preset("baseline").with_total_steps(steps)
    scheduled = [s for s in range(1, cfg.densify_until) if s % cfg.opacity_reset_every == 0]
    assert scheduled == [] and 0 < cfg.densify_from < cfg.densify_until
    _, log = train_mvgs.training(scene, steps, "baseline")
    assert log["reset"] == ([cfg.densify_from] if background == (1.0, 1.0, 1.0) else [])
    assert log["densify"] and min(log["densify"]) > cfg.densify_from  # densification starts after it, as in 3DGS
