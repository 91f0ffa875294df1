"""The world-size prune rule (GS3DConfig.world_size_rule).

3DGS prunes every Gaussian whose largest scale exceeds max_world_size x the scene extent once
size pruning is on. "distance" keeps that limit within the extent of the scene centre and lets it
grow with the distance d from the centre beyond, max_world_size x max(extent, d), so the far
background keeps the large Gaussians a camera sees as small. The expected sets below are written
out per Gaussian from that definition with plain Python floats, not from the adapter's code.
"""

from __future__ import annotations

import math

import pytest
import torch

from mvgs_plugin import MVGS, MVGSConfig
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.protocol import DensifyContext
from mvgs_plugin.testing import synthetic_scene

EXTENT = 2.0
CENTER = (0.5, -1.0, 2.0)
# (distance from CENTER along a fixed direction, largest scale)
ROWS = [(0.5, 0.15), (0.5, 0.25), (1.9, 0.21), (3.0, 0.25), (3.0, 0.35), (8.0, 0.7), (8.0, 0.9),
        (20.0, 1.5), (20.0, 2.5)]


def expected_pruned(rule):
    out = set()
    for i, (d, s) in enumerate(ROWS):
        limit = 0.1 * (max(EXTENT, d) if rule == "distance" else EXTENT)
        if s > limit:
            out.add(i)
    return out


def model(rule):
    n = len(ROWS)
    direction = torch.tensor([2.0, -1.0, 2.0]) / 3.0  # unit length
    means = torch.tensor(CENTER) + torch.tensor([d for d, _ in ROWS])[:, None] * direction
    # anisotropic: the largest axis carries the size, the others are small
    scales = torch.tensor([[0.01, s, 0.02] for _, s in ROWS])
    return GS3DAdapter.from_tensors(means, rgb=torch.rand(n, 3), scales=scales, opacities=torch.full((n,), 0.5),
                                    scene_extent=EXTENT, config=GS3DConfig(world_size_rule=rule))


def surviving(a):
    """Indices of ROWS still present (matched by position: nothing moves in a prune-only call)."""
    d = (a.params["means"].detach() - torch.tensor(CENTER)).norm(dim=1).tolist()
    s = a.get_scales().detach().max(dim=1).values.tolist()
    return {min(range(len(ROWS)), key=lambda i: abs(ROWS[i][0] - di) + abs(ROWS[i][1] - si)) for di, si in zip(d, s)}


@pytest.mark.parametrize("rule", ["extent", "distance"])
def test_prune_only_call_follows_the_rule(rule):
    a = model(rule)
    ctx = DensifyContext(step=1, grad_threshold=math.inf, scene_extent=EXTENT, prune_large=True,
                         scene_center=torch.tensor(CENTER, dtype=torch.float64))
    rep = a.densify(ctx)
    gone = expected_pruned(rule)
    assert rep.pruned == len(gone) and a.num_primitives() == len(ROWS) - len(gone)
    assert surviving(a) == set(range(len(ROWS))) - gone
    # the two rules differ on this set: the distance rule keeps the far ones the extent rule cuts
    assert expected_pruned("extent") - expected_pruned("distance") == {3, 5, 7}


def test_without_size_pruning_or_centre():
    a = model("distance")
    rep = a.densify(DensifyContext(step=1, grad_threshold=math.inf, scene_extent=EXTENT, prune_large=False,
                                   scene_center=torch.tensor(CENTER)))
    assert rep.pruned == 0 and a.num_primitives() == len(ROWS)
    # no centre given: the distance rule falls back to 3DGS's extent rule
    rep = model("distance").densify(DensifyContext(step=1, grad_threshold=math.inf, scene_extent=EXTENT,
                                                   prune_large=True))
    assert rep.pruned == len(expected_pruned("extent"))


def test_bad_rule_is_refused_by_name():
    with pytest.raises(ValueError, match="world_size_rule.*'distance'.*'far'"):
        GS3DConfig(world_size_rule="far")


def test_the_rule_survives_a_checkpoint():
    a = model("distance")
    b = model("extent")
    b.load_state_dict(a.state_dict())
    assert b.config.world_size_rule == "distance"


def test_the_trainer_gives_the_scene_centre_to_every_densification_call():
    scene = synthetic_scene(n_train=6, n_test=1, size=16, n_points=60)
    steps = 200
    cfg = MVGSConfig.baseline(grad_threshold_width=None).with_total_steps(steps)
    torch.manual_seed(0)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=steps, world_size_rule="distance"))
    trainer = MVGS(adapter, scene, cfg)
    seen = []
    original = adapter.densify

    def spy(ctx):
        seen.append((ctx.prune_large, None if ctx.scene_center is None else ctx.scene_center.tolist()))
        return original(ctx)

    adapter.densify = spy
    trainer.fit(progress=False)
    centres = torch.stack([c.center for c in scene.train_cameras]).mean(dim=0).tolist()
    assert len(seen) >= 3 and any(p for p, _ in seen)  # size pruning was on for some calls
    for _, c in seen:
        assert c == pytest.approx(centres, abs=1e-9)


def test_the_flag_reaches_the_model_config_and_refuses_other_values(capsys):
    import argparse

    from mvgs_plugin.cli import common_args, model_config, world_size_arg

    ap = world_size_arg(common_args(argparse.ArgumentParser(), out="out"))
    cfg = MVGSConfig.baseline().with_total_steps(100)
    assert model_config(cfg, 0, world_size_rule=ap.parse_args([]).world_size_rule).world_size_rule == \
        GS3DConfig().world_size_rule
    for rule in ("extent", "distance"):
        assert model_config(cfg, 0, world_size_rule=ap.parse_args(["--world-size-rule", rule]).world_size_rule) \
            .world_size_rule == rule
    with pytest.raises(SystemExit):
        ap.parse_args(["--world-size-rule", "far"])
    assert "far" in capsys.readouterr().err
    # Scaffold-GS has no world-size pruning: its example does not take the flag
    assert "--world-size-rule" not in common_args(argparse.ArgumentParser(), out="out").format_help()
