"""Camera: validation, pose algebra, projection, rays, pyramid scaling, batching.

Expected values come from hand formulas written here (numpy), not from the Camera code.
"""

import math

import numpy as np
import pytest
import torch

from mvgs_plugin.camera import Camera, scaled_size, stack_cameras


def rotation(axis_angle):
    """Rotation matrix from an axis-angle vector (Rodrigues, numpy)."""
    v = np.asarray(axis_angle, dtype=np.float64)
    theta = np.linalg.norm(v)
    if theta == 0:
        return np.eye(3)
    k = v / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * Kx @ Kx


def rigid(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


R0 = rotation([0.3, -0.5, 0.2])
T0 = np.array([0.4, -0.2, 5.0])
K0 = np.array([[120.0, 0, 33.0], [0, 110.0, 21.5], [0, 0, 1]])


def make_cam(**kw):
    args = dict(uid=7, name="train/r_007.png", K=K0, world_to_camera=rigid(R0, T0), width=64,
                height=48, time=None)
    args.update(kw)
    return Camera(**args)


def test_fields_are_float64_tensors():
    cam = make_cam(K=K0.tolist(), world_to_camera=torch.tensor(rigid(R0, T0), dtype=torch.float32))
    assert cam.K.dtype == torch.float64 and cam.world_to_camera.dtype == torch.float64
    assert torch.allclose(cam.K, torch.from_numpy(K0))
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (120.0, 110.0, 33.0, 21.5)


@pytest.mark.parametrize("kw, message", [
    (dict(K=np.zeros((3, 4))), r"K must be \[3,3\], got \[3,4\]"),
    (dict(K=[[-5.0, 0, 1], [0, 5, 1], [0, 0, 1]]), "fx=-5.0"),
    (dict(K=[[5.0, 0, 1], [0, 0.0, 1], [0, 0, 1]]), "fy=0.0"),
    (dict(K=[[5.0, 0.3, 1], [0, 5, 1], [0, 0, 1]]), "0.3"),
    (dict(K=[[5.0, 0, 1], [0, 5, 1], [0, 0, 2]]), r"\[0,0,1\]"),
    (dict(K=[[5.0, 0, float("nan")], [0, 5, 1], [0, 0, 1]]), "finite"),
    (dict(world_to_camera=np.eye(3)), r"world_to_camera must be \[4,4\], got \[3,3\]"),
    (dict(world_to_camera=rigid(2.0 * R0, T0)), "orthonormal"),
    (dict(world_to_camera=rigid(np.diag([1.0, 1.0, -1.0]), T0)), "det"),
    (dict(world_to_camera=rigid(R0, [0.0, float("nan"), 1.0])), "finite"),
    (dict(world_to_camera=np.vstack([rigid(R0, T0)[:3], [[0, 0, 1, 1]]])), "last row"),
    (dict(width=0), "width must be a positive int, got 0"),
    (dict(height=12.5), "height must be a positive int, got 12.5"),
    (dict(width=True), "width"),
    (dict(time=1.5), r"time must be in \[0,1\], got 1.5"),
    (dict(time=float("nan")), "time"),
    (dict(uid="a"), "uid"),
])
def test_constructor_rejects_bad_values(kw, message):
    with pytest.raises(ValueError, match=message):
        make_cam(**kw)


def test_center_and_inverse_pose():
    cam = make_cam()
    expected_center = -R0.T @ T0  # C = -R^T t for x_cam = R x_world + t
    assert np.allclose(cam.center.numpy(), expected_center, atol=1e-12)
    assert torch.allclose(cam.camera_to_world @ cam.world_to_camera, torch.eye(4, dtype=torch.float64),
                          atol=1e-12)
    # the camera's optical axis (+z) in world coordinates is the third row of R
    assert np.allclose(cam.camera_to_world[:3, 2].numpy(), R0[2], atol=1e-12)


def test_project_matches_hand_formula():
    cam = make_cam()
    pts = np.array([[0.1, 0.2, 0.3], [-0.5, 0.4, 0.0], [0.0, 0.0, 0.0]])
    pc = pts @ R0.T + T0
    u = K0[0, 0] * pc[:, 0] / pc[:, 2] + K0[0, 2]
    v = K0[1, 1] * pc[:, 1] / pc[:, 2] + K0[1, 2]
    pix, depth = cam.project(torch.from_numpy(pts))
    assert np.allclose(pix.numpy(), np.stack([u, v], 1), atol=1e-9)
    assert np.allclose(depth.numpy(), pc[:, 2], atol=1e-12)


def test_rays_pass_through_the_point_that_projects_to_the_pixel():
    cam = make_cam()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(20, 3))
    pix, _ = cam.project(torch.from_numpy(pts))
    origins, dirs = cam.rays(pix)
    assert origins.shape == (20, 3) and dirs.shape == (20, 3)
    assert np.allclose(np.linalg.norm(dirs.numpy(), axis=1), 1.0, atol=1e-12)
    to_point = pts - origins.numpy()
    # distance from each point to its ray, and the point is in front (t > 0)
    t = np.sum(to_point * dirs.numpy(), axis=1)
    miss = np.linalg.norm(to_point - t[:, None] * dirs.numpy(), axis=1)
    assert np.all(t > 0) and miss.max() < 1e-9
    assert np.allclose(origins.numpy(), -R0.T @ T0)


