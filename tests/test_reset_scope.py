"""GS3DConfig.opacity_reset_scope: "all" resets every opacity (3DGS); "inside" leaves the far
background (at least FAR_RESET_FRACTION of the initial model's farthest distance from the scene
centre) as it is. Checked against the distances computed here, not against the adapter's mask."""

from __future__ import annotations

import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import FAR_RESET_FRACTION, GS3DAdapter, GS3DConfig

CENTER = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
DISTANCES = [0.0, 1.0, 4.0, 5.99, 6.01, 7.0, 8.0]  # the farthest, 8, sets far_distance: the line is at 6
OPACITIES = [0.5, 0.9, 0.2, 0.7, 0.6, 0.95, 0.004]
RESET = 0.01


def model(scope, center=CENTER):
    gen = torch.Generator().manual_seed(0)
    n = len(DISTANCES)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1)
    means = CENTER + torch.tensor(DISTANCES, dtype=torch.float64)[:, None] * direction
    return GS3DAdapter.from_tensors(means, rgb=torch.rand(n, 3, generator=gen, dtype=torch.float64),
                                    scales=torch.full((n, 3), 0.05, dtype=torch.float64),
                                    opacities=torch.tensor(OPACITIES, dtype=torch.float64), scene_extent=2.0,
                                    config=GS3DConfig(opacity_reset_scope=scope), scene_center=center)


def expected_after_reset(distances, far_distance):
    line = FAR_RESET_FRACTION * far_distance
    return [o if d >= line else min(o, RESET) for d, o in zip(distances, OPACITIES)]


def test_inside_resets_the_gaussians_within_the_line_and_leaves_the_far_background():
    a = model("inside")
    assert a.far_distance == pytest.approx(8.0)
    a.reset_opacity()
    got = a.get_opacities().detach().tolist()
    assert got == pytest.approx(expected_after_reset(DISTANCES, 8.0), rel=1e-9)
    # 3 of the 7 lie at 6 or beyond and keep 0.6, 0.95 and 0.004 (below the reset value already)
    assert sum(g > 2 * RESET for g in got) == 2 and got[-1] == pytest.approx(0.004, rel=1e-9)


def test_all_is_3dgs_and_inside_without_a_centre_is_all():
    for a in (model("all"), model("inside", center=None)):
        a.reset_opacity()
        assert a.get_opacities().detach().tolist() == pytest.approx([min(o, RESET) for o in OPACITIES], rel=1e-9)


def test_the_line_follows_where_a_gaussian_is_now_not_where_it_started():
    a = model("inside")
    with torch.no_grad():  # the Gaussian at distance 1 moves out to 7, the one at 7 in to 1
        means = a.params["means"]
        means[[1, 5]] = means[[5, 1]].clone()
    distances = torch.linalg.vector_norm(a.params["means"].detach() - CENTER, dim=1).tolist()
    assert distances[1] == pytest.approx(7.0) and distances[5] == pytest.approx(1.0)
    a.reset_opacity()
    assert a.get_opacities().detach().tolist() == pytest.approx(expected_after_reset(distances, 8.0), rel=1e-9)


def test_a_reset_zeroes_the_opacity_moments_and_keeps_the_other_groups():
    a = model("inside")
    for p in a.params.values():
        p.grad = torch.ones_like(p)
    a.set_step(0)
    a.optimizer_step()
    means_moment = a.optimizer.state[a.params["means"]]["exp_avg"].clone()
    a.reset_opacity()
    state = a.optimizer.state[a.params["opacities"]]
    assert all(float(v.abs().max()) == 0.0 for k, v in state.items() if k in ("exp_avg", "exp_avg_sq"))
    assert torch.equal(a.optimizer.state[a.params["means"]]["exp_avg"], means_moment)


def test_bad_scope_is_refused_naming_it():
    with pytest.raises(ValueError, match="opacity_reset_scope must be one of 'all', 'inside', got 'far'"):
        GS3DConfig(opacity_reset_scope="far")


