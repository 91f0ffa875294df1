"""Random initialisation of a rig round a still scene without points (2026-12-01): one point per
pixel ray of the training views, at the depth along it that the neighbouring views' colours agree
on (mvgs_plugin.data.init.ray_sweep). The images here are made by exact ray-sphere intersection,
not by any renderer of the package, so where the points should be is known in closed form."""

from __future__ import annotations

import argparse
import math

import torch

from mvgs_plugin.camera import Camera
from mvgs_plugin.data.init import InitRegion, init_region, random_init_points, ray_sweep
from mvgs_plugin.data.triangulate import fill_points

RADIUS = 1.5  # the textured sphere at the origin


def look(center, target=(0.0, 0.0, 0.0), f=40.0, size=48, uid=0, time=None):
    """A camera at `center` looking at `target`, world z up (OpenCV axes: x right, y down, z ahead)."""
    c, t = torch.tensor(center, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    z = (t - c) / torch.linalg.norm(t - c)
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    x = x / torch.linalg.norm(x)
    y = torch.linalg.cross(z, x)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ c
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float64)
    return Camera(uid=uid, name=f"c{uid}", K=K, world_to_camera=w2c, width=size, height=size, time=time)


def ring(n=16, distance=4.0, height=0.6, times=False):
    return [look((distance * math.cos(2 * math.pi * k / n), distance * math.sin(2 * math.pi * k / n), height), uid=k,
                 time=(k / n if times else None)) for k in range(n)]


def texture(p):
    """The sphere's colour at surface points p [..., 3]: smooth stripes over longitude and height."""
    lon = torch.atan2(p[..., 1], p[..., 0])
    return torch.stack([0.5 + 0.4 * torch.sin(5 * lon), 0.5 + 0.4 * torch.cos(4 * p[..., 2] + 1),
                        0.5 + 0.4 * torch.sin(3 * lon + 3 * p[..., 2])], -1)


def sky(d):
    """The colour far away in unit direction d [..., 3] (a sky of many colours, so no backdrop)."""
    return torch.stack([0.3 + 0.2 * d[..., 2], 0.4 + 0.2 * torch.sin(2 * torch.atan2(d[..., 1], d[..., 0])),
                        0.7 + 0.1 * d[..., 0]], -1)


def image(cam, factor=1):
    """The view of the sphere in front of the sky, 3 x 3 rays a pixel averaged (exact intersections);
    made once per camera and level."""
    key = (cam.uid, cam.time, factor, tuple(cam.center.tolist()))
    if key not in _IMAGES:
        _IMAGES[key] = _render(cam, factor)
    return _IMAGES[key]


_IMAGES: dict = {}


def _render(cam, factor):
    small = cam.scaled(factor) if factor != 1 else cam
    sub = (torch.arange(3, dtype=torch.float64) + 0.5) / 3
    j, i, b, a = torch.meshgrid(torch.arange(small.height, dtype=torch.float64), torch.arange(small.width, dtype=torch.float64),
                                sub, sub, indexing="ij")
    o, d = small.rays(torch.stack([i + a, j + b], -1))
    # |o + t d| = RADIUS, the nearer root
    od = (o * d).sum(-1)
    disc = od * od - ((o * o).sum(-1) - RADIUS ** 2)
    t = -od - disc.clamp_min(0).sqrt()
    hit = (disc > 0) & (t > 0)
    colour = torch.where(hit[..., None], texture(o + d * t[..., None]), sky(d))
    return colour.mean(dim=(2, 3)).float()


def scene_of(cams):
    centres = torch.stack([c.center for c in cams])
    centre = centres.mean(0)
    extent = 1.1 * float(torch.linalg.norm(centres - centre, dim=1).max())
    return argparse.Namespace(train_cameras=cams, background=None, center=centre, extent=extent, image=image)


def near_sphere(xyz, margin=0.5):
    r = torch.linalg.norm(xyz, dim=1)
    return r < RADIUS + margin, (r - RADIUS).abs()


def test_rays_that_meet_the_sphere_put_their_points_on_it_with_its_colour():
    scene = scene_of(ring())
    n = 3000
    xyz, rgb, said = random_init_points(scene, n, torch.Generator().manual_seed(0))
    assert said.startswith("random init: cube") and "pixel rays" in said, said
    assert "(3000 rays scored" in said  # 12 neighbours see every candidate's region from a ring
    close, off = near_sphere(xyz)
    # a depth slice is (cube size) / 32, about 0.3 here: the winner is within it of the surface
    on = close & (off < 0.2)
    assert float(on.double().sum() / close.double().sum()) > 0.8, float(on.double().sum() / close.double().sum())
    # the sphere fills about a third of every image: about that share of the rays end on it
    assert float(on.double().mean()) > 0.25, float(on.double().mean())
    # points uniform in the cube (3DGS) near the sphere lie in that shell about a third of the time
    cube = init_region(scene.train_cameras, scene.center, scene.extent).sample(n, torch.Generator().manual_seed(0))
    c_close, c_off = near_sphere(cube)
    assert float((c_close & (c_off < 0.2)).double().sum() / c_close.double().sum()) < 0.5
    # the colour is the texture's where the point is (its nearest surface point), up to the slice's error
    want = texture(xyz[on] * (RADIUS / torch.linalg.norm(xyz[on], dim=1, keepdim=True)))
    assert float((rgb[on] - want).abs().median()) < 0.06, float((rgb[on] - want).abs().median())


