"""HyperNeRF (and Nerfies) captures: a phone moving round a moving subject, one of 4DGS's
benchmarks. Read as 4DGS reads them, with the lens undistorted as the other loaders do.

    scene/
      dataset.json          {"ids": [...], "train_ids": [...], "val_ids": [...]}
      metadata.json         {id: {"warp_id": k, "camera_id": c, ...}}   (the frame's time index)
      scene.json            {"center": [x, y, z], "scale": s, ...}      (optional)
      camera/<id>.json      one camera per frame (below)
      rgb/1x/<id>.png, rgb/2x/<id>.png, ...
      points.npy            optional: [N, 3] points, in the cameras' world

A camera file holds ``orientation`` (3 x 3, world-to-camera rotation: its rows are the camera's
axes in the world, x right, y down, z forward, OpenCV's), ``position`` (the camera's centre in
the world), ``focal_length``, ``pixel_aspect_ratio`` (fy = focal x ratio), ``principal_point``,
``skew`` (must be 0), ``radial_distortion`` (k1, k2, k3), ``tangential_distortion`` (p1, p2) and
``image_size`` (width, height) of the full-size (1x) image. A folder ``rgb/Nx`` holds the images
downscaled by N; the cameras are scaled to the images read. Pixel centres are at +0.5, as here.

With scene.json, positions and points are mapped to (p - center) x scale, as 4DGS and HyperNeRF
train (the frame the exported model lives in). Times: warp_id / the largest warp_id. Split:
``val_ids`` when dataset.json lists any (the "vrig" captures, a second phone), else 4DGS's
protocol for the "interp" captures: every 4th frame from the first trains (frames 0, 4, 8, ...),
and the frame two after each but the last is a test view (2, 6, ...; 4DGS drops the last).
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..camera import Camera
from .colmap import _downscaled, check_inside, normalize_name
from .distortion import Distortion, UndistortedImage, shared_undistortion
from .images import IMAGE_SUFFIXES, image_size
from .scene import PointCloud, Scene

__all__ = ["load_hypernerf", "is_hypernerf", "RGB_FOLDERS", "POINTS_GREY"]

LOG = logging.getLogger("mvgs_plugin")

# the image folders tried in order when none is named: 4DGS trains HyperNeRF at half size (2x)
RGB_FOLDERS = ("rgb/2x", "rgb/1x", "rgb/4x", "rgb/8x", "rgb/16x")
POINTS_GREY = 0.5  # points.npy carries no colour: its points start grey


def is_hypernerf(path) -> bool:
    """Whether ``path`` holds a HyperNeRF / Nerfies capture (dataset.json and camera/)."""
    path = Path(path)
    return (path / "dataset.json").is_file() and (path / "camera").is_dir()


def _json(file: Path) -> dict:
    if not file.is_file():
        raise FileNotFoundError(f"missing {file}")
    try:
        with open(file) as f:
            data = json.load(f)
    except json.JSONDecodeError as err:
        raise ValueError(f"{file}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{file}: expected a JSON object, got {type(data).__name__}")
    return data


def _numbers(cam: dict, key: str, shape: tuple, where: str, default=None) -> np.ndarray:
    if key not in cam:
        if default is not None:
            return np.asarray(default, dtype=np.float64)
        raise ValueError(f"{where}: missing '{key}'")
    try:
        arr = np.asarray(cam[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: '{key}' must be numbers, got {cam[key]!r}") from None
    if arr.shape != shape or not np.isfinite(arr).all():
        raise ValueError(f"{where}: '{key}' must be {'a number' if shape == () else f'{shape} finite numbers'}, "
                         f"got {cam[key]!r}")
    return arr


def _ids(data: dict, key: str, file: Path) -> list[str]:
    ids = data.get(key, [])
    if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
        raise ValueError(f"{file}: '{key}' must be a list of frame ids (strings), got {ids!r}")
    return ids


def _rgb_folder(root: Path, images: Optional[str]) -> Path:
    """The folder of the images to read (a camera is scaled to its image's size when read)."""
    if images is not None:
        name = normalize_name(str(images))
        folder = root / check_inside(name, root, f"images={images!r}")
        if not folder.is_dir():
            raise ValueError(f"images={images!r}: {folder} does not exist (a HyperNeRF capture's images are in "
                             "rgb/1x, rgb/2x, ...)")
    else:
        folder = next((root / f for f in RGB_FOLDERS if (root / f).is_dir()), None)
        if folder is None:
            raise FileNotFoundError(f"{root}: no image folder ({', '.join(RGB_FOLDERS)})")
    return folder


def _image_file(folder: Path, frame: str) -> Path:
    for suffix in IMAGE_SUFFIXES:
        file = folder / f"{frame}{suffix}"
        if file.is_file():
            return file
    raise FileNotFoundError(f"no image for frame {frame!r} in {folder} ({', '.join(IMAGE_SUFFIXES)})")


def _camera(root: Path, frame: str, uid: int, file: Path, time: float, center, scale: float,
            undistortions: dict) -> tuple[Camera, object]:
    cfile = root / "camera" / f"{frame}.json"
    where = str(cfile)
    cam = _json(cfile)
    R = _numbers(cam, "orientation", (3, 3), where)
    position = _numbers(cam, "position", (3,), where)
    f = float(_numbers(cam, "focal_length", (), where))
    aspect = float(_numbers(cam, "pixel_aspect_ratio", (), where, default=1.0))
    cx, cy = _numbers(cam, "principal_point", (2,), where)
    skew = float(_numbers(cam, "skew", (), where, default=0.0))
    k = _numbers(cam, "radial_distortion", (3,), where, default=(0.0, 0.0, 0.0))
    p = _numbers(cam, "tangential_distortion", (2,), where, default=(0.0, 0.0))
    full = tuple(int(v) for v in _numbers(cam, "image_size", (2,), where))
    if skew != 0.0:
        raise ValueError(f"{where}: skew {skew:g}: a camera with skewed pixels is not a pinhole this renderer draws")
    if not (f > 0 and aspect > 0 and min(full) >= 1):
        raise ValueError(f"{where}: focal_length {f:g}, pixel_aspect_ratio {aspect:g} and image_size {list(full)} "
                         "must be positive")
    K = np.array([[f, 0.0, cx], [0.0, f * aspect, cy], [0.0, 0.0, 1.0]])
    width, height = image_size(file)
    if (width, height) != full:
        K, width, height = _downscaled(K, full[0], full[1], (width, height), file, f"{cfile.name}'s image_size")
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ ((position - center) * scale)
    source = file
    dist = Distortion(k1=float(k[0]), k2=float(k[1]), k3=float(k[2]), p1=float(p[0]), p2=float(p[1]))
    try:
        if dist:
            und = shared_undistortion(undistortions, K, width, height, dist, where)
            K, width, height, source = und.K_out, und.width_out, und.height_out, UndistortedImage(file, und)
        name = file.relative_to(root).as_posix()
        return Camera(uid=uid, name=name, K=K, world_to_camera=w2c, width=width, height=height, time=time), source
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None


def load_hypernerf(path, images: Optional[str] = None) -> Scene:
    """Load a HyperNeRF / Nerfies capture (see the module docstring). ``images``: the image
    folder relative to ``path`` (default: the first of :data:`RGB_FOLDERS` that exists; 4DGS
    trains at rgb/2x). Uids count train frames then test frames; names are image paths relative
    to ``path``. Photographs: the scene has no background colour."""
    root = Path(path)
    dataset_file = root / "dataset.json"
    dataset, meta = _json(dataset_file), _json(root / "metadata.json")
    ids = _ids(dataset, "ids", dataset_file)
    train_ids, val_ids = _ids(dataset, "train_ids", dataset_file), _ids(dataset, "val_ids", dataset_file)
    if val_ids:
        split = {"train": train_ids or [i for i in ids if i not in set(val_ids)], "test": val_ids}
        how = f"dataset.json's val_ids ({len(val_ids)})"
    else:  # 4DGS's protocol: frames 0, 4, 8, ... train, 2, 6, 10, ... test but the last (dropped, as 4DGS drops it)
        ordered = ids or train_ids
        train = list(range(0, len(ordered), 4))
        split = {"train": [ordered[i] for i in train], "test": [ordered[i + 2] for i in train[:-1]]}
        how = (f"no val_ids: 4DGS's protocol for interpolation captures, every 4th frame from the first trains "
               f"({len(split['train'])}), every 4th from the third is a test view, the last of them left out as 4DGS "
               f"leaves it ({len(split['test'])})")
        warnings.warn(f"{root}: {how}", stacklevel=2)
    if not split["train"]:
        raise ValueError(f"{dataset_file}: no training frames (ids, train_ids)")
    warps = {}  # every frame's time index: the times are over the largest of all of them, as 4DGS reads them
    for frame in dict.fromkeys(ids + split["train"] + split["test"]):
        entry = meta.get(frame)
        warp = entry.get("warp_id", entry.get("time_id")) if isinstance(entry, dict) else None
        if isinstance(warp, bool) or not isinstance(warp, (int, float)) or not np.isfinite(warp) or warp < 0:
            raise ValueError(f"{root / 'metadata.json'}: frame {frame!r} needs a 'warp_id' >= 0 (its time index), got "
                             f"{entry!r}")
        warps[frame] = float(warp)
    top = max(warps.values())
    center, scale = np.zeros(3), 1.0
    if (root / "scene.json").is_file():
        info = _json(root / "scene.json")
        where = str(root / "scene.json")
        center = _numbers(info, "center", (3,), where, default=(0.0, 0.0, 0.0))
        scale = float(_numbers(info, "scale", (), where, default=1.0))
        if not scale > 0:
            raise ValueError(f"{where}: 'scale' must be positive, got {scale:g}")
    folder = _rgb_folder(root, images)
    cams: dict[str, list[Camera]] = {"train": [], "test": []}
    files, undistortions, uid = {}, {}, 0
    for part in ("train", "test"):
        for frame in split[part]:
            file = _image_file(folder, frame)
            cam, source = _camera(root, frame, uid, file, warps[frame] / top if top > 0 else 0.0, center, scale,
                                  undistortions)
            cams[part].append(cam)
            files[uid] = source
            uid += 1
    points = None
    if (root / "points.npy").is_file():
        xyz = np.load(root / "points.npy", allow_pickle=False)
        if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.isfinite(xyz).all():
            raise ValueError(f"{root / 'points.npy'}: expected [N, 3] finite points, got shape {tuple(xyz.shape)}")
        if len(xyz):
            xyz = (xyz.astype(np.float64) - center) * scale
            points = PointCloud(torch.from_numpy(xyz), torch.full((len(xyz), 3), POINTS_GREY))
    scene = Scene(cams["train"], cams["test"], files, points=points, check_sizes=False, source=root)
    if points is not None:
        scene.points_origin = f"{len(points)} points given with the scene (points.npy, grey: it has no colours)"
    LOG.info("%s: HyperNeRF capture, %d train and %d test frames from %s; split by %s", root, len(cams["train"]),
             len(cams["test"]), folder.relative_to(root).as_posix(), how)
    return scene
