"""LLFF's poses_bounds.npy: still images (LLFF) and multi-camera videos (DyNeRF / Neu3D as 4DGS
extracts them), the first instant of a synchronized rig for initial points, and the image cache's
bound that a video's thousands of frames need.

Cameras are checked against LLFF's definition worked by hand (a camera whose stored axes are
down = -y, right = +x, back = +z looks along -z with +y up in its image), and against
pinhole projection of points through cameras built here in OpenCV's axes; the cache against
images decoded directly from their files.
"""

import math
import warnings

import numpy as np
import pytest
import skimage.io
import torch
from plyfile import PlyData, PlyElement

from mvgs_plugin.camera import Camera
from mvgs_plugin.data import Scene, load_scene
from mvgs_plugin.data import triangulate as tri
from mvgs_plugin.data.llff import llff_rows, load_llff
from mvgs_plugin.data.load import scene_layout

W, H, F = 40, 30, 36.0


def _look_at(centre, target=(0.0, 0.0, 0.0)):
    """OpenCV camera-to-world: z towards the target, x right, y down (world z up)."""
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], axis=1)
    c2w[:3, 3] = centre
    return c2w


def _row(c2w, h=H, w=W, f=F, near=1.0, far=9.0):
    """LLFF's row for an OpenCV camera-to-world, written from the format's definition: axes
    down (OpenCV's y), right (its x), back (minus its z); the centre; height, width, focal."""
    m = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [h, w, f]], axis=1)
    return np.concatenate([m.reshape(-1), [near, far]])


def _centres(n, radius=4.0):
    return [(radius * math.cos(a), radius * math.sin(a), 1.0 + 0.1 * k)
            for k, a in enumerate(np.linspace(-0.6, 0.6, n))]


def _save(path, rng, h=H, w=W):
    path.parent.mkdir(parents=True, exist_ok=True)
    skimage.io.imsave(path, rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8), check_contrast=False)


def _stills(root, n, folder="images", size=(W, H)):
    rng = np.random.default_rng(0)
    c2ws = [_look_at(c) for c in _centres(n)]
    np.save(root / "poses_bounds.npy", np.stack([_row(c) for c in c2ws]))
    for k in range(n):
        _save(root / folder / f"IMG_{k:04d}.JPG.png", rng, h=size[1], w=size[0])
    return c2ws


def _video(root, cams, frames, counts=None):
    rng = np.random.default_rng(1)
    c2ws = [_look_at(c) for c in _centres(cams)]
    np.save(root / "poses_bounds.npy", np.stack([_row(c) for c in c2ws]))
    for c in range(cams):
        (root / f"cam{c:02d}" / "images").mkdir(parents=True)
        for k in range((counts or {}).get(c, frames)):
            _save(root / f"cam{c:02d}" / "images" / f"{k:04d}.png", rng)
    return c2ws


def test_a_camera_stored_looking_down_minus_z_looks_there(tmp_path):
    # LLFF's axes (down, right, back) = (-y, +x, +z): the OpenGL camera at rest, looking along -z
    m = np.zeros((3, 5))
    m[:, 0], m[:, 1], m[:, 2], m[:, 3], m[:, 4] = [0, -1, 0], [1, 0, 0], [0, 0, 1], [1.0, 2.0, 3.0], [H, W, F]
    for k in range(2):
        _save(tmp_path / "images" / f"{k}.png", np.random.default_rng(k))
    np.save(tmp_path / "poses_bounds.npy", np.stack([np.concatenate([m.reshape(-1), [1.0, 5.0]])] * 2))
    cam = load_llff(tmp_path).cameras[0]
    points = torch.tensor([[1.0, 2.0, -2.0], [1.0, 3.0, -2.0], [2.0, 2.0, -2.0]], dtype=torch.float64)
    uv, depth = cam.project(points)
    assert depth.tolist() == pytest.approx([5.0, 5.0, 5.0])  # in front, 5 along -z
    assert uv[0].tolist() == pytest.approx([W / 2, H / 2])  # principal point: the image centre
    assert uv[1, 1] == pytest.approx(H / 2 - F / 5)  # a point above (+y) is higher in the image
    assert uv[2, 0] == pytest.approx(W / 2 + F / 5)  # a point to the right (+x) is right in it


