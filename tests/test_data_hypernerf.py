"""HyperNeRF / Nerfies captures: cameras against the Nerfies camera model worked by hand
(orientation = world-to-camera rotation, position = centre, fy = focal x pixel aspect), the
scene.json normalisation applied to cameras and points alike, the rgb/Nx folders, both splits,
and lens distortion resampled as the other loaders do."""

import json
import math

import numpy as np
import pytest
import skimage.io
import torch

from mvgs_plugin.data import load_scene
from mvgs_plugin.data.distortion import Distortion, Undistortion
from mvgs_plugin.data.hypernerf import load_hypernerf
from mvgs_plugin.data.load import scene_layout

W, H = 40, 32


def _orientation(centre, target=(0.0, 0.0, 0.0)):
    """World-to-camera rotation whose rows are the camera's x (right), y (down), z (forward)."""
    z = np.asarray(target, float) - np.asarray(centre, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def _capture(root, n=12, val=(), scale=None, center=None, sizes=("1x", "2x"), distortion=(0.0, 0.0, 0.0),
             points=None):
    rng = np.random.default_rng(0)
    ids = [f"frame_{k:03d}" for k in range(n)]
    (root / "camera").mkdir(parents=True)
    cams = {}
    for k, frame in enumerate(ids):
        a = 2 * math.pi * k / n
        centre = np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 0.5])
        cam = {"orientation": _orientation(centre).tolist(), "position": centre.tolist(), "focal_length": 30.0 + k,
               "pixel_aspect_ratio": 1.05, "principal_point": [W / 2 + 1.0, H / 2 - 0.5], "skew": 0.0,
               "radial_distortion": list(distortion), "tangential_distortion": [0.0, 0.0], "image_size": [W, H]}
        (root / "camera" / f"{frame}.json").write_text(json.dumps(cam))
        cams[frame] = cam
        for size in sizes:
            s = int(size[:-1])
            (root / "rgb" / size).mkdir(parents=True, exist_ok=True)
            skimage.io.imsave(root / "rgb" / size / f"{frame}.png",
                              rng.integers(0, 256, size=(H // s, W // s, 3), dtype=np.uint8), check_contrast=False)
    train = [i for i in ids if i not in val]
    (root / "dataset.json").write_text(json.dumps({"count": n, "ids": ids, "train_ids": train, "val_ids": list(val)}))
    (root / "metadata.json").write_text(json.dumps({f: {"warp_id": k, "appearance_id": k, "camera_id": 0}
                                                    for k, f in enumerate(ids)}))
    if scale is not None:
        (root / "scene.json").write_text(json.dumps({"scale": scale, "center": list(center), "near": 0.1, "far": 5}))
    if points is not None:
        np.save(root / "points.npy", np.asarray(points, dtype=np.float64))
    return cams


def _by_hand(cam, pts, scale=1.0, center=(0.0, 0.0, 0.0), factor=1.0):
    """The Nerfies projection of world points (before the scene.json map), in pixels of an image
    downscaled by ``factor``."""
    R, c = np.asarray(cam["orientation"]), np.asarray(cam["position"])
    # the scene.json map is a similarity: projecting mapped points through mapped cameras is
    # projecting the points through the cameras
    local = (R @ (pts - c).T).T
    x, y = local[:, 0] / local[:, 2], local[:, 1] / local[:, 2]
    f, aspect, (cx, cy) = cam["focal_length"], cam["pixel_aspect_ratio"], cam["principal_point"]
    return np.c_[f * x + cx, f * aspect * y + cy] / factor


def test_cameras_follow_the_nerfies_model_at_half_size(tmp_path):
    cams = _capture(tmp_path, val=("frame_003", "frame_007"))
    assert scene_layout(tmp_path) == "hypernerf"
    scene = load_scene(tmp_path, init=None)
    assert [c.name for c in scene.test_cameras] == ["rgb/2x/frame_003.png", "rgb/2x/frame_007.png"]
    assert len(scene.train_cameras) == 10 and scene.background is None
    pts = np.array([[0.2, -0.3, 0.4], [-0.5, 0.1, 0.0]])
    for cam in scene.cameras:
        frame = cam.name.split("/")[-1][:-4]
        assert (cam.width, cam.height) == (W // 2, H // 2)
        uv, _ = cam.project(torch.from_numpy(pts))
        np.testing.assert_allclose(uv.numpy(), _by_hand(cams[frame], pts, factor=2.0), atol=1e-9)
    assert [c.time for c in scene.train_cameras][:3] == pytest.approx([0.0, 1 / 11, 2 / 11])


def test_scene_json_maps_cameras_and_points_alike(tmp_path):
    world = np.array([[0.3, 0.2, -0.1], [0.0, -0.4, 0.6]])
    cams = _capture(tmp_path, val=("frame_000",), scale=0.25, center=(1.0, -2.0, 0.5), points=world)
    scene = load_scene(tmp_path, images="rgb/1x", init=None)
    np.testing.assert_allclose(scene.points.xyz.numpy(), (world - [1.0, -2.0, 0.5]) * 0.25, rtol=1e-6)
    assert scene.points.rgb.unique().tolist() == [0.5]
    cam = scene.test_cameras[0]
    uv, _ = cam.project(scene.points.xyz.double())  # the mapped points through the mapped camera
    np.testing.assert_allclose(uv.numpy(), _by_hand(cams["frame_000"], world), atol=1e-5)
    centre = (np.asarray(cams["frame_000"]["position"]) - [1.0, -2.0, 0.5]) * 0.25
    np.testing.assert_allclose(cam.center.numpy(), centre, atol=1e-12)


@pytest.mark.parametrize("n, train, test", [
    (13, ["000", "004", "008", "012"], ["002", "006", "010"]),
    (12, ["000", "004", "008"], ["002", "006"]),  # 4DGS drops the last test frame even when it exists
])
def test_without_val_ids_4dgs_interpolation_protocol(tmp_path, n, train, test):
    _capture(tmp_path, n=n, sizes=("2x",))
    with pytest.warns(UserWarning, match="every 4th frame from the first trains"):
        scene = load_scene(tmp_path, init=None)
    assert [c.name[-7:-4] for c in scene.train_cameras] == train
    assert [c.name[-7:-4] for c in scene.test_cameras] == test
    # warp_id over the largest of every frame's, used or not (n - 1 here, as 4DGS divides)
    assert [c.time for c in scene.test_cameras] == pytest.approx([int(t) / (n - 1) for t in test])


def test_lens_distortion_is_resampled_to_a_pinhole(tmp_path):
    _capture(tmp_path, val=("frame_001",), sizes=("1x",), distortion=(-0.08, 0.01, 0.0))
    scene = load_scene(tmp_path, init=None)
    cam = scene.test_cameras[0]
    und = scene.undistortion(cam)
    assert und is not None and und.distortion == Distortion(k1=-0.08, k2=0.01)
    K = np.array([[31.0, 0, W / 2 + 1.0], [0, 31.0 * 1.05, H / 2 - 0.5], [0, 0, 1.0]])
    expect = Undistortion(K, W, H, Distortion(k1=-0.08, k2=0.01))
    np.testing.assert_allclose(cam.K.numpy(), expect.K_out)
    assert scene.image(cam).shape == (cam.height, cam.width, 3)


@pytest.mark.parametrize("change, match", [
    (lambda c: c.update(skew=0.1), "skew 0.1"),
    (lambda c: c.pop("focal_length"), "missing 'focal_length'"),
    (lambda c: c.update(orientation=[[1, 0], [0, 1]]), "'orientation' must be"),
])
def test_a_bad_camera_file_is_named(tmp_path, change, match):
    cams = _capture(tmp_path, val=("frame_001",))
    cam = dict(cams["frame_005"])
    change(cam)
    (tmp_path / "camera" / "frame_005.json").write_text(json.dumps(cam))
    with pytest.raises(ValueError, match=f"frame_005.json: .*{match}"):
        load_scene(tmp_path, init=None)


def test_a_frame_without_a_time_is_named(tmp_path):
    _capture(tmp_path, val=("frame_001",))
    meta = json.loads((tmp_path / "metadata.json").read_text())
    del meta["frame_004"]["warp_id"]
    (tmp_path / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="frame 'frame_004' needs a 'warp_id'"):
        load_scene(tmp_path, init=None)
