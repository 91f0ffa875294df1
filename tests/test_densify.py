"""MVAD threshold rule and CRD box geometry on constructed rigs with known answers."""

import math

import numpy as np
import pytest
import torch

from mvgs_plugin.camera import Camera
from mvgs_plugin.densify import best_windows, closest_points, cross_ray_boxes, mvad_threshold
from mvgs_plugin.testing import look_at

BETA = 2e-4


def ring(angles_deg, radius=3.0, center=(0.0, 0.0, 0.0)):
    c = torch.tensor(center, dtype=torch.float64)
    return torch.stack([c + radius * torch.tensor([math.cos(math.radians(a)), math.sin(math.radians(a)), 0.0],
                                                  dtype=torch.float64) for a in angles_deg])


# ---- MVAD -----------------------------------------------------------------------------------

def test_one_camera_keeps_the_threshold():
    assert mvad_threshold(ring([0]), BETA) == BETA


@pytest.mark.parametrize("angle,fires", [(30, False), (59, False), (61, True), (180, True)])
def test_chord_on_the_unit_sphere(angle, fires):
    # Two cameras `angle` degrees apart about the centre: chord = 2 sin(angle / 2) >= 1 iff angle >= 60.
    assert mvad_threshold(ring([0, angle]), BETA) == (BETA / 2 if fires else BETA)


def test_all_cameras_at_one_point():
    centers = torch.tensor([[1.0, 2.0, 3.0]] * 4, dtype=torch.float64)
    assert mvad_threshold(centers, BETA) == BETA


def test_camera_at_the_normalisation_centre_has_no_direction():
    at_centre = torch.zeros(1, 3, dtype=torch.float64)
    assert mvad_threshold(torch.cat([at_centre, ring([0])]), BETA) == BETA  # no valid pair
    assert mvad_threshold(torch.cat([at_centre, ring([0, 180])]), BETA) == BETA / 2


def test_duplicated_cameras_and_the_fraction_rule():
    centers = ring([0, 0, 180])  # pairs: 0 (the duplicates), 2, 2
    assert mvad_threshold(centers, BETA, rule="any") == BETA / 2
    assert mvad_threshold(centers, BETA, rule=0.6) == BETA / 2  # 2/3 of the pairs
    assert mvad_threshold(centers, BETA, rule=0.9) == BETA
    assert mvad_threshold(ring([0, 0]), BETA) == BETA


def test_normalisation_centre_matters():
    # A rig that surrounds (10, 0, 0) closely: seen from the world origin (the released code)
    # every camera sits in almost the same direction; about the rig's own centre they do not.
    centers = ring([0, 120, 240], radius=1.0, center=(10.0, 0.0, 0.0))
    assert mvad_threshold(centers, BETA, origin=None) == BETA
    assert mvad_threshold(centers, BETA, origin=torch.tensor([10.0, 0.0, 0.0])) == BETA / 2


def test_rotation_term():
    centers = ring([0, 10])  # chord 0.17: translation alone does not fire
    axes = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]], dtype=torch.float64)  # opposite optical axes
    assert mvad_threshold(centers, BETA, axes=axes, rotation_weight=0.0) == BETA
    assert mvad_threshold(centers, BETA, axes=axes, rotation_weight=1.0) == BETA / 2
    with pytest.raises(ValueError, match="optical axes"):
        mvad_threshold(centers, BETA, rotation_weight=1.0)


@pytest.mark.parametrize("rule", ["all", 0.0, 1.5])
def test_bad_rule(rule):
    with pytest.raises(ValueError, match="rule must be 'any' or a fraction"):
        mvad_threshold(ring([0, 90]), BETA, rule=rule)


# ---- CRD ------------------------------------------------------------------------------------

def test_one_hot_window_is_chosen_and_partial_strips_are_skipped():
    maps = torch.rand(2, 50, 90, generator=torch.Generator().manual_seed(0)) * 0.1
    maps[0, 20:40, 40:80] = 1.0  # window (row 1, column 1) of a 20 x 40 tiling
    maps[1, 40:50, 80:90] = 5.0  # only in the partial last strips: not a candidate
    maps[1, 0:20, 0:40] += 0.5
    win = best_windows(maps, (20, 40))
    assert win[0].tolist() == [20, 40, 20, 40]
    assert win[1].tolist() == [0, 0, 20, 40]


def test_window_larger_than_the_image_is_clamped():
    assert best_windows(torch.rand(1, 6, 8), (20, 40))[0].tolist() == [0, 0, 6, 8]


