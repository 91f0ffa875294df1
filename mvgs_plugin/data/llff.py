"""Scenes whose poses come in LLFF's ``poses_bounds.npy``: LLFF's forward-facing captures (one
image per row), and multi-camera videos as DyNeRF (Neu3D) ships them and 4DGS trains on them
(one camera per row, its video extracted to frames).

``poses_bounds.npy`` holds one row of 17 numbers per camera: a 3 x 5 matrix (row-major) and the
near and far depth of its content. The matrix's first three columns are the camera's axes in
the world, in LLFF's order: down, right, backwards (the camera looks along minus the third);
the fourth is its centre; the fifth is (height, width, focal length) in pixels of the images the
poses were made for. So in OpenCV's axes (x right, y down, z forward) the camera-to-world
rotation's columns are (right, down, forward) = (column 2, column 1, minus column 3). The
principal point is the image centre (LLFF writes none). Images of another size, a copy
downscaled by one factor (LLFF's ``images_4``, 4DGS's half-size frames), scale the camera to it.

Layouts (:func:`load_llff`, read by :func:`~mvgs_plugin.data.load_scene` for a folder holding
``poses_bounds.npy`` and no COLMAP model or transforms json):

* **Still images**: ``images/`` (or a downscaled copy named by ``images``), one image per row in
  name order; every 8th image from the first is a test view (3DGS's "llffhold").
* **Multi-camera video** (DyNeRF / Neu3D): one folder per camera, ``cam00``, ``cam01``, ... in
  name order, one per row, each holding its video's frames as images (``camNN/images/0000.png``
  as 4DGS's preprocessing extracts them, or the frames in ``camNN/`` itself). Frame k of a video
  of n frames is at time k / (n - 1). The first camera (``cam00``, DyNeRF's held-out view) is the
  test camera at every frame; the others train. Videos that were not extracted are refused with
  the command that extracts them (decoding video would add a dependency).

Initial points: ``points3d.ply`` beside ``poses_bounds.npy``, else 4DGS's
``points3D_downsample2.ply``, else none (``load_scene`` makes them; a multi-camera video is
triangulated from its cameras' views at a few instants: triangulate.synchronized_views).
"""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from ..camera import Camera
from .colmap import _downscaled, check_inside, normalize_name
from .images import IMAGE_SUFFIXES, image_size
from .nerf import TEST_EVERY, read_points_ply
from .scene import Scene

__all__ = ["load_llff", "is_llff", "is_video", "llff_rows", "POSES_FILE", "POINT_FILES"]

LOG = logging.getLogger("mvgs_plugin")

POSES_FILE = "poses_bounds.npy"
POINT_FILES = ("points3d.ply", "points3D_downsample2.ply")  # ours, then 4DGS's name for Neu3D's points
_CAMERA_FOLDER = re.compile(r"cam\d+")
_VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv")
# LLFF's rotation blocks come from COLMAP's quaternions in float64; one saved in float32 or rounded
# is re-orthonormalised (the nearest rotation) when it is this close to one, else refused
_ROTATION_REPAIR = 1e-3


def is_llff(path) -> bool:
    """Whether ``path`` holds LLFF's poses_bounds.npy."""
    return (Path(path) / POSES_FILE).is_file()


def is_video(path) -> bool:
    """Whether the LLFF folder ``path`` is a multi-camera video (camera folders cam00, ...)."""
    return bool(_camera_folders(Path(path)))


def llff_rows(file) -> np.ndarray:
    """The [N, 17] float64 rows of a poses_bounds.npy; a ValueError naming the file and what is
    wrong (shape, non-finite numbers) otherwise. The file is read without pickle."""
    file = Path(file)
    try:
        rows = np.load(file, allow_pickle=False)
    except ValueError as err:
        raise ValueError(f"{file}: not a numeric .npy array ({err})") from None
    if rows.ndim != 2 or rows.shape[1] != 17 or rows.shape[0] == 0 or not np.issubdtype(rows.dtype, np.number):
        raise ValueError(f"{file}: expected an [N, 17] array of numbers (a 3 x 5 pose and near / far per camera, "
                         f"LLFF's poses_bounds), got shape {tuple(rows.shape)} of {rows.dtype}")
    rows = rows.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if bad.size:
        raise ValueError(f"{file}: row {int(bad[0])} holds a non-finite number: {rows[bad[0]].tolist()}")
    return rows


