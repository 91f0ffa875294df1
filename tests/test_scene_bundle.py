"""Consistency of the bundled Mitsuba scene (examples/scenes/tabletop).

The scene ships in two layouts made from the same cameras: NeRF-synthetic json + PNGs, and a
COLMAP model (pycolmap binary) naming the same PNGs. These tests read the files with plain
numpy / pycolmap / plyfile / scikit-image only (not mitsuba, not mvgs_plugin's loaders) and check
that both layouts describe the same cameras and that the sparse points are where the tracks say.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pycolmap
import pytest
from plyfile import PlyData
from skimage import io

SCENE = os.path.join(os.path.dirname(__file__), "..", "examples", "scenes", "tabletop")
SPLITS = ("train", "test")
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z: OpenGL <-> OpenCV axes


def _transforms(split: str) -> dict:
    with open(os.path.join(SCENE, f"transforms_{split}.json")) as fh:
        return json.load(fh)


@pytest.fixture(scope="module")
def meta() -> dict:
    return {split: _transforms(split) for split in SPLITS}


@pytest.fixture(scope="module")
def rec() -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(os.path.join(SCENE, "sparse", "0"))


def _cam_from_world(image) -> tuple[np.ndarray, np.ndarray]:
    """(R [3,3], t [3]) of an image's world-to-camera pose, across pycolmap versions."""
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose
    return np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)


def _json_frames(meta: dict) -> dict[str, np.ndarray]:
    """Image name (as COLMAP stores it) -> OpenGL camera-to-world [4, 4]."""
    return {f["file_path"] + ".png": np.asarray(f["transform_matrix"], dtype=np.float64)
            for split in SPLITS for f in meta[split]["frames"]}


def test_json_headers(meta):
    for split in SPLITS:
        m = meta[split]
        for key in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h", "frames"):
            assert key in m, f"transforms_{split}.json lacks {key}"
        assert len(m["frames"]) > 0
        # camera_angle_x and fl_x state the same horizontal field of view
        assert m["camera_angle_x"] == pytest.approx(2 * math.atan(0.5 * m["w"] / m["fl_x"]),
                                                    rel=1e-9)
        for f in m["frames"]:
            assert f["file_path"].startswith(f"{split}/r_")
            assert not os.path.splitext(f["file_path"])[1], "file_path has no extension"
            c2w = np.asarray(f["transform_matrix"])
            assert c2w.shape == (4, 4)
            np.testing.assert_allclose(c2w[3], [0, 0, 0, 1])
            np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-9)
            assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
    assert len(meta["train"]["frames"]) == 48 and len(meta["test"]["frames"]) == 12


def test_images_exist_with_json_size(meta):
    for split in SPLITS:
        m = meta[split]
        for f in m["frames"]:
            path = os.path.join(SCENE, f["file_path"] + ".png")
            assert os.path.isfile(path), path
            img = io.imread(path)
            assert img.shape == (m["h"], m["w"], 3), (path, img.shape)
            assert img.dtype == np.uint8


def test_colmap_has_the_json_images_and_camera(meta, rec):
    names = sorted(img.name for img in rec.images.values())
    assert names == sorted(_json_frames(meta))
    assert len(rec.cameras) == 1
    cam = next(iter(rec.cameras.values()))
    assert cam.model_name == "PINHOLE"
    m = meta["train"]
    assert (cam.width, cam.height) == (m["w"], m["h"])
    np.testing.assert_allclose(cam.params, [m["fl_x"], m["fl_y"], m["cx"], m["cy"]], rtol=1e-9)


def test_colmap_poses_match_json(meta, rec):
    frames = _json_frames(meta)
    for img in rec.images.values():
        R, t = _cam_from_world(img)
        c2w_cv = frames[img.name] @ GL_TO_CV
        # same orientation (OpenCV axes) and same camera centre
        np.testing.assert_allclose(R, c2w_cv[:3, :3].T, atol=1e-5, err_msg=img.name)
        np.testing.assert_allclose(-R.T @ t, c2w_cv[:3, 3], atol=1e-5, err_msg=img.name)


def test_cameras_look_at_the_scene(meta):
    """OpenCV +z (OpenGL -z) of every camera points at the scene near the origin."""
    for c2w in _json_frames(meta).values():
        centre, forward = c2w[:3, 3], -c2w[:3, 2]
        closest = centre + forward * np.dot(-centre, forward)
        assert np.linalg.norm(closest) < 0.5
        assert centre[2] > 0  # upper hemisphere


def test_test_views_interleave_with_train(meta):
    """Every test camera has a train camera within the typical train-to-train spacing."""
    def dirs(split):
        c = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in meta[split]["frames"]])
        return c / np.linalg.norm(c, axis=1, keepdims=True)
    train, test = dirs("train"), dirs("test")
    cos_tt = train @ train.T
    np.fill_diagonal(cos_tt, -1)
    spacing = np.arccos(np.clip(cos_tt.max(1), -1, 1)).max()
    to_train = np.arccos(np.clip((test @ train.T).max(1), -1, 1))
    assert to_train.max() <= spacing + 1e-9


def test_points_project_into_their_track_views(rec):
    assert 1000 <= rec.num_points3D() <= 5000
    for pid, p in rec.points3D.items():
        elems = p.track.elements
        assert len(elems) >= 2, f"point {pid} has a track of {len(elems)}"
        for e in elems:
            img = rec.images[e.image_id]
            R, t = _cam_from_world(img)
            assert (R @ p.xyz + t)[2] > 0, f"point {pid} behind {img.name}"
            uv = np.asarray(img.project_point(p.xyz)).ravel()
            cam = rec.cameras[img.camera_id]
            assert 0 <= uv[0] < cam.width and 0 <= uv[1] < cam.height, (pid, img.name, uv)
            np.testing.assert_allclose(uv, img.points2D[e.point2D_idx].xy, atol=1e-3)


def test_ply_matches_colmap_points(rec):
    v = PlyData.read(os.path.join(SCENE, "points3d.ply"))["vertex"]
    assert [p.name for p in v.properties] == ["x", "y", "z", "red", "green", "blue"]
    xyz = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    ids = sorted(rec.points3D)
    col_xyz = np.array([rec.points3D[i].xyz for i in ids])
    col_rgb = np.array([rec.points3D[i].color for i in ids])
    assert len(xyz) == len(ids)
    order = np.lexsort(xyz.T)
    col_order = np.lexsort(col_xyz.T)
    np.testing.assert_allclose(xyz[order], col_xyz[col_order], atol=1e-6)
    np.testing.assert_array_equal(rgb[order], col_rgb[col_order])


def test_bundle_is_small():
    total = sum(os.path.getsize(os.path.join(d, f))
                for d, _, files in os.walk(SCENE) for f in files)
    assert total < 5 * 1024 * 1024, f"bundled scene is {total / 2**20:.2f} MiB"
