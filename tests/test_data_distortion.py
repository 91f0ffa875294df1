"""Captures with lens distortion: the pinhole camera and images they are loaded as.

The distortion model is checked against COLMAP's own (pycolmap's img_from_cam / cam_from_img,
C++); distorted test images are made by sampling an analytic picture at the rays COLMAP gives
for each distorted pixel, so the loaded, undistorted image can be compared with the picture
itself at the rays of the pinhole camera the loader chose.
"""

import json
import math

import numpy as np
import pycolmap
import pytest
import skimage.io
import torch

from mvgs_plugin.data import load_colmap, load_nerf_synthetic
from mvgs_plugin.data.distortion import Distortion, Undistortion
from test_data_colmap import look_at
from test_data_nerf import gl_camera_to_world

pytestmark = [pytest.mark.filterwarnings("ignore:the COLMAP model .* holds 0 3D points"),
              pytest.mark.filterwarnings("ignore:.*held out as test views")]

W, H = 96, 72
FX, FY, CX, CY = 80.0, 82.0, 47.3, 36.4
LENSES = {  # COLMAP model: (params after the pinhole ones, our Distortion)
    "SIMPLE_RADIAL": ([0.12], Distortion(k1=0.12)),
    "RADIAL": ([-0.21, 0.04], Distortion(k1=-0.21, k2=0.04)),
    "OPENCV": ([-0.18, 0.05, 0.003, -0.004], Distortion(k1=-0.18, k2=0.05, p1=0.003, p2=-0.004)),
    "FULL_OPENCV": ([-0.18, 0.05, 0.003, -0.004, 0.01, 0.0, 0.0, 0.0],
                    Distortion(k1=-0.18, k2=0.05, k3=0.01, p1=0.003, p2=-0.004)),
    "OPENCV_FISHEYE": ([0.05, -0.02, 0.01, -0.003], Distortion(k1=0.05, k2=-0.02, k3=0.01, k4=-0.003, fisheye=True)),
    "SIMPLE_RADIAL_FISHEYE": ([0.04], Distortion(k1=0.04, fisheye=True)),
    "RADIAL_FISHEYE": ([-0.03, 0.01], Distortion(k1=-0.03, k2=0.01, fisheye=True)),
    "SIMPLE_FISHEYE": ([], Distortion(fisheye=True)),  # equidistant: theta_d = theta
    "FISHEYE": ([], Distortion(fisheye=True)),
}
ONE_FOCAL = ("SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "SIMPLE_FISHEYE")


def colmap_camera(model, camera_id=1):
    extra = LENSES[model][0]
    pinhole = [FX, CX, CY] if model in ONE_FOCAL else [FX, FY, CX, CY]
    return pycolmap.Camera(camera_id=camera_id, model=model, width=W, height=H, params=pinhole + extra)


def fy_of(model):
    return FX if model in ONE_FOCAL else FY


def picture(x, y):
    """The analytic scene, as a function of the ray (x, y) = (X/Z, Y/Z): smooth, in [0.05, 0.95]."""
    return np.stack([0.5 + 0.45 * np.sin(9.0 * x + 2.0 * y), 0.5 + 0.45 * np.cos(7.0 * y - 3.0 * x),
                     0.5 + 0.45 * np.sin(5.0 * (x + y))], axis=-1)


def distorted_image(cam):
    """[H, W, 3] uint8: each pixel the picture at the ray COLMAP's model gives its centre."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = cam.cam_from_img(np.stack([u.ravel(), v.ravel()], -1).astype(np.float64))
    img = picture(rays[:, 0], rays[:, 1]).reshape(H, W, 3)
    return np.round(img * 255).astype(np.uint8)


@pytest.mark.parametrize("model", list(LENSES))
def test_the_lens_model_is_colmaps(model):
    cam, dist = colmap_camera(model), LENSES[model][1]
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.5, 0.5, size=(200, 2))
    theirs = cam.img_from_cam(np.concatenate([xy, np.ones((200, 1))], 1))
    xd, yd = dist.distort(xy[:, 0], xy[:, 1])
    assert np.allclose(np.stack([FX * xd + CX, fy_of(model) * yd + CY], -1), theirs, atol=1e-9)
    pix = rng.uniform([0, 0], [W, H], size=(200, 2))
    rays = cam.cam_from_img(pix)
    x, y = dist.undistort((pix[:, 0] - CX) / FX, (pix[:, 1] - CY) / fy_of(model))
    assert np.allclose(np.stack([x, y], -1), rays, atol=1e-8)


def test_a_fourth_radial_coefficient_is_the_r8_term():
    """nerfstudio's k4 (no COLMAP model has it): the polynomial written out, and its inverse."""
    dist = Distortion(k1=-0.1, k4=0.3)
    x, y = np.array([0.3, -0.45]), np.array([0.2, 0.1])
    r2 = x * x + y * y
    xd, yd = dist.distort(x, y)
    assert np.allclose(xd, x * (1 - 0.1 * r2 + 0.3 * r2 ** 4), atol=1e-15)
    assert np.allclose(np.stack(dist.undistort(xd, yd)), np.stack([x, y]), atol=1e-10)


@pytest.mark.parametrize("model", list(LENSES))
def test_the_pinhole_crop_lies_inside_the_capture_and_keeps_most_of_it(model):
    und = Undistortion(np.array([[FX, 0, CX], [0, fy_of(model), CY], [0, 0, 1]]), W, H, LENSES[model][1])
    su, sv = und.source_pixels()
    assert su.min() >= 0.5 - 1e-6 and su.max() <= W - 0.5 + 1e-6
    assert sv.min() >= 0.5 - 1e-6 and sv.max() <= H - 0.5 + 1e-6
    assert und.width_out >= 0.8 * W and und.height_out >= 0.8 * H  # these lenses bend the edge a few pixels
    assert und.K_out[0, 0] == FX and und.K_out[1, 1] == fy_of(model)


def _write_colmap(root, model, n=6):
    rec = pycolmap.Reconstruction()
    cam = colmap_camera(model)
    rec.add_camera_with_trivial_rig(cam)
    img = distorted_image(cam)
    (root / "images").mkdir(parents=True)
    for k in range(n):
        angle = 2 * math.pi * k / n
        R, t = look_at(np.array([4.0 * math.cos(angle), 4.0 * math.sin(angle), 1.0]))
        name = f"v_{k:02d}.png"
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=k + 1),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        skimage.io.imsave(root / "images" / name, img, check_contrast=False)
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(root / "sparse" / "0"))
    return rec