def test_a_checkpoint_keeps_its_scope_and_one_from_before_the_field_resets_everything():
    a = model("inside")
    state = a.state_dict()
    b = model("all")
    b.load_state_dict(state)
    assert b.config.opacity_reset_scope == "inside"
    old = dict(state, config={k: v for k, v in state["config"].items() if k != "opacity_reset_scope"})
    c = model("inside")
    c.load_state_dict(old)
    assert c.config.opacity_reset_scope == "all"
    c.reset_opacity()
    assert max(c.get_opacities().detach().tolist()) == pytest.approx(RESET, rel=1e-9)
    assert math.isfinite(sum(c.get_opacities().detach().tolist()))


def test_the_flag_reaches_the_model(capsys):
    import argparse

    from mvgs_plugin import MVGSConfig
    from mvgs_plugin.cli import common_args, model_config, world_size_arg

    ap = world_size_arg(common_args(argparse.ArgumentParser(), out="out"))
    cfg = MVGSConfig.baseline().with_total_steps(100)
    default = model_config(cfg, 0, opacity_reset_scope=ap.parse_args([]).opacity_reset_scope)
    assert default.opacity_reset_scope == "inside" == GS3DConfig().opacity_reset_scope
    for scope in ("all", "inside"):
        args = ap.parse_args(["--opacity-reset-scope", scope])
        assert model_config(cfg, 0, opacity_reset_scope=args.opacity_reset_scope).opacity_reset_scope == scope
    with pytest.raises(SystemExit):
        ap.parse_args(["--opacity-reset-scope", "far"])
    assert "far" in capsys.readouterr().err


def test_a_training_run_spares_the_far_background_at_every_reset_and_resumes_exactly(tmp_path):
    """A controller run through densification, two opacity resets and a resume: at each reset
    the Gaussians at 3/4 of the initial farthest distance or more keep their opacity, the others
    are capped (distances computed here from the means at that moment), and the resumed run ends
    where the whole run ends."""
    from mvgs_plugin import MVGSConfig
    from mvgs_plugin.testing import synthetic_scene
    from test_means_lr_rule import whole_and_resumed  # the whole run, and one cut and resumed

    scene = synthetic_scene(n_train=6, n_points=120, size=16, seed=4)
    scene.points.xyz[:40] *= 4.0  # a third of the points far out: a background
    # on 3DGS's 30k clock, compressed to 100 steps (with its floors): densify every 10 from 50 to 80, reset every 30
    config = MVGSConfig.baseline(seed=0, densify_from=1500, densify_every=1500, densify_until=24000,
                                 opacity_reset_every=9000, min_densify_per_reset=1,
                                 grad_threshold_width=None).with_total_steps(100)

    def make():
        adapter = GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=100, opacity_reset_scope="inside"))
        reset, adapter.seen = adapter.reset_opacity, []

        def watched():
            center, far = adapter.scene_center.float(), adapter.far_distance
            means = adapter.params["means"].detach().clone()
            before = adapter.get_opacities().detach().clone()
            reset()
            after = adapter.get_opacities().detach()
            outside = torch.linalg.vector_norm(means - center, dim=1) >= FAR_RESET_FRACTION * far
            adapter.seen.append((int(outside.sum()), int((~outside).sum())))
            assert torch.equal(after[outside], before[outside])
            assert bool((after[~outside] <= RESET * (1 + 1e-5)).all())
        adapter.reset_opacity = watched
        return adapter

    a, b = whole_and_resumed(make, scene, config, 45, tmp_path / "ck.pt")
    seen = a.seen  # the whole run's resets
    assert len(seen) == 2 and all(o > 0 and i > 0 for o, i in seen), seen  # resets at 30 and 60, both sides
    assert a.num_primitives() != 120  # densified
    assert b.config.opacity_reset_scope == "inside"
    for k in a.params:
        assert torch.equal(a.params[k], b.params[k]), k
