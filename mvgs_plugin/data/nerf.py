"""NeRF-synthetic (Blender) and D-NeRF scenes: transforms_{train,test}.json + images; or one
transforms.json (instant-ngp, nerfstudio) split as the COLMAP loader splits."""

from __future__ import annotations

import json
import logging
import math
import warnings
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import torch

from ..camera import Camera
from .colmap import _downscaled, check_inside, normalize_name
from .distortion import Distortion, UndistortedImage, shared_undistortion
from .images import BORDER_TOLERANCE, check_background, has_transparency, image_size, may_have_alpha, uniform_border
from .scene import PointCloud, Scene

__all__ = ["load_nerf_synthetic", "load_dnerf", "is_dynamic", "read_points_ply", "transforms_files", "OPENGL_TO_OPENCV"]

# Blender/OpenGL cameras look down -z with y up; OpenCV looks down +z with y down. Flipping the
# camera's y and z axes (right-multiplying camera-to-world) converts one into the other.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])

LOG = logging.getLogger("mvgs_plugin")

_SPLITS = ("train", "test")  # transforms_val.json, when present, is not used (as the original 3DGS)
# a folder with one transforms.json (or no test json) holds out every 8th frame of the name-sorted
# frames, indices 0, 8, 16, ... (the original 3DGS's "llffhold", as load_colmap's test_every)
TEST_EVERY = 8
# lens distortion keys (nerfstudio, instant-ngp): images with them are resampled to a pinhole
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
# nerfstudio reads SIMPLE_RADIAL and RADIAL as perspective cameras with the same k1, k2 keys as OPENCV
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE")


def _read_json(file: Path) -> tuple[list[dict], dict]:
    """The frames of one transforms json, with top-level camera keys copied into each frame, and
    the top-level keys."""
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
    return out, shared


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


def _distortion(frame: dict, where: str) -> Distortion:
    """The frame's lens distortion (k1..k4, p1, p2; 0 when absent; the fisheye model's k1..k4 for
    nerfstudio's OPENCV_FISHEYE and for instant-ngp's is_fisheye, which its colmap2nerf writes for
    COLMAP's fisheye models); ValueError for a camera_model this loader cannot resample
    (EQUIRECTANGULAR) and for is_fisheye beside a camera_model that is not a fisheye."""
    model = frame.get("camera_model")
    if model is not None and model not in _PINHOLE_MODELS:
        raise ValueError(f"{where}: camera_model {model!r}: supported are {', '.join(_PINHOLE_MODELS)} (OPENCV "
                         "and SIMPLE_RADIAL / RADIAL with lens distortion k1..k4, p1, p2, OPENCV_FISHEYE with k1..k4, "
                         "undistorted when read); "
                         "convert the capture to one, e.g. with COLMAP's image_undistorter")
    flag = frame.get("is_fisheye", False)
    if not isinstance(flag, bool):
        raise ValueError(f"{where}: 'is_fisheye' must be true or false, got {flag!r}")
    if flag and model not in (None, "OPENCV_FISHEYE"):
        raise ValueError(f"{where}: is_fisheye is set beside camera_model {model!r}: one says a fisheye lens, the "
                         "other not; keep the one that describes the capture")
    values = {k: v for k, v in ((k, _number(frame, k, where)) for k in _DISTORTION) if v is not None}
    if model == "OPENCV_FISHEYE" or flag:  # instant-ngp's is_fisheye: OpenCV's fisheye model with k1..k4
        if values.get("p1") or values.get("p2"):
            name = "camera_model 'OPENCV_FISHEYE'" if model else "is_fisheye (OpenCV's fisheye model)"
            raise ValueError(f"{where}: {name} has no tangential terms, got p1="
                             f"{values.get('p1', 0):g}, p2={values.get('p2', 0):g}")
        return Distortion(**{k: v for k, v in values.items() if k not in ("p1", "p2")}, fisheye=True)
    return Distortion(**values)


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
    if c2w.shape == (3, 4):  # the last row left out
        c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
    if c2w.shape != (4, 4):
        raise ValueError(f"{where}: 'transform_matrix' must be 4x4 (or 3x4), got {list(c2w.shape)}")
    if not np.isfinite(c2w).all():
        raise ValueError(f"{where}: 'transform_matrix' is not finite: {c2w.tolist()}")
    try:
        return np.linalg.inv(c2w @ OPENGL_TO_OPENCV)
    except np.linalg.LinAlgError:
        raise ValueError(f"{where}: 'transform_matrix' is singular: {c2w.tolist()}") from None