@pytest.mark.parametrize("model", list(LENSES))
def test_colmap_images_are_undistorted_to_the_pinhole_camera(tmp_path, model):
    rec = _write_colmap(tmp_path, model)
    scene = load_colmap(tmp_path)
    cam = scene.train_cameras[0]
    assert scene.undistortion(cam) is not None
    got = scene.image(cam).double().numpy()
    assert got.shape == (cam.height, cam.width, 3)
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    truth = picture((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
    err = np.abs(got - truth).max()
    assert err < 0.01, err  # bilinear resampling of a smooth picture
    raw = skimage.io.imread(tmp_path / "images" / cam.name) / 255.0  # the file, taken as a pinhole image
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    assert np.abs(raw - picture((u - CX) / FX, (v - CY) / fy_of(model))).max() > 10 * err
    # a world point lands where COLMAP's distorted camera puts it, through the resampling
    image = rec.images[cam.uid]
    X = np.array([[0.3, -0.2, 0.25], [-0.1, 0.15, -0.3]])
    ours, _ = cam.project(torch.from_numpy(X))
    theirs = rec.cameras[1].img_from_cam((image.cam_from_world() * X) if callable(image.cam_from_world)
                                         else image.cam_from_world * X)
    und = scene.undistortion(cam)
    x = (ours[:, 0].numpy() - cam.cx) / cam.fx
    y = (ours[:, 1].numpy() - cam.cy) / cam.fy
    xd, yd = und.distortion.distort(x, y)
    assert np.allclose(np.stack([und.K[0, 0] * xd + und.K[0, 2], und.K[1, 1] * yd + und.K[1, 2]], -1), theirs,
                       atol=1e-6)


@pytest.mark.parametrize("model", ["OPENCV", "SIMPLE_RADIAL", "RADIAL", "OPENCV_FISHEYE", "is_fisheye"])
def test_a_nerfstudio_folder_with_distortion_loads_as_colmaps_does(tmp_path, model):
    """The same lens through nerfstudio's transforms.json keys (or instant-ngp's is_fisheye with
    k1..k4, as its colmap2nerf writes a COLMAP fisheye): the same pinhole camera and pixels."""
    flag = model == "is_fisheye"
    model = "OPENCV_FISHEYE" if flag else model
    _write_colmap(tmp_path / "colmap", model)
    via_colmap = load_colmap(tmp_path / "colmap")
    lens = (dict(zip(("k1", "k2", "p1", "p2"), LENSES[model][0])) if model in ("OPENCV", "SIMPLE_RADIAL", "RADIAL")
            else dict(zip(("k1", "k2", "k3", "k4"), LENSES[model][0])))
    frames = [{"file_path": f"images/{c.name}",  # OpenGL camera-to-world
               "transform_matrix": (np.linalg.inv(c.world_to_camera.numpy()) @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()}
              for c in via_colmap.cameras]
    (tmp_path / "ns").mkdir()
    (tmp_path / "ns" / "images").symlink_to(tmp_path / "colmap" / "images")
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps({
        **({"is_fisheye": True} if flag else {"camera_model": model}), "fl_x": FX, "fl_y": fy_of(model), "cx": CX, "cy": CY,
        "w": W, "h": H, **lens, "frames": frames}))
    via_ns = load_nerf_synthetic(tmp_path / "ns")
    a, b = via_colmap.camera(via_colmap.cameras[1].name), via_ns.camera("images/" + via_colmap.cameras[1].name)
    assert (a.width, a.height) == (b.width, b.height)
    assert np.allclose(a.K.numpy(), b.K.numpy(), atol=1e-12)
    assert np.allclose(a.world_to_camera.numpy(), b.world_to_camera.numpy(), atol=1e-9)
    assert torch.equal(via_colmap.image(a), via_ns.image(b))
    assert len({id(via_ns.undistortion(c)) for c in via_ns.cameras}) == 1  # one grid for the shared camera


def test_a_wide_fisheye_keeps_the_rays_its_edges_see_or_is_refused():
    """An equidistant lens (k = 0): a 100° field across keeps its edges' rays (the pinhole's edge
    pixel is the ray at the capture's edge midpoint, tan 50°); 160° across would need a pinhole
    tan(80°) / (80° in radians) = 4.1x as wide, and is refused naming the sizes."""
    dist = Distortion(fisheye=True)
    fx = (W / 2) / math.radians(50)  # the edge midpoints lie 50° off the axis
    und = Undistortion(np.array([[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]]), W, H, dist)
    # the edge pixel centres lie (W - 1) / W of 50° off the axis; the pinhole spans their tangents
    assert und.width_out == math.floor(2 * math.tan(math.radians(50) * (W - 1) / W) * fx)
    su, _ = und.source_pixels()
    assert su.min() >= 0.5 - 1e-6 and su.max() <= W - 0.5 + 1e-6
    fx = (W / 2) / math.radians(80)
    with pytest.raises(ValueError, match=r"fisheye \(equidistant\): the undistorted image would be \d+x\d+ px for a 96x72"):
        Undistortion(np.array([[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]]), W, H, dist)
    fx = (W / 2) / math.radians(100)  # 200 degrees across: the edge rays lie behind the camera's plane
    with pytest.raises(ValueError, match=r"fisheye \(equidistant\): the capture sees 180 degrees or more across its 96x72"):
        Undistortion(np.array([[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]]), W, H, dist)


def test_colmap_models_that_cannot_be_resampled_are_refused(tmp_path):
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model="FULL_OPENCV", width=W, height=H,
                                                    params=[FX, FY, CX, CY, -0.1, 0, 0, 0, 0, 0.02, 0, 0]))
    R, t = look_at(np.array([4.0, 0.0, 1.0]))
    rec.add_image_with_trivial_frame(pycolmap.Image(name="a.png", camera_id=1, image_id=1),
                                     pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    (tmp_path / "images").mkdir()
    skimage.io.imsave(tmp_path / "images" / "a.png", np.zeros((H, W, 3), np.uint8), check_contrast=False)
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(tmp_path / "sparse" / "0"))
    with pytest.raises(ValueError, match=r"camera model FULL_OPENCV with rational terms k4..k6: supported are"):
        load_colmap(tmp_path)


def test_triangulation_sees_the_undistorted_images(tmp_path):
    """pycolmap is given pinhole cameras: the images it reads must be the resampled ones, not
    links to the distorted files."""
    from mvgs_plugin.data.triangulate import _stage_images

    _write_colmap(tmp_path / "s", "RADIAL")
    scene = load_colmap(tmp_path / "s")
    names = _stage_images(scene, scene.train_cameras[:2], tmp_path / "staged")
    for cam, name in zip(scene.train_cameras, names):
        staged = tmp_path / "staged" / name
        assert not staged.is_symlink()
        pixels = skimage.io.imread(staged) / 255.0
        assert pixels.shape == (cam.height, cam.width, 3)
        assert np.abs(pixels - scene.image(cam).numpy()).max() <= 0.5 / 255 + 1e-6