def _camera(row: np.ndarray, k: int, uid: int, name: str, file: Path, poses: Path, time: Optional[float]) -> Camera:
    """The camera of row ``k`` for the image ``file`` (its size read from the header)."""
    m = row[:15].reshape(3, 5)
    h, w, f = (float(v) for v in m[:, 4])
    where = f"{poses}: row {k} ({name})"
    if not (h >= 1 and w >= 1 and f > 0):
        raise ValueError(f"{where}: its fifth column (height, width, focal) = ({h:g}, {w:g}, {f:g}) must be positive")
    down, right, back = m[:, 0], m[:, 1], m[:, 2]
    R = np.stack([right, down, -back], axis=1)  # OpenCV camera-to-world axes: x right, y down, z forward
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > _ROTATION_REPAIR or np.linalg.det(R) <= 0:
        raise ValueError(f"{where}: its first three columns (down, right, back) are not a rotation "
                         f"(max |R^T R - I| = {err:.3g}, det {np.linalg.det(R):.3g})")
    u, _, vt = np.linalg.svd(R)
    R = u @ vt
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, m[:, 3]
    width, height = int(round(w)), int(round(h))
    K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    size = image_size(file)
    if size != (width, height):
        K, width, height = _downscaled(K, width, height, size, file, f"{poses} row {k} (its height and width)")
    try:
        return Camera(uid=uid, name=name, K=K, world_to_camera=np.linalg.inv(c2w), width=width, height=height,
                      time=time)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None


def _images_in(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                  key=lambda p: p.name)


def _camera_folders(root: Path) -> list[Path]:
    return sorted((p for p in root.iterdir() if p.is_dir() and _CAMERA_FOLDER.fullmatch(p.name)), key=lambda p: p.name)


def _frames(folder: Path) -> list[Path]:
    """A camera folder's frames: camNN/images/ (4DGS's extraction), else camNN/ itself."""
    inner = folder / "images"
    return _images_in(inner) if inner.is_dir() else _images_in(folder)


def load_llff(path, images: Optional[str] = None) -> Scene:
    """Load a folder with LLFF's ``poses_bounds.npy`` (see the module docstring for the layouts).

    ``images``: still images only, the folder to read instead of ``images/`` (a downscaled copy,
    ``images_4``), relative to ``path``. Camera uids count the rows' images in order (a video:
    camera by camera, frame by frame); names are paths relative to ``path``. Images are
    photographs: the scene has no background colour (as a COLMAP scene).
    """
    root = Path(path)
    poses = root / POSES_FILE
    if not poses.is_file():
        raise FileNotFoundError(f"missing {poses}")
    rows = llff_rows(poses)
    folders = _camera_folders(root)
    if folders:
        if images is not None:
            raise ValueError(f"images={images!r}: {root} is a multi-camera video (camera folders "
                             f"{folders[0].name}, ...), whose frames are read from each camera's folder")
        scene = _load_video(root, poses, rows, folders)
    else:
        scene = _load_stills(root, poses, rows, images)
    for name in POINT_FILES:
        if (root / name).is_file():
            points = read_points_ply(root / name)
            if len(points):
                scene.points, scene.points_origin = points, f"{len(points)} points given with the scene ({name})"
            else:
                warnings.warn(f"{root / name} holds 0 points: the scene has no point cloud (load_scene's init makes "
                              "one)", stacklevel=2)
            break
    return scene


