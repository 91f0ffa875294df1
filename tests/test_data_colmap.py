"""COLMAP loader: a model written with pycolmap from known poses, checked against pycolmap's
own projection, hand-computed splits and normalisation, and one bad input per test."""

import math
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import skimage.io
import torch

from mvgs_plugin.data import load_colmap

W, H = 40, 30


def look_at(position, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    """OpenCV world-to-camera rotation [3,3] and translation [3] of a camera at ``position``."""
    f = np.asarray(target, float) - position
    f /= np.linalg.norm(f)
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    y = np.cross(f, x)  # points down the image, as OpenCV's y
    R = np.stack([x, y, f])
    return R, -R @ position


def write_model(root, n=10, fmt="bin", model="PINHOLE", seed=0, nan_image=None):
    """Write images/ and sparse/0 under ``root``; return what was written.

    ``nan_image``: index of an image whose translation is written as NaN."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    params = {"PINHOLE": [50.0, 52.0, 19.5, 15.2], "SIMPLE_RADIAL": [50.0, 20.0, 15.0, 0.01],
              "THIN_PRISM_FISHEYE": [50.0, 52.0, 19.5, 15.2, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.002, 0.0]}[model]
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(camera_id=1, model=model, width=W, height=H, params=params))
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(camera_id=2, model="SIMPLE_PINHOLE", width=W, height=H,
                        params=[45.0, 20.0, 14.0]))
    positions, names = {}, {}
    ids = rng.permutation(np.arange(1, n + 1))  # id order differs from name order
    for k in range(n):
        angle = 2 * math.pi * k / n
        pos = np.array([4.0 * math.cos(angle), 4.0 * math.sin(angle), 1.0 + 0.1 * k])
        R, t = look_at(pos)
        if k == nan_image:
            t = np.array([t[0], np.nan, t[2]])
        name = f"views/r_{k:03d}.png"
        image = pycolmap.Image(name=name, camera_id=1 + k % 2, image_id=int(ids[k]))
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        positions[name], names[int(ids[k])] = pos, name
        pixels = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        (root / "images" / "views").mkdir(parents=True, exist_ok=True)
        skimage.io.imsave(root / "images" / name, pixels, check_contrast=False)
    xyz = rng.uniform(-0.5, 0.5, size=(25, 3))
    rgb = rng.integers(0, 256, size=(25, 3), dtype=np.uint8)
    for p, c in zip(xyz, rgb):
        rec.add_point3D(p, pycolmap.Track(), c)
    model_dir = root / "sparse" / "0"
    model_dir.mkdir(parents=True)
    (rec.write_binary if fmt == "bin" else rec.write_text)(str(model_dir))
    return dict(positions=positions, names=names, xyz=xyz, rgb=rgb, model_dir=model_dir)


@pytest.fixture
def scene_dir(tmp_path):
    info = write_model(tmp_path)
    return tmp_path, info


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_projection_agrees_with_pycolmap(tmp_path, fmt):
    info = write_model(tmp_path, fmt=fmt)
    scene = load_colmap(tmp_path)
    rec = pycolmap.Reconstruction(str(info["model_dir"]))
    assert len(scene.cameras) == 10
    for cam in scene.cameras:
        image = rec.images[cam.uid]
        assert cam.name == image.name and (cam.width, cam.height) == (W, H)
        ours, depth = cam.project(torch.from_numpy(info["xyz"]))
        assert bool((depth > 0).all())
        theirs = np.stack([image.project_point(p) for p in info["xyz"]])
        assert np.allclose(ours.numpy(), theirs, atol=1e-9)


def test_rays_through_pycolmap_pixels_hit_the_point(scene_dir):
    root, info = scene_dir
    scene = load_colmap(root)
    rec = pycolmap.Reconstruction(str(info["model_dir"]))
    for cam in scene.cameras[:3]:
        pix = np.stack([rec.images[cam.uid].project_point(p) for p in info["xyz"]])
        o, d = cam.rays(torch.from_numpy(pix))
        v = info["xyz"] - o.numpy()
        t = (v * d.numpy()).sum(1)
        assert np.abs(v - t[:, None] * d.numpy()).max() < 1e-9 and (t > 0).all()


def test_scaled_camera_projects_to_pixel_over_s(scene_dir):
    root, info = scene_dir
    cam = load_colmap(root).train_cameras[0]
    image = pycolmap.Reconstruction(str(info["model_dir"])).images[cam.uid]
    theirs = np.stack([image.project_point(p) for p in info["xyz"]])
    small = cam.scaled(2)  # 40x30 divides by 2 exactly
    assert (small.width, small.height) == (20, 15)
    assert np.allclose(small.project(torch.from_numpy(info["xyz"]))[0].numpy(), theirs / 2, atol=1e-9)


def test_simple_pinhole_uses_one_focal(scene_dir):
    root, _ = scene_dir
    scene = load_colmap(root)
    simple = [c for c in scene.cameras if abs(c.fx - 45.0) < 1e-12]
    assert simple and all(c.fy == 45.0 and (c.cx, c.cy) == (20.0, 14.0) for c in simple)


def test_split_every_kth_by_name_and_explicit_names(scene_dir):
    root, info = scene_dir
    names = sorted(info["positions"])
    scene = load_colmap(root, test_every=3)
    assert [c.name for c in scene.test_cameras] == [names[i] for i in (0, 3, 6, 9)]
    assert [c.name for c in scene.train_cameras] == [names[i] for i in (1, 2, 4, 5, 7, 8)]
    default = load_colmap(root)  # test_every=8 -> indices 0 and 8
    assert [c.name for c in default.test_cameras] == [names[0], names[8]]
    explicit = load_colmap(root, test_names=["views/r_004.png", "./views/r_007.png"])
    assert sorted(c.name for c in explicit.test_cameras) == ["views/r_004.png", "views/r_007.png"]
    assert len(explicit.train_cameras) == 8
    assert load_colmap(root, test_every=None).test_cameras == []


def test_center_and_extent_as_original_3dgs(scene_dir):
    root, info = scene_dir
    scene = load_colmap(root, test_every=3)
    centres = np.stack([info["positions"][c.name] for c in scene.train_cameras])
    mean = centres.mean(0)
    assert np.allclose(scene.center.numpy(), mean, atol=1e-9)
    assert math.isclose(scene.extent, 1.1 * np.linalg.norm(centres - mean, axis=1).max(), rel_tol=1e-9)


def test_points_and_images(scene_dir):
    root, info = scene_dir
    scene = load_colmap(root)
    assert scene.points is not None and len(scene.points) == 25
    order = np.lexsort(info["xyz"].T)  # compare as sets: the model may reorder points
    got = scene.points.xyz.numpy().astype(np.float64)
    got_order = np.lexsort(got.T)
    assert np.allclose(got[got_order], info["xyz"][order], atol=1e-6)
    assert np.allclose(scene.points.rgb.numpy()[got_order], info["rgb"][order] / 255.0, atol=1e-6)
    cam = scene.train_cameras[0]
    img = scene.image(cam)
    expected = skimage.io.imread(root / "images" / cam.name) / 255.0
    assert img.dtype == torch.float32 and img.shape == (H, W, 3)
    assert np.allclose(img.numpy(), expected, atol=1e-6)
    assert scene.image(cam) is img  # cached
    small = scene.image(cam, 2)
    assert small.shape == (cam.scaled(2).height, cam.scaled(2).width, 3) == (15, 20, 3)


def test_legacy_model_without_rigs_and_frames(tmp_path):
    info = write_model(tmp_path, fmt="txt")
    for f in ("rigs.txt", "frames.txt"):  # COLMAP < 3.12 writes neither
        (info["model_dir"] / f).unlink()
    scene = load_colmap(tmp_path)
    assert len(scene.cameras) == 10
    cam = scene.camera("views/r_005.png")
    assert np.allclose(cam.center.numpy(), info["positions"]["views/r_005.png"], atol=1e-9)


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_a_model_without_its_points_file_loads_without_points(tmp_path, fmt):
    """Points are optional: a model with cameras and images but no points3D file loads with the
    same cameras as the full model and no points; the model folder is left as it was."""
    info = write_model(tmp_path, fmt=fmt)
    full = load_colmap(tmp_path)
    (info["model_dir"] / f"points3D.{fmt}").unlink()
    files = sorted(f.name for f in info["model_dir"].iterdir())
    with pytest.warns(UserWarning, match="holds 0 3D points \\(an empty or absent points3D file\\): the scene has no point cloud \\(the examples' --init makes "
                                         "one, by default triangulated from the training views"):
        scene = load_colmap(tmp_path)
    assert scene.points is None or len(scene.points) == 0
    assert [c.name for c in scene.cameras] == [c.name for c in full.cameras]
    for a, b in zip(scene.cameras, full.cameras):
        assert torch.equal(a.world_to_camera, b.world_to_camera) and torch.equal(a.K, b.K)
    assert sorted(f.name for f in info["model_dir"].iterdir()) == files
    other = "txt" if fmt == "bin" else "bin"
    (info["model_dir"] / f"points3D.{other}").write_bytes(bytes(8) if other == "bin" else b"")  # of the other format, 0 points
    with pytest.raises(ValueError, match=f"points3D.{other} beside cameras.{fmt} and images.{fmt}: pycolmap reads one"):
        load_colmap(tmp_path)
    (info["model_dir"] / f"points3D.{other}").unlink()
    (info["model_dir"] / f"images.{fmt}").unlink()
    with pytest.raises(FileNotFoundError, match=f"needs cameras and images files of one format.*found cameras.{fmt}"):
        load_colmap(tmp_path)


@pytest.mark.parametrize("fmt", ["bin", "txt"])
@pytest.mark.parametrize("dangling", ["image", "2D point"])
def test_points_whose_tracks_name_what_the_images_file_lacks_load_without_their_tracks(tmp_path, fmt, dangling):
    """Frames deleted from a model by hand (their image records gone, the points' tracks still
    naming them), or images' 2D points stripped: pycolmap refuses the model. It loads with the
    same cameras as the model before the edit and the points' own positions and colours, with a
    warning that says why; the model's files are left byte for byte as they were."""
    info = write_model(tmp_path, fmt=fmt)
    full = load_colmap(tmp_path)
    image_id, point2d = (99, 0) if dangling == "image" else (min(info["names"]), 5)  # no image has 2D points here
    points = info["model_dir"] / f"points3D.{fmt}"
    if fmt == "txt":
        lines = points.read_text().splitlines()
        points.write_text("\n".join(line if line.startswith("#") else f"{line.rstrip()} {image_id} {point2d}"
                                     for line in lines) + "\n")
    else:  # COLMAP's binary layout, written here: id, xyz, rgb, error, track length, (image id, 2D point index)
        body = b"".join(struct.pack("<Q3d3BdQII", k + 1, *p, *c, -1.0, 1, image_id, point2d)
                        for k, (p, c) in enumerate(zip(info["xyz"].tolist(), info["rgb"].tolist())))
        points.write_bytes(struct.pack("<Q", len(info["xyz"])) + body)
    with pytest.raises(Exception):
        pycolmap.Reconstruction(str(info["model_dir"]))
    before = {f.name: f.read_bytes() for f in info["model_dir"].iterdir()}
    with pytest.warns(UserWarning, match=f"cannot read the model with its points3D.{fmt} .*: its tracks name images or "
                                         "2D points the images file does not have .* its 25 points' positions and "
                                         "colours are kept"):
        scene = load_colmap(tmp_path)
    assert {f.name: f.read_bytes() for f in info["model_dir"].iterdir()} == before
    assert [c.name for c in scene.cameras] == [c.name for c in full.cameras]
    for a, b in zip(scene.cameras, full.cameras):
        assert torch.equal(a.world_to_camera, b.world_to_camera) and torch.equal(a.K, b.K)
    assert np.allclose(scene.points.xyz.numpy(), info["xyz"], atol=1e-6)
    assert np.allclose(scene.points.rgb.numpy(), info["rgb"] / 255.0, atol=1e-6)


def test_quaternions_rounded_in_images_txt_are_normalised_as_colmap_does(tmp_path):
    """images.txt (without frames.txt) with its quaternions rounded to 3 decimals (norm off by ~1e-3): the pose is the
    rotation of the normalised quaternion (computed here from its definition), not refused."""
    info = write_model(tmp_path, fmt="txt")
    for f in ("rigs.txt", "frames.txt"):  # a model of COLMAP < 3.12: the poses are in images.txt
        (info["model_dir"] / f).unlink()
    path = info["model_dir"] / "images.txt"
    lines, rounded = path.read_text().splitlines(), {}
    for i, line in enumerate(lines):
        parts = line.split()
        if line.startswith("#") or len(parts) < 10 or not parts[-1].endswith(".png"):
            continue
        q = [round(float(v), 3) for v in parts[1:5]]
        rounded[parts[-1]] = (np.array(q), np.array([float(v) for v in parts[5:8]]))
        lines[i] = " ".join([parts[0]] + [f"{v:.3f}" for v in q] + parts[5:])
    path.write_text("\n".join(lines) + "\n")
    assert len(rounded) == 10 and any(abs(np.linalg.norm(q) - 1) > 1e-4 for q, _ in rounded.values())
    scene = load_colmap(tmp_path)
    for name, (q, t) in rounded.items():
        w, x, y, z = q / np.linalg.norm(q)
        R = np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])
        w2c = scene.camera(name).world_to_camera.numpy()
        assert np.allclose(w2c[:3, :3], R, atol=1e-12) and np.allclose(w2c[:3, 3], t, atol=1e-12)