def _mask_file(frame: dict, root: Path, image: Path, width: int, height: int, where: str) -> Optional[Path]:
    """The frame's mask file (nerfstudio's ``mask_path``, relative to the json's folder) or None;
    it must exist and have its image's size."""
    if "mask_path" not in frame:
        return None
    mp = frame["mask_path"]
    if not isinstance(mp, str) or not mp.strip():
        raise ValueError(f"{where}: 'mask_path' must be a file name, got {mp!r}")
    file = root / check_inside(normalize_name(mp), root, f"{where}: mask_path")
    if not file.is_file():
        raise FileNotFoundError(f"{where}: its mask_path {mp!r} names {file}, which does not exist")
    w, h = image_size(file)
    if (w, h) != (width, height):
        raise ValueError(f"{where}: its mask {file} is {w}x{h} but its image {image} is {width}x{height} "
                         "(a mask has its image's size)")
    return file


def _in_copy(path: str, folder: str, copy: str, key: str, where: str, root: Path) -> str:
    """``path`` (a frame's file_path or mask_path) in its downscaled copy ``copy``/ (nerfstudio's
    images/ -> images_4/, masks/ -> masks_4/): the same sub-path under the copy when that file
    exists (images/a/b.png -> images_4/a/b.png), else the file's name directly under the copy
    (images_4/b.png, where nerfstudio looks). A path outside ``folder``/ is refused: two frames
    in train/ and test/ would share one name in the copy."""
    parts = normalize_name(path).split("/")
    if len(parts) < 2 or parts[0] != folder:
        raise ValueError(f"{where}: its {key} {path!r} does not lie in {folder}/, so it has no copy in {copy}/ "
                         f"(a downscaled folder replaces nerfstudio's {folder}/ folder)")
    mirrored, flat = "/".join([copy] + parts[1:]), f"{copy}/{parts[-1]}"
    for rel in ([mirrored, flat] if flat != mirrored else [mirrored]):
        if any((root / normalize_name(r)).is_file() for r in (rel, rel + ".png")):
            return rel
    return mirrored  # neither exists: the error names the mirrored file