def test_closest_points_of_skew_lines():
    o1, d1 = torch.tensor([0.0, 0, 0]), torch.tensor([1.0, 0, 0])
    o2, d2 = torch.tensor([0.0, 1.0, 2.0]), torch.tensor([0.0, -1.0, 0])
    t1, t2, mid, miss, sin2 = closest_points(o1, d1, o2, d2)
    assert float(t1) == pytest.approx(0.0) and float(t2) == pytest.approx(1.0)
    assert mid.tolist() == pytest.approx([0.0, 0.0, 1.0]) and float(miss) == pytest.approx(2.0)
    assert float(sin2) == pytest.approx(1.0)


def camera(uid, eye, target=(0.0, 0.0, 0.0), size=64, f=64.0):
    K = [[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]]
    return Camera(uid, f"c{uid}", K, look_at(eye, target), size, size)


def centred_window(size, h, w):
    return torch.tensor([(size - h) // 2, (size - w) // 2, h, w])


def reference_box(cams, windows, with_miss=False):
    """Independent: each corner's two rays from K^-1 and the pose, closest points by least squares."""
    mids, misses = [], []
    for k in range(4):
        pts = []
        for cam, win in zip(cams, windows):
            top, left, h, w = win.tolist()
            u = [left, left + w, left, left + w][k]
            v = [top, top, top + h, top + h][k]
            K, w2c = cam.K.numpy(), cam.world_to_camera.numpy()
            d_cam = np.linalg.solve(K, np.array([u, v, 1.0]))
            R, t = w2c[:3, :3], w2c[:3, 3]
            pts.append((-R.T @ t, R.T @ d_cam / np.linalg.norm(d_cam)))
        (o1, d1), (o2, d2) = pts
        A = np.stack([d1, -d2], axis=1)
        t, *_ = np.linalg.lstsq(A, o2 - o1, rcond=None)
        mids.append(0.5 * ((o1 + t[0] * d1) + (o2 + t[1] * d2)))
        misses.append(np.linalg.norm((o1 + t[0] * d1) - (o2 + t[1] * d2)))
    mids = np.array(mids)
    return (mids.min(0), mids.max(0)) + ((max(misses),) if with_miss else ())


def test_two_cameras_box_contains_the_point_and_has_the_predicted_size():
    # Two cameras 90 degrees apart, 4 units from the origin, both looking at it; their centred
    # windows see the origin, so the box must contain it. Each corner ray pair is skew; the
    # expected box comes from an independent least-squares computation.
    cams = [camera(0, (4.0, 0.0, 0.0)), camera(1, (0.0, 4.0, 0.0))]
    windows = torch.stack([centred_window(64, 8, 16)] * 2)
    boxes, pairs = cross_ray_boxes(cams, windows, forward_only=True, max_miss=10.0, min_angle_deg=1.0)
    assert boxes.shape == (1, 2, 3) and pairs.tolist() == [[0, 1]]
    lo, hi = boxes[0]
    assert (lo <= 0).all() and (hi >= 0).all()
    ref_lo, ref_hi = reference_box(cams, windows)
    assert np.allclose(lo.numpy(), ref_lo, atol=1e-9) and np.allclose(hi.numpy(), ref_hi, atol=1e-9)
    # Scale check by hand: the window spans 16 px of a 64 px focal length at distance 4, i.e.
    # 1 unit across; the box's horizontal extent is of that order, its vertical one half of it.
    size = (hi - lo).numpy()
    assert 0.5 < size[0] < 1.5 and 0.5 < size[1] < 1.5 and 0.25 < size[2] < 0.75


def test_three_cameras_give_three_boxes_around_the_point():
    target = (0.3, -0.2, 0.1)
    cams = [camera(i, eye, target) for i, eye in enumerate([(4.0, 0.0, 1.0), (0.0, 4.0, 0.5), (-3.0, -3.0, 2.0)])]
    windows = torch.stack([centred_window(64, 6, 6)] * 3)
    boxes, pairs = cross_ray_boxes(cams, windows, max_miss=1.0)
    assert sorted(map(tuple, pairs.tolist())) == [(0, 1), (0, 2), (1, 2)]
    t = torch.tensor(target, dtype=torch.float64)
    assert ((boxes[:, 0] <= t) & (t <= boxes[:, 1])).all()


def test_parallel_rays_give_no_box():
    # A stereo pair with parallel optical axes: corresponding corner rays are parallel.
    K = [[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]]
    cams = [Camera(i, f"s{i}", K, look_at((x, 0.0, -4.0), (x, 0.0, 0.0), up=(0.0, 1.0, 0.0)), 64, 64)
            for i, x in enumerate((0.0, 0.5))]
    windows = torch.stack([centred_window(64, 8, 8)] * 2)
    boxes, _ = cross_ray_boxes(cams, windows, forward_only=False)
    assert boxes.shape[0] == 0


def test_forward_only_drops_crossings_behind_a_camera():
    # Camera 1 looks away from the point where the rays' lines meet: the crossing is behind it.
    cams = [camera(0, (4.0, 0.0, 0.0)), camera(1, (0.0, 4.0, 0.0), target=(0.0, 8.0, 0.0))]
    windows = torch.stack([centred_window(64, 4, 4)] * 2)
    assert cross_ray_boxes(cams, windows, forward_only=True)[0].shape[0] == 0
    assert cross_ray_boxes(cams, windows, forward_only=False)[0].shape[0] == 1


def test_max_miss_and_clipping():
    cams = [camera(0, (4.0, 0.0, 0.0)), camera(1, (0.0, 4.0, 1.0), target=(0.0, 0.0, 1.0))]  # axes 1 unit apart
    windows = torch.stack([centred_window(64, 2, 2)] * 2)
    assert cross_ray_boxes(cams, windows, max_miss=0.5)[0].shape[0] == 0
    boxes, _ = cross_ray_boxes(cams, windows, max_miss=2.0)
    assert boxes.shape[0] == 1
    # The box spans z in [0.4375, 0.5625] (midway between the two axes at z = 0 and z = 1).
    assert boxes[0, 0, 2] < 0.5 < boxes[0, 1, 2]
    bounds = torch.tensor([[-1.0, -1.0, 0.5], [1.0, 1.0, 2.0]], dtype=torch.float64)
    clipped, _ = cross_ray_boxes(cams, windows, max_miss=2.0, bounds=bounds)
    assert float(clipped[0, 0, 2]) == 0.5 and torch.equal(clipped[0, 1], boxes[0, 1])
    outside = torch.tensor([[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]], dtype=torch.float64)
    assert cross_ray_boxes(cams, windows, max_miss=2.0, bounds=outside)[0].shape[0] == 0


def test_boxes_grow_by_half_the_largest_miss():
    # The two cameras' axes pass 1 unit apart, so every midpoint is uncertain by about 0.5: the
    # padded box is the plain one grown on every side by half the pair's largest miss.
    cams = [camera(0, (4.0, 0.0, 0.0)), camera(1, (0.0, 4.0, 1.0), target=(0.0, 0.0, 1.0))]
    windows = torch.stack([centred_window(64, 8, 8)] * 2)
    lo, hi, miss = reference_box(cams, windows, with_miss=True)
    assert 0.9 < miss < 1.1
    padded, _ = cross_ray_boxes(cams, windows, pad_by_miss=True)
    np.testing.assert_allclose(padded[0, 0].numpy(), lo - miss / 2, atol=1e-9)
    np.testing.assert_allclose(padded[0, 1].numpy(), hi + miss / 2, atol=1e-9)


def test_boxes_contain_is_the_public_inside_test_in_world_coordinates():
    """boxes_contain against a plain loop over points and boxes, with points on faces (not
    inside: strict), inside two boxes at once, and enough points to take several blocks."""
    import mvgs_plugin.densify.crd as crd
    from mvgs_plugin.densify import boxes_contain

    g = torch.Generator().manual_seed(5)
    boxes = torch.tensor([[[0.0, 0, 0], [1, 1, 1]], [[0.5, 0.5, 0.5], [2, 2, 2]], [[-3, -1, 5], [-2, 1, 6]]],
                         dtype=torch.float64)
    pts = torch.cat([torch.rand(3000, 3, generator=g, dtype=torch.float64) * 8 - 4,
                     torch.tensor([[1.0, 0.5, 0.5], [0.75, 0.75, 0.75], [-2.5, 0.0, 5.5], [0.0, 0.0, 0.0]],
                                  dtype=torch.float64)]).float()
    want = torch.tensor([any(bool(((p.double() > b[0]) & (p.double() < b[1])).all()) for b in boxes) for p in pts])
    old = crd._CHUNK_ELEMS
    try:
        crd._CHUNK_ELEMS = 90  # blocks of 10 points
        got = boxes_contain(pts, boxes)
    finally:
        crd._CHUNK_ELEMS = old
    assert torch.equal(got, want) and got[-3] and got[-2] and not got[-4] and not got[-1]
    assert boxes_contain(pts, boxes[:0]).sum() == 0 and boxes_contain(pts[:0], boxes).numel() == 0
