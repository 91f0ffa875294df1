"""Scenes without points get points triangulated from their known poses (issue 25, part 1):
the view pairs, pycolmap's tracks against the generator's true surface points, the fill, the
fall-backs, the cache, and the loader's and the adapters' use of it."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
from pathlib import Path

import pytest
import torch

from mvgs_plugin.data import Scene, load_nerf_synthetic, load_scene
from mvgs_plugin.data.init import random_init_points
from mvgs_plugin.data.triangulate import (EXHAUSTIVE_MAX, fill_points, initial_points, triangulate, view_pairs)

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"  # Mitsuba: 20 + 4 views, 64 px, points3d.ply = true surface samples


def bare_copy(dst: Path, timed: bool = False) -> Path:
    """forward64 without its point file (optionally with a time on every frame: a D-NeRF layout
    of a static scene)."""
    for name in ("train", "test"):
        shutil.copytree(FORWARD / name, dst / name)
        meta = json.loads((FORWARD / f"transforms_{name}.json").read_text())
        if timed:
            for i, frame in enumerate(meta["frames"]):
                frame["time"] = i / max(1, len(meta["frames"]) - 1)
        (dst / f"transforms_{name}.json").write_text(json.dumps(meta))
    return dst


def snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in folder.rglob("*")}


def surface_distance(xyz: torch.Tensor) -> torch.Tensor:
    """[P] distance of each point to the nearest of the generator's true surface samples."""
    truth = load_nerf_synthetic(FORWARD).points.xyz.double()
    return torch.cdist(xyz.double(), truth).min(1).values


def test_view_pairs_exhaustive_small_nearest_large_and_by_time():
    from mvgs_plugin.testing import synthetic_scene

    small = synthetic_scene(n_train=6, n_test=1, size=16).train_cameras
    assert view_pairs(small) == [(i, j) for i in range(6) for j in range(i + 1, 6)]

    # a long line of cameras, all looking the same way: a view's pairs are its nearest neighbours
    from tests.test_forward_init import parallel_rig

    line = parallel_rig([0.1 * i for i in range(EXHAUSTIVE_MAX + 20)])
    pairs = view_pairs(line, neighbours=4)
    for i in range(len(line)):
        partners = sorted({j for a, b in pairs for j in (a, b) if i in (a, b) and j != i})
        brute = sorted(sorted(range(len(line)), key=lambda j: (abs(i - j), j))[1:5])
        assert set(brute) <= set(partners), (i, partners, brute)  # its 4 nearest, plus those that chose it
        assert max(abs(i - j) for j in partners) <= 4

    # timed views: neighbours in time only, whatever the poses
    timed = [dataclasses.replace(c, time=t) for c, t in zip(line[:10], [0.9, 0.1, 0.5, 0.3, 0.7, 0.0, 1.0, 0.2, 0.6, 0.4])]
    pairs = view_pairs(timed, time_neighbours=2)
    times = [c.time for c in timed]
    order = sorted(range(10), key=lambda i: times[i])
    rank = {v: r for r, v in enumerate(order)}
    assert all(1 <= abs(rank[a] - rank[b]) <= 2 for a, b in pairs)
    assert len(pairs) == 9 + 8


