"""NeRF-synthetic (Blender) and D-NeRF scenes: transforms_{train,test}.json + images."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..camera import Camera
from .colmap import check_inside, normalize_name
from .images import check_background, image_size
from .scene import PointCloud, Scene

__all__ = ["load_nerf_synthetic", "load_dnerf", "is_dynamic", "read_points_ply", "OPENGL_TO_OPENCV"]

# Blender/OpenGL cameras look down -z with y up; OpenCV looks down +z with y down. Flipping the
# camera's y and z axes (right-multiplying camera-to-world) converts one into the other.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])

_SPLITS = ("train", "test")  # transforms_val.json, when present, is not used (as the original 3DGS)


def _read_json(file: Path) -> list[dict]:
    """The frames of one transforms json, with top-level camera keys copied into each frame."""
    if not file.is_file():
        raise FileNotFoundError(f"missing {file}")
    try:
        meta = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{file}: not readable JSON: {err}") from None
    if not isinstance(meta, dict) or "frames" not in meta:
        raise ValueError(f"{file}: no 'frames' list")
    frames = meta["frames"]
    if not isinstance(frames, list):
        raise ValueError(f"{file}: 'frames' must be a list, got {type(frames).__name__}")
    if not frames:
        raise ValueError(f"{file}: 'frames' is empty")
    shared = {k: v for k, v in meta.items() if k != "frames"}
    out = []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise ValueError(f"{file}: frame {i} must be an object, got {type(frame).__name__}")
        # per-frame keys (fl_x, w, ...) win over top-level ones; _OWN remembers which were the frame's
        out.append({**shared, **frame, _OWN: frozenset(frame)})
    return out


def _number(frame: dict, key: str, where: str) -> Optional[float]:
    if key not in frame:
        return None
    v = frame[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{where}: '{key}' must be a finite number, got {v!r}")
    return float(v)


_OWN = "\0own keys"  # not a JSON key anyone writes
_STALE = ("do the json's intrinsics belong to this image? (images resized after the json was written "
          "keep the old fl_x/fl_y/cx/cy: scale them with the images, or drop them and keep camera_angle_x)")
# fl_x and camera_angle_x may both be given; they must agree to this relative tolerance
_FOCAL_AGREEMENT = 0.01
# a principal point further than this share of the size from the centre is used, with a warning
_OFF_CENTRE = 0.2


def _focal(frame: dict, axis: str, size: int, where: str) -> Optional[float]:
    """fl_<axis>, or the focal camera_angle_<axis> implies for an image `size` pixels across;
    both given at the same level (both top-level, or both in the frame): they must agree (a
    resized image with stale fl_* is caught here)."""
    fl = _number(frame, f"fl_{axis}", where)
    angle = _number(frame, f"camera_angle_{axis}", where)
    if angle is not None and not 0 < angle < math.pi:
        raise ValueError(f"{where}: camera_angle_{axis} must be in (0, pi), got {angle}")
    from_angle = None if angle is None else 0.5 * size / math.tan(0.5 * angle)
    if fl is not None and not fl > 0:
        raise ValueError(f"{where}: fl_{axis} must be > 0, got {fl}")
    own = frame.get(_OWN, frozenset())
    same_level = (f"fl_{axis}" in own) == (f"camera_angle_{axis}" in own)  # a frame's fl_x overrides a shared angle
    if fl is not None and from_angle is not None and same_level and abs(fl / from_angle - 1.0) > _FOCAL_AGREEMENT:
        fits = fl * 2.0 * math.tan(0.5 * angle)
        raise ValueError(f"{where}: fl_{axis}={fl:g} but camera_angle_{axis}={angle:g} gives {from_angle:g} for "
                         f"this image, {size} px across (fl_{axis} fits an image {fits:.0f} px across); {_STALE}")
    return fl if fl is not None else from_angle


def _intrinsics(frame: dict, width: int, height: int, where: str) -> np.ndarray:
    """K [3,3] from fl_x/fl_y/cx/cy or camera_angle_x/_y; cx, cy default to W/2, H/2. Values
    that cannot belong to an image of this size (a principal point outside it, fl_x against
    camera_angle_x) are refused; a principal point far from the centre is used with a warning."""
    fx = _focal(frame, "x", width, where)
    if fx is None:
        raise ValueError(f"{where}: needs 'camera_angle_x' or 'fl_x'")
    fy = _focal(frame, "y", height, where)
    fy = fx if fy is None else fy
    centre = []
    for key, size in (("cx", width), ("cy", height)):
        c = _number(frame, key, where)
        if c is None:
            c = 0.5 * size
        elif not 0 < c < size:
            raise ValueError(f"{where}: {key}={c:g} lies outside the image ({width}x{height} px); {_STALE}")
        elif abs(c - 0.5 * size) > _OFF_CENTRE * size:
            warnings.warn(f"{where}: {key}={c:g} is {abs(c - 0.5 * size) / size:.0%} of the image size from its "
                          f"centre {0.5 * size:g} ({width}x{height} px); used as given, but {_STALE}", stacklevel=4)
        centre.append(c)
    return np.array([[fx, 0.0, centre[0]], [0.0, fy, centre[1]], [0.0, 0.0, 1.0]])


def _world_to_camera(frame: dict, where: str) -> np.ndarray:
    """OpenCV world-to-camera [4,4] from the frame's OpenGL camera-to-world matrix."""
    if "transform_matrix" not in frame:
        raise ValueError(f"{where}: missing 'transform_matrix'")
    try:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: 'transform_matrix' must be a numeric 4x4 matrix") from None
    if c2w.shape != (4, 4):
        raise ValueError(f"{where}: 'transform_matrix' must be 4x4, got {list(c2w.shape)}")
    if not np.isfinite(c2w).all():
        raise ValueError(f"{where}: 'transform_matrix' is not finite: {c2w.tolist()}")
    try:
        return np.linalg.inv(c2w @ OPENGL_TO_OPENCV)
    except np.linalg.LinAlgError:
        raise ValueError(f"{where}: 'transform_matrix' is singular: {c2w.tolist()}") from None