def test_still_images_pair_with_rows_in_name_order_and_hold_out_every_eighth(tmp_path):
    c2ws = _stills(tmp_path, 10)
    assert scene_layout(tmp_path) == "llff"
    scene = load_scene(tmp_path, init=None)
    assert [c.name for c in scene.test_cameras] == ["images/IMG_0000.JPG.png", "images/IMG_0008.JPG.png"]
    assert len(scene.train_cameras) == 8 and scene.background is None
    pts = torch.tensor([[0.3, -0.2, 0.1], [-0.4, 0.5, 0.6]], dtype=torch.float64)
    for cam in scene.cameras:
        k = int(cam.name[len("images/IMG_"):][:4])
        cam_pts = (np.linalg.inv(c2ws[k]) @ np.c_[pts.numpy(), np.ones(2)].T)[:3].T  # OpenCV, by hand
        expect = np.c_[F * cam_pts[:, 0] / cam_pts[:, 2] + W / 2, F * cam_pts[:, 1] / cam_pts[:, 2] + H / 2]
        uv, _ = cam.project(pts)
        np.testing.assert_allclose(uv.numpy(), expect, atol=1e-9)
    assert torch.equal(scene.image(scene.train_cameras[0]),
                       torch.from_numpy(skimage.io.imread(tmp_path / scene.train_cameras[0].name)).float() / 255)


def test_a_downscaled_copy_scales_the_camera(tmp_path):
    _stills(tmp_path, 9)
    _stills(tmp_path, 9, folder="images_2", size=(W // 2, H // 2))
    full, half = load_scene(tmp_path, init=None), load_scene(tmp_path, init=None, images="images_2")
    assert half.cameras[1].width == W // 2 and half.cameras[1].height == H // 2
    np.testing.assert_allclose(half.cameras[1].K.numpy(), np.diag([0.5, 0.5, 1.0]) @ full.cameras[1].K.numpy())


def test_a_colmap_model_beside_the_rows_is_read_as_colmap(tmp_path):
    _stills(tmp_path, 9)
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    assert scene_layout(tmp_path) == "colmap"


@pytest.mark.parametrize("rows, match", [
    (np.zeros((3, 15)), r"expected an \[N, 17\] array"),
    (np.full((9, 17), np.nan), "row 0 holds a non-finite number"),
])
def test_malformed_rows_are_named(tmp_path, rows, match):
    np.save(tmp_path / "poses_bounds.npy", rows)
    with pytest.raises(ValueError, match=match):
        llff_rows(tmp_path / "poses_bounds.npy")


def test_rows_and_images_must_pair_one_to_one(tmp_path):
    _stills(tmp_path, 9)
    (tmp_path / "images" / "IMG_0003.JPG.png").unlink()
    with pytest.raises(ValueError, match="9 rows but .* holds 8 images"):
        load_scene(tmp_path, init=None)


def test_a_row_that_is_not_a_rotation_is_refused(tmp_path):
    _stills(tmp_path, 9)
    rows = np.load(tmp_path / "poses_bounds.npy")
    rows[2, 0] *= 2.0  # the down axis of row 2 twice as long
    np.save(tmp_path / "poses_bounds.npy", rows)
    with pytest.raises(ValueError, match=r"row 2 .*not a rotation"):
        load_scene(tmp_path, init=None)


def test_videos_without_frames_are_refused_with_the_command_that_extracts_them(tmp_path):
    np.save(tmp_path / "poses_bounds.npy", np.stack([_row(_look_at(c)) for c in _centres(3)]))
    for c in range(3):
        (tmp_path / f"cam{c:02d}.mp4").write_bytes(b"\x00")
    with pytest.raises(ValueError, match="ffmpeg -i .*cam00.mp4 .*cam00/images/%04d.png"):
        load_scene(tmp_path, init=None)


def test_a_multi_camera_video_holds_out_cam00_at_every_frame(tmp_path):
    c2ws = _video(tmp_path, cams=4, frames=5)
    scene = load_scene(tmp_path, init=None)
    assert [c.name for c in scene.test_cameras] == [f"cam00/images/{k:04d}.png" for k in range(5)]
    assert len(scene.train_cameras) == 15
    assert sorted({c.time for c in scene.cameras}) == pytest.approx([0.0, 0.25, 0.5, 0.75, 1.0])
    by_folder = {}
    for cam in scene.cameras:
        by_folder.setdefault(int(cam.name[3:5]), []).append(cam)
    for c, cams in by_folder.items():  # every frame of a camera is that camera's row
        for cam in cams:
            np.testing.assert_allclose(cam.world_to_camera.numpy(), np.linalg.inv(c2ws[c]), atol=1e-12)


def test_cameras_with_unequal_frame_counts_use_the_frames_all_have(tmp_path):
    _video(tmp_path, cams=3, frames=4, counts={2: 6})
    with pytest.warns(UserWarning, match="4 to 6 frames; the first 4"):
        scene = load_scene(tmp_path, init=None)
    assert len(scene.cameras) == 12 and max(c.time for c in scene.cameras) == 1.0


def test_a_camera_folder_without_frames_is_named(tmp_path):
    _video(tmp_path, cams=3, frames=2, counts={1: 0})
    with pytest.raises(ValueError, match="camera folder cam01 holds no frames"):
        load_scene(tmp_path, init=None)


def test_4dgs_points_file_is_read(tmp_path):
    _video(tmp_path, cams=3, frames=2)
    xyz = np.array([(0.1, 0.2, 0.3, 10, 20, 30), (0.4, 0.5, 0.6, 40, 50, 60)],
                   dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    PlyData([PlyElement.describe(xyz, "vertex")]).write(str(tmp_path / "points3D_downsample2.ply"))
    scene = load_scene(tmp_path, init="random")  # points given: no init runs
    np.testing.assert_allclose(scene.points.xyz.numpy(), [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], rtol=1e-6)
    assert "points3D_downsample2.ply" in scene.points_origin


def _cam(uid, centre, time):
    return Camera(uid=uid, name=f"{uid}.png", K=np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]]),
                  world_to_camera=np.linalg.inv(_look_at(centre)), width=W, height=H, time=time)


