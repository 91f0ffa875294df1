"""GS3DConfig.budget_growth_order: under a binding Gaussian budget, "inside-first" grows every
candidate inside the far line (FAR_RESET_FRACTION of the initial model's farthest distance from
the scene centre) before any beyond it, each group by score; "score" ranks them all by score.
The expected rows are worked out here from the distances and gradients, not read from the
adapter; "auto" is resolved by the rig in from_scene, and old checkpoints keep "score"."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from mvgs_plugin.adapters.gs3d import FAR_RESET_FRACTION, GS3DAdapter, GS3DConfig
from mvgs_plugin.data import load_scene
from mvgs_plugin.protocol import DensifyContext
from mvgs_plugin.testing import synthetic_scene

ROOT = Path(__file__).resolve().parents[1]
CENTER = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
# the farthest, 8, sets far_distance: the line is at 6; rows 4-7 are beyond it
DISTANCES = [0.5, 1.0, 3.0, 5.5, 6.5, 7.0, 7.5, 8.0]
# every row a clone candidate (>= BETA); the far rows pull hardest, as the textured background does
GRADS = [3e-4, 5e-4, 4e-4, 2.5e-4, 9e-4, 8e-4, 1e-3, 7e-4]
BETA = 2e-4


def model(order, center=CENTER):
    gen = torch.Generator().manual_seed(0)
    n = len(DISTANCES)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=1)
    means = CENTER + torch.tensor(DISTANCES, dtype=torch.float64)[:, None] * direction
    rgb = torch.zeros(n, 3, dtype=torch.float64)
    a = GS3DAdapter.from_tensors(means, rgb=rgb, scales=torch.full((n, 3), 1e-3, dtype=torch.float64),
                                 opacities=torch.full((n,), 0.5, dtype=torch.float64), scene_extent=2.0,
                                 config=GS3DConfig(budget_growth_order=order), scene_center=center)
    a.params["sh0"].data[:, 0, 0] = torch.arange(n, dtype=a.params["sh0"].dtype)  # a key per row and its copies
    a.grad_accum = torch.tensor(GRADS, dtype=a.grad_accum.dtype)
    a.denom = torch.ones(n, dtype=a.denom.dtype)
    return a


def keys(a):
    return sorted(a.params["sh0"].detach()[:, 0, 0].round().long().tolist())


def grow(a, room):
    return a.densify(DensifyContext(step=600, grad_threshold=BETA, scene_extent=2.0, max_primitives=len(DISTANCES) + room,
                                    rank_by="gradient"))


def expected_clones(room, order):
    """The rows cloned into `room`: by gradient, the far ones after the rest with inside-first."""
    line = FAR_RESET_FRACTION * max(DISTANCES)
    rows = range(len(DISTANCES))
    if order == "inside-first":
        ranked = sorted(rows, key=lambda i: (DISTANCES[i] >= line, -GRADS[i]))
    else:
        ranked = sorted(rows, key=lambda i: -GRADS[i])
    return ranked[:room]


@pytest.mark.parametrize("room", [2, 4, 5, 7])
def test_inside_first_fills_the_room_with_the_object_before_the_far_background(room):
    a = model("inside-first")
    assert a.far_distance == pytest.approx(8.0)
    rep = grow(a, room)
    want = expected_clones(room, "inside-first")
    assert rep.cloned == room and rep.after == len(DISTANCES) + room
    assert keys(a) == sorted(list(range(len(DISTANCES))) + want)
    if room <= 4:  # the room holds only inside rows: no far row grew, though all four outscore them
        assert all(DISTANCES[i] < 6.0 for i in want)


@pytest.mark.parametrize("order", ["score", "auto"])  # "auto" unresolved (no from_scene): by score
def test_score_order_takes_the_largest_gradients_wherever_they_are(order):
    a = model(order)
    rep = grow(a, 3)
    want = expected_clones(3, "score")
    assert rep.cloned == 3 and keys(a) == sorted(list(range(len(DISTANCES))) + want)
    assert all(DISTANCES[i] >= 6.0 for i in want)  # here the far rows take it all


def test_without_a_scene_centre_inside_first_is_the_score_order():
    a = model("inside-first", center=None)
    grow(a, 3)
    assert keys(a) == sorted(list(range(len(DISTANCES))) + expected_clones(3, "score"))


def test_without_a_cap_the_order_changes_nothing():
    a, b = model("inside-first"), model("score")
    for m in (a, b):
        m.densify(DensifyContext(step=600, grad_threshold=BETA, scene_extent=2.0))
    assert keys(a) == keys(b) == sorted(list(range(len(DISTANCES))) * 2)


def test_auto_is_resolved_by_the_rig():
    """A rig round the scene grows the object first; a forward-facing one (where the far part is
    the back wall every view sees) by score; an explicit order is kept on either."""
    around = synthetic_scene(n_train=8, n_test=2, size=16, n_points=80)
    forward = load_scene(ROOT / "tests" / "data" / "forward64")
    assert GS3DAdapter.from_scene(around).config.budget_growth_order == "inside-first"
    assert GS3DAdapter.from_scene(forward).config.budget_growth_order == "score"
    assert GS3DAdapter.from_scene(around, GS3DConfig(budget_growth_order="score")).config.budget_growth_order == "score"
    told = GS3DAdapter.from_scene(forward, GS3DConfig(budget_growth_order="inside-first"))
    assert told.config.budget_growth_order == "inside-first"


def test_a_checkpoint_from_before_the_order_keeps_growing_by_score():
    a = model("inside-first")
    state = a.state_dict()
    del state["config"]["budget_growth_order"]
    b = model("inside-first")
    b.load_state_dict(state)
    assert b.config.budget_growth_order == "score"
    state = a.state_dict()
    c = model("score")
    c.load_state_dict(state)
    assert c.config.budget_growth_order == "inside-first"


def test_bad_orders_are_refused_by_name():
    with pytest.raises(ValueError, match="budget_growth_order must be one of 'auto', 'inside-first', 'score', got 'near'"):
        GS3DConfig(budget_growth_order="near")


def test_the_command_line_reaches_the_model(tmp_path):
    sys.path.insert(0, str(ROOT / "examples"))
    try:
        import train_3dgs
    finally:
        sys.path.pop(0)
    scene = synthetic_scene(n_train=8, n_test=2, size=16, n_points=80)
    for flags, want in (([], "inside-first"), (["--budget-growth-order", "score"], "score")):
        args = train_3dgs.parse_args(["--steps", "10", "--out", str(tmp_path / "o"), *flags])
        config = train_3dgs.config_from_args(args, scene)
        assert train_3dgs.build_adapter(args, scene, config).config.budget_growth_order == want
    with pytest.raises(SystemExit):
        train_3dgs.parse_args(["--budget-growth-order", "near", "--out", str(tmp_path / "o")])
