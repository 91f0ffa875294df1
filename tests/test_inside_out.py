"""Rigs whose axes spread but do not meet (cameras that stand together and look outwards, a room
shot from its middle; also walks and several orbits): mvgs_plugin.data.init.look_convergence
measures it, the background shell is dropped when the scene's points lie beyond its sphere, and
random init draws from the cube and the frusta for photo-consistency to choose. Checked on
analytic rigs whose answer is known without the code (rings looking in or out, axes through a
known point, one shared centre) and on the generator's rigs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mvgs_plugin.data.init import (
    CONVERGING_COSINE, FAR_OVER_NEAR, SHELL_RADIUS, background_shell, init_region, look_convergence, random_init_points,
)
from test_background_shell import constant_images, orbit
from test_forward_init import look


def inside_out_ring(n=12, radius=0.3, height=1.0, f=40.0, size=32):
    """n cameras on a small level circle about (0, 0, height), each looking radially outwards
    (and 0.2 down), like a room scanned from its middle."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        c = (radius * math.cos(a), radius * math.sin(a), height)
        cams.append(look(c, (3.0 * math.cos(a), 3.0 * math.sin(a), height - 0.2 * 2.7), f, size, i))
    return cams


def axis(cam):
    return cam.camera_to_world[:3, 2]


def test_a_ring_looking_in_converges_fully_and_one_looking_out_is_negative():
    assert look_convergence(orbit(n=8)) == pytest.approx(1.0, abs=1e-9)
    # Outward ring: by symmetry the point nearest all axes lies on the ring's vertical axis,
    # (0, 0, z*); z* is found here by a dense scan of the least-squares objective (no linear
    # algebra), and each camera's direction to that point is behind its outward heading.
    cams = inside_out_ring()
    centers = torch.stack([c.center for c in cams])
    d = torch.stack([axis(c) / torch.linalg.norm(axis(c)) for c in cams])
    # minimise sum |(I - d d^T)(p - c)|^2 over p = (0, 0, z) by a dense scan (no linear algebra)
    zs = torch.linspace(-2.0, 4.0, 60001, dtype=torch.float64)
    p = torch.zeros(len(zs), 3, dtype=torch.float64)
    p[:, 2] = zs
    v = p[:, None, :] - centers[None]  # [Z, n, 3]
    off_axis = v - (v * d[None]).sum(-1, keepdim=True) * d[None]
    z_star = zs[off_axis.square().sum((-1, -2)).argmin()]
    to_point = torch.tensor([0.0, 0.0, float(z_star)], dtype=torch.float64) - centers
    expected = float(((to_point * d).sum(1) / torch.linalg.norm(to_point, dim=1)).mean())
    assert expected < -0.5  # the cameras look away from the point their axes pass nearest
    assert look_convergence(cams) == pytest.approx(expected, abs=1e-4)


def test_axes_through_one_point_count_plus_one_facing_it_and_minus_one_facing_away():
    q = (1.0, 2.0, 0.5)
    toward = look((0.0, 0.0, 0.0), q, uid=0)
    away = look((3.0, 0.0, 0.0), (3.0 + (3.0 - q[0]), -q[1], -q[2]), uid=1)  # its axis line passes q, pointing away
    third = look((0.0, 4.0, 1.0), q, uid=2)
    assert look_convergence([toward, third]) == pytest.approx(1.0, abs=1e-9)
    assert look_convergence([toward, away, third]) == pytest.approx((1.0 - 1.0 + 1.0) / 3.0, abs=1e-9)


def test_cameras_at_one_centre_count_zero():
    c = (0.5, -0.2, 1.0)
    cams = [look(c, (c[0] + math.cos(a), c[1] + math.sin(a), c[2]), uid=i)
            for i, a in enumerate([0.0, 1.5, 3.0, 4.5])]
    assert look_convergence(cams) == pytest.approx(0.0, abs=1e-6)


def test_the_analytic_rigs_fall_on_either_side_of_the_threshold():
    assert look_convergence(orbit(n=24, radius=4.0, height=2.0)) > CONVERGING_COSINE
    assert look_convergence(inside_out_ring()) < CONVERGING_COSINE


