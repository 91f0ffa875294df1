"""A budget's cut before training re-sizes what it keeps (issue 27, the quarter gate).

The initial model is sized by its points' spacing (3DGS: a Gaussian's scale is the root mean
squared distance to its three nearest points; Scaffold-GS: an anchor's scaling likewise). A cut
to the budget before the first optimizer step keeps a subset whose spacing is wider: the kept
Gaussians are re-sized as if the model had been built from the kept points, so a thinned region
has no holes between them. After a step the scales are the optimizer's and a cut leaves them.

Checked against a dense reference: the three nearest other points of every kept point by a
full pairwise distance matrix (torch.cdist), not the package's kNN search.
"""

from __future__ import annotations

import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig
from mvgs_plugin.protocol import DensifyContext
from mvgs_plugin.testing import synthetic_scene


def dense_spacing_log(points: torch.Tensor) -> torch.Tensor:
    """[P] log of the root mean squared distance to the 3 nearest other points, by brute force."""
    p = points.detach().double()
    d2 = torch.cdist(p, p).square()
    d2.fill_diagonal_(math.inf)
    return torch.log(d2.topk(3, dim=1, largest=False).values.mean(dim=1).clamp_min(1e-7).sqrt())


def cut(model, cap, scene):
    return model.densify(DensifyContext(step=0, grad_threshold=math.inf, scene_extent=float(scene.extent),
                                        scene_center=scene.center, max_primitives=cap))


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(n_train=6, n_test=2, size=16, n_points=200)


def test_a_cut_before_training_sizes_3dgs_by_the_kept_points(scene):
    model = GS3DAdapter.from_scene(scene, GS3DConfig())
    before = model.params["scales"].detach().clone()
    assert torch.allclose(before[:, 0].double(), dense_spacing_log(model.params["means"]), atol=1e-5)
    report = cut(model, 50, scene)
    assert report.after == 50
    means, scales = model.params["means"].detach(), model.params["scales"].detach()
    want = dense_spacing_log(means)
    for col in range(3):
        assert torch.allclose(scales[:, col].double(), want, atol=1e-5)
    # a quarter of the points: the kept ones are farther apart, so larger
    assert float(scales.mean()) > float(before.mean()) + 0.3
    assert all(torch.isfinite(p).all() for p in model.params.values())


def test_a_cut_after_a_step_keeps_the_trained_scales(scene):
    model = GS3DAdapter.from_scene(scene, GS3DConfig())
    for p in model.params.values():
        p.grad = torch.zeros_like(p)
    model.optimizer_step()  # a step with zero gradients: the values stay, the model is trained
    rows = {tuple(m): s.clone() for m, s in zip(model.params["means"].detach().tolist(),
                                                model.params["scales"].detach())}
    cut(model, 50, scene)
    for m, s in zip(model.params["means"].detach().tolist(), model.params["scales"].detach()):
        assert torch.equal(s, rows[tuple(m)])


def test_a_model_loaded_from_a_state_is_not_resized(scene):
    trained = GS3DAdapter.from_scene(scene, GS3DConfig())
    model = GS3DAdapter.from_scene(scene, GS3DConfig())
    model.load_state_dict(trained.state_dict())
    before = model.params["scales"].detach().clone()
    means = model.params["means"].detach().clone()
    cut(model, 50, scene)
    kept = [int((means == m).all(dim=1).nonzero()) for m in model.params["means"].detach()]
    assert torch.equal(model.params["scales"].detach(), before[kept])


def test_4dgs_canonical_gaussians_are_resized_by_a_first_cut():
    moving = synthetic_scene(n_train=6, n_test=2, size=16, n_points=200, time=True)
    model = GS4DAdapter.from_scene(moving, GS4DConfig())
    assert model.sized_by_spacing
    cut(model, 60, moving)
    want = dense_spacing_log(model.params["means"])
    assert torch.allclose(model.params["scales"].detach()[:, 0].double(), want, atol=1e-5)


def test_a_cut_before_training_sizes_scaffold_anchors_by_the_kept_anchors(scene):
    model = ScaffoldAdapter.from_scene(scene, ScaffoldConfig(voxel_size=0.02))
    n = model.num_primitives()
    assert n > 80
    cut(model, n // 4, scene)
    assert model.num_primitives() == n // 4
    want = dense_spacing_log(model.anchors)
    scaling = model.params["scaling"].detach()
    for col in range(6):
        assert torch.allclose(scaling[:, col].double(), want, atol=1e-5)
    # and after a step a cut leaves the scalings alone
    model = ScaffoldAdapter.from_scene(scene, ScaffoldConfig(voxel_size=0.02))
    for p in model.params.values():
        p.grad = torch.zeros_like(p)
    model.optimizer_step()
    rows = {tuple(a): s.clone() for a, s in zip(model.anchors.tolist(), model.params["scaling"].detach())}
    cut(model, n // 4, scene)
    for a, s in zip(model.anchors.tolist(), model.params["scaling"].detach()):
        assert torch.equal(s, rows[tuple(a)])
