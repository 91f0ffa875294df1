"""Input checks: image paths that leave the scene folder, stale NeRF intrinsics, corrupt COLMAP
binary counts, the training script's arguments, mixed image sizes in one step, divergence
guards, and Gaussian / point PLY files that cannot be trained on.

Every bad input must give an error naming the bad value or file and what was expected; every
refusal is paired with the accepted input next to it (the untouched scene loads, consistent
intrinsics load without warnings, a normal run completes)."""

import dataclasses
import importlib.util
import json
import math
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import skimage.io
import torch
from plyfile import PlyData, PlyElement

from mvgs_plugin.adapters.gs3d import MAX_LOG_SCALE, GS3DAdapter, GS3DConfig
from mvgs_plugin.adapters.ply import ply_property_names, read_gaussian_ply, write_gaussian_ply
from mvgs_plugin import CRDConfig, MVGS, MVGSConfig, Stage
from mvgs_plugin.camera import Camera
from mvgs_plugin.data import PointCloud, Scene, load_colmap, load_nerf_synthetic
from mvgs_plugin.losses import photometric_loss
from mvgs_plugin.testing import look_at, synthetic_scene

try:
    from tests.test_controller import grads_at_optimizer_step
except ImportError:  # tests/ itself on sys.path
    from test_controller import grads_at_optimizer_step

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "examples" / "scenes" / "tabletop"
EXAMPLE = ROOT / "examples" / "train_3dgs.py"
F64 = torch.float64
BIG_COUNT = 2 ** 40