def _frame_camera(frame: dict, uid: int, root: Path, with_time: bool, where: str,
                  undistortions: dict, images: Optional[str] = None,
                  ) -> tuple[Camera, Union[Path, UndistortedImage], Union[None, Path, UndistortedImage]]:
    fp = frame.get("file_path")
    if not isinstance(fp, str) or not fp.strip():
        raise ValueError(f"{where}: missing 'file_path'")
    original = None  # the full-size file, when the images are read from a downscaled copy
    if images is not None:
        original = fp
        fp = _in_copy(fp, "images", images, "file_path", where, root)
    rel = fp if Path(fp).suffix else fp + ".png"  # Blender scenes omit the extension
    if rel == fp and not (root / normalize_name(fp)).is_file() and (root / normalize_name(fp + ".png")).is_file():
        rel = fp + ".png"  # a name with a dot and no extension ("r.0"), the extension omitted as above
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
    full = (width, height)  # the size the json's intrinsics are for
    if original is not None:
        declared = (_number(frame, "w", where), _number(frame, "h", where))
        if None in declared:  # the full-size image's header says it
            first = root / check_inside(normalize_name(original), root, where)
            full = image_size(first) if first.is_file() else None
            if full is None:
                raise ValueError(f"{where}: reading a downscaled copy needs the full size its intrinsics are for: give "
                                 f"'w' and 'h', or keep the full-size image {first}")
        else:
            full = (int(declared[0]), int(declared[1]))
    for key, actual in (("w", full[0]), ("h", full[1])):
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
    source = file
    if images is not None and isinstance(frame.get("mask_path"), str):
        copy = "masks" + images[len("images"):]
        frame = {**frame, "mask_path": _in_copy(frame["mask_path"], "masks", copy, "mask_path", where, root)}
    mask = _mask_file(frame, root, file, width, height, where)
    try:
        K = _intrinsics(frame, full[0], full[1], where)
        if full != (width, height):  # a copy downscaled by one factor: the camera scaled to it
            K, width, height = _downscaled(K, full[0], full[1], (width, height), file, "the full-size image its intrinsics are for")
        dist = _distortion(frame, where)
        if dist:
            und = shared_undistortion(undistortions, K, width, height, dist, where)
            K, width, height, source = und.K_out, und.width_out, und.height_out, UndistortedImage(file, und)
            mask = None if mask is None else UndistortedImage(mask, und)
        cam = Camera(uid=uid, name=name, K=K, world_to_camera=_world_to_camera(frame, where), width=width,
                     height=height, time=time)
    except ValueError as err:
        msg = str(err)
        raise ValueError(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return cam, source, mask


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


def transforms_files(path) -> tuple[Path, Optional[Path]]:
    """(train json, test json or None) of a NeRF-style folder: transforms_train.json with its
    transforms_test.json (None when absent), else transforms.json (instant-ngp, nerfstudio) with
    None; FileNotFoundError when the folder holds neither."""
    root = Path(path)
    train = root / "transforms_train.json"
    if train.is_file():
        test = root / "transforms_test.json"
        return train, (test if test.is_file() else None)
    single = root / "transforms.json"
    if single.is_file():
        return single, None
    raise FileNotFoundError(f"missing {train} (or one {single})")


def _held_out(frames: list, jfile: Path, where_test: str) -> tuple[list, list]:
    """(train, test) lists of (index in the json, frame): every TEST_EVERY-th frame of the frames
    sorted by file_path is a test frame, starting with the first."""
    def name(item):
        fp = item[1].get("file_path")
        return normalize_name(fp) if isinstance(fp, str) else ""

    ordered = sorted(enumerate(frames), key=name)  # (index in the json, frame)
    test = [item for k, item in enumerate(ordered) if k % TEST_EVERY == 0]
    train = [item for k, item in enumerate(ordered) if k % TEST_EVERY != 0]
    if not train:
        raise ValueError(f"{jfile}: {len(frames)} frame(s): {where_test} holds out every {TEST_EVERY}th frame "
                         "(the first included) for testing, which leaves none to train on")
    return train, test


def _points_file(root: Path, shared: dict, jfile: Path) -> Optional[Path]:
    """points3d.ply beside the jsons, else the ply a transforms.json names (nerfstudio's
    ply_file_path)."""
    ply = root / "points3d.ply"
    if ply.is_file():
        return ply
    named = shared.get("ply_file_path")
    if named is None:
        return None
    if not isinstance(named, str) or not named.strip():
        raise ValueError(f"{jfile}: 'ply_file_path' must be a file name, got {named!r}")
    file = root / check_inside(normalize_name(named), root, f"{jfile}: ply_file_path")
    if not file.is_file():
        raise FileNotFoundError(f"{jfile}: its ply_file_path {named!r} names {file}, which does not exist")
    return file


def _load_blender(path, background, with_time: bool, images: Optional[str] = None) -> Scene:
    root = Path(path)
    if images is not None:
        images = str(images)
        if not images.startswith("images") or "/" in images.strip("/") or not (root / images).is_dir():
            raise ValueError(f"images={images!r}: a NeRF-style scene takes a downscaled copy of nerfstudio's images/ "
                             f"folder beside its json (e.g. images_4), which must exist in {root}")
    if not root.is_dir():
        raise FileNotFoundError(f"scene folder not found: {root}")
    auto = isinstance(background, str)
    if auto and background != "auto":
        raise ValueError(f"background must be 'auto', 3 floats in [0,1] or None, got {background!r}")
    bg = (1.0, 1.0, 1.0) if auto else check_background(background)
    train_json, test_json = transforms_files(root)
    frames, shared = _read_json(train_json)
    if test_json is not None:
        by_split = {"train": list(enumerate(frames)), "test": list(enumerate(_read_json(test_json)[0]))}
        where = {"train": train_json, "test": test_json}
    else:
        how = ("this folder has one transforms.json" if train_json.name == "transforms.json"
               else f"{root / 'transforms_test.json'} is missing")
        train, test = _held_out(frames, train_json, how)
        by_split, where = {"train": train, "test": test}, {"train": train_json, "test": train_json}
        said = (f"{root}: {how}: its frames sorted by file_path, every {TEST_EVERY}th from the first "
                f"({len(test)} of {len(frames)}) are held out as test views, the rest ({len(train)}) train")
        warnings.warn(said, stacklevel=3)
    splits: dict[str, list[Camera]] = {}
    files: dict[int, Union[Path, UndistortedImage]] = {}
    masks: dict[int, Union[Path, UndistortedImage]] = {}
    undistortions: dict = {}
    uid = 0
    for split in _SPLITS:
        cams = []
        for i, frame in by_split[split]:  # i: the frame's index in its json
            cam, file, mask = _frame_camera(frame, uid, root, with_time, f"{where[split]}: frame {i}", undistortions,
                                            images)
            cams.append(cam)
            files[uid] = file
            if mask is not None:
                masks[uid] = mask
            uid += 1
        splits[split] = cams
    _warn_repeated(splits, root)
    ply = _points_file(root, shared, train_json)
    points = read_points_ply(ply) if ply is not None else None
    if points is not None and len(points) == 0:
        warnings.warn(f"{ply} holds 0 points: the scene has no point cloud (the examples' "
                      "--init makes one, by default triangulated from the training views; an adapter given none "
                      "initialises randomly, where the cameras look)", stacklevel=3)
        points = None
    # sizes were read from the headers above, so the Scene need not read them again
    scene = Scene(splits["train"], splits["test"], files, points=points, background=bg,
                  check_sizes=False, source=root, masks=masks)
    if masks:
        LOG.info("%s: %d of %d frames have a mask (mask_path): the loss and the test metrics count the pixels "
                 "it keeps", root, len(masks), uid)
    if not auto:
        scene.background_origin = "given" if bg is not None else "none (alpha dropped)"
        return scene
    alpha = {cam.uid: may_have_alpha(scene.image_file(cam)) for cam in scene.train_cameras}  # headers only
    # decoded up to the first image with a see-through pixel (usually the first): RGBA captures
    # are not read twice at start-up; files without an alpha channel are opaque unread
    if any(has_transparency(scene.image_file(cam)) for cam in scene.train_cameras if alpha[cam.uid]):
        scene.background_origin = "white: RGBA images composited on it (the default)"
        opaque = [cam for cam in scene.train_cameras if not alpha[cam.uid]]
        shown = uniform_border(*_full_reads(scene, opaque)) if opaque else None
        if shown is not None and max(abs(c - 1.0) for c in shown) > BORDER_TOLERANCE:
            warnings.warn(f"{root}: {len(opaque)} of the {len(scene.train_cameras)} training images have no transparent "
                          f"pixel and their borders show ({shown[0]:.3f}, {shown[1]:.3f}, {shown[2]:.3f}), not the white "
                          f"the other, RGBA, images are composited on (e.g. {opaque[0].name!r}): the Gaussians would be "
                          "trained against two backdrops; composite them alike, or give the background they share",
                          stacklevel=3)
    else:  # opaque images, composited already: the colour their borders show, if they show one
        found = uniform_border(*_full_reads(scene, scene.train_cameras))
        if found is not None:
            scene.background = found
            scene.background_origin = ("the training images have no transparent pixel and their borders are one colour, "
                                       f"({found[0]:.3f}, {found[1]:.3f}, {found[2]:.3f})")
        else:
            scene.background_origin = ("white (the default): the training images have no transparent pixel and "
                                       "their borders are not one colour")
    return scene


def _full_reads(scene: Scene, cameras) -> tuple:
    """(images, masks) of ``cameras`` at full resolution for uniform_border, as generators that
    read one camera at a time without caching (Scene.read, Scene.read_mask): the border look
    at load time holds no image beyond the one it reads."""
    return (scene.read(cam) for cam in cameras), (scene.read_mask(cam) for cam in cameras)


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
    'time'); a malformed transforms_train.json (or transforms.json) is named in a ValueError."""
    return "time" in _read_json(transforms_files(path)[0])[0][0]


def load_nerf_synthetic(path, background: Union[str, Sequence[float], None] = "auto",
                        images: Optional[str] = None) -> Scene:
    """Load a NeRF-synthetic (Blender) scene, or a folder with one ``transforms.json``
    (instant-ngp, nerfstudio).

    Reads ``transforms_train.json`` and ``transforms_test.json`` in ``path`` (the val split is
    not used). Without ``transforms_test.json``, or with one ``transforms.json`` instead, the
    frames sorted by ``file_path`` are split as :func:`load_colmap` splits: every 8th, from the
    first, is a test frame (with a warning saying so). Per frame: ``file_path`` relative to the
    json's folder, ".png" appended when it has no extension; ``transform_matrix`` an OpenGL
    camera-to-world (4x4, or 3x4 without the last row), converted to an OpenCV world-to-camera.
    Intrinsics, per frame or top-level (per frame wins): ``fl_x``/``fl_y``, else fx = W / (2
    tan(camera_angle_x / 2)) and fy from ``camera_angle_y`` or fy = fx; ``cx``/``cy`` default to
    W/2, H/2; ``w``/``h``, when given, must match the image; lens distortion (``k1``..``k4``,
    ``p1``, ``p2``) is undistorted when the images are read (:mod:`~mvgs_plugin.data.distortion`),
    as is the ``OPENCV_FISHEYE`` ``camera_model`` (k1..k4) and instant-ngp's ``is_fisheye``. ``points3d.ply`` next to
    the jsons, else the ply a transforms.json names in ``ply_file_path`` (nerfstudio), becomes
    ``scene.points``. Uids count train frames then test frames from 0; names are the image paths
    relative to ``path`` (e.g. "train/r_000.png"). A frame's ``mask_path`` (nerfstudio: a one-channel
    image of the image's size, zero where a pixel is to be ignored, e.g. a person walking through)
    becomes its :meth:`Scene.mask`: the training loss and the test metrics count only the pixels it
    keeps; a frame without one counts all of its pixels.

    ``images``: the name of a downscaled copy of nerfstudio's ``images/`` folder beside the json
    (``images_2``, ``images_4``, ... as ``ns-process-data`` writes them): every ``file_path``
    under ``images/`` is read from it instead (masks from ``masks_2``, ...), and each camera is
    scaled to its copy's size (the json's intrinsics are for the full size: its ``w``/``h``, or
    the full-size image's header).

    ``background``: "auto" (default) composites RGBA images on white, as the Blender scenes are
    evaluated; when no training image has a transparent pixel, the images were composited
    already, and the colour their one-pixel borders show, when it is one colour
    (:func:`~mvgs_plugin.data.images.uniform_border`), is the scene's background (white when it
    is not: a photograph's border). A colour composites RGBA images on it and is the scene's
    background whatever the images hold; None drops alpha. ``scene.background_origin`` says which.
    """
    return _load_blender(path, background, with_time=False, images=images)


def load_dnerf(path, background: Union[str, Sequence[float], None] = "auto", images: Optional[str] = None) -> Scene:
    """Load a D-NeRF scene: as :func:`load_nerf_synthetic`, plus every frame's ``time`` in [0,1]
    (required) on ``Camera.time``."""
    return _load_blender(path, background, with_time=True, images=images)