def test_ray_through_principal_point_is_the_optical_axis_and_pixel_centres_are_half_offset():
    cam = make_cam()
    _, d = cam.rays(torch.tensor([cam.cx, cam.cy]))
    assert np.allclose(d.numpy(), R0[2], atol=1e-12)
    # pixel (i, j) has its centre at (i + 0.5, j + 0.5): the ray through that centre leaves the
    # camera with slope ((i + 0.5 - cx) / fx, (j + 0.5 - cy) / fy, 1) in camera axes
    i, j = 10, 40
    _, d = cam.rays(torch.tensor([[i + 0.5, j + 0.5]], dtype=torch.float64))
    d_cam = R0 @ d[0].numpy()
    assert np.allclose(d_cam[:2] / d_cam[2], [(i + 0.5 - 33.0) / 120.0, (j + 0.5 - 21.5) / 110.0])


def test_rays_keep_batch_shape_and_dtype():
    cam = make_cam()
    pix = torch.rand(4, 5, 2, dtype=torch.float32) * 40
    o, d = cam.rays(pix)
    assert o.shape == (4, 5, 3) and d.shape == (4, 5, 3) and d.dtype == torch.float32
    with pytest.raises(ValueError, match=r"\[...,2\]"):
        cam.rays(torch.zeros(3, 3))


