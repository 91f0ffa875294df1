"""The means' step rule (GS3DConfig.means_lr_rule).

3DGS moves every mean with the same learning rate, lr x the scene extent. "distance" multiplies
each mean's Adam step by max(extent, d) / extent, d its distance from the scene centre, so a step
turns a Gaussian by about the same angle as seen from the rig wherever it lies. The expected
moves below come from a second adapter with the "extent" rule (torch's Adam, untouched) times the
factor written out per row from that definition with plain Python floats.
"""

from __future__ import annotations

import argparse

import pytest
import torch

from mvgs_plugin import MVGS, MVGSConfig
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
from mvgs_plugin.testing import synthetic_scene

EXTENT = 2.0
CENTER = (0.5, -1.0, 2.0)
DISTANCES = [0.0, 0.7, 1.99, 2.0, 3.0, 8.0, 40.0]


def model(rule, center=CENTER, seed=0):
    gen = torch.Generator().manual_seed(seed)
    n = len(DISTANCES)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1)
    means = torch.tensor(CENTER, dtype=torch.float64) + torch.tensor(DISTANCES, dtype=torch.float64)[:, None] * direction
    return GS3DAdapter.from_tensors(means, rgb=torch.rand(n, 3, generator=gen, dtype=torch.float64),
                                    scales=torch.full((n, 3), 0.05, dtype=torch.float64),
                                    opacities=torch.full((n,), 0.5, dtype=torch.float64), scene_extent=EXTENT,
                                    config=GS3DConfig(means_lr_rule=rule), scene_center=center)


def step_with(adapter, grads):
    before = {k: p.detach().clone() for k, p in adapter.params.items()}
    for name, p in adapter.params.items():
        p.grad = grads[name].clone()
    adapter.set_step(0)
    adapter.optimizer_step()
    return {k: adapter.params[k].detach() - before[k] for k in before}


def test_each_mean_moves_by_the_extent_rules_step_times_its_factor():
    gen = torch.Generator().manual_seed(1)
    ref, dist = model("extent"), model("distance")
    grads = {k: torch.randn(p.shape, generator=gen, dtype=p.dtype) for k, p in ref.params.items()}
    factors = [max(EXTENT, d) / EXTENT for d in DISTANCES]
    # the factor the adapter reports (from the positions before the step) is the one written out here
    assert dist.means_step_scale().tolist() == pytest.approx(factors, rel=1e-9)
    assert ref.means_step_scale() is None
    moved_ref, moved = step_with(ref, grads), step_with(dist, grads)
    assert [round(f, 6) for f in factors[:4]] == [1.0] * 4 and factors[-1] == 20.0
    for i, f in enumerate(factors):
        assert torch.allclose(moved["means"][i], f * moved_ref["means"][i], rtol=1e-9, atol=1e-15), i
    assert float(moved_ref["means"].abs().min()) > 0  # every row moved, so the comparison is not vacuous
    for name in ("sh0", "shN", "scales", "quats", "opacities"):  # only the means follow the rule
        assert torch.equal(moved[name], moved_ref[name]), name


def test_disparity_moves_along_the_line_of_sight_by_the_factor_squared():
    """"disparity": across the line of sight from the centre the extent rule's move times f, along
    it times f^2 (steps uniform in angle and in 1 / d), written out per row with numpy."""
    import numpy as np

    gen = torch.Generator().manual_seed(5)
    ref, disp = model("extent"), model("disparity")
    start = ref.params["means"].detach().numpy().copy()
    grads = {k: torch.randn(p.shape, generator=gen, dtype=p.dtype) for k, p in ref.params.items()}
    m_ref, m = step_with(ref, grads)["means"].numpy(), step_with(disp, grads)["means"].numpy()
    for i, d in enumerate(DISTANCES):
        f = max(EXTENT, d) / EXTENT
        if d == 0.0:
            assert np.allclose(m[i], m_ref[i], rtol=1e-9, atol=1e-15)  # no line of sight: f = 1 anyway
            continue
        u = (start[i] - np.asarray(CENTER)) / np.linalg.norm(start[i] - np.asarray(CENTER))
        along = float(m_ref[i] @ u)
        expected = f * (m_ref[i] - along * u) + f * f * along * u
        assert np.allclose(m[i], expected, rtol=1e-7, atol=1e-13), (i, m[i], expected)
    for name in ("sh0", "scales", "opacities"):
        assert torch.equal(disp.params[name], ref.params[name])


def test_without_a_centre_the_distance_rule_is_the_extent_rule():
    gen = torch.Generator().manual_seed(2)
    ref, dist = model("extent"), model("distance", center=None)
    grads = {k: torch.randn(p.shape, generator=gen, dtype=p.dtype) for k, p in ref.params.items()}
    assert dist.means_step_scale() is None
    assert torch.equal(step_with(ref, grads)["means"], step_with(dist, grads)["means"])