def test_images_dir_and_model_folder_given_directly(scene_dir):
    root, info = scene_dir
    scene = load_colmap(info["model_dir"], images_dir=root / "images")
    assert len(scene.cameras) == 10


# ---- bad input: one clear error each -----------------------------------------------------

def test_a_thin_prism_camera_model_is_refused(tmp_path):
    """Radial, OpenCV and fisheye lenses are undistorted when read (test_data_distortion.py); a
    thin-prism fisheye is not."""
    write_model(tmp_path, model="THIN_PRISM_FISHEYE")
    with pytest.raises(ValueError, match="THIN_PRISM_FISHEYE: supported are .*image_undistorter"):
        load_colmap(tmp_path)


def test_missing_model(tmp_path):
    with pytest.raises(FileNotFoundError, match="no COLMAP model"):
        load_colmap(tmp_path)


def test_missing_image_file(scene_dir):
    root, _ = scene_dir
    (root / "images" / "views" / "r_003.png").unlink()
    with pytest.raises(FileNotFoundError, match="r_003.png"):
        load_colmap(root)


def test_image_size_disagrees_with_camera(scene_dir):
    root, _ = scene_dir
    skimage.io.imsave(root / "images" / "views" / "r_002.png",
                      np.zeros((H, W + 1, 3), np.uint8), check_contrast=False)
    with pytest.raises(ValueError, match=r"r_002.png is 41x30 but its camera \d is 40x30, and it is not a copy "
                                         r"downscaled alike on both axes"):
        load_colmap(root)