def test_the_shell_is_dropped_when_the_points_lie_beyond_it_and_kept_when_they_lie_inside():
    grey = constant_images([(0.5, 0.5, 0.5)] * 12)
    cams = inside_out_ring()
    centre = torch.stack([c.center for c in cams]).mean(0)
    rig = float(torch.linalg.norm(torch.stack([c.center for c in cams]) - centre, dim=1).max())
    # walls all round at 2.5 from the middle: median distance 2.5 > the sphere's 2 x 0.3
    a = torch.linspace(0, 2 * math.pi, 200, dtype=torch.float64)
    walls = centre + torch.stack([2.5 * torch.cos(a), 2.5 * torch.sin(a), torch.zeros_like(a)], 1)
    xyz, rgb, said = background_shell(cams, centre, 500, grey, points=walls)
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    assert "beyond its sphere" in said and f"{SHELL_RADIUS * rig:.4g}" in said
    # the same rig with its content inside the sphere (the median point at 0.5 x its radius) keeps it
    inside = centre + (0.5 * SHELL_RADIUS * rig / 2.5) * (walls - centre)
    xyz, _, said = background_shell(cams, centre, 500, grey, points=inside)
    assert xyz.shape[0] > 0, said
    # without points the rig's look decides: outwards, none; an orbit looking in, a shell
    xyz, _, said = background_shell(cams, centre, 500, grey)
    assert xyz.shape[0] == 0 and "look convergence" in said
    ring = orbit(n=8)
    xyz, _, said = background_shell(ring, torch.stack([c.center for c in ring]).mean(0), 500, grey)
    assert xyz.shape[0] > 0, said


def test_two_orbits_round_two_objects_keep_their_shell_given_their_points():
    """Two rings of cameras about objects 10 apart do not look at one place (their axes meet at
    two), but their points lie inside the sphere: the shell stays."""
    left = [look((-5 + 2 * math.cos(t), 2 * math.sin(t), 0.5), (-5.0, 0.0, 0.0), uid=i)
            for i, t in enumerate(torch.linspace(0, 6.0, 8).tolist())]
    right = [look((5 + 2 * math.cos(t), 2 * math.sin(t), 0.5), (5.0, 0.0, 0.0), uid=8 + i)
             for i, t in enumerate(torch.linspace(0, 6.0, 8).tolist())]
    cams = left + right
    assert look_convergence(cams) < CONVERGING_COSINE
    centre = torch.stack([c.center for c in cams]).mean(0)
    objects = torch.tensor([[-5.0, 0.0, 0.0], [5.0, 0.0, 0.0]], dtype=torch.float64).repeat(50, 1)
    xyz, _, said = background_shell(cams, centre, 500, constant_images([(0.5, 0.5, 0.5)] * 16), points=objects)
    assert xyz.shape[0] > 0, said


def depth_in(cam, p):
    """Camera-space depth of p, and whether p projects inside the image (independent pinhole)."""
    x = cam.world_to_camera[:3, :3] @ p + cam.world_to_camera[:3, 3]
    u = cam.K[0, 0] * x[0] / x[2] + cam.K[0, 2]
    v = cam.K[1, 1] * x[1] / x[2] + cam.K[1, 2]
    return float(x[2]), bool(x[2] > 0 and 0 <= u <= cam.width and 0 <= v <= cam.height)


def test_an_inside_out_rig_draws_half_its_candidates_in_the_cube_and_half_in_its_frusta():
    cams = inside_out_ring(radius=0.3)
    centers = torch.stack([c.center for c in cams])
    radius = float(torch.linalg.norm(centers - centers.mean(0), dim=1).max())
    centre, extent = centers.mean(0), 1.1 * radius
    region = init_region(cams, centre, extent=extent)
    assert region.kind == "cube+frusta", region.description
    assert region.near == pytest.approx(radius) and region.far == pytest.approx(FAR_OVER_NEAR * radius)
    pts = region.sample(401, torch.Generator().manual_seed(3))
    assert pts.shape == (401, 3)
    assert bool(((pts[:200] - centre).abs() <= extent + 1e-9).all())  # the 3DGS cube
    for p in pts[200:]:
        # some camera sees it at a depth within [near, far]
        assert any(depth_in(c, p)[1] and radius - 1e-9 <= depth_in(c, p)[0] <= FAR_OVER_NEAR * radius + 1e-9
                   for c in cams)
    # the frusta half lies outside the cube: the content the rig looks out at
    assert float((pts[200:] - centre).abs().max(dim=1).values.median()) > extent


def test_a_fanning_rig_whose_axes_share_a_direction_gets_the_forward_rule():
    """Axes fanned +-40 degrees about +z (spread above the forward threshold, mean axis shared,
    meeting behind the cameras): the frusta with the forward rule's depth scan, asked for
    (kind="frusta", the triangulation's fill) or not (the cube about five cameras 0.4 apart
    would hold none of what they look at)."""
    cams = [look((0.1 * i, 0.0, 0.0), (0.1 * i + math.tan(math.radians(a)), 0.0, 1.0), uid=i)
            for i, a in enumerate([-40.0, -20.0, 0.0, 20.0, 40.0])]
    region = init_region(cams, torch.stack([c.center for c in cams]).mean(0), extent=0.3, kind="frusta")
    assert region.kind == "frusta" and "first depth" in region.description, region.description
    region = init_region(cams, torch.stack([c.center for c in cams]).mean(0), extent=0.3)
    assert region.kind == "frusta" and "meet nowhere in front" in region.description, region.description