def test_finer_slices_bring_the_points_closer_to_the_surface():
    scene = scene_of(ring())
    region = init_region(scene.train_cameras, scene.center, scene.extent)
    spread = []
    for depths in (8, 32, 128):
        xyz, _, _ = ray_sweep(region, scene.train_cameras, image, 1000, torch.Generator().manual_seed(1), depths=depths)
        close, off = near_sphere(xyz)
        spread.append(float(off[close & (off < 0.5)].median()))
    assert spread[0] > spread[1] > spread[2], spread
    assert spread[2] < 0.03, spread  # 128 slices: about 0.07 each


def test_a_moving_scene_keeps_the_3dgs_cube_and_says_why():
    scene = scene_of(ring(times=True))
    xyz, rgb, said = random_init_points(scene, 500, torch.Generator().manual_seed(0))
    assert "several times" in said and "pixel rays" not in said, said
    half = torch.as_tensor(scene.extent)
    assert bool(((xyz - scene.center).abs() <= half + 1e-9).all())
    assert float((xyz - scene.center).abs().max()) > 0.8 * float(half)  # spread over the cube


def test_a_given_half_size_is_the_plain_cube():
    scene = scene_of(ring())
    xyz, _, said = random_init_points(scene, 500, torch.Generator().manual_seed(0), half_size=2.0)
    assert "pixel rays" not in said and bool((xyz - scene.center).abs().max() <= 2.0)


def test_one_camera_and_a_plain_image_give_random_depths_with_the_pixels_colour():
    cam = look((0.0, -4.0, 0.0), size=24)
    flat = lambda c, factor=1: torch.full((c.scaled(factor).height, c.scaled(factor).width, 3), 0.25)
    region = InitRegion("cube", "test", center=torch.zeros(3, dtype=torch.float64), half=5.0)
    xyz, rgb, said = ray_sweep(region, [cam], flat, 400, torch.Generator().manual_seed(0))
    assert "(0 rays scored" in said and torch.allclose(rgb, torch.full_like(rgb, 0.25), atol=1e-6)
    depth = cam.project(xyz)[1]
    assert float(depth.min()) > 0 and float(depth.std()) > 1.0  # spread along the rays, not at one depth
    # many cameras, one plain colour: every candidate ties, and ties go to random depths, not the nearest
    cams = ring(8)
    xyz, _, said = ray_sweep(region, cams, flat, 400, torch.Generator().manual_seed(0))
    assert "(400 rays scored" in said
    from_camera = torch.linalg.norm(xyz[:, None, :] - torch.stack([c.center for c in cams])[None], dim=2).amin(1)
    # the first of 32 slices of a ray 5 to 10 long ends within 0.45 of its camera: ties sent to the
    # nearest candidate would put nearly every point there
    assert float((from_camera < 0.5).double().mean()) < 0.2, float((from_camera < 0.5).double().mean())
    assert bool(torch.isfinite(xyz).all())


def test_the_triangulations_fill_round_the_scene_sweeps_every_pixels_ray_in_the_cube():
    """fill_points on a rig round the scene: given a few exact tracks on the sphere, its points
    lie on the sphere where the rays meet it (the whole ray in the cube searched, not only the
    tracks' depth range), and rays go through the tracks' pixels too: the half of the sphere's
    image near the tracks gets its share of the points, not none."""
    scene = scene_of(ring())
    gen = torch.Generator().manual_seed(3)
    # 60 tracks on the sphere's band facing +x (longitude within 40 degrees of 0), near z = 0
    lon = (torch.rand(60, generator=gen, dtype=torch.float64) - 0.5) * math.radians(80)
    z = (torch.rand(60, generator=gen, dtype=torch.float64) - 0.5) * 0.6
    rho = (RADIUS ** 2 - z ** 2).sqrt()
    tracks = torch.stack([rho * torch.cos(lon), rho * torch.sin(lon), z], 1)
    xyz, rgb, said = fill_points(scene, tracks, 2000, torch.Generator().manual_seed(0))
    assert xyz.shape == (2000, 3) and "one on each of 2000 rays through the training views" in said, said
    close, off = near_sphere(xyz)
    on = close & (off < 0.2)
    assert float(on.double().sum() / close.double().sum()) > 0.8
    assert float(on.double().mean()) > 0.25
    # the tracks' side of the sphere (x > 0.5) holds points in proportion to what the views see of it
    facing = on & (xyz[:, 0] > 0.5)
    assert float(facing.double().sum() / on.double().sum()) > 0.15, float(facing.double().sum() / on.double().sum())


