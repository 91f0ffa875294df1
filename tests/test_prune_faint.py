"""The blend statistics the renderer reports (rasterization(..., blend_stats=True)) and the cut
of the faintest splats built on them (MVGSConfig.prune_faint, --prune-faint S).

The statistics are checked against a closed form (wide splats stacked in front of a camera),
against the image's own alpha (the weights of a pixel add up to its opacity), and the compiled
kernels against the PyTorch backend; the cut against rows ranked here by hand, and through a
densification call whose removed rows are the ones a dense per-pixel walk names."""

from __future__ import annotations

import argparse
import dataclasses
import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig, faint_rows
from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig
from mvgs_plugin.camera import Camera
from mvgs_plugin.cli import common_args, config_from_args
from mvgs_plugin.config import MVGSConfig
from mvgs_plugin.controller import MVGS
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.protocol import DensifyContext
from mvgs_plugin.reference_renderer import available_backends, rasterization
from mvgs_plugin.adapters.gs4d import GS4DAdapter
from mvgs_plugin.testing import check_adapter, look_at, synthetic_scene
from test_adapter_gs4d import tiny_config

BACKENDS = [b for b in ("cpp", "torch") if b in available_backends()]


def cameras(C, width, height, dtype):
    viewmats = torch.eye(4, dtype=dtype).repeat(C, 1, 1)
    viewmats[:, 2, 3] = 4.0
    viewmats[1:, 0, 3] = 0.4
    Ks = torch.tensor([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]], dtype=dtype).repeat(C, 1, 1)
    return viewmats, Ks