def _frame_camera(frame: dict, uid: int, root: Path, with_time: bool,
                  where: str) -> tuple[Camera, Path]:
    fp = frame.get("file_path")
    if not isinstance(fp, str) or not fp.strip():
        raise ValueError(f"{where}: missing 'file_path'")
    rel = fp if Path(fp).suffix else fp + ".png"  # Blender scenes omit the extension
    name = check_inside(normalize_name(rel), root, where)
    file = root / name
    where = f"{where} ({name})"
    try:
        width, height = image_size(file)  # FileNotFoundError names the file
    except FileNotFoundError as err:
        if rel == fp:
            raise
        raise FileNotFoundError(f"{err} ({where}: its file_path {fp!r} has no extension, so '.png' was added, as "
                                "Blender scenes omit it; write the extension in file_path)") from None
    for key, actual in (("w", width), ("h", height)):
        declared = _number(frame, key, where)
        if declared is not None and declared != actual:
            raise ValueError(f"{where}: '{key}' is {declared:g} but the image {file} is "
                             f"{width}x{height}")
    time = None
    if with_time:
        if "time" not in frame:
            raise ValueError(f"{where}: missing 'time' (D-NeRF frames need a time in [0,1])")
        time = _number(frame, "time", where)
        if not 0.0 <= time <= 1.0:
            raise ValueError(f"{where}: 'time' must be in [0,1], got {time}")
    try:
        cam = Camera(uid=uid, name=name, K=_intrinsics(frame, width, height, where),
                     world_to_camera=_world_to_camera(frame, where), width=width,
                     height=height, time=time)
    except ValueError as err:
        msg = str(err)
        raise ValueError(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return cam, file


def read_points_ply(file: Path) -> PointCloud:
    """Points from a PLY with vertex properties x y z and optionally red green blue.

    Integer colours are divided by their type's maximum (255 for uchar); float colours must
    already be in [0,1]. Without colour properties every point is mid-grey (0.5).
    """
    from plyfile import PlyData

    try:
        vertex = PlyData.read(str(file))["vertex"]
    except Exception as err:  # plyfile raises PlyParseError, KeyError, ValueError, ...
        raise ValueError(f"{file}: cannot read a 'vertex' element: {err}") from None
    props = {p.name for p in vertex.properties}
    if not {"x", "y", "z"} <= props:
        raise ValueError(f"{file}: vertex needs x, y, z properties, has {sorted(props)}")
    xyz = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"], axis=1)
    if {"red", "green", "blue"} <= props:
        cols = [np.asarray(vertex[k]) for k in ("red", "green", "blue")]
        rgb = np.stack([c.astype(np.float64) / (np.iinfo(c.dtype).max
                                                 if np.issubdtype(c.dtype, np.integer) else 1.0)
                        for c in cols], axis=1)
    else:
        rgb = np.full_like(xyz, 0.5)
    try:
        return PointCloud(xyz=torch.from_numpy(xyz), rgb=torch.from_numpy(rgb))
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None


def _load_blender(path, background, with_time: bool) -> Scene:
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"scene folder not found: {root}")
    bg = check_background(background)
    splits: dict[str, list[Camera]] = {}
    files: dict[int, Path] = {}
    uid = 0
    for split in _SPLITS:
        jfile = root / f"transforms_{split}.json"
        cams = []
        for i, frame in enumerate(_read_json(jfile)):
            cam, file = _frame_camera(frame, uid, root, with_time, f"{jfile}: frame {i}")
            cams.append(cam)
            files[uid] = file
            uid += 1
        splits[split] = cams
    _warn_repeated(splits, root)
    ply = root / "points3d.ply"
    points = read_points_ply(ply) if ply.is_file() else None
    if points is not None and len(points) == 0:
        warnings.warn(f"{ply} holds 0 points: the scene has no point cloud (the examples' "
                      "--init makes one, by default triangulated from the training views; an adapter given none "
                      "initialises randomly, where the cameras look)", stacklevel=3)
        points = None
    # sizes were read from the headers above, so the Scene need not read them again
    return Scene(splits["train"], splits["test"], files, points=points, background=bg,
                 check_sizes=False, source=root)