def test_pixels_a_mask_ignores_give_no_colour():
    """A red square (a passer-by) painted into every view and ignored by the views' masks: without
    the masks some points take its red, with them none does, and every ray still gets a point."""
    cams = ring()

    def painted(cam, factor=1):
        img = image(cam, factor).clone()
        h, w = img.shape[:2]
        img[h // 4: h // 2, w // 4: w // 2] = torch.tensor([1.0, 0.0, 0.0])
        return img

    def mask(cam, factor=1):
        small = cam.scaled(factor) if factor != 1 else cam
        m = torch.ones(small.height, small.width, 1)
        m[small.height // 4: small.height // 2, small.width // 4: small.width // 2] = 0.0
        return m

    region = init_region(cams, scene_of(cams).center, scene_of(cams).extent)
    red = lambda rgb: int(((rgb[:, 0] > 0.9) & (rgb[:, 1:] < 0.1).all(1)).sum())  # the texture and sky have none
    _, rgb, _ = ray_sweep(region, cams, painted, 2000, torch.Generator().manual_seed(0))
    assert red(rgb) > 20, red(rgb)
    xyz, rgb, said = ray_sweep(region, cams, painted, 2000, torch.Generator().manual_seed(0), mask=mask)
    assert red(rgb) == 0 and xyz.shape == (2000, 3) and bool(torch.isfinite(xyz).all())


def turn(cam, R):
    """``cam`` in a world turned by the rotation R [3, 3] about the origin (same image, same uid)."""
    w2c = cam.world_to_camera.clone()
    w2c[:3, :3] = w2c[:3, :3] @ R.T
    return Camera(uid=cam.uid, name=cam.name, K=cam.K, world_to_camera=w2c, width=cam.width, height=cam.height,
                  time=cam.time)


def rotation(axis, degrees):
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / torch.linalg.norm(a)
    k = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=torch.float64)
    t = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def test_the_sweeps_span_is_where_the_ray_meets_the_ball_round_the_cube():
    """sweep_span against the closed form: where a ray starts outside the ball of radius sqrt(3) x
    half, its span's ends lie on that sphere; from inside, it starts SWEEP_NEAR x half off the
    camera; a ray that misses the ball gets twice the half size."""
    from mvgs_plugin.data.init import SWEEP_NEAR, sweep_span

    half, centre = 2.0, torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    region = InitRegion("cube", "test", center=centre, half=half)
    gen = torch.Generator().manual_seed(0)
    d = torch.randn(500, 3, generator=gen, dtype=torch.float64)
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    outside = centre + 6.0 * torch.nn.functional.normalize(torch.randn(500, 3, generator=gen, dtype=torch.float64), dim=1)
    towards = torch.nn.functional.normalize(centre + 0.5 * torch.randn(500, 3, generator=gen, dtype=torch.float64) - outside,
                                            dim=1)
    near, far = sweep_span(outside, towards, region)
    for t in (near, far):
        assert torch.allclose(torch.linalg.norm(outside + towards * t[:, None] - centre, dim=1),
                              torch.full((500,), math.sqrt(3.0) * half, dtype=torch.float64), atol=1e-9)
    assert bool((far > near).all())
    inside = centre + 0.3 * torch.randn(500, 3, generator=gen, dtype=torch.float64)
    near, far = sweep_span(inside, d, region)
    assert torch.allclose(near, torch.full_like(near, SWEEP_NEAR * half))
    assert torch.allclose(torch.linalg.norm(inside + d * far[:, None] - centre, dim=1),
                          torch.full((500,), math.sqrt(3.0) * half, dtype=torch.float64), atol=1e-9)
    away = -towards  # from outside, looking away: misses
    near, far = sweep_span(outside, away, region)
    assert torch.allclose(far - near, torch.full_like(far, 2.0 * half))


def test_random_init_does_not_depend_on_which_way_the_worlds_axes_point():
    """The same ring and sphere in a world turned about an oblique axis: the points found there,
    turned back, are the unturned world's (same seed): the sweep's search and the region's choice
    depend on the scene, not on its axes. With the axis-aligned cube of 3DGS bounding the search
    (the rule until 2026-12-01) the rays' spans, and so the points, changed with the turn."""
    cams = ring()
    R = rotation((1.0, 2.0, 3.0), 50.0)
    by_uid = {c.uid: c for c in cams}
    turned = [turn(c, R) for c in cams]
    scene, other = scene_of(cams), scene_of(turned)
    other.image = lambda cam, factor=1: image(by_uid[cam.uid], factor)  # the world turned with its cameras
    xyz, rgb, said = random_init_points(scene, 2000, torch.Generator().manual_seed(0))
    xyz_t, rgb_t, said_t = random_init_points(other, 2000, torch.Generator().manual_seed(0))
    assert "pixel rays" in said and "pixel rays" in said_t
    back = xyz_t @ R  # R^T applied to each row
    same = torch.linalg.norm(back - xyz, dim=1) < 1e-6
    assert float(same.double().mean()) > 0.99, float(same.double().mean())
    assert torch.allclose(rgb[same], rgb_t[same], atol=1e-5)