@pytest.mark.parametrize("backend", BACKENDS)
def test_wide_stacked_splats_blend_the_closed_form(backend):
    """Three splats far wider than the view, at depths 1 < 2 < 3 in front of the camera, opacities
    o1, o2, o3: every pixel blends them with weights o1, o2 (1 - o1), o3 (1 - o1)(1 - o2)."""
    W, H = 21, 13  # not a multiple of the tile: the tiles' pixels past the edges are not the image's
    o = torch.tensor([0.5, 0.3, 0.6], dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, -2.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    viewmats, Ks = cameras(1, W, H, torch.float64)
    scales = torch.full((3, 3), 1e4, dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64)
    _, alphas, meta = rasterization(means, quats, scales, o, torch.rand(3, 3, dtype=torch.float64), viewmats, Ks,
                                    W, H, backend=backend, blend_stats=True)
    per_pixel = torch.stack([o[0], o[1] * (1 - o[0]), o[2] * (1 - o[0]) * (1 - o[1])])
    torch.testing.assert_close(meta["blend_weight"][0], per_pixel * W * H, rtol=1e-6, atol=0)
    assert meta["blend_pixels"][0].tolist() == [W * H] * 3
    torch.testing.assert_close(alphas.sum(), per_pixel.sum() * W * H, rtol=1e-6, atol=0)


def random_splats(N, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(N, 3, generator=g, dtype=torch.float64) * 0.7
    quats = torch.randn(N, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(N, 3, generator=g, dtype=torch.float64) * 0.12 + 0.01
    opacities = torch.rand(N, generator=g, dtype=torch.float64) * 0.95
    colors = torch.rand(N, 3, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, opacities, colors)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_kernels_report_what_the_pytorch_backend_does_and_the_weights_make_the_alpha(dtype):
    if "cpp" not in BACKENDS:
        pytest.skip("the compiled backend is not available here: only the PyTorch one to compare")
    W, H = 75, 50
    splats = random_splats(2500, dtype)
    viewmats, Ks = cameras(3, W, H, dtype)
    out = {}
    for backend in ("cpp", "torch"):
        _, alphas, meta = rasterization(*splats, viewmats, Ks, W, H, backend=backend, blend_stats=True)
        # a pixel's weights add up to its opacity 1 - T, so a camera's to its summed alpha
        torch.testing.assert_close(meta["blend_weight"].sum(-1).double(), alphas.sum(dim=(1, 2, 3)).double(),
                                   rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=0)
        assert not meta["blend_weight"].requires_grad and meta["blend_pixels"].dtype == dtype
        out[backend] = meta
    blended = out["torch"]["blend_pixels"]
    assert 1000 < int((blended > 0).sum()) and int(blended.sum()) > 20 * W * H  # most splats blend, many per pixel
    assert torch.equal(out["cpp"]["blend_pixels"], blended)
    tol = dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out["cpp"]["blend_weight"], out["torch"]["blend_weight"], **tol)
    # not asked: nothing reported, and the same image
    img, _, meta = rasterization(*splats, viewmats, Ks, W, H, backend="cpp")
    assert "blend_weight" not in meta and "blend_pixels" not in meta


def test_faint_rows_takes_the_least_weight_per_pixel_up_to_the_share():
    weight = torch.tensor([1.0, 4.0, 0.5, 10.0, 2.0, 0.0, 3.0])
    pixels = torch.tensor([10.0, 8.0, 1.0, 10.0, 40.0, 0.0, 3.0])
    seen = torch.tensor([True, True, True, True, True, True, False])
    # per pixel: 0.1, 0.5, 0.5, 1.0, 0.05, 0 (never blended), row 6 not seen; total weight 20.5
    # order: 5 (0), 4 (0.05), 0 (0.1), 1 (0.5), 2 (0.5, tie: row order), 3; cumulative 0, 2, 3, 7, 7.5, 17.5
    for share, want in ((0.0, []), (0.05, [5]), (0.1, [4, 5]), (0.15, [0, 4, 5]), (0.3, [0, 4, 5]),
                        (0.35, [0, 1, 4, 5]), (0.5, [0, 1, 2, 4, 5]), (0.99, [0, 1, 2, 3, 4, 5])):
        got = faint_rows(weight, pixels, seen, share).nonzero().squeeze(1).tolist()
        assert got == want, (share, got, want)
    assert not faint_rows(torch.zeros(4), torch.zeros(4), torch.ones(4, dtype=torch.bool), 0.5).any()


def pinhole(uid, eye, size=32):
    K = [[40.0, 0.0, size / 2], [0.0, 40.0, size / 2], [0.0, 0.0, 1.0]]
    return Camera(uid, f"v{uid}", K, look_at(eye, (0.0, 0.0, 0.0)), size, size)


def dense_weights(adapter, cams):
    """Per Gaussian, its blend weight and blended pixels over `cams`, walked here pixel by pixel
    in float64 (depth order, alpha = min(0.999, o exp(-q/2)) kept from 1/255, a pixel stops
    before T would fall below 1e-4, a splat drawn only in the 16 px tiles its radius r reaches:
    floor((u - r) / 16) <= tile < floor((u + r + 15) / 16)), from the renderer's projected means,
    conics, depths and radii."""
    weight = torch.zeros(adapter.num_primitives(), dtype=torch.float64)
    pixels = torch.zeros_like(weight)
    for cam in cams:
        with torch.no_grad():
            res = adapter.render([cam], torch.zeros(1, 3))
        meta = res.aux
        m2d, con, dep = meta["means2d"][0].double(), meta["conics"][0].double(), meta["depths"][0].double()
        op, radius = meta["opacities"][0].double(), meta["radii"][0, :, 0].double()
        order = [int(i) for i in torch.argsort(dep, stable=True) if radius[i] > 0]
        tiles = {i: [math.floor((float(m2d[i, a]) - float(radius[i])) / 16) for a in (0, 1)]
                 + [math.floor((float(m2d[i, a]) + float(radius[i]) + 15) / 16) for a in (0, 1)] for i in order}
        for y in range(cam.height):
            for x in range(cam.width):
                T = 1.0
                for i in order:
                    x0, y0, x1, y1 = tiles[i]
                    if not (x0 <= x // 16 < x1 and y0 <= y // 16 < y1):
                        continue
                    dx, dy = m2d[i, 0] - (x + 0.5), m2d[i, 1] - (y + 0.5)
                    q = 0.5 * (con[i, 0] * dx * dx + con[i, 2] * dy * dy) + con[i, 1] * dx * dy
                    alpha = min(0.999, float(op[i] * torch.exp(-q)))
                    if q < 0 or alpha < 1 / 255:
                        continue
                    if T * (1 - alpha) < 1e-4:
                        break
                    weight[i] += alpha * T
                    pixels[i] += 1
                    T *= 1 - alpha
    return weight, pixels


def faint_model(collect=True):
    """An opaque red splat in front of a wide, faint grey one (behind it everywhere it is blended)
    and three small splats of medium opacity about them."""
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.6, 0.0], [0.5, -0.2, 0.3], [-0.4, -0.1, 0.2], [0.1, -0.3, -0.5]],
                         dtype=torch.float64)
    scales = torch.tensor([[0.35] * 3, [0.9] * 3, [0.1] * 3, [0.12] * 3, [0.08] * 3], dtype=torch.float64)
    opacities = torch.tensor([0.98, 0.03, 0.6, 0.5, 0.7], dtype=torch.float64)
    rgb = torch.tensor([[1.0, 0, 0], [0.5, 0.5, 0.5], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]], dtype=torch.float64)
    m = GS3DAdapter.from_tensors(means, scales=scales, opacities=opacities, rgb=rgb, scene_extent=1.0,
                                 config=GS3DConfig(sh_degree=0, min_opacity=0.001))
    if collect:
        m.collect_blend_stats()
    return m