def load_example():
    spec = importlib.util.spec_from_file_location("train_3dgs", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def copy_scene(tmp_path, name="scene"):
    dest = tmp_path / name
    shutil.copytree(BUNDLED, dest)
    return dest


def edit_json(scene_dir, split, edit):
    file = scene_dir / f"transforms_{split}.json"
    meta = json.loads(file.read_text())
    edit(meta)
    file.write_text(json.dumps(meta))
    return meta


def numbers_in(text):
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", text)]


@pytest.fixture(scope="module")
def bundled_scene():
    return load_nerf_synthetic(BUNDLED)


# ---- 1. image paths that leave the scene folder ------------------------------------------------

def outside_image(tmp_path):
    """A real image next to (not inside) the scene folder: without the check it would load."""
    target = tmp_path / "outside.png"
    shutil.copy(BUNDLED / "train" / "r_000.png", target)
    return target


@pytest.mark.parametrize("kind", ["parent", "detour", "absolute"])
def test_nerf_image_path_outside_the_folder_is_refused(tmp_path, kind):
    scene_dir = copy_scene(tmp_path)
    target = outside_image(tmp_path)
    path = {"parent": "../outside", "detour": "train/../../outside.png", "absolute": str(target)}[kind]
    named = "'../outside.png'" if kind != "absolute" else repr(str(target))
    edit_json(scene_dir, "train", lambda m: m["frames"][3].update(file_path=path))
    with pytest.raises(ValueError) as info:
        load_nerf_synthetic(scene_dir)
    msg = str(info.value)
    assert named in msg and f"leaves the folder {scene_dir}" in msg, msg
    assert "transforms_train.json: frame 3" in msg, msg


def test_nerf_image_path_with_detour_that_stays_inside_loads(tmp_path):
    scene_dir = copy_scene(tmp_path)
    edit_json(scene_dir, "train", lambda m: m["frames"][0].update(file_path="./test/../train/./r_000"))
    scene = load_nerf_synthetic(scene_dir)
    assert scene.train_cameras[0].name == "train/r_000.png"


def rename_colmap_image(scene_dir, new_name):
    model = scene_dir / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    first = min(rec.images)
    rec.images[first].name = new_name
    rec.write(str(model))
    return first


@pytest.mark.parametrize("kind", ["parent", "absolute"])
def test_colmap_image_path_outside_the_folder_is_refused(tmp_path, kind):
    scene_dir = copy_scene(tmp_path)
    target = outside_image(tmp_path)
    name = "../outside.png" if kind == "parent" else str(target)
    image_id = rename_colmap_image(scene_dir, name)
    assert pycolmap.Reconstruction(str(scene_dir / "sparse" / "0")).images[image_id].name == name
    with pytest.raises(ValueError) as info:
        load_colmap(scene_dir)
    msg = str(info.value)
    assert repr(name) in msg and f"leaves the folder {scene_dir}" in msg, msg
    assert f"image {image_id}" in msg, msg


def test_colmap_untouched_and_renamed_inside_models_load(tmp_path):
    scene_dir = copy_scene(tmp_path)
    assert len(load_colmap(scene_dir, test_every=None).cameras) == 60
    # a name with a detour that stays inside is accepted and normalised
    rename_colmap_image(scene_dir, "test/../train/r_000.png")
    names = [c.name for c in load_colmap(scene_dir, test_every=None).cameras]
    assert "train/r_000.png" in names and len(names) == 60


# ---- 2. stale NeRF intrinsics ------------------------------------------------------------------

def halve_images(scene_dir):
    for png in list((scene_dir / "train").glob("*.png")) + list((scene_dir / "test").glob("*.png")):
        img = skimage.io.imread(png).astype(np.float64)
        h, w = img.shape[:2]
        small = img.reshape(h // 2, 2, w // 2, 2, -1).mean(axis=(1, 3))
        skimage.io.imsave(png, np.round(small).astype(np.uint8), check_contrast=False)


def drop(meta, *keys):
    for k in keys:
        meta.pop(k, None)


def test_resized_images_with_stale_fl_x_are_refused(tmp_path):
    scene_dir = copy_scene(tmp_path)
    halve_images(scene_dir)
    meta = edit_json(scene_dir, "train", lambda m: drop(m, "w", "h"))
    edit_json(scene_dir, "test", lambda m: drop(m, "w", "h"))
    angle, fl_x = meta["camera_angle_x"], meta["fl_x"]
    with pytest.raises(ValueError) as info:
        load_nerf_synthetic(scene_dir)
    msg = str(info.value)
    assert "fl_x" in msg and "camera_angle_x" in msg, msg
    # the focal camera_angle_x implies for the 64 px image, and the width fl_x was made for
    from_angle = 0.5 * 64 / math.tan(0.5 * angle)
    fits = fl_x * 2 * math.tan(0.5 * angle)
    assert round(fits) == 128
    nums = numbers_in(msg)
    assert any(math.isclose(v, from_angle, rel_tol=1e-4) for v in nums), (from_angle, msg)
    assert "64 px" in msg and f"{round(fits)} px" in msg, msg


def test_resized_images_with_scaled_or_dropped_intrinsics_load(tmp_path):
    scene_dir = copy_scene(tmp_path)
    halve_images(scene_dir)
    # keep only camera_angle_x: the focal follows the image
    for split in ("train", "test"):
        meta = edit_json(scene_dir, split, lambda m: drop(m, "w", "h", "fl_x", "fl_y", "cx", "cy"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_nerf_synthetic(scene_dir)
    f = 0.5 * 64 / math.tan(0.5 * meta["camera_angle_x"])
    for cam in scene.cameras:
        assert (cam.width, cam.height) == (64, 64)
        assert torch.allclose(cam.K, torch.tensor([[f, 0, 32.0], [0, f, 32.0], [0, 0, 1]], dtype=F64))
    # fl_x, fl_y, cx, cy scaled with the images
    original = json.loads((BUNDLED / "transforms_train.json").read_text())

    def scaled(m):
        m.update({k: original[k] / 2 for k in ("fl_x", "fl_y", "cx", "cy")}, w=64, h=64)

    for split in ("train", "test"):
        edit_json(scene_dir, split, scaled)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_nerf_synthetic(scene_dir)
    assert math.isclose(scene.train_cameras[0].fx, original["fl_x"] / 2, rel_tol=1e-12)
    assert scene.train_cameras[0].cx == original["cx"] / 2


@pytest.mark.parametrize("key,value", [("cx", 200.0), ("cx", 128.0), ("cx", -3.0), ("cy", 0.0)])
def test_principal_point_outside_the_image_is_refused(tmp_path, key, value):
    scene_dir = copy_scene(tmp_path)
    edit_json(scene_dir, "train", lambda m: m.update({key: value}))
    with pytest.raises(ValueError) as info:
        load_nerf_synthetic(scene_dir)
    msg = str(info.value)
    assert f"{key}={value:g}" in msg and "outside the image" in msg and "128x128" in msg, msg
    assert "transforms_train.json" in msg, msg


def test_off_centre_principal_point_warns_and_is_used(tmp_path):
    scene_dir = copy_scene(tmp_path)
    cx = 64 + 0.3 * 128  # 30 % of the width off-centre, inside the image
    edit_json(scene_dir, "train", lambda m: m.update(cx=cx))
    with pytest.warns(UserWarning, match=r"cx=102\.4 .*centre 64") as record:
        scene = load_nerf_synthetic(scene_dir)
    assert len([w for w in record if "cx=102.4" in str(w.message)]) == len(scene.train_cameras)
    for cam in scene.train_cameras:
        assert float(cam.K[0, 2]) == cx and float(cam.K[1, 2]) == 64.0
    assert all(float(c.K[0, 2]) == 64.0 for c in scene.test_cameras)


def test_consistent_intrinsics_load_without_warnings(tmp_path):
    scene_dir = copy_scene(tmp_path)
    # 19.5 % off-centre: below the 20 % warning line, used as given
    edit_json(scene_dir, "test", lambda m: m.update(cx=89.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_nerf_synthetic(scene_dir)
    f = 0.5 * 128 / math.tan(0.5 * json.loads((BUNDLED / "transforms_train.json").read_text())["camera_angle_x"])
    assert all(math.isclose(c.fx, f, rel_tol=1e-9) and c.cx == 64.0 for c in scene.train_cameras)
    assert all(c.cx == 89.0 for c in scene.test_cameras)


# ---- 3. COLMAP binary record counts ------------------------------------------------------------

def set_count(file, count):
    data = bytearray(file.read_bytes())
    data[:8] = int(count).to_bytes(8, "little")
    file.write_bytes(bytes(data))


@pytest.mark.parametrize("name", ["points3D.bin", "images.bin", "cameras.bin"])
def test_huge_declared_count_is_refused_quickly(tmp_path, name):
    scene_dir = copy_scene(tmp_path)
    file = scene_dir / "sparse" / "0" / name
    set_count(file, BIG_COUNT)
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as info:
        load_colmap(scene_dir)
    assert time.perf_counter() - t0 < 1.0
    msg = str(info.value)
    assert str(file) in msg and str(BIG_COUNT) in msg, msg


def test_truncated_points_file_below_its_declared_count_is_refused(tmp_path):
    scene_dir = copy_scene(tmp_path)
    file = scene_dir / "sparse" / "0" / "points3D.bin"
    declared = int.from_bytes(file.read_bytes()[:8], "little")
    assert declared == len(pycolmap.Reconstruction(str(BUNDLED / "sparse" / "0")).points3D) == 4000
    file.write_bytes(file.read_bytes()[:1000])
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as info:
        load_colmap(scene_dir)
    assert time.perf_counter() - t0 < 1.0
    msg = str(info.value)
    assert str(file) in msg and f"declares {declared} records" in msg and "1000" in msg, msg


def test_an_unknown_camera_model_does_not_end_the_walk(tmp_path):
    """A camera model id the walk does not know leaves cameras.bin to pycolmap, but the image and
    point files after it are still walked: a truncated points3D.bin is still refused by name."""
    scene_dir = copy_scene(tmp_path)
    cams = scene_dir / "sparse" / "0" / "cameras.bin"
    data = bytearray(cams.read_bytes())
    data[12:16] = (99).to_bytes(4, "little", signed=True)  # record 0: u64 count, i32 id, i32 model
    cams.write_bytes(bytes(data))
    points = scene_dir / "sparse" / "0" / "points3D.bin"
    points.write_bytes(points.read_bytes()[:1000])
    with pytest.raises(ValueError, match=re.escape(str(points)) + ".*declares 4000 records"):
        load_colmap(scene_dir)


def test_count_header_itself_truncated_is_refused(tmp_path):
    scene_dir = copy_scene(tmp_path)
    file = scene_dir / "sparse" / "0" / "images.bin"
    file.write_bytes(file.read_bytes()[:5])
    with pytest.raises(ValueError, match=re.escape(str(file)) + ".*5 bytes"):
        load_colmap(scene_dir)


_CHILD = textwrap.dedent("""
    import resource, sys, time
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))  # a runaway allocation fails here, not the machine
    import torch
    torch.set_num_threads(1)
    from mvgs_plugin.data import load_colmap
    t0 = time.perf_counter()
    try:
        load_colmap(sys.argv[1])
        print("LOADED")
    except BaseException as exc:
        print(type(exc).__name__, time.perf_counter() - t0, str(exc).replace(chr(10), " "))
""")


def test_half_truncated_points_file_is_refused_quickly(tmp_path):
    """Cut in the middle of the point records, the declared count still fits the remaining bytes
    (tracks are most of the file): the loader must still refuse it at once, naming the file, not
    hand it to a reader that allocates from garbage track lengths. Run in a child process with a
    3 GB address-space cap and a timeout, so a regression cannot exhaust this machine."""
    scene_dir = copy_scene(tmp_path)
    file = scene_dir / "sparse" / "0" / "points3D.bin"
    data = file.read_bytes()
    file.write_bytes(data[:len(data) // 2])
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    try:
        out = subprocess.run([sys.executable, "-c", _CHILD, str(scene_dir)], capture_output=True, text=True,
                             timeout=30, env=env, cwd=str(ROOT)).stdout.strip()
    except subprocess.TimeoutExpired:
        pytest.fail("load_colmap on a half-truncated points3D.bin ran for more than 30 s")
    kind, seconds, msg = (out.split(" ", 2) + ["", ""])[:3]
    assert kind == "ValueError", out
    assert float(seconds) < 1.0 and str(file) in msg, out


# ---- 4. examples/train_3dgs.py arguments -------------------------------------------------------

@pytest.mark.parametrize("option,value", [
    ("--views", "0"), ("--steps", "0"), ("--threads", "0"), ("--seed", "-1"), ("--budget", "nan"),
    ("--budget", "-1"), ("--threshold-width", "-5"), ("--max-gaussians", "0"), ("--resolution-scale", "0"),
    # past what any run needs, where the run would overflow later (a seed, a budget past int32) or never end
    ("--seed", "99999999999999999999"), ("--max-gaussians", "100000000000000000000"), ("--budget", "1e30"),
    ("--steps", "1000000000000"), ("--background-points", "100000000000"), ("--out", ""), ("--out", "  "),
])
def test_bad_argument_is_a_usage_error_naming_the_option(capsys, option, value):
    example = load_example()
    with pytest.raises(SystemExit) as info:
        example.parse_args([option, value])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "usage:" in err and f"argument {option}:" in err and value in err.split(f"argument {option}:")[1], err


def test_good_arguments_parse(tmp_path):
    args = load_example().parse_args(["--views", "1", "--steps", "1", "--threads", "1", "--seed", "0", "--budget",
                                      "0.5", "--threshold-width", "0", "--max-gaussians", "1",
                                      "--resolution-scale", "1", "--out", str(tmp_path / "o")])
    assert (args.views, args.steps, args.threads, args.seed, args.budget) == (1, 1, 1, 0, 0.5)
    assert (args.threshold_width, args.max_gaussians, args.resolution_scale) == (0.0, 1, 1)
    top = load_example().parse_args(["--seed", "4294967295", "--max-gaussians", "2147483647", "--steps", "100000000",
                                     "--budget", "1e8", "--background-points", "10000000"])
    assert (top.seed, top.max_gaussians, top.steps, top.budget, top.background_points) == (
        2**32 - 1, 2**31 - 1, 10**8, 1e8, 10**7)


def test_the_config_bounds_a_budget_and_a_seed_where_they_would_overflow():
    from mvgs_plugin import MVGSConfig
    with pytest.raises(ValueError, match=r"max_gaussians must be an int in 1\.\.2147483647, got 2147483648"):
        MVGSConfig(max_gaussians=2**31)
    with pytest.raises(ValueError, match=r"seed must be an int in 0\.\.4294967295, got 4294967296"):
        MVGSConfig(seed=2**32)
    assert MVGSConfig(max_gaussians=2**31 - 1, seed=2**32 - 1).max_gaussians == 2**31 - 1


@pytest.mark.parametrize("where", ["file", "under_file", "unmakeable"])
def test_bad_out_is_refused_before_any_work(tmp_path, monkeypatch, where):
    """An --out that is a file, under a file, or where no folder can be made though the
    permissions say yes (/proc: the run used to train, then fail on its first write)."""
    example = load_example()
    calls = []
    monkeypatch.setattr(example, "run", lambda *a: calls.append("run"))
    monkeypatch.setattr(example, "scene_from_args", lambda *a: calls.append("load_scene"))
    blocker = tmp_path / "a_file"
    blocker.write_text("keep me")
    out = {"file": blocker, "under_file": blocker / "sub" / "dir", "unmakeable": Path("/proc/mvgs-out/run")}[where]
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as info:
        example.main(["--out", str(out), "--steps", "2", "--no-progress", "--debug"])
    assert time.perf_counter() - t0 < 1.0
    msg = str(info.value)
    if where == "unmakeable":
        assert msg.startswith(f"--out {out}: a folder cannot be made in /proc ("), msg
    else:
        assert str(out) in msg and (str(blocker) in msg) and "file" in msg, msg
    assert calls == []
    assert blocker.is_file() and blocker.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


@pytest.mark.parametrize("content", [b'{"camera_angle_x": 0.7, "frames": [', b"\xff\xfe{}", b""])
def test_malformed_transforms_json_is_named(tmp_path, content):
    example = load_example()
    scene_dir = copy_scene(tmp_path)
    file = scene_dir / "transforms_train.json"
    file.write_bytes(content)
    out = tmp_path / "out"
    for load in (lambda: example.main(["--data", str(scene_dir), "--steps", "2", "--out", str(out),
                                        "--no-progress", "--debug"]),
                 lambda: load_nerf_synthetic(scene_dir)):
        with pytest.raises(ValueError) as info:
            load()
        assert not isinstance(info.value, json.JSONDecodeError), type(info.value)
        assert str(file) in str(info.value) and "JSON" in str(info.value), str(info.value)
    assert not out.exists()


# ---- 5. images of mixed sizes in one step ------------------------------------------------------

def mixed_scene():
    """Two training cameras of different sizes (and a third size for the test camera)."""
    g = torch.Generator().manual_seed(0)
    sizes = [(16, 16), (24, 12), (20, 14)]
    cams, images = [], {}
    for i, (w, h) in enumerate(sizes):
        a = 2 * math.pi * i / len(sizes)
        f = 1.2 * max(w, h)
        cams.append(Camera(uid=i, name=f"view_{i}", K=[[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]],
                           world_to_camera=look_at((3 * math.cos(a), 3 * math.sin(a), 0.8)), width=w, height=h))
        images[i] = torch.rand(h, w, 3, generator=g)
    pts = torch.nn.functional.normalize(torch.randn(60, 3, generator=g, dtype=F64), dim=-1) * 0.6
    return Scene(cams[:2], cams[2:], images, points=PointCloud(pts, torch.rand(60, 3, generator=g)))


def make_adapter(scene, dtype=F64, **cfg):
    torch.manual_seed(0)
    return GS3DAdapter.from_scene(scene, GS3DConfig(**cfg), dtype=dtype)


def test_mixed_size_step_gradient_is_the_sum_of_single_view_gradients():
    scene = mixed_scene()
    config = MVGSConfig(stages=(Stage(1, 2, 5),), chunk_size=2, reduction="sum", densify_from=100)
    trainer = MVGS(make_adapter(scene), scene, config)
    # The gradients the controller hands to the optimizer, read by a spy on optimizer_step (the
    # public step() path; comparing post-Adam parameters would hide gradient errors in Adam's
    # normalisation).
    seen, info = grads_at_optimizer_step(trainer)
    assert sorted(info.views) == [0, 1]
    assert len({(scene.train_cameras[i].width, scene.train_cameras[i].height) for i in info.views}) == 2

    # Independent: a fresh identical model renders each view alone; loss = sum of per-view
    # photometric losses (plan weight 1 for "sum"), one backward per view.
    ref = make_adapter(scene)
    ref.set_step(1)
    total = 0.0
    for i in info.views:
        cam = scene.train_cameras[i]
        out = ref.render([cam], torch.zeros(1, 3, dtype=F64))
        assert tuple(out.images[0].shape) == (cam.height, cam.width, 3)
        loss = 1.0 * photometric_loss(out.images[0], scene.image(cam).to(out.images[0]), config.lambda_dssim)
        loss.backward()
        total += loss.item()
    assert math.isclose(info.loss, total, rel_tol=1e-12)
    compared = 0
    for name, g in ref.named_gradients().items():
        if g is None or not bool(g.abs().max() > 0):
            continue
        err = float((seen[name] - g).abs().max() / g.abs().max())
        assert err <= 1e-10, f"{name}: relative difference {err}"
        compared += 1
    assert compared >= 3  # means, sh0, scales, opacities get gradients here


def test_crd_densification_step_with_mixed_sizes():
    scene = mixed_scene()
    config = MVGSConfig.multiview(stages=(Stage(1, 2, 5),), chunk_size=2, densify_from=0, densify_every=1,
                                  crd=CRDConfig(enabled=True))
    assert config.crd and config.mvad
    trainer = MVGS(make_adapter(scene, torch.float32), scene, config)
    shapes = []
    original = trainer.schedule.densify_context

    def spy(plan, maps, *args, **kwargs):
        shapes.append(sorted(tuple(m.shape) for m in maps))
        return original(plan, maps, *args, **kwargs)

    trainer.schedule.densify_context = spy
    info = trainer.step()
    assert shapes == [[(12, 24), (16, 16)]]  # one loss map per view, at its own size
    assert info.densify is not None and info.num_primitives == info.densify.after
    assert bool(torch.isfinite(trainer.adapter.positions()).all())


# ---- 6. divergence -----------------------------------------------------------------------------

LOW_RES = (Stage(8, 1, 12),)  # 16 px views of the bundled scene


def step_of(msg):
    m = re.match(r"step (\d+):", msg)
    assert m, msg
    return int(m.group(1))


def expected_level(losses, decay=0.9, floor=0.01):
    """The running level of the per-view losses of the steps that passed (documented in
    controller.py and MVGSConfig.divergence_factor)."""
    level = losses[0]
    for v in losses[1:]:
        level = decay * level + (1 - decay) * v
    return max(level, floor)


def test_colour_learning_rate_explosion_stops_on_the_loss(bundled_scene, tmp_path):
    scene = bundled_scene
    config = MVGSConfig(stages=LOW_RES, densify_from=1000)
    trainer = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(lr_sh0=1e3)), scene, config)
    assert config.divergence_factor == 100.0
    infos, saved = [], []
    save = trainer.save_checkpoint

    def save_spy(path):
        saved.append(path)
        save(path)

    trainer.save_checkpoint = save_spy

    def callback(info):  # a user's "checkpoint every step"
        infos.append(info)
        trainer.save_checkpoint(str(tmp_path / f"ck_{info.step}.pt"))

    with pytest.raises(FloatingPointError) as err:
        trainer.fit(progress=False, callback=callback)
    msg = str(err.value)
    step = step_of(msg)
    assert 2 <= step <= 4 and "divergence_factor" in msg, msg
    assert [i.step for i in infos] == list(range(1, step))
    # the level in the message is the running average of the steps that passed
    level = expected_level([i.loss for i in infos])  # one view per step, weight 1: loss per view
    per_view, ratio, reported = numbers_in(msg.split("loss per view is ")[1])[:3]
    assert math.isclose(reported, level, rel_tol=1e-3), (level, msg)
    assert per_view > 100 * level and math.isclose(ratio, per_view / level, rel_tol=1e-2)
    # fit itself saves nothing; the callback's checkpoints stop at the last good step
    assert saved == [str(tmp_path / f"ck_{s}.pt") for s in range(1, step)]
    assert sorted(p.name for p in tmp_path.glob("ck_*.pt")) == sorted(f"ck_{s}.pt" for s in range(1, step))
    fresh = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(lr_sh0=1e3)), scene, config)
    fresh.load_checkpoint(saved[-1])
    assert fresh.step_count == step - 1
    assert all(bool(torch.isfinite(p).all()) for p in fresh.adapter.gradient_parameters().values())


def test_divergence_factor_none_disables_the_loss_check(bundled_scene):
    scene = bundled_scene
    trainer = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig(lr_sh0=1e3)), scene,
                   MVGSConfig(stages=(Stage(8, 1, 6),), densify_from=1000, divergence_factor=None))
    infos = []
    trainer.fit(progress=False, callback=infos.append)
    assert trainer.step_count == 6
    # the same jump the default factor stops on
    assert max(i.loss for i in infos[1:]) > 100 * infos[0].loss


@pytest.mark.parametrize("overrides,group", [
    (dict(lr_scales=1e6), "scales"),
    (dict(lr_means_init=1e6, lr_means_final=1e6), "means"),
])
def test_parameter_explosion_is_named(bundled_scene, tmp_path, overrides, group):
    scene = bundled_scene
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(**overrides))
    initial = {k: p.detach().clone() for k, p in adapter.params.items()}
    trainer = MVGS(adapter, scene, MVGSConfig(stages=LOW_RES, densify_from=1000))
    calls = []
    with pytest.raises(FloatingPointError) as err:
        trainer.fit(progress=False, callback=lambda info: (calls.append(info.step),
                                                          trainer.save_checkpoint(str(tmp_path / "ck.pt"))))
    msg = str(err.value)
    assert step_of(msg) == 1 and f"group '{group}'" in msg, msg
    assert calls == [] and not (tmp_path / "ck.pt").exists()
    if group == "scales":  # the broken state really exists in memory, and was never saved
        assert float(adapter.params["scales"].detach().max()) > MAX_LOG_SCALE
    else:
        assert float((adapter.params["means"].detach() - initial["means"]).abs().max()) > 1e4 * scene.extent


def test_scales_diverging_past_what_the_renderer_takes_are_named_at_their_step():
    """The divergence check on log-scales is the renderer's own limit in the parameters' dtype
    (float32 squares a scale in the covariance: log 37.45), so a run whose scales' learning rate
    diverges (10 where 3DGS's is 0.005) stops at the optimizer step that crossed
    it, naming the group, and not at the next render with the renderer's input error."""
    assert MAX_LOG_SCALE == pytest.approx(math.log(math.sqrt(torch.finfo(torch.float32).max) / 1e3))
    scene = synthetic_scene(n_train=6, n_test=2, size=24, n_points=300)
    config = MVGSConfig.baseline().for_scene(scene).with_total_steps(100)
    adapter = GS3DAdapter.from_scene(scene, dataclasses.replace(GS3DConfig.for_run(config), lr_scales=10.0))
    infos = []
    with pytest.raises(FloatingPointError) as err:
        MVGS(adapter, scene, config).fit(progress=False, callback=infos.append)
    msg = str(err.value)
    assert f"step {len(infos) + 1}: after the optimizer step, group 'scales': a log-scale reached" in msg, msg
    assert "(> 37.45," in msg and "torch.float32" in msg
    top = float(adapter.params["scales"].detach().max())
    assert MAX_LOG_SCALE < top < 80  # the old limit (80) let this through to the renderer


@pytest.mark.parametrize("group,value", [("opacities", math.nan), ("quats", math.inf), ("sh0", -math.inf)])
def test_non_finite_parameter_after_the_optimizer_step_is_named(bundled_scene, group, value):
    scene = bundled_scene
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig())
    trainer = MVGS(adapter, scene, MVGSConfig(stages=LOW_RES, densify_from=1000))
    real_step = adapter.optimizer_step

    def poisoned():
        real_step()
        if adapter._step >= 2:  # from the second step on
            with torch.no_grad():
                adapter.params[group].view(-1)[[5, 17]] = value

    adapter.optimizer_step = poisoned
    infos = []
    with pytest.raises(FloatingPointError) as err:
        trainer.fit(progress=False, callback=infos.append)
    msg = str(err.value)
    assert step_of(msg) == 2 and f"2 non-finite values in group '{group}'" in msg, msg
    assert [i.step for i in infos] == [1]