@pytest.mark.parametrize("factor", [2, 4])
def test_a_downscaled_image_folder_scales_the_intrinsics(tmp_path, factor):
    """Mip-NeRF 360's layout: images_N/ beside images/, the model at full size. Each camera is the
    model's scaled to its image (pycolmap's projection times the size ratio); the pixels are the
    copies'."""
    from skimage.transform import resize

    info = write_model(tmp_path)
    small = tmp_path / f"images_{factor}"
    sizes = {}
    for f in (tmp_path / "images").rglob("*.png"):
        img = skimage.io.imread(f)
        w, h = math.floor(W / factor + 0.5), math.floor(H / factor + 0.5)
        out = (resize(img, (h, w), anti_aliasing=True) * 255).round().astype(np.uint8)
        (small / f.parent.name).mkdir(parents=True, exist_ok=True)
        skimage.io.imsave(small / f.parent.name / f.name, out, check_contrast=False)
        sizes[f.name] = out
    scene = load_colmap(tmp_path, images_dir=small)
    rec = pycolmap.Reconstruction(str(info["model_dir"]))
    for cam in scene.cameras:
        image = rec.images[cam.uid]
        assert (cam.width, cam.height) == (w, h)
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        theirs = rec.cameras[image.camera_id].img_from_cam(pose * info["xyz"]) * np.array([w / W, h / H])
        ours, _ = cam.project(torch.from_numpy(info["xyz"]))
        assert np.allclose(ours.numpy(), theirs, atol=1e-6)
        assert np.allclose(scene.image(cam).numpy(), sizes[Path(cam.name).name] / 255.0, atol=1e-6)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio probing its plugins