def test_from_scene_takes_the_scene_centre_and_4dgs_and_checkpoints_keep_it(tmp_path):
    scene = synthetic_scene(n_train=4, n_points=60, size=16, seed=3, time=True)
    a = GS3DAdapter.from_scene(scene, GS3DConfig(means_lr_rule="disparity"))
    assert a.scene_center.tolist() == pytest.approx(scene.center.tolist())
    d4 = GS4DAdapter.from_scene(scene, GS4DConfig(canonical=GS3DConfig(means_lr_rule="distance"), init_random_points=0))
    assert d4.scene_center.tolist() == pytest.approx(scene.center.tolist()) and d4.config.means_lr_rule == "distance"
    state = a.state_dict()
    b = model("distance", center=(9.0, 9.0, 9.0))
    b.load_state_dict(state)
    assert b.scene_center.tolist() == pytest.approx(scene.center.tolist())
    old = {k: v for k, v in state.items() if k != "scene_center"}  # an earlier release's checkpoint:
    old["config"] = {k: v for k, v in state["config"].items() if k != "means_lr_rule"}  # no centre, no rule
    c = model("distance", center=(1.0, 2.0, 3.0))
    c.load_state_dict(old)
    assert c.scene_center.tolist() == [1.0, 2.0, 3.0]
    assert c.config.means_lr_rule == "extent"  # the rule that release ran, not this adapter's


def test_auto_is_disparity_on_a_forward_facing_rig_and_extent_around_a_scene():
    """GS3DConfig's default "auto" is resolved by from_scene from the rig (is_forward_facing, the
    classifier for_scene uses): the bundled 64 px forward-facing test scene gets "disparity",
    a ring looking in (synthetic_scene) "extent"; from_tensors, without a rig, moves as "extent"."""
    from pathlib import Path

    from mvgs_plugin.data import load_scene
    from mvgs_plugin.data.init import is_forward_facing

    assert GS3DConfig().means_lr_rule == "auto"
    forward = load_scene(Path(__file__).parent / "data" / "forward64")
    ring = synthetic_scene(n_train=6, n_points=60, size=16, seed=3)
    assert is_forward_facing(forward.train_cameras) and not is_forward_facing(ring.train_cameras)
    f, r = GS3DAdapter.from_scene(forward), GS3DAdapter.from_scene(ring)
    assert f.config.means_lr_rule == "disparity" and r.config.means_lr_rule == "extent"
    assert float(f.means_step_scale().max()) > 1.0 and r.means_step_scale() is None
    assert GS4DAdapter.from_scene(forward, GS4DConfig(init_random_points=0)).config.means_lr_rule == "disparity"
    assert model("auto").means_step_scale() is None  # a centre but no rig: 3DGS's step


def whole_and_resumed(make_adapter, scene, config, cut, path):
    """The adapters of a whole controller run and of a run resumed from the checkpoint another
    run wrote after `cut` steps (each run's adapter made by make_adapter())."""
    def run(steps=None, resume=None):
        adapter = make_adapter()
        trainer = MVGS(adapter, scene, config)
        if resume is not None:
            trainer.load_checkpoint(resume)
        trainer.fit(steps, progress=False)
        return trainer, adapter

    _, whole = run()
    half, _ = run(steps=cut)
    half.save_checkpoint(str(path))
    _, resumed = run(resume=str(path))
    return whole, resumed


def test_a_run_with_far_content_stays_finite_and_resumes_exactly(tmp_path):
    """A short controller run whose points lie far outside the rig's extent (the factor reaches
    ~10): every step finite, and a resume from the middle ends where the whole run ends."""
    scene = synthetic_scene(n_train=6, n_points=80, size=16, seed=4)
    scene.points.xyz.mul_(50.0)  # a shell of radius 30 about a ring of radius 3 (extent 3.3)
    config = MVGSConfig.baseline(seed=0).with_total_steps(60)

    def make():
        adapter = GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=60, means_lr_rule="disparity"))
        assert float(adapter.means_step_scale().max()) > 5.0
        return adapter

    a, b = whole_and_resumed(make, scene, config, 30, tmp_path / "ck.pt")
    assert bool(torch.isfinite(a.params["means"]).all())
    assert torch.equal(a.params["means"], b.params["means"])


def test_bad_values_are_refused_and_the_flag_reaches_the_model(capsys):
    with pytest.raises(ValueError, match="means_lr_rule must be one of 'auto', 'extent', 'distance', 'disparity', got 'far'"):
        GS3DConfig(means_lr_rule="far")
    with pytest.raises(ValueError, match="scene_center must be 3 finite numbers"):
        model("distance", center=(0.0, float("nan"), 0.0))
    from mvgs_plugin.cli import common_args, model_config, world_size_arg

    ap = world_size_arg(common_args(argparse.ArgumentParser(), out="out"))
    cfg = MVGSConfig.baseline().with_total_steps(100)
    assert model_config(cfg, 0, means_lr_rule=ap.parse_args([]).means_lr_rule).means_lr_rule == "auto"
    for rule in ("auto", "extent", "distance", "disparity"):
        assert model_config(cfg, 0, means_lr_rule=ap.parse_args(["--means-lr-rule", rule]).means_lr_rule) \
            .means_lr_rule == rule
    with pytest.raises(SystemExit):
        ap.parse_args(["--means-lr-rule", "far"])
    assert "far" in capsys.readouterr().err