def test_normal_short_run_with_densification_and_reset_completes(bundled_scene):
    scene = bundled_scene
    config = MVGSConfig.default().with_total_steps(60)
    config = dataclasses.replace(config, stages=tuple(Stage(s.factor * 4, s.views, s.steps) for s in config.stages),
                                 densify_from=2, densify_every=4, opacity_reset_every=20, densify_until=10 ** 6)
    assert config.divergence_factor == 100.0
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(position_lr_max_steps=config.clock_length,
                                                       sh_degree_interval=2))
    trainer = MVGS(adapter, scene, config)
    infos = []
    trainer.fit(progress=False, callback=infos.append)
    assert trainer.step_count == 60 == len(infos)
    assert sum(i.densify is not None for i in infos) >= 3 and sum(i.opacity_reset for i in infos) >= 1
    assert all(math.isfinite(i.loss) for i in infos)
    assert all(bool(torch.isfinite(p).all()) for p in adapter.gradient_parameters().values())


# ---- 7. Gaussian PLY and point files -----------------------------------------------------------

def gaussian_rows(n=10, seed=0):
    g = torch.Generator().manual_seed(seed)
    return dict(means=torch.randn(n, 3, generator=g), sh0=torch.randn(n, 1, 3, generator=g),
                shN=torch.zeros(n, 0, 3), opacities=torch.randn(n, generator=g),
                scales=torch.randn(n, 3, generator=g) - 3, quats=torch.randn(n, 4, generator=g))


