"""Initial points for posed scenes that come without them: triangulated from the known poses.

NeRF-synthetic, LLFF-style and D-NeRF captures arrive with poses and no points; what users of
graphdeco's 3DGS or nerfstudio do by hand before training is to run COLMAP with the poses
fixed. :func:`triangulate` does that with pycolmap on the CPU, from the training views only:

1. SIFT features of every training image (``pycolmap.extract_features``; the cameras written
   into the database are the scene's own PINHOLE intrinsics);
2. matches between pairs of views chosen from the known poses (``pycolmap.match_image_pairs``
   with geometric verification): every pair up to ``EXHAUSTIVE_MAX`` views, else each view
   with its ``NEIGHBOURS`` nearest views by centre distance and axis angle; for a dynamic
   (D-NeRF) scene only views close in time, so the moving parts of far-apart frames never
   make a track;
3. tracks triangulated with the poses held fixed (``pycolmap.triangulate_points``).

Tracks only cover texture that SIFT finds. :func:`fill_points` adds points where the
training images hold no projected track: candidates on rays through the uncovered pixels,
between the depths the tracks span in that view, the most photo-consistent kept
(:func:`~mvgs_plugin.data.init.photo_consistent`).

:func:`initial_points` chooses between that and the random rules of
:mod:`mvgs_plugin.data.init` (``method`` "triangulate", "random", "frusta" or "cube") and says
what it did; :func:`~mvgs_plugin.data.load_scene` calls it for scenes without a point file.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..camera import Camera
from .images import may_have_alpha
from .init import (CANDIDATES_PER_POINT, SWEEP_DEPTHS, _silhouettes_read, init_region, on_silhouettes,
                   photo_consistent, pose_distance, random_init_points, silhouettes_of, sweep_rays,
                   sweep_span)
from .scene import PointCloud, Scene

__all__ = ["INIT_METHODS", "Tracks", "InitPoints", "triangulate", "fill_points", "initial_points",
           "view_pairs", "synchronized_instant", "synchronized_views", "MIN_TRACKS", "EXHAUSTIVE_MAX", "NEIGHBOURS", "TIME_NEIGHBOURS"]

INIT_METHODS = ("triangulate", "random", "frusta", "cube")
# fewer triangulated points than this and the scene falls back to the random rule: a handful of
# tracks (a textureless or tiny capture) says too little about where the surfaces are
MIN_TRACKS = 50
# views up to which every pair is matched (1,770 pairs for 60 views, about a second at 128 px);
# beyond it each view is matched with its NEIGHBOURS nearest views
EXHAUSTIVE_MAX = 60
NEIGHBOURS = 20
# a dynamic scene: each view is matched with this many views nearest in time (before and after)
TIME_NEIGHBOURS = 6
# a dynamic scene with at least this many training views at one time is a synchronized rig (a
# multi-camera video): its points are made from the views of a few instants (synchronized_views)
SYNCHRONIZED_MIN = 3
# fill: a pixel (at the photo-consistency width) counts as covered by a track within this many
# pixels of it; candidate depths span the view's track depths widened by this factor each way
COVER_RADIUS = 2
DEPTH_MARGIN = 1.5
# pycolmap extraction: images larger than this (longest side) are downscaled for SIFT
MAX_IMAGE_SIZE = 1600
# bump when the cached result would change (2: fill and fall-back carved to silhouettes on a backdrop;
# 3: silhouettes from alpha; 4: the fill one point per ray, ray_sweep's rule; 5: its search in the ball round the cube)
_VERSION = 5


@dataclasses.dataclass(frozen=True)
class Tracks:
    """Triangulated points: xyz [P, 3] float64 (world), rgb [P, 3] float64 in [0, 1], mean
    reprojection error [P] (pixels) and track length [P]; the seconds each stage took."""

    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    length: np.ndarray
    seconds: dict
    pairs: int

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclasses.dataclass(frozen=True)
class InitPoints:
    """What :func:`initial_points` made: the points, the method that made them ("triangulate",
    or the random rule it used: "frusta" or "cube"), a sentence for the log and metrics.json,
    the number of triangulated tracks among the points and the seconds it took."""

    points: PointCloud
    method: str
    description: str
    tracks: int = 0
    seconds: float = 0.0


def view_pairs(cameras: Sequence[Camera], exhaustive_max: int = EXHAUSTIVE_MAX,
               neighbours: int = NEIGHBOURS, time_neighbours: int = TIME_NEIGHBOURS) -> list[tuple[int, int]]:
    """Index pairs (i < j) of the views to match. Views with a time (a dynamic scene): each with
    its ``time_neighbours`` nearest in time. Otherwise every pair up to ``exhaustive_max`` views,
    else each view with its ``neighbours`` nearest by :func:`~mvgs_plugin.data.init.pose_distance`."""
    n = len(cameras)
    times = [c.time for c in cameras]
    if all(t is not None for t in times) and n > 1:
        order = sorted(range(n), key=lambda i: (times[i], i))
        pairs = {tuple(sorted((order[a], order[b]))) for a in range(n)
                 for b in range(a + 1, min(n, a + 1 + time_neighbours))}
    elif n <= exhaustive_max:
        pairs = {(i, j) for i in range(n) for j in range(i + 1, n)}
    else:
        dist = pose_distance(cameras)
        dist.fill_diagonal_(math.inf)
        near = torch.topk(dist, min(neighbours, n - 1), dim=1, largest=False).indices
        pairs = {tuple(sorted((i, int(j)))) for i in range(n) for j in near[i]}
    return sorted(pairs)


def _stage_images(scene: Scene, cameras: Sequence[Camera], folder: Path) -> list[str]:
    """The training images as pycolmap reads them, under short names in ``folder``: a link to
    the file when it holds no alpha, else the image the model trains on (alpha composited on
    the scene's background) written as an 8-bit PNG."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for k, cam in enumerate(cameras):
        src = scene.image_file(cam)
        if src is not None and scene.undistortion(cam) is None and not (may_have_alpha(src) and scene.background is not None):
            name = f"{k:05d}{src.suffix.lower()}"
            try:
                os.symlink(src.resolve(), folder / name)
            except OSError:  # no symlinks here: copy
                shutil.copyfile(src, folder / name)
        else:
            name = f"{k:05d}.png"
            img = (scene.read(cam).clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()
            Image.fromarray(img).save(folder / name)
        names.append(name)
    return names


def _stage_masks(scene: Scene, cameras: Sequence[Camera], names: list, folder: Path) -> Path:
    """The training views' masks as COLMAP reads them: ``folder/<image name>.png``, 0 where the
    scene's mask ignores a pixel (weight below 1/2), 255 elsewhere."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for cam, name in zip(cameras, names):
        keep = (scene.read_mask(cam)[..., 0] >= 0.5).numpy()
        Image.fromarray((keep * 255).astype(np.uint8)).save(folder / f"{name}.png")
    return folder


def _pinhole(cam: Camera):
    import pycolmap

    K = cam.K.to(torch.float64)
    return pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                           params=[float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])


def triangulate(scene: Scene, work_dir, threads: Optional[int] = None, exhaustive_max: int = EXHAUSTIVE_MAX,
                neighbours: int = NEIGHBOURS) -> Tracks:
    """Points triangulated from the training views of ``scene`` at their known poses.

    ``work_dir`` receives the staged images, the feature database (database.db), the view pairs
    and the model; it is created if missing and must not hold an earlier database. ``threads``: pycolmap's
    threads (default: torch's). pycolmap's failures arrive as RuntimeError or ValueError.
    """
    import pycolmap

    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db_path, image_dir = work / "database.db", work / "images"
    if db_path.exists():
        raise ValueError(f"{db_path} exists: triangulate needs a fresh work folder")
    cameras = list(scene.train_cameras)
    threads = int(threads or torch.get_num_threads())
    seconds = {}
    t0 = time.perf_counter()
    names = _stage_images(scene, cameras, image_dir)
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # pycolmap's INFO lines are many and say nothing to a trainer
    try:
        return _run_pycolmap(scene, cameras, names, work, threads, exhaustive_max, neighbours, seconds, t0)
    finally:
        pycolmap.logging.minloglevel = level


def _run_pycolmap(scene: Scene, cameras: list, names: list, work: Path, threads: int, exhaustive_max: int,
                  neighbours: int, seconds: dict, t0: float) -> Tracks:
    """triangulate()'s pycolmap part: features, matches, tracks (logging already quietened)."""
    import pycolmap

    db_path, image_dir = work / "database.db", work / "images"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    if getattr(scene, "has_masks", False):  # no feature where a mask ignores the pixels (COLMAP's mask_path)
        reader.mask_path = str(_stage_masks(scene, cameras, names, work / "masks"))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.max_image_size = MAX_IMAGE_SIZE
    pycolmap.extract_features(db_path, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["extract"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pairs = view_pairs(cameras, exhaustive_max, neighbours)
    pair_file = work / "pairs.txt"
    pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pycolmap.match_image_pairs(db_path, matching_options=matching,
                               pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pair_file),
                               device=pycolmap.Device.cpu)
    seconds["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    rec = pycolmap.Reconstruction()
    db = pycolmap.Database.open(str(db_path))
    try:
        by_name = dict(zip(names, cameras))
        for image in db.read_all_images():
            cam = by_name[image.name]
            camera = _pinhole(cam)
            camera.camera_id = image.camera_id
            db.update_camera(camera)  # the database holds what the reader guessed; the scene's intrinsics win
            rec.add_camera_with_trivial_rig(camera)
            w2c = cam.world_to_camera.to(torch.float64).numpy()
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id), pose)
    finally:
        db.close()
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = 0
    out = work / "model"
    out.mkdir(exist_ok=True)
    model = pycolmap.triangulate_points(rec, db_path, image_dir, out, options=options)
    seconds["triangulate"] = time.perf_counter() - t0
    pts = list(model.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.float64).reshape(-1, 3) / 255.0
    error = np.array([p.error for p in pts], dtype=np.float64)
    length = np.array([p.track.length() for p in pts], dtype=np.int64)
    ok = np.isfinite(xyz).all(1)
    return Tracks(xyz[ok], rgb[ok], error[ok], length[ok], seconds, len(pairs))


def fill_points(scene: Scene, xyz: torch.Tensor, n: int, generator: torch.Generator,
                max_width: int = 64) -> tuple[torch.Tensor, torch.Tensor, str]:
    """n points where the training images show no projected track, photo-consistent.

    Per training view (downsampled to at most ``max_width`` across): the tracks it sees give a
    depth range (their 5th and 95th percentile widened by DEPTH_MARGIN; all tracks' range for a
    view that sees fewer than 5) and a coverage mask (pixels within COVER_RADIUS of a projected
    track). n rays through uncovered pixels (a view at random, weighted by its uncovered pixels)
    each get one point, at the depth within that view's range (SWEEP_DEPTHS of them, uniform in
    disparity) whose colour its nearest views agree on best (:func:`~mvgs_plugin.data.init.sweep_rays`,
    the rule of :func:`~mvgs_plugin.data.init.ray_sweep`; until 2026-12-01 the n most
    photo-consistent of CANDIDATES_PER_POINT x n candidates, which gathered on plain surfaces and
    the sky). On a rig round the scene (the 3DGS cube's region) the rays go through every pixel
    and search the whole ray about the cube (:func:`~mvgs_plugin.data.init.sweep_span`), as
    ray_sweep does: a few hundred tracks cover most of the pixels there (54-91 % at 64 px), and
    a fill kept off them crowded the rest; on the generated tabletop and arc scenes tracks plus a
    fill of uncovered pixels trained 1.3 and 2.2 dB below tracks plus a fill of all pixels (plain
    3DGS, 1000 steps). On a still object on a
    backdrop (:func:`~mvgs_plugin.data.init.silhouettes_of`) that older rule stays, with only the
    candidates inside the views' silhouettes
    (:func:`~mvgs_plugin.data.init.on_silhouettes`): a ray through a backdrop pixel has nothing
    on it, and a point in that air, backdrop-coloured from every side, is as photo-consistent as a
    point can be. Returns (xyz, rgb [k, 3] float64, description), k = n but where the silhouettes
    leave fewer candidates.
    """
    cameras = scene.train_cameras
    xyz = torch.as_tensor(xyz, dtype=torch.float64)
    small = [c.scaled(max(1, -(-c.width // max_width))) for c in cameras]
    all_depths = []
    ranges, free = [], []
    for cam in small:
        pix, z = cam.project(xyz)
        inside = (z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height)
        depths = z[inside]
        all_depths.append(depths)
        hit = torch.zeros(1, 1, cam.height, cam.width)
        cells = pix[inside].floor().to(torch.int64)
        hit[0, 0, cells[:, 1], cells[:, 0]] = 1.0
        # covered: a track's pixel within COVER_RADIUS (a square window)
        covered = torch.nn.functional.max_pool2d(hit, 2 * COVER_RADIUS + 1, stride=1, padding=COVER_RADIUS)
        free.append(covered[0, 0] == 0)
        ranges.append(depths)
    pooled = torch.cat(all_depths) if all_depths else torch.zeros(0, dtype=torch.float64)
    if pooled.numel() < 5:
        raise ValueError("fill_points needs tracks that the training views see")
    lo_all, hi_all = float(pooled.quantile(0.05)), float(pooled.quantile(0.95))
    bounds = []
    for depths in ranges:
        lo, hi = (float(depths.quantile(0.05)), float(depths.quantile(0.95))) if depths.numel() >= 5 else (lo_all, hi_all)
        bounds.append((max(lo / DEPTH_MARGIN, 1e-6), hi * DEPTH_MARGIN))
    weights = torch.tensor([float(m.sum()) for m in free], dtype=torch.float64)
    if not weights.sum() > 0:
        weights = torch.ones(len(free), dtype=torch.float64)
        free = [torch.ones_like(m) for m in free]
    share = float(sum(float(m.sum()) for m in free)) / float(sum(m.numel() for m in free))
    backdrop = silhouettes_of(scene)
    if backdrop is None:  # a ray through each of n free pixels, its point where the views agree (init.ray_sweep)
        region = init_region(cameras, scene.center, float(scene.extent))
        if region.kind == "cube":  # round the scene: rays through every pixel, the tracks' or not (docstring)
            free = [torch.ones_like(m) for m in free]
            weights = torch.tensor([float(m.sum()) for m in free], dtype=torch.float64)
        pick = torch.multinomial(weights / weights.sum(), n, replacement=True, generator=generator)
        pixels = torch.empty(n, 2, dtype=torch.float64)
        near, far = torch.empty(n, dtype=torch.float64), torch.empty(n, dtype=torch.float64)
        for i, (cam, small_cam, mask) in enumerate(zip(cameras, small, free)):
            rows = (pick == i).nonzero().flatten()
            if rows.numel() == 0:
                continue
            at = _pixels_in(mask, rows.numel(), generator)
            pixels[rows] = at * torch.tensor([cam.width / small_cam.width, cam.height / small_cam.height], dtype=torch.float64)
            origin, direction = cam.rays(pixels[rows])
            if region.kind == "cube":  # round the scene: the whole ray about the cube, as ray_sweep
                near[rows], far[rows] = sweep_span(origin, direction, region)
            else:
                axis = cam.camera_to_world[:3, 2] / torch.linalg.norm(cam.camera_to_world[:3, 2])
                cos = (direction @ axis.to(direction.dtype)).clamp_min(1e-6)  # a depth z lies z / cos along the ray
                near[rows], far[rows] = bounds[i][0] / cos, bounds[i][1] / cos
        kept, rgb, scored = sweep_rays(cameras, scene.image, pick, pixels, near, far, generator,
                                       disparity=region.kind != "cube", max_width=max_width, mask=getattr(scene, "mask", None))
        where = (f"one on each of {n} rays through the training views' pixels, at the depth (of {SWEEP_DEPTHS} in the "
                 "ball round the cube)"
                 if region.kind == "cube" else
                 f"where no track projects ({share:.0%} of the pixels at {max_width} px), one on each of {n} rays through "
                 f"them, at the depth (of {SWEEP_DEPTHS} between the tracks' depths)")
        return kept, rgb, f"{n} fill points {where} the nearest views agree on best ({int(scored.sum())} scored)"
    # an object on a backdrop: candidates, a view at random (weighted by its free pixels), a free pixel in it, a depth
    total = CANDIDATES_PER_POINT * n
    pick = torch.multinomial(weights / weights.sum(), total, replacement=True, generator=generator)
    candidates = torch.empty(total, 3, dtype=torch.float64)
    for i, (cam, mask) in enumerate(zip(small, free)):
        rows = (pick == i).nonzero().flatten()
        if rows.numel() == 0:
            continue
        origin, direction = cam.rays(_pixels_in(mask, rows.numel(), generator))
        axis = cam.camera_to_world[:3, 2] / torch.linalg.norm(cam.camera_to_world[:3, 2])
        cos = (direction @ axis.to(direction.dtype)).clamp_min(1e-6)
        near, far = bounds[i]
        disparity = 1.0 / far + torch.rand(rows.numel(), generator=generator, dtype=torch.float64) * (1.0 / near - 1.0 / far)
        candidates[rows] = origin + direction * (1.0 / disparity / cos)[:, None]
    inside = on_silhouettes(candidates, cameras, scene.image, backdrop, max_width, mask=getattr(scene, "mask", None),
                            coverage=getattr(scene, "coverage", None))
    candidates = candidates[inside]
    n = min(n, candidates.shape[0])
    carved = (f", {candidates.shape[0]} of them inside the views' silhouettes"
              f"{_silhouettes_read(cameras, getattr(scene, 'coverage', None))} on the backdrop {[round(v, 3) for v in backdrop]}")
    kept, rgb, seen = photo_consistent(candidates, cameras, scene.image, n, max_width, mask=getattr(scene, "mask", None))
    return kept, rgb, (f"{n} fill points where no track projects ({share:.0%} of the pixels at {max_width} px), the "
                       f"most photo-consistent of {total} candidates between the tracks' depths{carved} "
                       f"({seen} seen by >= 3 views)")


def _pixels_in(mask: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """[count, 2] pixel coordinates (x, y) drawn uniformly in the pixels ``mask`` [H, W] keeps,
    each anywhere inside its pixel."""
    cells = mask.flatten().nonzero().flatten()
    cell = cells[torch.randint(cells.numel(), (count,), generator=generator)]
    width = mask.shape[1]
    corner = torch.stack([(cell % width).to(torch.float64), (cell // width).to(torch.float64)], 1)
    return corner + torch.rand(count, 2, generator=generator, dtype=torch.float64)


def _cache_key(scene: Scene, method: str, n: int, seed: int) -> str:
    """A digest of what the result depends on: the training cameras, their image files (path,
    size, modification time) or pixels, the method, the counts and this module's version."""
    h = hashlib.sha256(json.dumps({"v": _VERSION, "method": method, "n": n, "seed": seed,
                                   "bg": scene.background}).encode())
    for cam in scene.train_cameras:
        h.update(cam.K.to(torch.float64).numpy().tobytes())
        h.update(cam.world_to_camera.to(torch.float64).numpy().tobytes())
        h.update(f"{cam.width}x{cam.height}|{cam.time}".encode())
        src = scene.image_file(cam)
        if src is None:
            h.update(scene.image(cam).numpy().tobytes())
        else:
            h.update(_file_id(src))
            und = scene.undistortion(cam)
            if und is not None:  # the pixels are the file resampled through the lens model
                h.update(repr((und.K.tolist(), und.distortion)).encode())
        if getattr(scene, "has_masks", False):  # a mask file as its image file; one given in memory, its values
            file = scene.mask_file(cam)
            if file is not None:
                h.update(b"mask " + _file_id(file))
            elif scene.masked([cam]):
                h.update(scene.read_mask(cam).numpy().tobytes())
    return h.hexdigest()[:16]


def _file_id(path: Path) -> bytes:
    """A file as the cache key knows it: its resolved path, size and modification time."""
    st = path.stat()
    return f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode()


def _save_points(folder: Path, result: InitPoints) -> None:
    from ..io import atomic_write_text

    folder.mkdir(parents=True, exist_ok=True)
    data = {"method": result.method, "description": result.description, "tracks": result.tracks,
            "seconds": result.seconds, "xyz": result.points.xyz.tolist(), "rgb": result.points.rgb.tolist()}
    atomic_write_text(folder / "points.json", json.dumps(data))


def _load_points(folder: Path) -> Optional[InitPoints]:
    file = folder / "points.json"
    if not file.is_file():
        return None
    try:
        data = json.loads(file.read_text())
        points = PointCloud(torch.tensor(data["xyz"], dtype=torch.float64).reshape(-1, 3),
                            torch.tensor(data["rgb"], dtype=torch.float64).reshape(-1, 3))
        return InitPoints(points, str(data["method"]), f"{data['description']} (cached in {folder})",
                          int(data["tracks"]), 0.0)
    except (ValueError, KeyError, TypeError, json.JSONDecodeError):
        return None  # a damaged cache is made again


def _random(scene: Scene, method: str, n: int, generator: torch.Generator, why: str = "") -> InitPoints:
    if method == "cube":
        xyz, rgb, text = random_init_points(scene, n, generator, half_size=float(scene.extent))
    elif method == "frusta":
        region = init_region(scene.train_cameras, scene.center, float(scene.extent), kind="frusta")
        if region.kind == "cube":
            xyz = region.sample(n, generator)
            rgb, text = torch.rand(n, 3, generator=generator, dtype=torch.float64), region.description
        else:
            candidates = region.sample(CANDIDATES_PER_POINT * n, generator)
            xyz, rgb, seen = photo_consistent(candidates, scene.train_cameras, scene.image, n,
                                              mask=getattr(scene, "mask", None))
            text = f"{region.description}; kept the {n} most photo-consistent of {candidates.shape[0]} candidates"
    else:
        xyz, rgb, text = random_init_points(scene, n, generator)
    kind = "cube" if text.startswith("random init: cube") else "frusta"
    return InitPoints(PointCloud(xyz, rgb), kind, why + text)


def synchronized_instant(cameras: Sequence[Camera]) -> list[Camera]:
    """The views of a synchronized rig's first instant: when at least SYNCHRONIZED_MIN views
    share one time (several cameras filming together, DyNeRF / Neu3D), those of the earliest
    time that most views share; else [] (a still scene, or one camera moving through time,
    D-NeRF)."""
    groups = _instants(cameras)
    if not groups:
        return []
    most = max(len(g) for g in groups.values())
    return groups[min(t for t, g in groups.items() if len(g) == most)]


def _instants(cameras: Sequence[Camera]) -> dict:
    """A synchronized rig's views by time (SYNCHRONIZED_MIN or more share one), else {}."""
    groups: dict = {}
    for cam in cameras:
        if cam.time is not None:
            groups.setdefault(cam.time, []).append(cam)
    if not groups or max(len(g) for g in groups.values()) < SYNCHRONIZED_MIN:
        return {}
    return groups


def synchronized_views(cameras: Sequence[Camera], max_views: int = EXHAUSTIVE_MAX) -> list[Camera]:
    """The views a synchronized rig's points are made from: those of as many instants as
    ``max_views`` holds (at least one), spread evenly over its times from the first; [] for a
    scene that is not a synchronized rig. The views of one instant are a still capture of that
    instant; several instants add what one lacks (a small rig's few views give few tracks) while
    the count stays that of a still scene's exhaustive matching."""
    groups = _instants(cameras)
    if not groups:
        return []
    times = sorted(groups)
    per = max(len(g) for g in groups.values())
    k = max(1, min(len(times), max_views // per))
    picked = sorted({times[round(i * (len(times) - 1) / (k - 1))] for i in range(k)} if k > 1 else {times[0]})
    return [cam for t in picked for cam in groups[t]]


def initial_points(scene: Scene, method: str = "triangulate", n: int = 10_000, seed: int = 0,
                   cache_dir=None, threads: Optional[int] = None, min_tracks: int = MIN_TRACKS,
                   fill: bool = True) -> InitPoints:
    """Initial points for ``scene`` (which has none) by ``method``:

    * "triangulate": :func:`triangulate` from the training views, then, when the tracks are
      fewer than ``n`` and ``fill`` is on, ``n`` - tracks points from :func:`fill_points`. With
      fewer than ``min_tracks`` tracks (or when pycolmap fails) it falls back to "random" and
      the description says why.
    * "random": today's rule (:func:`~mvgs_plugin.data.init.random_init_points`): the 3DGS cube
      when the cameras surround the scene, photo-consistent points in the training frusta when
      the rig is forward-facing.
    * "frusta" / "cube": that region whatever the rig (frusta falls back to the cube when no
      depth is seen by half of the cameras).

    A synchronized rig (a multi-camera video) is worked on as the still scene of its views at a
    few instants (:func:`synchronized_views`), and the description says so.

    ``cache_dir``: a folder to keep the result (and the feature database) in, under a digest of
    the cameras, images and settings, so a second run with the same scene reads it back; None
    works in a temporary folder, removed afterwards. Nothing is written elsewhere (the scene
    folder is never touched unless ``cache_dir`` points into it).
    """
    if method not in INIT_METHODS:
        raise ValueError(f"init method must be one of {', '.join(INIT_METHODS)}, got {method!r}")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"init point count must be a positive int, got {n!r}")
    generator = torch.Generator().manual_seed(int(seed))
    views = synchronized_views(scene.train_cameras)
    if views:  # a multi-camera video: its views of a few instants, matched as a still scene
        made = initial_points(scene.subset(views, untimed=True), method, n, seed, cache_dir, threads, min_tracks, fill)
        times = sorted({c.time for c in views})
        said = (f"a multi-camera video: from {len(views)} of its {len(scene.train_cameras)} training views, the "
                f"cameras' views at {len(times)} instant(s) ({', '.join(f'{t:.3g}' for t in times[:6])}"
                f"{', ...' if len(times) > 6 else ''}) matched as a still scene: ")
        return dataclasses.replace(made, description=said + made.description)
    if method != "triangulate":
        return _random(scene, method, n, generator)
    folder = None
    if cache_dir is not None:
        folder = Path(cache_dir) / f"triangulate-{_cache_key(scene, method, n, seed)}"
        cached = _load_points(folder)
        if cached is not None:
            return cached
    start = time.perf_counter()
    # work in a fresh folder (beside the cache, so its database moves in with a rename): two runs
    # sharing a cache (ranks of one torchrun job) never write the same file
    if folder is not None:
        folder.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".triangulate-", dir=None if folder is None else folder.parent))
    try:
        try:
            tracks = triangulate(scene, work, threads)
        except (RuntimeError, ValueError) as err:
            result = _random(scene, "random", n, generator,
                             f"triangulation failed ({str(err).splitlines()[0]}); falling back: ")
            return dataclasses.replace(result, seconds=time.perf_counter() - start)
        took = ", ".join(f"{k} {v:.1f} s" for k, v in tracks.seconds.items())
        if len(tracks) < min_tracks:
            result = _random(scene, "random", n, generator,
                             f"triangulation found {len(tracks)} points (< {min_tracks}) from {tracks.pairs} view pairs; "
                             "falling back: ")
        else:
            xyz, rgb = torch.from_numpy(tracks.xyz), torch.from_numpy(tracks.rgb)
            text = (f"triangulated {len(tracks)} points from the {len(scene.train_cameras)} training views at their "
                    f"poses ({tracks.pairs} view pairs, median track length {int(np.median(tracks.length))}, "
                    f"median reprojection error {float(np.median(tracks.error)):.2f} px; {took})")
            if fill and len(tracks) < n:
                more, more_rgb, fill_text = fill_points(scene, xyz, n - len(tracks), generator)
                xyz, rgb = torch.cat([xyz, more]), torch.cat([rgb, more_rgb])
                text += f" plus {fill_text}"
            result = InitPoints(PointCloud(xyz, rgb.clamp(0, 1)), "triangulate", text, len(tracks))
        result = dataclasses.replace(result, seconds=time.perf_counter() - start)
        if folder is not None:
            folder.mkdir(exist_ok=True)
            os.replace(work / "database.db", folder / "database.db")  # the features, for a rerun by hand
            _save_points(folder, result)
        return result
    finally:
        shutil.rmtree(work, ignore_errors=True)