def test_a_densification_call_removes_the_rows_a_dense_walk_names_faint():
    cams = [pinhole(0, (0.0, -3.0, 0.0)), pinhole(1, (1.0, -2.8, 0.5))]
    m = faint_model()
    weight, pixels = dense_weights(m, cams)
    for cam in cams:  # a training step's views, folded in after their backward
        m.zero_grad()
        res = m.render([cam], torch.zeros(1, 3))
        res.images.sum().backward()
        m.accumulate_stats(res)
    torch.testing.assert_close(m.blend_weight_accum, weight, rtol=1e-9, atol=1e-12)
    assert torch.equal(m.blend_pixels_accum, pixels)
    # by hand from the dense walk: least weight per pixel first, while the summed weight stays within 10 %
    order = sorted(range(5), key=lambda i: (float(weight[i] / max(pixels[i], 1.0)), i))
    total, acc, want = float(weight.sum()), 0.0, []
    for i in order:
        acc += float(weight[i])
        if acc > 0.1 * total:
            break
        want.append(i)
    assert want == [1]  # the faint wide splat (7 % of the weight, on the most pixels), and nothing else
    kept = m.params["means"].detach()[[0, 2, 3, 4]].clone()
    report = m.densify(DensifyContext(step=100, grad_threshold=math.inf, scene_extent=1.0, faint_share=0.1))
    assert report.extra["faint"] == 1 and report.pruned == 1 and report.after == 4
    assert torch.equal(m.params["means"].detach(), kept)
    assert float(m.blend_weight_accum.abs().sum()) == 0  # the window's statistics start again
    with pytest.raises(ValueError, match="faint_share=0.1 needs blend statistics, and none were folded in"):
        m.densify(DensifyContext(step=101, grad_threshold=math.inf, scene_extent=1.0, faint_share=0.1))


def test_without_the_statistics_the_rule_says_so_and_off_it_asks_for_nothing():
    calls = []

    def without_blend(*args, **kwargs):
        calls.append(kwargs.get("blend_stats", False))
        kwargs.pop("blend_stats", None)
        return rasterization(*args, **kwargs)

    m = faint_model()
    m.config.rasterize = without_blend
    res = m.render([pinhole(0, (0.0, -3.0, 0.0))], torch.zeros(1, 3))
    res.images.sum().backward()
    with pytest.raises(ValueError, match=r"asked for the blend weights.*blend_stats=True"):
        m.accumulate_stats(res)
    off = faint_model(collect=False)
    off.config.rasterize = without_blend
    res = off.render([pinhole(0, (0.0, -3.0, 0.0))], torch.zeros(1, 3))
    res.images.sum().backward()
    off.accumulate_stats(res)  # nothing asked, nothing needed
    assert calls == [True, False]
    assert off.densify(DensifyContext(step=1, grad_threshold=math.inf, scene_extent=1.0)).extra["faint"] == 0


def test_the_schedule_cuts_once_after_twice_the_views_and_keeps_collecting_until_then():
    from mvgs_plugin.testing import synthetic_scene

    scene = synthetic_scene(n_train=6, n_test=1, size=16)
    config = MVGSConfig.baseline().with_total_steps(120)
    cfg = dataclasses.replace(config, prune_faint=0.01, densify_from=10, densify_until=60, densify_every=10,
                              opacity_reset_every=30)
    plans = list(ViewSchedule(scene, cfg, load_images=False))
    cut = [p.step for p in plans if p.faint_cut]
    # the window closes at step 60 (clock < 60 collects): steps 60..71 are 12 = 2 x 6 one-view steps
    assert cut == [71] and all(p.densify for p in plans if p.faint_cut)
    assert [p.step for p in plans if p.densify and not p.faint_cut] == list(range(20, 60, 10))
    assert all(p.stats == [True] for p in plans if p.step <= 71) and all(p.stats == [False] for p in plans[71:])
    assert [p.step for p in plans if p.reset_opacity] == [30]  # none after the window
    plain = list(ViewSchedule(scene, dataclasses.replace(cfg, prune_faint=0.0), load_images=False))
    assert not any(p.faint_cut for p in plain) and all(p.stats == [False] for p in plain[59:])
    # the context of the cut: no growth, no boxes, the share
    sched = ViewSchedule(scene, cfg, load_images=False)
    for _ in range(64):
        sched.next()
    state = sched.state_dict()
    rest = [sched.next() for _ in range(10)]
    again = ViewSchedule(scene, cfg, load_images=False)
    again.load_state_dict(state)  # a resume in between cuts at the same step
    assert [p.faint_cut for p in rest] == [again.next().faint_cut for _ in range(10)]
    plan = next(p for p in rest if p.faint_cut)
    ctx = sched.densify_context(plan)
    assert ctx.faint_share == 0.01 and ctx.grad_threshold == math.inf and ctx.boxes is None


