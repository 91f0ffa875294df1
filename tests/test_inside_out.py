"""Inside-out rigs (cameras that stand together and look outwards, a room shot from its middle):
mvgs_plugin.data.init.look_convergence tells them from rigs that look in at a scene, and the
background shell and the random init region follow it. Checked on analytic rigs whose answer is
known without the code: rings looking in or out, axes through a known point, one shared centre."""

from __future__ import annotations

import math

import pytest
import torch

from mvgs_plugin.data.init import (
    CONVERGING_COSINE, FAR_OVER_NEAR, background_shell, init_region, look_convergence, random_init_points,
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


def test_a_ring_looking_in_converges_fully_and_one_looking_out_is_minus_one():
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


def test_the_generated_rigs_fall_on_either_side_of_the_threshold():
    assert look_convergence(orbit(n=24, radius=4.0, height=2.0)) > CONVERGING_COSINE
    assert look_convergence(inside_out_ring()) < CONVERGING_COSINE


def test_an_inside_out_rig_gets_no_background_shell_and_an_orbit_still_does():
    grey = constant_images([(0.5, 0.5, 0.5)] * 12)
    cams = inside_out_ring()
    centre = torch.stack([c.center for c in cams]).mean(0)
    xyz, rgb, said = background_shell(cams, centre, 500, grey)
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    assert "look convergence" in said and "no background shell" in said
    ring = orbit(n=8)
    xyz, _, said = background_shell(ring, torch.stack([c.center for c in ring]).mean(0), 500, grey)
    assert xyz.shape[0] > 0, said


def depth_in(cam, p):
    """Camera-space depth of p, and whether p projects inside the image (independent pinhole)."""
    x = cam.world_to_camera[:3, :3] @ p + cam.world_to_camera[:3, 3]
    u = cam.K[0, 0] * x[0] / x[2] + cam.K[0, 2]
    v = cam.K[1, 1] * x[1] / x[2] + cam.K[1, 2]
    return float(x[2]), bool(x[2] > 0 and 0 <= u <= cam.width and 0 <= v <= cam.height)


def test_an_inside_out_rig_draws_random_points_in_its_frusta_beyond_the_cameras():
    cams = inside_out_ring(radius=0.3)
    centers = torch.stack([c.center for c in cams])
    radius = float(torch.linalg.norm(centers - centers.mean(0), dim=1).max())
    region = init_region(cams, centers.mean(0), extent=1.1 * radius)
    assert region.kind == "frusta", region.description
    assert region.near == pytest.approx(radius) and region.far == pytest.approx(FAR_OVER_NEAR * radius)
    assert "inside-out" in region.description
    pts = region.sample(400, torch.Generator().manual_seed(3))
    for p in pts:
        # some camera sees it at a depth within [near, far] (the 3DGS cube would put it among the cameras)
        assert any(depth_in(c, p)[1] and radius - 1e-9 <= depth_in(c, p)[0] <= FAR_OVER_NEAR * radius + 1e-9
                   for c in cams)


def test_an_inside_out_rig_of_one_centre_has_no_depth_cue_and_keeps_the_cube():
    c = (0.0, 0.0, 1.0)
    cams = [look(c, (math.cos(a), math.sin(a), 1.0), uid=i) for i, a in enumerate(torch.linspace(0, 6.0, 8).tolist())]
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
    assert xyz.shape == (50, 3) and "inside-out" in said
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


def test_the_generators_room_rig_is_inside_out_and_inside_its_room():
    from mvgs_plugin.camera import Camera
    from mvgs_plugin.data.init import CONVERGING_SPREAD, axis_spread
    ms = load_make_scene()
    views = ms.make_views("room", 48, 12, 64)
    assert sum(v.split == "train" for v in views) == 48 and sum(v.split == "test" for v in views) == 12
    cams = [Camera(uid=i, name=v.name, K=torch.tensor(v.K), world_to_camera=torch.tensor(v.w2c),
                   width=v.width, height=v.height) for i, v in enumerate(views)]
    assert axis_spread(cams) >= CONVERGING_SPREAD  # spread like an orbit's ...
    assert look_convergence(cams) < CONVERGING_COSINE  # ... but looking out
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