def write_raw_ply(path, columns):
    """A binary PLY with one float vertex property per column, in ply_property_names(0) order."""
    names = ply_property_names(0)
    n = len(next(iter(columns.values())))
    data = np.zeros(n, dtype=[(name, "<f4") for name in names])
    for name in names:
        data[name] = columns.get(name, np.zeros(n))
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))


def test_gaussian_ply_round_trip_is_the_accepted_case(tmp_path):
    path = tmp_path / "g.ply"
    rows = gaussian_rows()
    write_gaussian_ply(path, **rows)
    back = read_gaussian_ply(path)
    for name, t in rows.items():
        assert torch.equal(getattr(back, name), t.float()), name


@pytest.mark.parametrize("content", [b"hello, not a ply\n", b"", b"ply\nformat nonsense 9\nend_header\n"])
def test_not_a_ply_is_a_value_error_naming_the_path(tmp_path, content):
    path = tmp_path / "model.ply"
    path.write_bytes(content)
    with pytest.raises(ValueError) as info:
        read_gaussian_ply(path)
    assert str(path) in str(info.value), str(info.value)


def test_gaussian_ply_with_nan_names_the_property(tmp_path):
    path = tmp_path / "nan.ply"
    cols = {name: np.linspace(0.1, 1.0, 6) for name in ply_property_names(0)}
    cols["scale_1"] = np.array([0.1, 0.2, np.nan, 0.4, 0.5, 0.6])
    write_raw_ply(path, cols)
    with pytest.raises(ValueError) as info:
        read_gaussian_ply(path)
    msg = str(info.value)
    # the property (scale_1) or its family (the scale properties), and not only the file
    assert str(path) in msg and "scale" in msg.replace(str(path), ""), msg


