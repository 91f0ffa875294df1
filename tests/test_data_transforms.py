"""A user's own NeRF-style data: one transforms.json (instant-ngp, nerfstudio), lens distortion
refused, nerfstudio's ply_file_path, and the background of images that carry no alpha.

Cameras are checked against the Blender pinhole formula applied to the written OpenGL matrices
(test_data_nerf's helpers); backgrounds against the colour the test composited the images on.
"""

import json
import math
import warnings

import numpy as np
import pytest
import skimage.io
import torch
from plyfile import PlyData, PlyElement

from mvgs_plugin.data import load_dnerf, load_nerf_synthetic, load_scene
from mvgs_plugin.data.images import BORDER_SHARE, BORDER_TOLERANCE, uniform_border
from test_data_nerf import POINTS, blender_project, gl_camera_to_world

pytestmark = pytest.mark.filterwarnings("ignore:.*held out as test views")

W, H = 48, 36


def _frames(n, root, folder="images", seed=0, paint=None, ext="png"):
    """n frames around the origin; image k is paint(k) (uint8 [H,W,3]) or random RGB."""
    rng = np.random.default_rng(seed)
    (root / folder).mkdir(parents=True, exist_ok=True)
    frames, c2ws = [], {}
    for k in range(n):
        angle = 2 * math.pi * k / n
        c2w = gl_camera_to_world(np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 0.4 + 0.05 * k]))
        pixels = paint(k) if paint is not None else rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        name = f"{folder}/frame_{k:05d}.{ext}"
        if ext == "png":
            skimage.io.imsave(root / name, pixels, check_contrast=False)
        else:
            from PIL import Image
            Image.fromarray(pixels).save(root / name, quality=90)
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
        c2ws[name] = c2w
    return frames, c2ws