def test_the_controller_asks_the_adapter_for_its_statistics_and_runs_one_without_them_without_the_cut():
    from mvgs_plugin.testing import synthetic_scene

    scene = synthetic_scene(n_train=6, n_test=1, size=16)
    cfg = dataclasses.replace(MVGSConfig.baseline().with_total_steps(400), prune_faint=0.01)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(cfg, sh_degree=0))
    assert MVGS(adapter, scene, cfg).config.prune_faint == 0.01
    assert adapter.blend_stats
    # Scaffold-GS's anchors have no blend statistics: the default preset's cut is dropped, said once
    with pytest.warns(UserWarning, match=r"prune_faint=0.01: ScaffoldAdapter reports no blend weights"):
        trainer = MVGS(ScaffoldAdapter.from_scene(scene, ScaffoldConfig.for_run(cfg)), scene, cfg)
    assert trainer.config.prune_faint == 0.0 and trainer.schedule.config.prune_faint == 0.0
    assert not any(p.faint_cut for p in trainer.schedule)
    # a rasterizer without the blend_stats keyword (gsplat's call shape, as gsplat's own): the same

    def gsplat_shaped(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **rest):
        return rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **rest)

    other = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(cfg, sh_degree=0, rasterize=gsplat_shaped))
    assert other.collect_blend_stats() is False and not other.blend_stats
    with pytest.warns(UserWarning, match="GS3DAdapter reports no blend weights"):
        assert MVGS(other, scene, cfg).config.prune_faint == 0.0


def test_a_hand_written_loop_gets_the_statistics_from_densify_context_and_keeps_them_over_a_resume():
    """The three-line wrap's loop never calls collect_blend_stats(): the schedule asks the adapter
    at the first densification (densify_context(adapter=...)), early enough for the cut, which
    uses the statistics after the window's last call; an adapter restored from a checkpoint
    made after that goes on collecting (its state_dict says so)."""
    scene = synthetic_scene(n_train=6, n_test=1, size=16)
    cfg = dataclasses.replace(MVGSConfig.baseline().with_total_steps(120), prune_faint=0.01, densify_from=10,
                              densify_until=60, densify_every=10, opacity_reset_every=30)
    sched = ViewSchedule(scene, cfg)
    model = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(cfg, sh_degree=0))
    cut, state = None, None
    for plan in sched:
        res = model.render(plan.cameras, plan.backgrounds)
        ((res.images - torch.stack(plan.images)) ** 2).mean().backward()
        if any(plan.stats):
            model.accumulate_stats(res)
        model.optimizer_step()
        if plan.densify:
            report = model.densify(sched.densify_context(plan, adapter=model))
            assert model.blend_stats  # asked at the first call (step 20), before the window's last
            if plan.faint_cut:
                cut = (plan.step, report.extra["faint"], report.before, report.after)
        if plan.step == 64:  # after the window, before the cut
            state = model.state_dict()
    assert cut is not None and cut[0] == 71 and cut[1] >= 1 and cut[3] == cut[2] - cut[1]
    again = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(cfg, sh_degree=0))
    assert not again.blend_stats
    again.load_state_dict(state)
    assert again.blend_stats and state["blend_stats"] is True
    del state["blend_stats"]  # a checkpoint from before the cut existed: nothing asked
    fresh = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(cfg, sh_degree=0))
    fresh.load_state_dict(state)
    assert not fresh.blend_stats


def test_the_config_the_flag_and_the_conformance_suite():
    for bad in (-0.1, 1.0, math.nan, True):
        with pytest.raises(ValueError, match="prune_faint must be a share of the blend weight in"):
            dataclasses.replace(MVGSConfig.default(), prune_faint=bad)
    ap = common_args(argparse.ArgumentParser(), out="out")
    # the default preset cuts 1 %; the others, and --prune-faint 0, do not
    assert MVGSConfig.default().prune_faint == 0.01 and config_from_args(ap.parse_args([])).prune_faint == 0.01
    assert all(MVGSConfig.from_preset(p).prune_faint == 0.0 for p in ("baseline", "compact", "multiview", "paper"))
    assert config_from_args(ap.parse_args(["--prune-faint", "0"])).prune_faint == 0.0
    assert config_from_args(ap.parse_args(["--preset", "baseline", "--prune-faint", "0.02"])).prune_faint == 0.02
    for bad in ("-1", "1", "nan"):
        with pytest.raises(SystemExit):
            ap.parse_args(["--prune-faint", bad])
    # the protocol holds with the rule on (render, statistics, densify, checkpoint round trip), in
    # the 4DGS adapter too (its deformed Gaussians' blend weights fold into the canonical rows)
    def collecting(adapter):
        adapter.collect_blend_stats()
        return adapter

    check_adapter(lambda scene: collecting(GS3DAdapter.from_scene(scene, GS3DConfig(sh_degree=1))))
    check_adapter(lambda scene: collecting(GS4DAdapter.from_scene(scene, tiny_config())), synthetic_scene(time=True))
