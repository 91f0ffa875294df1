"""A budget's cut before any view (no coverage yet) keeps the object's and the far background's
shares of the model, each spread over its extent (gs3d.spread_order, gs3d.even_cut_order), in every
adapter that cuts: GS3DAdapter (GS4DAdapter through it), ScaffoldAdapter and MVGSStrategy (in
tests/test_gsplat_loop.py).

The expected subsets are built here from integer grid indices and group labels, not from the
code's own cells."""

import itertools
import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import (FAR_RESET_FRACTION, SPREAD_LEVELS, GS3DAdapter, even_cut_order,
                                       keep_scores_of, spread_order)
from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig
from mvgs_plugin.protocol import DensifyContext


def _grid_points(side: int) -> torch.Tensor:
    """side^3 points at the centres (i + 0.5) / side of a unit cube's cells, then the cube's two
    corners (0,0,0) and (1,1,1), so that the bounding cube is [0, 1]^3 exactly."""
    idx = torch.tensor(list(itertools.product(range(side), repeat=3)), dtype=torch.float64)
    return torch.cat([(idx + 0.5) / side, torch.zeros(1, 3), torch.ones(1, 3)])


def _block(points: torch.Tensor, blocks: int) -> torch.Tensor:
    """Block index (of blocks^3 equal blocks of [0, 1]^3) per point; (1,1,1) is in the last."""
    b = (points * blocks).floor().long().clamp(0, blocks - 1)
    return b[:, 0] * blocks * blocks + b[:, 1] * blocks + b[:, 2]


def _two_groups():
    """The object: an 8 x 8 x 8 grid of points in [-0.5, 0.5]^3 with the cube's two corners (514
    points); a far shell: 100 points on a sphere of radius 4 (beyond 3/4 of the farthest distance)."""
    inner = _grid_points(8) - 0.5
    g = torch.Generator().manual_seed(5)
    d = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=torch.float64), dim=1)
    return torch.cat([inner, 4.0 * d]), torch.zeros(3, dtype=torch.float64)


@pytest.mark.parametrize("blocks", [1, 2, 4, 8])
def test_every_prefix_holds_one_point_of_every_block(blocks):
    p = _grid_points(16)
    order = torch.sort(spread_order(p), descending=True, stable=True).indices
    kept = order[:blocks ** 3]
    assert sorted(_block(p[kept], blocks).tolist()) == list(range(blocks ** 3))


def test_a_lone_point_comes_before_a_dense_cluster():
    g = torch.Generator().manual_seed(3)
    cluster = 0.5 + 0.01 * torch.rand(500, 3, generator=g, dtype=torch.float64)
    lone = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 1.0]], dtype=torch.float64)
    p = torch.cat([cluster, lone])
    top = set(torch.sort(spread_order(p), descending=True, stable=True).indices[:8].tolist())
    assert set(range(500, 504)) <= top


def test_scores_range_ties_and_degenerate_inputs():
    p = _grid_points(4)
    s = spread_order(p)
    assert s.dtype == torch.float64 and bool((s > 0).all()) and bool((s <= 1).all())
    assert len(torch.unique(s)) == len(s)  # a strict order
    assert spread_order(torch.zeros(0, 3)).shape == (0,)
    same = spread_order(torch.ones(5, 3))  # one position: one representative, the rest on the last level
    assert int((same > (SPREAD_LEVELS - 1) / (SPREAD_LEVELS + 1)).sum()) == 1 and bool((same > 0).all())
    # translation and scale do not change the order; float32 input gives the float64 order
    assert torch.equal(torch.argsort(spread_order(p * 7.5 - 3.0)), torch.argsort(s))
    assert torch.equal(torch.argsort(spread_order(p.float())), torch.argsort(s))