def test_gaussian_ply_with_no_vertices_is_refused(tmp_path):
    path = tmp_path / "empty.ply"
    write_raw_ply(path, {name: np.zeros(0) for name in ply_property_names(0)})
    assert PlyData.read(str(path))["vertex"].count == 0
    with pytest.raises(ValueError) as info:
        read_gaussian_ply(path)
    assert str(path) in str(info.value), str(info.value)


def test_gaussian_ply_with_zero_quaternions_names_the_rows(tmp_path):
    path = tmp_path / "zeroquat.ply"
    rows = gaussian_rows(n=10)
    rows["quats"][[1, 4, 8]] = 0.0
    write_gaussian_ply(path, **rows)
    with pytest.raises(ValueError) as info:
        read_gaussian_ply(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    assert re.search(r"\b3\b", msg.replace(str(path), "")), msg  # the number of zero rows


def test_points_ply_with_no_vertices_loads_without_points_and_warns(tmp_path):
    scene_dir = copy_scene(tmp_path)
    ply = scene_dir / "points3d.ply"
    original = PlyData.read(str(BUNDLED / "points3d.ply"))["vertex"]
    empty = np.zeros(0, dtype=original.data.dtype)
    PlyData([PlyElement.describe(empty, "vertex")]).write(str(ply))
    assert {p.name for p in original.properties} >= {"x", "y", "z", "red", "green", "blue"}
    with pytest.warns(UserWarning, match=re.escape(str(ply))):
        scene = load_nerf_synthetic(scene_dir)
    assert scene.points is None
    assert len(load_nerf_synthetic(BUNDLED).points) == original.count == 4000
