"""NeRF-synthetic and D-NeRF loaders, plus the Scene image pyramid.

Scenes are written here from known OpenGL camera-to-world matrices; projections are checked
against the Blender pinhole formula applied to those matrices directly (no OpenCV conversion).
"""

import json
import math

import numpy as np
import pytest
import skimage.io
import torch
from plyfile import PlyData, PlyElement

from mvgs_plugin.camera import Camera
from mvgs_plugin.data import Scene, load_dnerf, load_nerf_synthetic

W, H = 40, 30
ANGLE_X = 0.8


def gl_camera_to_world(position, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    """Blender/OpenGL camera-to-world [4,4]: columns right, up, backward, position."""
    back = np.asarray(position, float) - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, position
    return c2w


def blender_project(c2w, point, fx, fy, cx, cy):
    """Pixel of a world point for an OpenGL camera: it looks down -z with y up."""
    x, y, z = (np.linalg.inv(c2w) @ np.append(point, 1.0))[:3]
    return np.array([cx + fx * x / -z, cy - fy * y / -z])


def write_blender(root, counts=(("train", 4), ("test", 2)), times=False, rgba=True, frame_extra=None,
                  top_extra=None, seed=0):
    """Write transforms_<split>.json and PNGs; return {name: (c2w, rgba uint8 array, time)}."""
    rng = np.random.default_rng(seed)
    written = {}
    for split, n in counts:
        frames = []
        (root / split).mkdir(parents=True, exist_ok=True)
        for k in range(n):
            angle = 2 * math.pi * k / n + (0.3 if split == "test" else 0.0)
            pos = np.array([3.0 * math.cos(angle), 3.0 * math.sin(angle), 0.5 + 0.2 * k])
            c2w = gl_camera_to_world(pos)
            pixels = rng.integers(0, 256, size=(H, W, 4 if rgba else 3), dtype=np.uint8)
            skimage.io.imsave(root / split / f"r_{k:03d}.png", pixels, check_contrast=False)
            # train frames omit the extension (as the Blender scenes do), test frames keep it
            fp = f"./{split}/r_{k:03d}" + (".png" if split == "test" else "")
            frame = {"file_path": fp, "transform_matrix": c2w.tolist()}
            time = k / max(n - 1, 1)
            if times:
                frame["time"] = time
            frame.update((frame_extra or {}).get((split, k), {}))
            frames.append(frame)
            written[f"{split}/r_{k:03d}.png"] = (c2w, pixels, time)
        meta = {"camera_angle_x": ANGLE_X, "frames": frames}
        meta.update(top_extra or {})
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return written


FX = 0.5 * W / math.tan(0.5 * ANGLE_X)
POINTS = np.array([[0.1, 0.2, 0.3], [-0.4, 0.3, -0.2], [0.0, 0.0, 0.0], [0.3, -0.3, 0.4]])


def test_projection_matches_blender_formula(tmp_path):
    written = write_blender(tmp_path)
    scene = load_nerf_synthetic(tmp_path)
    assert len(scene.train_cameras) == 4 and len(scene.test_cameras) == 2
    assert len({c.uid for c in scene.cameras}) == 6
    for cam in scene.cameras:
        c2w = written[cam.name][0]
        assert (cam.width, cam.height) == (W, H) and cam.time is None
        ours = cam.project(torch.from_numpy(POINTS))[0].numpy()
        theirs = np.stack([blender_project(c2w, p, FX, FX, W / 2, H / 2) for p in POINTS])
        assert np.allclose(ours, theirs, atol=1e-9)
        assert np.allclose(cam.center.numpy(), c2w[:3, 3], atol=1e-12)


def test_rays_and_scaled_projection(tmp_path):
    written = write_blender(tmp_path)
    cam = load_nerf_synthetic(tmp_path).train_cameras[1]
    c2w = written[cam.name][0]
    pix = np.stack([blender_project(c2w, p, FX, FX, W / 2, H / 2) for p in POINTS])
    o, d = cam.rays(torch.from_numpy(pix))
    v = POINTS - o.numpy()
    t = (v * d.numpy()).sum(1)
    assert (t > 0).all() and np.abs(v - t[:, None] * d.numpy()).max() < 1e-9
    small = cam.scaled(2)
    assert np.allclose(small.project(torch.from_numpy(POINTS))[0].numpy(), pix / 2, atol=1e-9)


def test_per_frame_and_top_level_intrinsics(tmp_path):
    extra = {("train", 1): {"fl_x": 30.0, "fl_y": 33.0, "cx": 18.0, "cy": 16.0, "w": W, "h": H}}
    written = write_blender(tmp_path, frame_extra=extra, top_extra={"camera_angle_y": 0.5})
    scene = load_nerf_synthetic(tmp_path)
    special = scene.camera("train/r_001.png")
    assert (special.fx, special.fy, special.cx, special.cy) == (30.0, 33.0, 18.0, 16.0)
    c2w = written["train/r_001.png"][0]
    theirs = np.stack([blender_project(c2w, p, 30.0, 33.0, 18.0, 16.0) for p in POINTS])
    assert np.allclose(special.project(torch.from_numpy(POINTS))[0].numpy(), theirs, atol=1e-9)
    other = scene.camera("train/r_000.png")  # fy from camera_angle_y
    assert math.isclose(other.fx, FX) and math.isclose(other.fy, 0.5 * H / math.tan(0.25))


@pytest.mark.parametrize("background", [(1.0, 1.0, 1.0), (0.0, 0.25, 0.5)])
def test_rgba_composited_on_background(tmp_path, background):
    written = write_blender(tmp_path)
    scene = load_nerf_synthetic(tmp_path, background=background)
    assert scene.background == background
    for name in ("train/r_000.png", "test/r_001.png"):
        px = written[name][1] / 255.0
        expected = px[..., :3] * px[..., 3:] + np.asarray(background) * (1 - px[..., 3:])
        img = scene.image(scene.camera(name))
        assert img.dtype == torch.float32 and img.shape == (H, W, 3)
        assert np.allclose(img.numpy(), expected, atol=1e-6)


def test_rgb_images_and_dropped_alpha(tmp_path):
    written = write_blender(tmp_path, rgba=False)
    img = load_nerf_synthetic(tmp_path).image(load_nerf_synthetic(tmp_path).camera("train/r_002.png"))
    assert np.allclose(img.numpy(), written["train/r_002.png"][1] / 255.0, atol=1e-6)
    written = write_blender(tmp_path / "b")
    scene = load_nerf_synthetic(tmp_path / "b", background=None)
    img = scene.image(scene.camera("train/r_002.png"))
    assert np.allclose(img.numpy(), written["train/r_002.png"][1][..., :3] / 255.0, atol=1e-6)


def test_a_cmyk_jpeg_reads_as_its_rgb_not_as_rgba(tmp_path):
    """A CMYK JPEG decodes to four channels; taken as RGBA its K channel became alpha (an all-white
    scene on a white background). It reads as the RGB Pillow converts it to, close to the smooth
    image it was made from, and an RGBA PNG is still composited."""
    from PIL import Image

    from mvgs_plugin.data.images import read_rgb

    yy, xx = np.mgrid[0:H, 0:W]
    rgb = np.stack([xx / (W - 1), yy / (H - 1), 0.3 + 0.4 * (xx + yy) / (W + H)], -1)
    pixels = np.round(rgb * 255).astype(np.uint8)
    Image.fromarray(pixels).convert("CMYK").save(tmp_path / "c.jpg", quality=100, subsampling=0)
    with Image.open(tmp_path / "c.jpg") as img:
        assert img.mode == "CMYK"
    got = read_rgb(tmp_path / "c.jpg", background=(1.0, 1.0, 1.0)).numpy()
    assert got.shape == (H, W, 3) and np.abs(got - pixels / 255.0).max() < 8 / 255
    rgba = np.concatenate([pixels, np.full((H, W, 1), 128, np.uint8)], -1)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    a = 128 / 255
    assert np.allclose(read_rgb(tmp_path / "a.png", background=(0.0, 0.0, 0.0)).numpy(), pixels / 255.0 * a, atol=1e-6)


def test_transparency_in_a_trns_chunk_is_alpha(tmp_path):
    """PNGs whose transparency is a tRNS chunk, not a channel: a palette with an alpha per entry
    (pngquant's and Pillow's quantize output from RGBA renders), an RGB and a grey image with a
    colour key. Each is composited by that alpha, its alpha is read, and the NeRF loader sees an
    RGBA scene (white behind it); the expected values are the palette's and keys' own numbers."""
    from PIL import Image

    from mvgs_plugin.data.images import read_alpha, read_rgb

    palette = np.array([[200, 10, 30], [0, 255, 0], [0, 0, 0], [40, 80, 120]], np.uint8)
    entry_alpha = np.array([255, 128, 0, 64], np.uint8)
    rng = np.random.default_rng(0)
    index = rng.integers(0, 4, size=(H, W), dtype=np.uint8)
    want_a = entry_alpha[index][..., None] / 255.0
    want = palette[index] / 255.0 * want_a + 1.0 * (1 - want_a)  # on white
    for split, n in (("train", 4), ("test", 2)):
        (tmp_path / split).mkdir()
        for k in range(n):
            img = Image.fromarray(index, "P")
            img.putpalette(palette.reshape(-1).tolist())
            img.save(tmp_path / split / f"r_{k:03d}.png", transparency=entry_alpha.tobytes())
    written = write_blender(tmp_path / "cams")  # the cameras; their jsons name the same file paths
    for split in ("train", "test"):
        (tmp_path / f"transforms_{split}.json").write_text((tmp_path / "cams" / f"transforms_{split}.json").read_text())
    with Image.open(tmp_path / "train" / "r_000.png") as img:
        assert img.mode == "P" and "transparency" in img.info
    assert np.allclose(read_alpha(tmp_path / "train" / "r_000.png").numpy(), want_a, atol=1e-6)
    scene = load_nerf_synthetic(tmp_path)
    assert scene.background == (1.0, 1.0, 1.0) and scene.background_origin.startswith("white: RGBA"), \
        scene.background_origin
    assert np.allclose(scene.image(scene.camera("train/r_001.png")).numpy(), want, atol=1e-6)
    assert written  # (the random RGBA images write_blender put in cams/ are not read)
    # an RGB and a grey PNG with a colour key: the key's pixels are transparent, the rest opaque
    rgb = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    rgb[: H // 2] = (7, 8, 9)
    Image.fromarray(rgb).save(tmp_path / "key.png", transparency=(7, 8, 9))
    keyed = (rgb == (7, 8, 9)).all(-1)[..., None]
    got = read_rgb(tmp_path / "key.png", background=(0.0, 0.5, 1.0)).numpy()
    assert np.allclose(got, np.where(keyed, np.array([0.0, 0.5, 1.0]), rgb / 255.0), atol=1e-6)
    assert np.array_equal(read_alpha(tmp_path / "key.png").numpy() == 0.0, keyed)
    grey = np.where(np.arange(W)[None, :] < W // 3, 0, 77 + np.arange(W)[None, :]).astype(np.uint8).repeat(H, 0)
    Image.fromarray(grey, "L").save(tmp_path / "grey.png", transparency=0)
    got = read_rgb(tmp_path / "grey.png", background=(1.0, 1.0, 1.0)).numpy()
    assert np.allclose(got, np.where(grey[..., None] == 0, 1.0, np.repeat(grey[..., None], 3, -1) / 255.0), atol=1e-6)


def test_center_extent_and_optional_points(tmp_path):
    written = write_blender(tmp_path)
    scene = load_nerf_synthetic(tmp_path)
    assert scene.points is None
    centres = np.stack([written[f"train/r_{k:03d}.png"][0][:3, 3] for k in range(4)])
    assert np.allclose(scene.center.numpy(), centres.mean(0))
    assert math.isclose(scene.extent, 1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max())
    vertex = np.array([(0.1, 0.2, 0.3, 255, 0, 128), (-1.0, 2.0, 0.5, 0, 51, 255)],
                      dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                             ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(tmp_path / "points3d.ply"))
    pts = load_nerf_synthetic(tmp_path).points
    assert np.allclose(pts.xyz.numpy(), [[0.1, 0.2, 0.3], [-1.0, 2.0, 0.5]], atol=1e-6)
    assert np.allclose(pts.rgb.numpy(), [[1.0, 0.0, 128 / 255], [0.0, 0.2, 1.0]], atol=1e-6)


def test_dnerf_times(tmp_path):
    write_blender(tmp_path, counts=(("train", 5), ("test", 2)), times=True)
    scene = load_dnerf(tmp_path)
    assert [c.time for c in scene.train_cameras] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert [c.time for c in scene.test_cameras] == [0.0, 1.0]


def test_scene_pyramid_size_and_geometry():
    # a bright blob centred at pixel coordinate (20.3, 17.6) of a 50x37 image: after
    # downsampling by 3 its centroid must sit where the scaled camera projects that point
    K = np.array([[40.0, 0, 25.0], [0, 40.0, 18.5], [0, 0, 1]])
    cam = Camera(uid=0, name="blob.png", K=K, world_to_camera=np.eye(4), width=50, height=37)
    u0, v0 = 20.3, 17.6
    jj, ii = np.mgrid[0:37, 0:50] + 0.5
    blob = np.exp(-((ii - u0) ** 2 + (jj - v0) ** 2) / (2 * 3.0 ** 2))
    img = torch.from_numpy(np.repeat(blob[..., None], 3, axis=2)).float()
    with pytest.warns(UserWarning, match="extent set to 1.0"):  # one camera: no spread
        scene = Scene([cam], [], {0: img})
    assert scene.extent == 1.0
    small = scene.image(cam, 3)
    s_cam = cam.scaled(3)
    assert small.shape == (s_cam.height, s_cam.width, 3) == (12, 17, 3)
    assert float(small.min()) >= 0 and float(small.max()) <= 1
    sj, si = np.mgrid[0:12, 0:17] + 0.5
    m = small[..., 0].double().numpy()
    centroid = np.array([(m * si).sum(), (m * sj).sum()]) / m.sum()
    point = np.array([(u0 - 25.0) / 40.0, (v0 - 18.5) / 40.0, 1.0])  # on the ray of (u0, v0)
    expected = s_cam.project(torch.from_numpy(point))[0].numpy()
    assert np.abs(centroid - expected).max() < 0.05
    assert scene.image(cam, 3) is small  # cached per factor
    with pytest.raises(ValueError, match="full-resolution camera"):
        scene.image(s_cam, 3)


# ---- bad input: one clear error each -----------------------------------------------------

def test_missing_test_json_holds_out_every_eighth_training_frame(tmp_path):
    write_blender(tmp_path, counts=(("train", 17), ("test", 2)))
    (tmp_path / "transforms_test.json").unlink()
    with pytest.warns(UserWarning, match=r"transforms_test.json is missing: .* every 8th from the first \(3 of 17\)"):
        scene = load_nerf_synthetic(tmp_path)
    assert [c.name for c in scene.test_cameras] == [f"train/r_{k:03d}.png" for k in (0, 8, 16)]
    assert len(scene.train_cameras) == 14 and not {c.name for c in scene.train_cameras} & {"train/r_008.png"}


def test_no_json_at_all(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"transforms_train.json \(or one .*transforms.json\)"):
        load_nerf_synthetic(tmp_path)


def test_json_without_frames(tmp_path):
    write_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": ANGLE_X}))
    with pytest.raises(ValueError, match="transforms_train.json: no 'frames'"):
        load_nerf_synthetic(tmp_path)


def test_empty_split(tmp_path):
    write_blender(tmp_path)
    (tmp_path / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": []}))
    with pytest.raises(ValueError, match="transforms_test.json: 'frames' is empty"):
        load_nerf_synthetic(tmp_path)


def test_nan_in_pose(tmp_path):
    write_blender(tmp_path)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta["frames"][2]["transform_matrix"][1][3] = float("nan")  # json.dumps writes NaN
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"transforms_train.json: frame 2 .*not finite"):
        load_nerf_synthetic(tmp_path)


def test_image_size_disagrees_with_declared_size(tmp_path):
    write_blender(tmp_path, frame_extra={("test", 1): {"w": W + 2}})
    with pytest.raises(ValueError, match=r"frame 1 \(test/r_001.png\): 'w' is 42"):
        load_nerf_synthetic(tmp_path)


def test_a_test_split_that_repeats_the_training_frames_is_said(tmp_path):
    import json
    import warnings

    write_blender(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_nerf_synthetic(tmp_path)
    assert not [w for w in caught if "training frame" in str(w.message)]
    train = json.loads((tmp_path / "transforms_train.json").read_text())
    (tmp_path / "transforms_test.json").write_text(json.dumps(train))  # the test json a copy of the train one
    train["frames"].append(train["frames"][1])  # and one training frame twice
    (tmp_path / "transforms_train.json").write_text(json.dumps(train))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_nerf_synthetic(tmp_path)
    said = [str(w.message) for w in caught]
    assert len(scene.train_cameras) == 5
    assert any("training frame 'train/r_001.png' appears more than once" in m for m in said), said
    assert any("4 of the 4 test frames are also training frames" in m for m in said), said


def test_missing_image(tmp_path):
    write_blender(tmp_path)
    (tmp_path / "train" / "r_003.png").unlink()
    with pytest.raises(FileNotFoundError, match="r_003.png"):
        load_nerf_synthetic(tmp_path)
    # a .jpg named without its extension: the error says '.png' was added to the file_path
    (tmp_path / "train" / "r_002.png").rename(tmp_path / "train" / "r_002.jpg")
    with pytest.raises(FileNotFoundError, match=r"r_002.png.*'./train/r_002' has no extension, so '.png' was added"):
        load_nerf_synthetic(tmp_path)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio probing its plugins
def test_unreadable_image(tmp_path):
    write_blender(tmp_path)
    (tmp_path / "test" / "r_000.png").write_bytes(b"\x00" * 10)
    with pytest.raises(ValueError, match="r_000.png"):
        load_nerf_synthetic(tmp_path)


def test_dnerf_time_missing_or_out_of_range(tmp_path):
    write_blender(tmp_path, times=True, frame_extra={("train", 2): {"time": 1.5}})
    with pytest.raises(ValueError, match=r"frame 2 .*'time' must be in \[0,1\], got 1.5"):
        load_dnerf(tmp_path)
    write_blender(tmp_path / "b", times=False)
    with pytest.raises(ValueError, match="missing 'time'"):
        load_dnerf(tmp_path / "b")