@pytest.mark.parametrize("jitter", [0.0, 1e-9])
def test_an_inside_out_rig_of_one_centre_has_no_depth_cue_and_keeps_the_cube(jitter):
    c = (0.0, 0.0, 1.0)
    cams = [look((c[0] + jitter * i, c[1], c[2]), (math.cos(a), math.sin(a), 1.0), uid=i)
            for i, a in enumerate(torch.linspace(0, 6.0, 8).tolist())]
    region = init_region(cams, torch.tensor(c, dtype=torch.float64), extent=1.0)
    assert region.kind == "cube" and "no depth cue" in region.description


def test_random_init_of_an_inside_out_scene_keeps_points_where_the_views_agree():
    """A scene-like object with flat grey views: the photo-consistency filter of the frusta path
    runs (colours from the views), where the cube path would draw colours at random."""
    cams = inside_out_ring(n=8)

    class FakeScene:
        train_cameras = cams
        center = torch.stack([c.center for c in cams]).mean(0)
        extent = 0.33
        image = staticmethod(constant_images([(0.4, 0.4, 0.4)] * 8))

    xyz, rgb, said = random_init_points(FakeScene, 50, torch.Generator().manual_seed(0))
    assert xyz.shape == (50, 3) and "photo-consistency chooses" in said
    assert torch.allclose(rgb, torch.full_like(rgb, 0.4), atol=1e-6)


def load_make_scene():
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "tools" / "make_scene.py"
    spec = importlib.util.spec_from_file_location("make_scene_for_tests", path)
    module = importlib.util.module_from_spec(spec)
    import sys
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)  # numpy only at import; Mitsuba is imported by main()
    return module


def cameras_of(views):
    """mvgs_plugin Cameras of the generator's Views (both OpenCV world-to-camera and pinhole K)."""
    from mvgs_plugin.camera import Camera
    return [Camera(uid=i, name=v.name, K=torch.tensor(v.K), world_to_camera=torch.tensor(v.w2c),
                   width=v.width, height=v.height) for i, v in enumerate(views)]


def test_the_generators_room_rig_looks_out_from_inside_its_room_and_its_360_rigs_look_in():
    from mvgs_plugin.data.init import CONVERGING_SPREAD, axis_spread
    ms = load_make_scene()
    views = ms.make_views("room", 48, 12, 64)
    assert sum(v.split == "train" for v in views) == 48 and sum(v.split == "test" for v in views) == 12
    cams = cameras_of(views)
    assert axis_spread(cams) >= CONVERGING_SPREAD  # spread like an orbit's ...
    assert look_convergence(cams) < CONVERGING_COSINE  # ... but looking out
    for variant in ("default", "sparse", "clutter", "moving"):  # the generator's rigs that look in
        vs = ms.make_views(variant, 48 if variant != "sparse" else 10, 12, 64)
        ring = cameras_of(vs)
        assert look_convergence(ring) > 0.99, variant
    for v in views:
        c = v.c2w[:3, 3]
        assert math.hypot(c[0], c[1]) <= ms.ROOM_EYE_RADIUS + 1e-9
        assert ms.ROOM_EYE_Z[0] - 1e-9 <= c[2] <= ms.ROOM_EYE_Z[1] + 1e-9
    # every surface of the room faces its inside: the normal (third column) points at the middle
    middle = torch.tensor([0.0, 0.0, ms.ROOM_HEIGHT / 2], dtype=torch.float64)
    for name, M in ms.room_rects().items():
        M = torch.tensor(M)
        assert float(M[:3, 2] @ (middle - M[:3, 3])) > 0, name
    # the primitives stand inside the walls and on the floor
    for p in ms.room_prims():
        assert max(abs(p.centre[0]), abs(p.centre[1])) + p.footprint < ms.ROOM_HALF
        assert p.centre[2] - (p.size if p.kind != "cylinder" else 0.0) == pytest.approx(0.0, abs=1e-9)


def test_the_generators_room_walk_does_not_meet_and_walks_its_loop():
    ms = load_make_scene()
    views = ms.make_views("room-walk", 48, 12, 64)
    cams = cameras_of(views)
    assert look_convergence(cams) < CONVERGING_COSINE
    for v in views:
        c = v.c2w[:3, 3]
        assert math.hypot(c[0], c[1]) == pytest.approx(ms.ROOM_WALK_RADIUS)
        # looking ahead along the loop: the axis' horizontal part is within 30 degrees of the tangent
        axis = v.c2w[:3, 2]
        tangent = np.array([-c[1], c[0], 0.0]) / math.hypot(c[0], c[1])
        horizontal = np.array([axis[0], axis[1], 0.0]) / math.hypot(axis[0], axis[1])
        assert float(horizontal @ tangent) >= math.cos(math.radians(30.0)) - 1e-9