def _warn_repeated(splits: dict, root: Path) -> None:
    """Warn when a frame repeats (the same image and camera twice in the training split), or a
    test frame is a training frame: the test metrics then measure the fit, not new views."""
    def key(cam: Camera) -> tuple:
        return cam.name, tuple(cam.world_to_camera.reshape(-1).tolist()), cam.time

    train = {}
    for cam in splits["train"]:
        if key(cam) in train:
            warnings.warn(f"{root}: training frame {cam.name!r} appears more than once (same image and camera): it "
                          "counts twice in the view sampling", stacklevel=4)
        train[key(cam)] = cam
    shared = [cam.name for cam in splits["test"] if key(cam) in train]
    if shared:
        warnings.warn(f"{root}: {len(shared)} of the {len(splits['test'])} test frames are also training frames "
                      f"(same image and camera, e.g. {shared[0]!r}): the test metrics measure the fit to the "
                      "training views, not new views", stacklevel=4)


def is_dynamic(path) -> bool:
    """Whether the NeRF-synthetic layout in ``path`` is a D-NeRF scene (its train frames carry a
    'time'); a malformed transforms_train.json is named in a ValueError."""
    return "time" in _read_json(Path(path) / "transforms_train.json")[0]


def load_nerf_synthetic(path, background: Optional[Sequence[float]] = (1.0, 1.0, 1.0)) -> Scene:
    """Load a NeRF-synthetic (Blender) scene.

    Reads ``transforms_train.json`` and ``transforms_test.json`` in ``path`` (the val split is
    not used). Per frame: ``file_path`` relative to the json's folder, ".png" appended when it
    has no extension; ``transform_matrix`` an OpenGL camera-to-world, converted to an OpenCV
    world-to-camera. Intrinsics, per frame or top-level (per frame wins): ``fl_x``/``fl_y``, else
    fx = W / (2 tan(camera_angle_x / 2)) and fy from ``camera_angle_y`` or fy = fx; ``cx``/``cy``
    default to W/2, H/2; ``w``/``h``, when given, must match the image. RGBA images are
    composited on ``background`` (None drops alpha). An optional ``points3d.ply`` next to the
    jsons becomes ``scene.points``. Uids count train frames then test frames from 0; names are
    the image paths relative to ``path`` (e.g. "train/r_000.png").
    """
    return _load_blender(path, background, with_time=False)


def load_dnerf(path, background: Optional[Sequence[float]] = (1.0, 1.0, 1.0)) -> Scene:
    """Load a D-NeRF scene: as :func:`load_nerf_synthetic`, plus every frame's ``time`` in [0,1]
    (required) on ``Camera.time``."""
    return _load_blender(path, background, with_time=True)