NERFSTUDIO = {"camera_model": "OPENCV", "fl_x": 41.0, "fl_y": 43.0, "cx": 23.0, "cy": 17.5, "w": W, "h": H,
              "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}


def _write(root, frames, **top):
    (root / "transforms.json").write_text(json.dumps({**NERFSTUDIO, **top, "frames": frames}))


def test_one_transforms_json_is_split_every_eighth_and_projects_as_blender(tmp_path):
    frames, c2ws = _frames(20, tmp_path)
    _write(tmp_path, list(reversed(frames)))  # the split follows file names, not the file's order
    with pytest.warns(UserWarning, match=r"one transforms.json: .* \(3 of 20\) are held out"):
        scene = load_scene(tmp_path, init=None)
    assert [c.name for c in scene.test_cameras] == [f"images/frame_{k:05d}.png" for k in (0, 8, 16)]
    assert len(scene.train_cameras) == 17 and len({c.uid for c in scene.cameras}) == 20
    for cam in scene.cameras:
        assert (cam.width, cam.height) == (W, H)
        theirs = np.stack([blender_project(c2ws[cam.name], p, 41.0, 43.0, 23.0, 17.5) for p in POINTS])
        assert np.allclose(cam.project(torch.from_numpy(POINTS))[0].numpy(), theirs, atol=1e-9)


def test_a_three_by_four_matrix_and_a_dynamic_transforms_json(tmp_path):
    frames, c2ws = _frames(9, tmp_path)
    for k, f in enumerate(frames):
        f["transform_matrix"] = f["transform_matrix"][:3]
        f["time"] = k / 8
    _write(tmp_path, frames)
    scene = load_scene(tmp_path, init=None)  # D-NeRF: its frames carry a time
    assert [c.time for c in scene.test_cameras] == [0.0, 1.0]
    cam = scene.camera("images/frame_00003.png")
    theirs = np.stack([blender_project(c2ws[cam.name], p, 41.0, 43.0, 23.0, 17.5) for p in POINTS])
    assert np.allclose(cam.project(torch.from_numpy(POINTS))[0].numpy(), theirs, atol=1e-9)
    assert load_dnerf(tmp_path).camera("images/frame_00005.png").time == 5 / 8


@pytest.mark.parametrize("extra, match", [
    ({"camera_model": "EQUIRECTANGULAR"}, r"camera_model 'EQUIRECTANGULAR': supported are PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, r"'OPENCV_FISHEYE' has no tangential terms, got p1=0.01, p2=0"),
    ({"k1": "0.1"}, r"'k1' must be a finite number, got '0.1'"),
    ({"k1": -3.0}, r"lens distortion k1=-3: it cannot be inverted over the image"),
    ({"camera_model": None, "is_fisheye": True, "p1": 0.01},
     r"is_fisheye \(OpenCV's fisheye model\) has no tangential terms, got p1=0.01"),
    ({"is_fisheye": True}, r"is_fisheye is set beside camera_model 'OPENCV': one says a fisheye lens"),
    ({"is_fisheye": "yes"}, r"'is_fisheye' must be true or false, got 'yes'"),
])
def test_lenses_that_cannot_be_resampled_are_refused(tmp_path, extra, match):
    frames, _ = _frames(3, tmp_path)
    _write(tmp_path, frames, **extra)
    with pytest.raises(ValueError, match=match) as err:
        load_nerf_synthetic(tmp_path)
    assert "transforms.json: frame 1 (images/frame_00001.png)" in str(err.value)  # frame 0 is held out


def test_an_error_names_the_frame_by_its_place_in_the_json(tmp_path):
    """The split sorts and holds out frames; an error still counts frames as the json lists them."""
    frames, _ = _frames(12, tmp_path)
    frames[10]["cx"] = -5.0
    _write(tmp_path, list(reversed(frames)))  # frame_00010 is the json's frame 1
    with pytest.raises(ValueError, match=r"transforms.json: frame 1 \(images/frame_00010.png\): cx=-5 lies outside"):
        load_nerf_synthetic(tmp_path)


def test_a_file_path_with_a_dot_and_no_extension_gets_png(tmp_path):
    frames, _ = _frames(3, tmp_path)
    for k, f in enumerate(frames):
        dotted = tmp_path / "images" / f"r.{k}.png"
        (tmp_path / f["file_path"]).rename(dotted)
        f["file_path"] = f"./images/r.{k}"
    _write(tmp_path, frames)
    assert sorted(c.name for c in load_nerf_synthetic(tmp_path).cameras) == [f"images/r.{k}.png" for k in range(3)]


def test_nerfstudio_ply_file_path_gives_the_points(tmp_path):
    frames, _ = _frames(4, tmp_path)
    vertex = np.array([(0.1, 0.2, 0.3, 255, 0, 51)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                                             ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(tmp_path / "sparse_pc.ply"))
    _write(tmp_path, frames, ply_file_path="sparse_pc.ply")
    pts = load_nerf_synthetic(tmp_path).points
    assert np.allclose(pts.xyz.numpy(), [[0.1, 0.2, 0.3]], atol=1e-6)
    assert np.allclose(pts.rgb.numpy(), [[1.0, 0.0, 0.2]], atol=1e-6)
    _write(tmp_path, frames, ply_file_path="missing.ply")
    with pytest.raises(FileNotFoundError, match="ply_file_path 'missing.ply'"):
        load_nerf_synthetic(tmp_path)
    _write(tmp_path, frames, ply_file_path="../outside.ply")
    with pytest.raises(ValueError, match="ply_file_path"):
        load_nerf_synthetic(tmp_path)


# ---- the background of images without alpha -------------------------------------------------

def _object_on(colour, reach_edge=lambda k: False):
    """A painter: a random-coloured object in the middle of each image on a flat `colour`
    (uint8 triple); when reach_edge(k), the object covers the whole left column too."""
    rng = np.random.default_rng(1)

    def paint(k):
        img = np.empty((H, W, 3), np.uint8)
        img[:] = colour
        img[8:28, 10:38] = rng.integers(0, 256, size=(20, 28, 3), dtype=np.uint8)
        if reach_edge(k):
            img[:, :12] = rng.integers(0, 256, size=(H, 12, 3), dtype=np.uint8)
        return img
    return paint


@pytest.mark.parametrize("colour", [(0, 0, 0), (51, 102, 204), (255, 255, 255)])
def test_images_without_alpha_get_the_colour_their_borders_show(tmp_path, colour):
    frames, _ = _frames(9, tmp_path, paint=_object_on(colour, reach_edge=lambda k: k == 4))
    _write(tmp_path, frames)
    scene = load_nerf_synthetic(tmp_path)
    assert np.allclose(scene.background, np.asarray(colour) / 255.0, atol=1e-6)
    assert "no transparent pixel and their borders are one colour" in scene.background_origin
    assert load_nerf_synthetic(tmp_path, background=(0.5, 0.5, 0.5)).background == (0.5, 0.5, 0.5)


def test_a_jpeg_backdrop_is_found_through_its_compression(tmp_path):
    frames, _ = _frames(9, tmp_path, paint=_object_on((0, 0, 0)), ext="jpg")
    _write(tmp_path, frames)
    scene = load_nerf_synthetic(tmp_path)
    assert max(scene.background) <= 3 / 255


def test_photographs_and_rgba_images_keep_white(tmp_path):
    frames, _ = _frames(9, tmp_path / "photo")  # random pixels: a border of many colours
    _write(tmp_path / "photo", frames)
    scene = load_nerf_synthetic(tmp_path / "photo")
    assert scene.background == (1.0, 1.0, 1.0) and "not one colour" in scene.background_origin
    rgba = lambda k: np.concatenate([np.zeros((H, W, 3), np.uint8), np.full((H, W, 1), 0, np.uint8)], -1)  # noqa: E731
    frames, _ = _frames(9, tmp_path / "rgba", paint=rgba)
    _write(tmp_path / "rgba", frames)
    scene = load_nerf_synthetic(tmp_path / "rgba")
    assert scene.background == (1.0, 1.0, 1.0) and "RGBA" in scene.background_origin
    assert np.allclose(scene.image(scene.train_cameras[0]).numpy(), 1.0)  # transparent black composited on white


def test_uniform_border_share_and_tolerance():
    """The rule at its edges: a border with exactly BORDER_SHARE of its pixels at the colour is
    uniform, one pixel fewer is not; a pixel off by the tolerance counts, beyond it does not."""
    n = 2 * 10 + 2 * 8  # the border of a 10 x 10 image
    img = torch.full((10, 10, 3), 0.25)
    ring = torch.cat([img[0], img[-1], img[1:-1, 0], img[1:-1, -1]])
    assert ring.shape[0] == n
    need = math.ceil(BORDER_SHARE * n)
    bad = n - need  # pixels that may differ
    img[0, :bad] = 0.9
    assert uniform_border([img]) == pytest.approx((0.25,) * 3)
    img[0, bad] = 0.9
    assert uniform_border([img]) is None
    img = torch.full((10, 10, 3), 0.25)
    img[-1, :] = 0.25 + BORDER_TOLERANCE * 0.999
    assert uniform_border([img]) == pytest.approx((0.25,) * 3)
    img[1:-1, 0] = 0.25 + BORDER_TOLERANCE * 1.01  # 8 beyond it: 28 of 36 within
    assert uniform_border([img]) is None
    with pytest.raises(ValueError, match=r"\[H, W, 3\] images, got \[10, 10\]"):
        uniform_border([torch.zeros(10, 10)])


def test_opaque_rgba_images_are_read_as_the_backdrop_they_show(tmp_path):
    """RGBA files whose alpha is 255 everywhere (many exporters write them) are composited already:
    the border rule applies, as for RGB."""
    paint = _object_on((0, 0, 0))
    opaque = lambda k: np.concatenate([paint(k), np.full((H, W, 1), 255, np.uint8)], -1)  # noqa: E731
    frames, _ = _frames(9, tmp_path, paint=opaque)
    _write(tmp_path, frames)
    scene = load_nerf_synthetic(tmp_path)
    assert scene.background == (0.0, 0.0, 0.0) and "no transparent pixel" in scene.background_origin


def test_rgba_images_beside_opaque_ones_on_another_backdrop_are_warned_about(tmp_path):
    """Training images of which some are RGBA with transparency (composited on white) and some are
    RGB on black: two backdrops for one model, said in a warning naming one of the RGB images."""
    paint = _object_on((0, 0, 0))

    def mixed(k):
        if k % 2:
            return paint(k)
        alpha = np.zeros((H, W, 1), np.uint8)
        alpha[8:28, 10:38] = 255
        return np.concatenate([paint(k), alpha], -1)
    frames, _ = _frames(9, tmp_path, paint=mixed)
    _write(tmp_path, frames)
    with pytest.warns(UserWarning, match=r"4 of the 7 training images have no transparent pixel and their borders "
                                         r"show \(0.000, 0.000, 0.000\), not the white .* 'images/frame_00001.png'"):
        scene = load_nerf_synthetic(tmp_path)
    assert scene.background == (1.0, 1.0, 1.0)


def _png16(path, arr):
    """A 16-bit RGB(A) PNG written by hand (zlib, filter 0): Pillow writes none."""
    import struct
    import zlib

    h, w, c = arr.shape
    raw = b"".join(b"\x00" + arr[y].astype(">u2").tobytes() for y in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    header = struct.pack(">IIBBBBB", w, h, 16, {3: 2, 4: 6}[c], 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_a_16_bit_colour_png_is_read_to_within_8_bits_and_said_once(tmp_path, monkeypatch):
    from mvgs_plugin.data import images

    monkeypatch.setattr(images, "_WARNED_16_BIT", False)
    values = np.array([1000, 30000, 65535], np.uint16)
    _png16(tmp_path / "a.png", np.broadcast_to(values, (4, 5, 3)).copy())
    _png16(tmp_path / "b.png", np.broadcast_to(values, (4, 5, 3)).copy())
    with pytest.warns(UserWarning, match=r"a.png is a 16-bit colour PNG: it is read at 8 bits per channel"):
        got = images.read_rgb(tmp_path / "a.png")
    assert np.abs(got[0, 0].numpy() - values / 65535.0).max() <= 1 / 255 + 1e-6
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        images.read_rgb(tmp_path / "b.png")  # said once