def test_the_first_instant_of_a_synchronized_rig():
    centres = _centres(4)
    video = [_cam(4 * k + c, centres[c], t) for k, t in enumerate([0.5, 0.0, 1.0]) for c in range(4)]
    assert sorted(c.uid for c in tri.synchronized_instant(video)) == [4, 5, 6, 7]  # time 0.0
    monocular = [_cam(k, centres[k % 4], k / 11) for k in range(12)]  # D-NeRF: one view per time
    assert tri.synchronized_instant(monocular) == []
    still = [_cam(k, centres[k], None) for k in range(4)]
    assert tri.synchronized_instant(still) == []


def test_a_rig_of_many_frames_is_matched_at_instants_spread_over_its_time():
    centres = _centres(20)
    video = [_cam(300 * c + k, centres[c], k / 299) for c in range(20) for k in range(300)]  # Neu3D's size
    views = tri.synchronized_views(video)
    assert len(views) == 60 and sorted({c.time for c in views}) == [0.0, 150 / 299, 1.0]  # 60 // 20 instants
    assert sorted({c.uid % 300 for c in views}) == [0, 150, 299]
    assert tri.synchronized_views([_cam(k, centres[k % 4], k / 11) for k in range(12)]) == []  # D-NeRF


def test_a_video_is_initialised_from_its_instants_as_a_still_scene(tmp_path, monkeypatch):
    _video(tmp_path, cams=4, frames=3)
    scene = load_scene(tmp_path, init=None)
    seen = {}

    def fake_triangulate(sub, work, threads=None):
        seen["cams"] = list(sub.train_cameras)
        raise RuntimeError("stop here")  # initial_points falls back to random, as on a failure

    monkeypatch.setattr(tri, "triangulate", fake_triangulate)
    made = tri.initial_points(scene, "triangulate", n=200)
    assert len(seen["cams"]) == 9 and all(c.time is None for c in seen["cams"])  # 3 cameras x 3 instants
    assert sorted(c.name for c in seen["cams"]) == sorted(f"cam0{c}/images/000{k}.png" for c in (1, 2, 3)
                                                          for k in range(3))
    assert made.description.startswith("a multi-camera video: from 9 of its 9 training views, the cameras' views at 3 "
                                       "instant(s) (0, 0.5, 1) matched as a still scene: ")
    assert len(made.points) == 200