def test_tracks_lie_on_the_true_surface(tmp_path):
    """pycolmap's tracks from the 20 posed views against the generator's surface samples
    (independent: Mitsuba's analytic shapes). Random points in the same frusta are the yardstick."""
    scene = load_nerf_synthetic(bare_copy(tmp_path / "scene"))
    tracks = triangulate(scene, tmp_path / "work", threads=1)
    assert len(tracks) >= 100, len(tracks)
    assert float(tracks.error.max()) <= 4.0 and int(tracks.length.min()) >= 2
    near = surface_distance(torch.from_numpy(tracks.xyz))
    random_xyz, _, _ = random_init_points(scene, 2000, torch.Generator().manual_seed(0))
    far = surface_distance(random_xyz)
    assert float(near.median()) < 0.1 * scene.extent, float(near.median())
    assert float(near.median()) < 0.6 * float(far.median()), (float(near.median()), float(far.median()))
    # colours are the images' own: the median track colour against the pixel it projects to
    cam = scene.train_cameras[0]
    pix, z = cam.project(torch.from_numpy(tracks.xyz))
    ok = (z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
    img = scene.image(cam)
    seen = img[pix[ok, 1].long(), pix[ok, 0].long()].double()
    assert float((seen - torch.from_numpy(tracks.rgb)[ok]).abs().median()) < 0.1


def test_fill_goes_where_no_track_projects_and_stays_near_the_surface(tmp_path):
    scene = load_nerf_synthetic(bare_copy(tmp_path / "scene"))
    tracks = triangulate(scene, tmp_path / "work", threads=1)
    xyz = torch.from_numpy(tracks.xyz)
    keep = xyz[:, 0] < float(xyz[:, 0].median())  # hide half of the tracks: their side must be filled
    fill, rgb, text = fill_points(scene, xyz[keep], 600, torch.Generator().manual_seed(0))
    assert fill.shape == (600, 3) and rgb.shape == (600, 3) and "fill points" in text
    assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1
    # most of the fill lies on the uncovered side
    assert float((fill[:, 0] >= float(xyz[:, 0].median())).double().mean()) > 0.5
    d = surface_distance(fill)
    random_xyz, _, _ = random_init_points(scene, 2000, torch.Generator().manual_seed(0))
    assert float(d.median()) < float(surface_distance(random_xyz).median()), float(d.median())


def test_initial_points_falls_back_with_the_reason_and_checks_its_arguments(tmp_path):
    scene = load_nerf_synthetic(bare_copy(tmp_path / "scene"))
    made = initial_points(scene, "triangulate", 500, min_tracks=10 ** 6, threads=1)
    assert made.method == "frusta" and len(made.points) == 500
    assert "falling back" in made.description and "< 1000000" in made.description
    cube = initial_points(scene, "cube", 300)
    off = (cube.points.xyz.double() - scene.center.double()).abs().max()
    assert cube.method == "cube" and float(off) <= scene.extent * (1 + 1e-6)
    with pytest.raises(ValueError, match="one of triangulate, random, frusta, cube, got 'sfm'"):
        initial_points(scene, "sfm")
    with pytest.raises(ValueError, match="positive int, got 0"):
        initial_points(scene, "random", 0)


def test_the_cache_is_read_back_and_the_scene_folder_is_never_written(tmp_path):
    folder = bare_copy(tmp_path / "scene")
    before = snapshot(folder)
    scene = load_scene(folder, init_points=2000, init_cache=tmp_path / "cache", threads=1)
    assert snapshot(folder) == before
    assert len(scene.points) == 2000 and scene.points_origin.startswith("triangulated")
    cached = list((tmp_path / "cache").iterdir())
    assert len(cached) == 1 and {p.name for p in cached[0].iterdir()} == {"points.json", "database.db"}
    again = load_scene(folder, init_points=2000, init_cache=tmp_path / "cache", threads=1)
    assert "(cached in" in again.points_origin
    assert torch.equal(again.points.xyz, scene.points.xyz) and torch.equal(again.points.rgb, scene.points.rgb)
    # no cache: a temporary folder, removed; nothing left in the scene folder either
    load_scene(folder, init_points=2000, threads=1)
    assert snapshot(folder) == before
    # a damaged cache is made again, not trusted
    (cached[0] / "points.json").write_text("{")
    third = load_scene(folder, init_points=2000, init_cache=tmp_path / "cache", threads=1)
    assert "(cached in" not in third.points_origin and len(third.points) == 2000
    # init=None keeps the scene as the files have it
    assert load_scene(folder, init=None).points is None


def test_a_dnerf_scene_triangulates_from_frames_close_in_time(tmp_path):
    scene = load_scene(bare_copy(tmp_path / "scene", timed=True), init_points=1000, threads=1)
    assert scene.train_cameras[0].time is not None
    assert scene.points_origin.startswith("triangulated"), scene.points_origin
    n_train = len(scene.train_cameras)
    from mvgs_plugin.data.triangulate import TIME_NEIGHBOURS

    want = sum(min(TIME_NEIGHBOURS, n_train - 1 - k) for k in range(n_train))
    assert f"({want} view pairs" in scene.points_origin, scene.points_origin


def test_scaffold_and_4dgs_take_scenes_without_points(tmp_path):
    """Scaffold-GS places anchors on random points where the cameras look (it refused before);
    4DGS's extra random points follow the same rule instead of the 3DGS cube."""
    from mvgs_plugin.adapters.gs3d import GS3DConfig
    from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
    from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig

    scene = load_nerf_synthetic(bare_copy(tmp_path / "scene"))
    assert scene.points is None
    model = ScaffoldAdapter.from_scene(scene, ScaffoldConfig(random_init=2000))
    assert model.num_primitives() > 100
    seen = torch.zeros(model.num_primitives(), dtype=torch.long)
    for cam in scene.train_cameras:
        pix, z = cam.project(model.positions().double())
        seen += ((z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)).long()
    assert float((seen >= 3).double().mean()) > 0.9  # anchors where the forward rig looks, not about the cameras

    timed = Scene([dataclasses.replace(c, time=0.5) for c in scene.train_cameras],
                  [dataclasses.replace(c, time=0.5) for c in scene.test_cameras],
                  {c.uid: scene.image(c) for c in scene.cameras}, points=None)
    config = GS4DConfig(canonical=GS3DConfig(random_init=500), init_random_points=400)
    extra = GS4DAdapter._with_random_points(timed, config)
    depth = torch.stack([c.project(extra.xyz.double())[1] for c in timed.train_cameras])
    assert len(extra) == 400 and bool((depth.min(0).values > 0).all())  # in front of every camera
    near = surface_distance(extra.xyz)
    cube = (torch.rand(400, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 2 - 1) * timed.extent + timed.center
    assert float(near.median()) < float(surface_distance(cube).median())


def test_images_with_alpha_are_staged_as_the_model_sees_them(tmp_path):
    """pycolmap reads the staged copies: an RGBA image is composited on the scene's background
    (checked against the composite computed here from the file), an RGB one is linked."""
    import numpy as np
    from PIL import Image

    from mvgs_plugin.data.triangulate import _stage_images

    folder = bare_copy(tmp_path / "scene")
    first = folder / "train" / "r_000.png"
    rgb = np.asarray(Image.open(first).convert("RGB"))
    alpha = np.full(rgb.shape[:2], 255, np.uint8)
    alpha[:, :20] = 0  # transparent strip, with colour that must not show
    garbage = rgb.copy()
    garbage[:, :20] = [0, 255, 0]
    Image.fromarray(np.dstack([garbage, alpha]), "RGBA").save(first)
    scene = load_nerf_synthetic(folder)  # composites on white
    names = _stage_images(scene, scene.train_cameras[:2], tmp_path / "staged")
    staged0, staged1 = tmp_path / "staged" / names[0], tmp_path / "staged" / names[1]
    assert not staged0.is_symlink() and staged1.is_symlink()
    want = rgb.astype(np.float64)
    want[:, :20] = 255.0  # white background where alpha is 0
    got = np.asarray(Image.open(staged0).convert("RGB")).astype(np.float64)
    assert np.abs(got - want).max() <= 1.0


@pytest.mark.parametrize("script", ["train_3dgs", "train_scaffold"])
def test_the_examples_triangulate_a_scene_without_points_into_their_output_folder(tmp_path, script):
    import importlib.util

    folder = bare_copy(tmp_path / "scene")
    before = snapshot(folder)
    spec = importlib.util.spec_from_file_location(script, ROOT / "examples" / f"{script}.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    out = tmp_path / "out"
    example.main(["--data", str(folder), "--steps", "3", "--out", str(out), "--no-progress", "--threads", "1"])
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["init"].startswith("triangulated") and "fill points" in saved["init"], saved["init"]
    assert [p.name for p in (out / "init").iterdir()][0].startswith("triangulate-")
    assert snapshot(folder) == before  # the scene folder is not written
    # --init random keeps the rule of earlier releases (the frusta for this forward rig)
    example.main(["--data", str(folder), "--steps", "3", "--out", str(tmp_path / "o2"), "--no-progress",
                  "--init", "random"])
    assert "training frusta" in json.loads((tmp_path / "o2" / "metrics.json").read_text())["init"]


def test_masks_keep_features_out_of_the_pixels_they_ignore(tmp_path):
    """With masks that keep only the right half of every training view, each track is seen (its
    projection lands, within 2 px, on kept pixels) by at least the two views it needs; without
    them many tracks are not: COLMAP got the masks."""
    loaded = load_nerf_synthetic(bare_copy(tmp_path / "scene"))
    files = {c.uid: loaded.image_file(c) for c in loaded.cameras}
    keep = {}
    for cam in loaded.train_cameras:
        m = torch.zeros(cam.height, cam.width)
        m[:, cam.width // 2:] = 1.0
        keep[cam.uid] = m
    masked = Scene(loaded.train_cameras, loaded.test_cameras, files, background=loaded.background, masks=keep)
    plain = Scene(loaded.train_cameras, loaded.test_cameras, files, background=loaded.background)

    def views_seeing(tracks) -> torch.Tensor:
        xyz = torch.from_numpy(tracks.xyz)
        count = torch.zeros(len(xyz), dtype=torch.int64)
        for cam in loaded.train_cameras:
            pix, z = cam.project(xyz)
            count += ((z > 0) & (pix[:, 0] >= cam.width // 2 - 2) & (pix[:, 0] < cam.width)
                      & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)).long()
        return count

    with_masks = triangulate(masked, tmp_path / "work_masked", threads=1)
    without = triangulate(plain, tmp_path / "work_plain", threads=1)
    assert len(with_masks) >= 20 and len(without) > len(with_masks), (len(with_masks), len(without))
    assert int(views_seeing(with_masks).min()) >= 2
    assert int((views_seeing(without) < 2).sum()) >= 10