def _load_stills(root: Path, poses: Path, rows: np.ndarray, images: Optional[str]) -> Scene:
    folder = root / "images"
    if images is not None:
        folder = root / check_inside(normalize_name(images), root, f"images={images!r}")
    if not folder.is_dir():
        videos = sorted(p.name for p in root.iterdir() if p.suffix.lower() in _VIDEO_SUFFIXES)
        if videos:
            more = ", ..." if len(videos) > 3 else ""
            raise ValueError(f"{root}: {POSES_FILE} beside videos ({', '.join(videos[:3])}{more}) whose frames are "
                             "not extracted: a multi-camera video is read from one folder of frames per camera, e.g. "
                             f"mkdir -p {root}/cam00/images && ffmpeg -i {root}/{videos[0]} "
                             f"{root}/cam00/images/%04d.png (one per video, in the rows' order)")
        raise FileNotFoundError(f"{root}: {POSES_FILE} needs its images in {folder} (one per row, in name order) "
                                "or one folder of frames per camera (cam00, cam01, ...)")
    files = _images_in(folder)
    if len(files) != len(rows):
        raise ValueError(f"{poses} has {len(rows)} rows but {folder} holds {len(files)} images: LLFF pairs the rows "
                         "with the images in name order, one each")
    cams = [_camera(row, k, k, file.relative_to(root).as_posix(), file, poses, None)
            for k, (row, file) in enumerate(zip(rows, files))]
    test = [c for k, c in enumerate(cams) if k % TEST_EVERY == 0]
    train = [c for k, c in enumerate(cams) if k % TEST_EVERY != 0]
    if not train:
        raise ValueError(f"{poses}: {len(cams)} image(s): every {TEST_EVERY}th from the first is held out for testing, "
                         "which leaves none to train on")
    return Scene(train, test, {c.uid: root / c.name for c in cams}, check_sizes=False, source=root)


def _load_video(root: Path, poses: Path, rows: np.ndarray, folders: list[Path]) -> Scene:
    if len(folders) != len(rows):
        named = ", ".join(f.name for f in folders[:4]) + (", ..." if len(folders) > 4 else "")
        raise ValueError(f"{poses} has {len(rows)} rows but {root} holds {len(folders)} camera folders ({named}): one "
                         "per row, in name order")
    if len(folders) < 2:
        raise ValueError(f"{root}: one camera folder: a multi-camera video holds out its first camera "
                         f"({folders[0].name}) for testing and trains on the others")
    frames = [_frames(f) for f in folders]
    empty = [f.name for f, fr in zip(folders, frames) if not fr]
    if empty:
        raise ValueError(f"{root}: camera folder {empty[0]} holds no frames ({', '.join(IMAGE_SUFFIXES)} images in "
                         f"{empty[0]}/images/ or {empty[0]}/): extract its video first, e.g. ffmpeg -i "
                         f"{empty[0]}.mp4 {empty[0]}/images/%04d.png")
    counts = sorted({len(fr) for fr in frames})
    n = min(counts)
    if len(counts) > 1:
        warnings.warn(f"{root}: the cameras hold {counts[0]} to {counts[-1]} frames; the first {n} of each are used "
                      "(frame k at time k / (frames - 1) of every camera)", stacklevel=3)
    split: dict[str, list[Camera]] = {"train": [], "test": []}
    files = {}
    uid = 0
    for c, (folder, fr) in enumerate(zip(folders, frames)):
        for k, file in enumerate(fr[:n]):
            time = k / (n - 1) if n > 1 else 0.0
            name = file.relative_to(root).as_posix()
            cam = _camera(rows[c], c, uid, name, file, poses, time)
            split["test" if c == 0 else "train"].append(cam)
            files[uid] = file
            uid += 1
    LOG.info("%s: a multi-camera video, %d cameras x %d frames; %s held out for testing", root, len(folders), n,
             folders[0].name)
    return Scene(split["train"], split["test"], files, check_sizes=False, source=root)