def test_a_move_below_float32_spacing_is_scaled_before_it_is_rounded():
    """A far float32 mean late in a run: Adam's move is a fraction of float32's spacing at the
    mean, so position + move rounds back to the position, and scaling that rounded move gave 0.
    The rule scales Adam's move first and adds it once: the mean moves by f x Adam's move to
    within one spacing."""
    spacing = float(torch.finfo(torch.float32).eps) * 16  # float32's spacing at 16..32
    adam = 0.3 * spacing  # step 1 with a constant gradient: Adam moves each coordinate by lr against it
    means = torch.tensor([[20.0, 20.0, 20.0], [-20.0, 18.0, 24.0]], dtype=torch.float32)
    extent = 2.0
    a = GS3DAdapter.from_tensors(means, rgb=torch.full((2, 3), 0.5), scales=torch.full((2, 3), 0.05),
                                 opacities=torch.full((2,), 0.5), scene_extent=extent, scene_center=(0.0, 0.0, 0.0),
                                 config=GS3DConfig(means_lr_rule="distance", lr_means_init=adam / extent,
                                                   lr_means_final=adam / extent))
    for p in a.params.values():
        p.grad = torch.ones_like(p)
    a.set_step(0)
    before = a.params["means"].detach().double().clone()
    assert a.learning_rates()["means"] == pytest.approx(adam)
    f = before.norm(dim=1) / extent  # 17.3 and 18.0: the moves are 5-6 spacings
    a.optimizer_step()
    moved = a.params["means"].detach().double() - before
    expected = -(f * adam)[:, None].expand(2, 3)
    assert bool((moved != 0).all())
    assert torch.allclose(moved, expected, atol=spacing, rtol=0)


def test_the_factor_stops_growing_beyond_the_initial_models_farthest_mean():
    a = model("distance")  # initial means up to 40 from the centre
    assert a.far_distance == pytest.approx(40.0)
    with torch.no_grad():
        a.params["means"][-1] = torch.tensor(CENTER, dtype=torch.float64) + torch.tensor([400.0, 0.0, 0.0])
    assert float(a.means_step_scale()[-1]) == pytest.approx(40.0 / EXTENT)
    b = model("distance")
    b.load_state_dict(a.state_dict())
    assert b.far_distance == pytest.approx(40.0)


def test_a_checkpoint_keeps_its_rule_unless_the_command_asks_for_another(tmp_path, capsys, monkeypatch):
    """On a forward-facing rig "auto" is disparity; a checkpoint made with extent (an earlier
    release, or --means-lr-rule extent) resumes under the command that made it, continuing with
    extent, and a command that asks for another rule by name is refused naming the field."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("train_3dgs_rule", root / "examples" / "train_3dgs.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    base = ["--data", str(root / "tests" / "data" / "forward64"), "--steps", "40", "--threads", "1", "--no-progress"]
    whole = example.main(base + ["--out", str(tmp_path / "w"), "--means-lr-rule", "extent"])
    from mvgs_plugin import controller

    step = controller.MVGS.step

    def interrupted(self):  # stop after the checkpoint of step 20
        if self.step_count == 25:
            raise KeyboardInterrupt
        return step(self)

    monkeypatch.setattr(controller.MVGS, "step", interrupted)
    with pytest.raises(SystemExit):
        example.main(base + ["--out", str(tmp_path / "a"), "--means-lr-rule", "extent", "--checkpoint-every", "20"])
    monkeypatch.setattr(controller.MVGS, "step", step)
    ckpt = tmp_path / "a" / "checkpoint.pt"
    resumed = example.main(base + ["--out", str(tmp_path / "b"), "--resume", str(ckpt)])  # no rule asked: auto
    assert whole["model"]["means_lr_rule"] == "extent" and resumed["model"]["means_lr_rule"] == "extent"
    assert resumed["num_gaussians"] == whole["num_gaussians"]
    assert resumed["psnr"] == pytest.approx(whole["psnr"], abs=1e-6)  # the same run, continued with its rule
    capsys.readouterr()
    with pytest.raises(SystemExit) as err:
        example.main(base + ["--out", str(tmp_path / "c"), "--resume", str(ckpt), "--means-lr-rule", "disparity"])
    assert err.value.code == 2
    assert "means_lr_rule: checkpoint 'extent', this command 'disparity'" in capsys.readouterr().err