def test_unreadable_image(scene_dir):
    root, _ = scene_dir
    (root / "images" / "views" / "r_001.png").write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="r_001.png") as err:
        load_colmap(root)
    assert "pip install" not in str(err.value)  # imageio's advice for video plugins does not apply


def test_names_with_spaces_in_images_txt_are_named_with_the_cause(tmp_path):
    """COLMAP's text format ends an image name at its first space, so "my cam/r_000.png" reads as
    "my" for every image: the error names that name, its count and the cause, where it said only
    "duplicate image names"."""
    info = write_model(tmp_path, fmt="txt")
    path = info["model_dir"] / "images.txt"
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        parts = line.split()
        if not line.startswith("#") and len(parts) >= 10 and parts[-1].endswith(".png"):
            lines[i] = " ".join(parts[:-1] + ["my cam/" + parts[-1].split("/")[-1]])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"duplicate image names in the model: 'my' appears 10 times \(COLMAP's text "
                                         r"format ends a name at its first space"):
        load_colmap(tmp_path)


@pytest.mark.parametrize("damage", ["camera", "quaternion", "point", "camera_param"])
def test_a_damaged_text_model_is_named_by_file_line_and_value(tmp_path, damage):
    """pycolmap's own errors for these say "Check failed" or name a rig the model does not have:
    the loader names the file, the line and the value first."""
    info = write_model(tmp_path, fmt="txt")
    name = {"camera": "images.txt", "quaternion": "images.txt", "point": "points3D.txt",
            "camera_param": "cameras.txt"}[damage]
    file = info["model_dir"] / name
    lines = file.read_text().splitlines()
    records = [i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")]
    k = records[2] if name == "images.txt" else records[0]  # records[2]: the second image (each has a points line)
    fields = lines[k].split()
    if damage == "camera":
        fields[8] = "7"
    elif damage == "quaternion":
        fields[2] = "nan"
    elif damage == "point":
        fields[3] = "inf"
    else:
        fields[4] = "nan"
    lines[k] = " ".join(fields)
    file.write_text("\n".join(lines) + "\n")
    image = fields[9] if name == "images.txt" else None
    want = {"camera": rf"images.txt:{k + 1}: image '{image}' names camera 7, which .*cameras.txt does not list "
                      r"\(it lists 1, 2\)",
            "quaternion": rf"images.txt:{k + 1}: the pose of image '{image}': 'nan' is not a finite number",
            "point": rf"points3D.txt:{k + 1}: the position of point {fields[0]}: 'inf' is not a finite number",
            "camera_param": rf"cameras.txt:{k + 1}: the parameters of camera {fields[0]}: 'nan' is not a finite number"}[damage]
    with pytest.raises(ValueError, match=want):
        load_colmap(tmp_path)


def test_nan_pose(tmp_path):
    # COLMAP's text reader rejects "nan" itself; the binary format stores it as is
    write_model(tmp_path, fmt="bin", nan_image=4)
    with pytest.raises(ValueError, match=r"r_004.png.*finite"):
        load_colmap(tmp_path)


def test_empty_train_split_and_unknown_test_name(scene_dir):
    root, _ = scene_dir
    with pytest.raises(ValueError, match=r"train split is empty: every one of its 10 image\(s\) is a test view \(one image "
                                         r"in every 1 by name is held out.*test_every=None"):
        load_colmap(root, test_every=1)
    with pytest.raises(ValueError, match="nope.png"):
        load_colmap(root, test_names=["nope.png"])


# ---- the bundled scene ---------------------------------------------------------------------

def test_bundled_scene_loads_identically_in_both_layouts():
    from pathlib import Path

    from mvgs_plugin.data import load_nerf_synthetic

    root = Path(__file__).resolve().parent.parent / "examples" / "scenes" / "tabletop"
    nerf = load_nerf_synthetic(root)
    test_names = sorted(p.relative_to(root).as_posix() for p in (root / "test").glob("*.png"))
    colmap = load_colmap(root, test_names=test_names)
    assert sorted(c.name for c in colmap.test_cameras) == sorted(c.name for c in nerf.test_cameras) \
        == test_names
    assert sorted(c.name for c in colmap.train_cameras) == sorted(c.name for c in nerf.train_cameras)
    for cam in colmap.cameras:
        other = nerf.camera(cam.name)
        assert (cam.width, cam.height) == (other.width, other.height)
        assert torch.allclose(cam.K, other.K, atol=1e-6, rtol=0)
        assert torch.allclose(cam.world_to_camera, other.world_to_camera, atol=1e-6, rtol=0)
    assert torch.allclose(colmap.center, nerf.center, atol=1e-6)
    assert math.isclose(colmap.extent, nerf.extent, rel_tol=1e-6)
    name = colmap.test_cameras[0].name  # same pixels through both loaders
    assert torch.equal(colmap.image(colmap.camera(name)), nerf.image(nerf.camera(name)))
    # the PLY next to the json and the COLMAP points3D hold the same points
    a, b = colmap.points, nerf.points
    assert a is not None and b is not None and len(a) == len(b)
    ia, ib = np.lexsort(a.xyz.numpy().T), np.lexsort(b.xyz.numpy().T)
    assert torch.allclose(a.xyz[ia], b.xyz[ib], atol=1e-5)
    assert torch.allclose(a.rgb[ia], b.rgb[ib], atol=1e-6)


def test_a_camera_line_with_too_few_parameters_names_its_model_and_count(tmp_path):
    """pycolmap says only "Check failed: camera.VerifyParams()"; a PINHOLE camera has fx fy cx cy."""
    info = write_model(tmp_path, fmt="txt")
    file = info["model_dir"] / "cameras.txt"
    lines = file.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip() and not line.startswith("#"))
    fields = lines[k].split()
    model = fields[1]
    lines[k] = " ".join(fields[:-1])
    file.write_text("\n".join(lines) + "\n")
    count = {"PINHOLE": 4, "SIMPLE_PINHOLE": 3, "SIMPLE_RADIAL": 4, "OPENCV": 8}[model]
    with pytest.raises(ValueError, match=rf"cameras.txt:{k + 1}: camera {fields[0]} is a {model} camera, which has "
                                         rf"{count} parameters .*the line gives {count - 1}"):
        load_colmap(tmp_path)


def test_image_lines_without_their_points_lines_are_refused_not_halved(tmp_path):
    """A model written by hand from known poses with one line per image: pycolmap reads every
    other image and takes the rest for 2D points. The loader counts the records itself (ten
    images here) and refuses; with an empty line after each, every image loads."""
    info = write_model(tmp_path, fmt="txt")
    file = info["model_dir"] / "images.txt"
    records = [line for line in file.read_text().splitlines()
               if not line.startswith("#") and len(line.split()) >= 10 and line.split()[-1].endswith(".png")]
    assert len(records) == 10
    file.write_text("# hand-written\n" + "\n".join(records) + "\n")
    with pytest.raises(ValueError, match=r"images.txt(:\d+: the line after image .* is an image record|: 10 lines look like "
                                         r"image records .* but pycolmap read 5 images): COLMAP.s text format follows"):
        load_colmap(tmp_path)
    file.write_text("# hand-written\n" + "".join(f"{line}\n\n" for line in records))
    scene = load_colmap(tmp_path)
    assert len(scene.train_cameras) + len(scene.test_cameras) == 10