@pytest.mark.parametrize("keep", [61, 306, 500])
def test_the_cut_keeps_each_groups_share(keep):
    """Each group (inside / beyond the far line) keeps its share of the rows within one, and the
    object's kept points cover it: one or more in every block of the finest grid of 2^j blocks a
    side with no more blocks than kept points."""
    p, c = _two_groups()
    assert math.isclose(FAR_RESET_FRACTION * 4.0, 3.0)  # the shell is beyond the line, the object inside it
    kept = torch.sort(even_cut_order(p, c), descending=True, stable=True).indices[:keep]
    assert abs(int((kept >= 514).sum()) - keep * 100 / 614) <= 1
    inner = kept[kept < 514]
    j = int(math.floor(math.log(len(inner)) / math.log(8) + 1e-9))  # 8^j <= kept < 8^(j+1)
    assert j >= 1
    assert int(torch.bincount(_block(p[inner] + 0.5, 2 ** j), minlength=8 ** j).min()) >= 1
    if j == 1:  # and no block of the next grid (64 blocks, more than kept) holds two
        assert int(torch.bincount(_block(p[inner] + 0.5, 4), minlength=64).max()) <= 1
    # without a centre: one group, the plain spread, which puts the far shell first
    top = torch.sort(even_cut_order(p), descending=True, stable=True).indices[:100]
    assert int((top >= 514).sum()) > 60


def test_keep_scores_use_the_cut_order_only_before_any_view():
    p, c = _two_groups()
    n = len(p)
    opacity = torch.full((n,), 0.1, dtype=torch.float64)
    assert torch.allclose(keep_scores_of(opacity, torch.zeros(n, dtype=torch.float64), p, c), 0.1 * even_cut_order(p, c))
    coverage = torch.rand(n, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert torch.allclose(keep_scores_of(opacity, coverage, p, c), 0.1 * coverage)


def _group_counts(positions):
    """(inside, beyond) counts of rows at the object's grid / the shell (told by radius)."""
    r = torch.linalg.vector_norm(positions.double(), dim=1)
    return int((r < 2).sum()), int((r >= 2).sum())


def test_gs3d_first_cut_keeps_the_shares():
    p, c = _two_groups()
    n = len(p)
    a = GS3DAdapter.from_tensors(p.float(), scales=torch.full((n, 3), 0.01), opacities=torch.full((n,), 0.1),
                                 rgb=torch.rand(n, 3, generator=torch.Generator().manual_seed(2)),
                                 scene_extent=1.0, scene_center=c)
    rep = a.densify(DensifyContext(step=0, grad_threshold=math.inf, scene_extent=1.0, scene_center=c,
                                   max_primitives=306))
    assert rep.after == 306 and rep.extra["shed_to_cap"] == 308
    inside, beyond = _group_counts(a.params["means"].detach())
    assert abs(beyond - 306 * 100 / 614) <= 1 and inside + beyond == 306


def test_scaffold_first_cut_keeps_the_shares():
    p, c = _two_groups()
    a = len(p)
    ad = ScaffoldAdapter(p, torch.zeros(a, 4, dtype=torch.float64), torch.zeros(a, 2, 3, dtype=torch.float64),
                         torch.zeros(a, 6, dtype=torch.float64), scene_extent=1.0, voxel_size=0.1,
                         config=ScaffoldConfig(feat_dim=4, n_offsets=2))
    rep = ad.densify(DensifyContext(step=0, grad_threshold=math.inf, scene_extent=1.0, scene_center=c,
                                    max_primitives=306))
    assert rep.after == 306 and rep.extra["shed_to_cap"] == 308
    inside, beyond = _group_counts(ad.anchors)
    assert abs(beyond - 306 * 100 / 614) <= 1
    # after views were folded in, their opacity decides, not the positions
    ad2 = ScaffoldAdapter(p, torch.zeros(a, 4, dtype=torch.float64), torch.zeros(a, 2, 3, dtype=torch.float64),
                          torch.zeros(a, 6, dtype=torch.float64), scene_extent=1.0, voxel_size=0.1,
                          config=ScaffoldConfig(feat_dim=4, n_offsets=2))
    ad2.opacity_accum = torch.linspace(1.0, 2.0, a, dtype=torch.float64)  # the last rows (the shell) show most
    ad2.densify(DensifyContext(step=0, grad_threshold=math.inf, scene_extent=1.0, scene_center=c, max_primitives=100))
    assert _group_counts(ad2.anchors) == (0, 100)