def test_subset_reads_the_same_images_without_test_views(tmp_path):
    _video(tmp_path, cams=3, frames=2)
    scene = load_scene(tmp_path, init=None)
    sub = scene.subset(scene.train_cameras[:2], untimed=True)
    assert sub.test_cameras == [] and [c.time for c in sub.train_cameras] == [None, None]
    assert torch.equal(sub.image(sub.train_cameras[1]), scene.image(scene.train_cameras[1]))
    with pytest.raises(KeyError, match="not part of this scene"):
        sub.subset(scene.test_cameras[:1])


def test_the_image_cache_holds_its_bound_and_reads_again_what_it_let_go(tmp_path):
    rng = np.random.default_rng(3)
    files, cams = {}, []
    for k in range(6):
        _save(tmp_path / f"{k}.png", rng)
        cams.append(_cam(k, _centres(6)[k], None))
        files[k] = tmp_path / f"{k}.png"
    given = torch.rand(H, W, 3)
    cams.append(_cam(6, (0.0, -4.0, 1.0), None))
    one = H * W * 3 * 4  # bytes of one float32 image
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = Scene(cams, [], {**files, 6: given}, cache_bytes=2 * one)
    direct = {k: torch.from_numpy(skimage.io.imread(files[k])).float() / 255 for k in files}
    for rounds in range(2):
        for cam in cams[:6]:
            assert torch.equal(scene.image(cam), direct[cam.uid])
            assert scene._cache_used <= 2 * one
        scene.image(cams[1], 2)  # a level below full resolution counts too
        assert scene._cache_used <= 2 * one
    assert (1, 2.0) in scene._cache and (5, 1.0) in scene._cache  # the two used last stay
    assert (0, 1.0) not in scene._cache  # the least recently used went
    assert torch.equal(scene.image(cams[6]), given)  # an image given in memory is never let go
    scene.clear_cache()
    assert list(scene._cache) == [(6, 1.0)] and scene._cache_used == 0
    with pytest.raises(ValueError, match="cache_bytes must be an int >= 0.*got -1"):
        Scene(cams[:1], [], {0: files[0]}, cache_bytes=-1)


def test_the_4dgs_example_reads_a_video_and_refuses_still_images(tmp_path):
    """The data path into the 4DGS trainer (its training phases are tested on the D-NeRF scenes in
    test_example_train): a video's training views are the cameras but cam00, its test views cam00's
    frames at their own times; LLFF still images are refused before they are read."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "train_4dgs.py"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    video, stills = tmp_path / "video", tmp_path / "stills"
    video.mkdir(), stills.mkdir()
    _video(video, cams=4, frames=3)
    _stills(stills, 9)
    proc = subprocess.run([sys.executable, str(script), "--data", str(stills), "--out", str(tmp_path / "o1"),
                           "--steps", "3", "--no-progress"], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 2 and "4DGS needs a dynamic scene" in proc.stderr and "poses_bounds.npy" in proc.stderr
    out = tmp_path / "o2"
    proc = subprocess.run([sys.executable, str(script), "--data", str(video), "--out", str(out), "--steps", "4",
                           "--init", "random", "--no-progress"], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert sorted(v["name"] for v in metrics["per_view"]) == [f"cam00/images/{k:04d}.png" for k in range(3)]
    assert metrics["init"].startswith("a multi-camera video: from 9 of its 9 training views")


def test_a_video_schedule_with_instant_steps_renders_one_time_per_step(tmp_path):
    """time_spread="instant" on a video: every step's views are distinct cameras at one time, so
    the 4DGS adapter deforms once per step (it groups a chunk's cameras by time)."""
    from mvgs_plugin import MVGSConfig, Stage, ViewSchedule

    _video(tmp_path, cams=5, frames=4)
    scene = load_scene(tmp_path, init=None)
    config = MVGSConfig.multiview(stages=(Stage(1, 3, 12),), time_spread="instant", seed=2)
    steps = 0
    for plan in ViewSchedule(scene, config):
        cams = [c for chunk in plan for c in chunk[0]]
        assert len(cams) == 3 and len({c.time for c in cams}) == 1 and len({c.name[:5] for c in cams}) == 3
        steps += 1
    assert steps == 12
