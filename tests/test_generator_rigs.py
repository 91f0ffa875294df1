"""The generator's ``arc`` rig (a handheld sweep round the front of a scene, in 4:3 landscape
images) and ``aerial`` rig (a drone survey looking down, in 3:4 portrait images): checked against
their definitions with plain geometry, and their cameras through the rig classifiers the presets
use (an arc is neither forward-facing nor inside-out; a survey is forward-facing); and the ``thin``
variant's fence of sub-pixel posts and wires."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mvgs_plugin.data.init import CONVERGING_COSINE, CONVERGING_SPREAD, axis_spread, look_convergence
from test_inside_out import cameras_of, load_make_scene


def test_the_arc_rig_sweeps_its_arc_in_order_at_its_distances_in_landscape_images():
    ms = load_make_scene()
    views = ms.make_views("arc", 48, 12, 128)
    assert sum(v.split == "train" for v in views) == 48 and sum(v.split == "test" for v in views) == 12
    step = math.radians(ms.ARC_SPAN_DEG) / 59
    lo = math.radians(ms.ARC_CENTRE_DEG - 0.5 * ms.ARC_SPAN_DEG)
    for k, v in enumerate(views_in_rig_order(ms, views)):
        assert (v.width, v.height) == (128, 96)
        # square pixels, the principal point at the centre of the non-square image
        assert v.K[0, 0] == v.K[1, 1] and (v.K[0, 2], v.K[1, 2]) == (64.0, 48.0)
        c = v.c2w[:3, 3] - ms.TARGET
        assert ms.ARC_DIST[0] - 1e-9 <= np.linalg.norm(c) <= ms.ARC_DIST[1] + 1e-9
        az = math.atan2(c[1], c[0])
        assert abs(az - (lo + k * step)) <= 0.2 * step + 1e-9  # in order along the arc
        elev = math.degrees(math.asin(c[2] / np.linalg.norm(c)))
        assert 8.0 - 1e-9 <= elev <= 40.0 + 1e-9
        # looking at a point near the target: it projects inside the image
        x = v.w2c[:3, :3] @ ms.TARGET + v.w2c[:3, 3]
        u, w = (v.K @ x)[:2] / x[2]
        assert x[2] > 0 and 0 < u < 128 and 0 < w < 96
    # the sweep spans its 120 degrees; the horizontal field is the other variants' 45 degrees
    assert math.degrees(2 * math.atan(64.0 / views[0].K[0, 0])) == pytest.approx(ms.FOV_X_DEG)


def views_in_rig_order(ms, views):
    """The views in the order the rig made them (make_views interleaves the splits)."""
    slots = ms.pick_test_slots(len(views), sum(v.split == "test" for v in views))
    train = iter(v for v in views if v.split == "train")
    test = iter(v for v in views if v.split == "test")
    return [next(test) if k in slots else next(train) for k in range(len(views))]


def test_the_arc_rig_converges_like_an_orbit_although_it_covers_a_third_of_one():
    ms = load_make_scene()
    cams = cameras_of([v for v in ms.make_views("arc", 48, 12, 64) if v.split == "train"])
    # the presets' classifier: not forward-facing (the pyramid and the extent step rule apply)
    assert axis_spread(cams) >= CONVERGING_SPREAD
    # and not inside-out: the axes meet in front of the cameras
    assert look_convergence(cams) >= CONVERGING_COSINE
    # near the analytic spread of directions uniform over +-60 degrees in one plane,
    # 1 - E[cos^2] = 0.29 (the rig's elevations and look-at jitter move it a little)
    half = math.radians(ms.ARC_SPAN_DEG / 2)
    planar = 1.0 - (0.5 + math.sin(2 * half) / (4 * half))
    assert abs(axis_spread(cams) - planar) < 0.05


def test_the_aerial_rig_flies_its_grid_looking_down_in_portrait_images():
    ms = load_make_scene()
    views = ms.make_views("aerial", 48, 12, 128)
    for v in views:
        assert (v.width, v.height) == (96, 128)
        assert v.K[0, 0] == v.K[1, 1] and (v.K[0, 2], v.K[1, 2]) == (48.0, 64.0)
        c = v.c2w[:3, 3]
        assert ms.AERIAL_Z[0] - 1e-9 <= c[2] <= ms.AERIAL_Z[1] + 1e-9
        assert abs(c[0]) <= ms.AERIAL_HALF[0] + 0.1 + 1e-9 and abs(c[1]) <= ms.AERIAL_HALF[1] + 0.1 + 1e-9
        axis = v.c2w[:3, 2]
        # 0-20 degrees off straight down, tilted towards the middle (never away from it)
        tilt = math.degrees(math.acos(-axis[2]))
        assert tilt <= 20.0
        if math.hypot(c[0], c[1]) > 0.6:
            assert float(axis[:2] @ -c[:2]) > 0
        # the image's up is the world's +y side (the down vector of the image has y < 0)
        assert v.c2w[1, 1] < 0
        # the ground point straight below the middle of the survey lies in front of every camera
        x = v.w2c[:3, :3] @ np.array([0.0, 0.0, 0.0]) + v.w2c[:3, 3]
        assert x[2] > 0
    # the presets' classifier reads the survey as forward-facing: the axes nearly share a direction
    cams = cameras_of([v for v in views if v.split == "train"])
    assert axis_spread(cams) < CONVERGING_SPREAD


def test_the_thin_variants_fence_stands_round_the_objects_and_its_points_lie_on_it():
    ms = load_make_scene()
    fence = ms.fence_segments()
    posts = [s for s in fence if s[3] == "post"]
    wires = [s for s in fence if s[3] == "wire"]
    assert len(posts) == ms.FENCE_POSTS and len(wires) == ms.FENCE_POSTS * len(ms.FENCE_WIRE_HEIGHTS)
    for p0, p1, r, _ in posts:  # upright, on the circle, from the ground
        assert math.hypot(p0[0], p0[1]) == pytest.approx(ms.FENCE_RADIUS) and p0[2] == 0.0
        assert np.allclose(p1 - p0, [0.0, 0.0, ms.FENCE_POST_HEIGHT])
    for p0, p1, r, _ in wires:  # level, between two neighbouring post tops' circle points
        assert p0[2] == p1[2] and p0[2] in ms.FENCE_WIRE_HEIGHTS
        assert np.linalg.norm(p1 - p0) == pytest.approx(2 * ms.FENCE_RADIUS * math.sin(math.pi / ms.FENCE_POSTS))
    # every object stands inside the fence, clear of its posts and wires
    obj = ms.objects_at("thin", 0.0)
    reach = max(math.hypot(*obj.ball_centre[:2]) + obj.ball_radius, math.hypot(*obj.metal_centre[:2]) + obj.metal_radius,
                math.hypot(*obj.box_centre[:2]) + math.sqrt(2) * obj.box_half,
                math.hypot(*obj.cyl_base[:2]) + obj.cyl_radius)
    inner = ms.FENCE_RADIUS * math.cos(math.pi / ms.FENCE_POSTS) - ms.FENCE_POST_RADIUS  # the wires' closest approach
    assert reach < inner
    # sampled points lie on the cylinders' sides (at their radius from the axis, within the
    # segment), shared among them by area: 2 pi r length each
    pts = ms.sample_segments(2000, fence, np.random.default_rng(0))
    off = np.full((len(pts), len(fence)), np.inf)
    for k, (p0, p1, r, _) in enumerate(fence):
        d = p1 - p0
        t = (pts - p0) @ d / (d @ d)
        radial = np.linalg.norm(pts - (p0 + t[:, None] * d), axis=1)
        off[:, k] = np.where((t >= -1e-9) & (t <= 1 + 1e-9), np.abs(radial - r), np.inf)
    assert off.min(axis=1).max() < 1e-9
    area = np.array([2 * math.pi * r * np.linalg.norm(p1 - p0) for p0, p1, r, _ in fence])
    is_post = np.array([kind == "post" for *_, kind in fence])
    share = float(is_post[off.argmin(axis=1)].mean())
    expected = float(area[is_post].sum() / area.sum())  # 0.42
    assert abs(share - expected) < 4 * math.sqrt(expected * (1 - expected) / len(pts))


def test_the_golden_angle_rigs_test_views_stand_among_their_training_views_at_any_count():
    # Checked by plain geometry: the angle (seen from the target) from every test view to its
    # nearest training view, against the training views' own spacing. Before, 20 + 12 views put
    # every test view in a 145-degree arc no training view faced (one 50.7 degrees from any).
    ms = load_make_scene()

    def directions(views, split):
        d = np.array([v.c2w[:3, 3] - ms.TARGET for v in views if v.split == split])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    for n_test in (8, 12):
        for n_train in (10, 16, 20, 24, 30, 32, 40, 48, 64, 96):
            views = ms.make_views("default", n_train, n_test, 32)
            train, test = directions(views, "train"), directions(views, "test")
            assert len(train) == n_train and len(test) == n_test
            to_train = np.degrees(np.arccos(np.clip(test @ train.T, -1, 1))).min(1)
            among = np.degrees(np.arccos(np.clip(train @ train.T, -1, 1)))
            np.fill_diagonal(among, np.inf)
            spacing = np.median(among.min(1))
            assert to_train.max() <= 2.5 * spacing, (n_train, n_test, to_train.max(), spacing)
            if n_train >= 30:
                assert to_train.max() <= 15.0, (n_train, n_test, to_train.max())
    # 48 + 12 (every generated 360-degree scene) keeps the evenly spaced slots of the rig's order
    views = ms.make_views("default", 48, 12, 32)
    rig = ms.rig_dense(60)
    expected = np.array([rig[k] for k in sorted(ms.pick_test_slots(60, 12))])
    got = np.array([v.c2w[:3, 3] for v in views if v.split == "test"])
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_the_object_rig_looks_at_its_objects_from_below_and_above_and_its_points_are_on_them():
    ms = load_make_scene()
    for variant in ms.ALPHA_VARIANTS:
        views = ms.make_views(variant, 48, 12, 128)
        assert sum(v.split == "train" for v in views) == 48 and sum(v.split == "test" for v in views) == 12
        elev = []
        for v in views:
            c = v.c2w[:3, 3] - ms.TARGET
            assert ms.OBJECT_DIST[0] - 1e-9 <= np.linalg.norm(c) <= ms.OBJECT_DIST[1] + 1e-9
            elev.append(math.degrees(math.asin(c[2] / np.linalg.norm(c))))
            x = v.w2c[:3, :3] @ ms.TARGET + v.w2c[:3, 3]  # the optical axis passes through the target
            assert x[2] > 0 and np.allclose(x[:2], 0.0, atol=1e-9)
        lo, hi = ms.OBJECT_ELEV_DEG
        assert lo - 1e-9 <= min(elev) < lo + 5.0 and hi - 5.0 < max(elev) <= hi + 1e-9
        # even in sine: a quarter of the band's sine range holds about a quarter of the cameras
        s = np.sin(np.radians(elev))
        q = np.sin(np.radians(lo)) + 0.25 * (np.sin(np.radians(hi)) - np.sin(np.radians(lo)))
        assert abs(float((s < q).mean()) - 0.25) <= 1.0 / 60 + 1e-9
        # test views on every side of the objects (azimuth gaps under twice an even share) and at every height
        tests = [v for v in views if v.split == "test"]
        assert ms.azimuth_gap_deg([v.c2w[:3, 3] for v in tests]) <= 2 * 360.0 / 12
        test_elev = [e for e, v in zip(elev, views) if v.split == "test"]
        assert min(test_elev) < 0.0 < max(test_elev)
        cams = cameras_of(views)
        assert axis_spread(cams) >= CONVERGING_SPREAD and look_convergence(cams) >= CONVERGING_COSINE
        # no ground: every sampled point lies on one of the four objects' surfaces
        obj = ms.objects_at(variant, 0.0)
        pts = ms.sample_surface(variant, 3000, np.random.default_rng(0))
        on_ball = np.abs(np.linalg.norm(pts - obj.ball_centre, axis=1) - obj.ball_radius) < 1e-9
        on_metal = np.abs(np.linalg.norm(pts - obj.metal_centre, axis=1) - obj.metal_radius) < 1e-9
        local = (pts - obj.box_centre) @ np.linalg.inv(ms.box_to_world(obj)[:3, :3]).T
        on_box = np.abs(np.abs(local).max(axis=1) - 1.0) < 1e-9
        radial = np.linalg.norm(pts[:, :2] - obj.cyl_base[:2], axis=1)
        height = pts[:, 2] - obj.cyl_base[2]
        on_cyl = ((np.abs(radial - obj.cyl_radius) < 1e-9) & (height > -1e-9) & (height < obj.cyl_height + 1e-9)) | (
            (np.abs(height - obj.cyl_height) < 1e-9) & (radial <= obj.cyl_radius + 1e-9))
        assert (on_ball | on_metal | on_box | on_cyl).all()
        assert min(on_ball.sum(), on_metal.sum(), on_box.sum(), on_cyl.sum()) > 100