@pytest.mark.parametrize("s", [2, 4, 8])
def test_scaled_divides_intrinsics_and_projection_by_s(s):
    cam = make_cam(K=[[128.0, 0, 30.0], [0, 96.0, 26.0], [0, 0, 1]], time=0.25)
    small = cam.scaled(s)
    assert (small.width, small.height) == (64 // s, 48 // s)
    expected_K = np.array([[128.0 / s, 0, 30.0 / s], [0, 96.0 / s, 26.0 / s], [0, 0, 1]])
    assert np.allclose(small.K.numpy(), expected_K, atol=1e-12)  # principal point not re-centred
    assert small.uid == cam.uid and small.name == cam.name and small.time == 0.25
    assert torch.equal(small.world_to_camera, cam.world_to_camera)
    pts = torch.tensor([[0.1, 0.2, 0.3], [-0.4, 0.1, -0.2]], dtype=torch.float64)
    assert torch.allclose(small.project(pts)[0], cam.project(pts)[0] / s, atol=1e-9)


def test_scaled_with_rounding_uses_actual_size_ratio():
    cam = make_cam(width=50, height=37)
    small = cam.scaled(3)
    # round half up: 50/3 = 16.67 -> 17, 37/3 = 12.33 -> 12
    assert (small.width, small.height) == (17, 12)
    sx, sy = 17 / 50, 12 / 37
    assert np.allclose(small.K.numpy(), np.diag([sx, sy, 1.0]) @ K0, atol=1e-12)
    # the full frame maps onto the full frame: image corners stay corners
    origins, dirs = cam.rays(torch.tensor([[0.0, 0.0], [50.0, 37.0]], dtype=torch.float64))
    corner_pts = origins + 3.0 * dirs
    pix, _ = small.project(corner_pts)
    assert np.allclose(pix.numpy(), [[0.0, 0.0], [17.0, 12.0]], atol=1e-9)


def test_scaled_size_rounding_and_minimum():
    assert scaled_size(800, 800, 8) == (100, 100)
    assert scaled_size(50, 10, 4) == (13, 3)  # 12.5 rounds up, 2.5 rounds up
    assert scaled_size(3, 2, 100) == (1, 1)  # never below one pixel
    assert (make_cam().scaled(1000).width, make_cam().scaled(1000).height) == (1, 1)
    for bad in (0, -2, float("nan"), float("inf"), "x"):
        with pytest.raises(ValueError, match="scale factor"):
            make_cam().scaled(bad)


def test_stack_cameras():
    a = make_cam()
    b = make_cam(uid=8, world_to_camera=rigid(rotation([0, 0.4, 0]), [1.0, 2.0, 3.0]),
                 K=[[50.0, 0, 10.0], [0, 60.0, 12.0], [0, 0, 1]])
    viewmats, Ks = stack_cameras([a, b])
    assert viewmats.shape == (2, 4, 4) and Ks.shape == (2, 3, 3)
    assert viewmats.dtype == torch.float32 and Ks.dtype == torch.float32
    assert np.allclose(viewmats[1].numpy(), rigid(rotation([0, 0.4, 0]), [1.0, 2.0, 3.0]), atol=1e-6)
    assert np.allclose(Ks[0].numpy(), K0, atol=1e-5)
    v64, _ = stack_cameras([a], dtype=torch.float64, device="cpu")
    assert v64.dtype == torch.float64 and torch.equal(v64[0], a.world_to_camera)
    with pytest.raises(ValueError, match="at least one camera"):
        stack_cameras([])


def test_plane_scene_images_are_the_analytic_texture():
    """mvgs_plugin.testing.plane_image: a camera straight above the origin sees the texture at the
    ground point under each pixel centre (pinhole geometry by hand), and black off the square."""
    from mvgs_plugin.testing import PLANE_HALF, look_at, plane_image, plane_texture

    size, f, h = 32, 16.0, 2.0  # 2 units above the plane, 90 degree field of view
    cam = Camera(0, "top", [[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]],
                 look_at((0.0, 0.0, h), up=(0.0, 1.0, 0.0)), size, size)
    img = plane_image(cam, supersample=1)
    # Pixel (i, j) centre -> camera ray ((j + .5 - 16) / f, (i + .5 - 16) / f, 1) -> ground point.
    j, i = 20, 9
    x_cam, y_cam = (j + 0.5 - size / 2) / f * h, (i + 0.5 - size / 2) / f * h
    right = cam.world_to_camera[0, :3].to(torch.float64)
    down = cam.world_to_camera[1, :3].to(torch.float64)
    ground = x_cam * right + y_cam * down  # camera x / y axes in world, from the origin under the camera
    expected = plane_texture(ground[0], ground[1]).float()
    assert torch.allclose(img[i, j], expected, atol=1e-5)
    assert abs(float(ground[0])) < PLANE_HALF and abs(float(ground[1])) < PLANE_HALF
    far = Camera(1, "far", [[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]],
                 look_at((0.0, 0.0, 40.0), up=(0.0, 1.0, 0.0)), size, size)
    edge = plane_image(far, supersample=1)
    assert float(edge[0, 0].abs().max()) == 0.0 and float(edge[16, 16].abs().min()) > 0.0
