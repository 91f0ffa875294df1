"""COLMAP sparse models (binary or text) read with pycolmap."""

from __future__ import annotations

import collections
import logging
import math
import os
import posixpath
import shutil
import tempfile
import struct
import warnings
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np
import torch

from ..checks import check_int
from ..camera import Camera
from .distortion import Distortion, UndistortedImage, shared_undistortion
from .images import image_size
from .scene import PointCloud, Scene

LOG = logging.getLogger("mvgs_plugin")

__all__ = ["load_colmap", "find_colmap_model", "normalize_name", "check_inside"]

_MODEL_FILES = ("cameras.bin", "cameras.txt")


def normalize_name(name: str) -> str:
    """'/'-separated relative image name without './' or '..' detours ("train/r_000.png")."""
    n = posixpath.normpath(str(name).replace("\\", "/"))
    return n[2:] if n.startswith("./") else n


def check_inside(name: str, folder: Path, where: str) -> str:
    """``name`` (normalised) if it stays inside ``folder``; a ValueError naming it otherwise.
    Image names that climb out ("../x.png") or are absolute would read files the scene folder
    does not hold (a copied or shared scene then trains on whatever lies there)."""
    drive = len(name) > 2 and name[0].isalpha() and name[1] == ":" and name[2] == "/"  # "C:/x" (normalised)
    if posixpath.isabs(name) or name == ".." or name.startswith("../") or drive:
        raise ValueError(f"{where}: image path {name!r} leaves the folder {folder}; image paths must be "
                         "relative and inside it (copy or link the images into the folder)")
    return name


def find_colmap_model(path: Path) -> Path:
    """The model folder: ``path/sparse/0``, else ``path/sparse``, else ``path`` itself."""
    path = Path(path)
    tried = [path / "sparse" / "0", path / "sparse", path]
    for folder in tried:
        if any((folder / f).is_file() for f in _MODEL_FILES):
            return folder
    raise FileNotFoundError(
        "no COLMAP model (cameras.bin or cameras.txt) in " + ", ".join(str(t) for t in tried))


# The fewest bytes one record of each binary model file takes (COLMAP's binary layout):
# cameras: id int32, model int32, width, height uint64, >= 3 float64 params;
# images: id uint32, qvec 4 + tvec 3 float64, camera id uint32, name >= its NUL, uint64 count;
# points3D: id uint64, xyz 3 float64, rgb 3 uint8, error float64, track length uint64.
_MIN_RECORD_BYTES = {"cameras.bin": 4 + 4 + 8 + 8 + 3 * 8, "images.bin": 4 + 7 * 8 + 4 + 1 + 8,
                     "points3D.bin": 8 + 3 * 8 + 3 + 8 + 8}
# Parameters per COLMAP camera model id (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
# OPENCV_FISHEYE, FULL_OPENCV, FOV, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, THIN_PRISM_FISHEYE,
# RAD_TAN_THIN_PRISM_FISHEYE)
_CAMERA_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}


class _Reader:
    """Bounds-checked walk over a binary model file (nothing is allocated from its counts)."""

    def __init__(self, file: Path):
        self.file, self.data, self.at = file, file.read_bytes(), 0

    def take(self, n: int, what: str) -> memoryview:
        if n < 0 or self.at + n > len(self.data):
            raise ValueError(f"{self.file}: truncated or corrupt: {what} needs {n} bytes at offset {self.at}, "
                             f"the file has {len(self.data)}")
        out = memoryview(self.data)[self.at:self.at + n]
        self.at += n
        return out

    def u64(self, what: str) -> int:
        return struct.unpack("<Q", self.take(8, what))[0]

    def name(self, what: str) -> None:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise ValueError(f"{self.file}: truncated or corrupt: {what} has no terminating NUL")
        self.at = end + 1

    def done(self) -> None:
        if self.at != len(self.data):
            raise ValueError(f"{self.file}: corrupt: {len(self.data) - self.at} bytes after the last record "
                             f"(the records end at offset {self.at})")


def _point_record(r: _Reader, i: int) -> memoryview:
    """Point i of points3D.bin at the reader's place: its first 43 bytes (id, xyz, rgb, error),
    its track skipped."""
    head = r.take(43, f"point {i}")
    r.take(8 * r.u64(f"point {i}'s track length"), f"point {i}'s track")
    return head


def check_binary_counts(model_dir: Path) -> None:
    """Walk the binary model files record by record, checking every count against the bytes
    that are there, before pycolmap reads them: a corrupt or crafted count (2^40 points, a
    track length from the middle of a truncated file) would make the reader allocate until it
    fails, and a file cut short by a few bytes would load its last record from nothing. The
    error names the file. Text models and files this layout does not cover are left to pycolmap."""
    for name, least in _MIN_RECORD_BYTES.items():
        file = Path(model_dir) / name
        if not file.is_file():
            continue
        r = _Reader(file)
        size = len(r.data)
        if size < 8:
            raise ValueError(f"{file}: {size} bytes, too short to hold its record count (8 bytes)")
        count = r.u64("the record count")
        if count * least > size - 8:  # the common damage, said in one line before the walk
            raise ValueError(f"{file} declares {count} records, which take at least {count * least} bytes, but "
                             f"the file has {size}: it is truncated or corrupt")
        known = True
        for i in range(count):
            if name == "points3D.bin":
                _point_record(r, i)
            elif name == "images.bin":
                r.take(64, f"image {i}")
                r.name(f"image {i}'s name")
                r.take(24 * r.u64(f"image {i}'s 2D point count"), f"image {i}'s 2D points")
            else:
                model = struct.unpack("<i", r.take(8, f"camera {i}")[4:8])[0]
                if model not in _CAMERA_PARAMS:  # a model this walk does not know: pycolmap decides on
                    known = False  # this (tiny) file; the image and point files are still walked
                    break
                r.take(16 + 8 * _CAMERA_PARAMS[model], f"camera {i}")
        if known:
            r.done()


def _text_lines(file: Path):
    """(line number, fields) of a COLMAP text file's records, comments and blank lines left out."""
    with open(file, encoding="utf-8", errors="replace") as fh:
        for number, line in enumerate(fh, 1):
            line = line.strip()
            if line and not line.startswith("#"):
                yield number, line.split()


def _finite_fields(file: Path, number: int, fields: Sequence[str], what: str) -> None:
    for text in fields:
        try:
            ok = math.isfinite(float(text))
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(f"{file}:{number}: {what}: {text!r} is not a finite number")


# parameters of each COLMAP camera model (COLMAP's src/colmap/sensor/models.h), for a text model's
# error message
PARAMETER_COUNTS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8,
                    "OPENCV_FISHEYE": 8, "FULL_OPENCV": 12, "FOV": 5, "SIMPLE_RADIAL_FISHEYE": 4, "RADIAL_FISHEYE": 5,
                    "THIN_PRISM_FISHEYE": 12, "RAD_TAN_THIN_PRISM_FISHEYE": 16}


def check_text_model(model_dir: Path) -> None:
    """Check a text model's records line by line, so an error names the file, the line and the
    value (pycolmap's own says "Check failed" or names a rig that does not exist): every
    camera's parameter count its model's and its numbers finite, every pose's numbers finite,
    every image's camera listed in cameras.txt and the line after each image not another image
    (its 2D points), every point's position finite. Only for a text model (a binary one is walked by
    check_binary_counts). _read_model runs it when pycolmap refuses a model, not before: on a
    model pycolmap reads it would double the load time (1.97 s against pycolmap's 2.24 s for
    a million points)."""
    model_dir = Path(model_dir)
    if all((model_dir / f"{stem}.bin").is_file() for stem in ("cameras", "images")):
        return
    cameras, images = model_dir / "cameras.txt", model_dir / "images.txt"
    if not (cameras.is_file() and images.is_file()):
        return
    ids = set()
    for number, fields in _text_lines(cameras):
        if len(fields) < 5:
            raise ValueError(f"{cameras}:{number}: a camera needs CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got "
                             f"{len(fields)} field(s)")
        ids.add(fields[0])
        want = PARAMETER_COUNTS.get(fields[1])
        if want is not None and len(fields) - 4 != want:
            raise ValueError(f"{cameras}:{number}: camera {fields[0]} is a {fields[1]} camera, which has {want} parameters "
                             f"after CAMERA_ID MODEL WIDTH HEIGHT; the line gives {len(fields) - 4}")
        _finite_fields(cameras, number, fields[4:], f"the parameters of camera {fields[0]}")
    with open(images, encoding="utf-8", errors="replace") as fh:
        lines = iter(enumerate(fh, 1))
        for number, line in lines:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split()
            if len(fields) < 10:
                raise ValueError(f"{images}:{number}: an image needs IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                                 f"got {len(fields)} field(s)")
            _finite_fields(images, number, fields[1:8], f"the pose of image {' '.join(fields[9:])!r}")
            if fields[8] not in ids:
                raise ValueError(f"{images}:{number}: image {' '.join(fields[9:])!r} names camera {fields[8]}, which "
                                 f"{cameras} does not list (it lists {', '.join(sorted(ids, key=str)) or 'none'})")
            following = next(lines, None)  # the image's 2D points: the next line, even a blank one
            if following is not None and _image_record(following[1].split(maxsplit=10)):
                raise ValueError(f"{images}:{following[0]}: the line after image {' '.join(fields[9:])!r} should hold its 2D "
                                 f"points but is an image record: {POINTS_LINE_HINT}")
    points = model_dir / "points3D.txt"
    if points.is_file():
        for number, fields in _text_lines(points):
            _finite_fields(points, number, fields[1:4], f"the position of point {fields[0]}")


def _read_model(pycolmap, model_dir: Path):
    """pycolmap.Reconstruction of model_dir. The points file is optional (the loader then has no
    points, and the examples triangulate or draw them), but pycolmap needs all three files of
    one format: a model without one is read from a copy with an empty points file. A model
    without its cameras or images file in either format is refused naming what is missing."""
    have = {stem: [ext for ext in ("bin", "txt") if (model_dir / f"{stem}.{ext}").is_file()]
            for stem in ("cameras", "images", "points3D")}
    fmt = next((ext for ext in ("bin", "txt") if ext in have["cameras"] and ext in have["images"]), None)
    if fmt is None:
        raise FileNotFoundError(
            f"{model_dir}: a COLMAP model needs cameras and images files of one format (cameras.bin + images.bin, "
            f"or cameras.txt + images.txt); found " + (", ".join(f"{k}.{e}" for k, v in have.items() for e in v) or "none"))
    if have["points3D"] and fmt not in have["points3D"]:
        raise ValueError(f"{model_dir}: points3D.{have['points3D'][0]} beside cameras.{fmt} and images.{fmt}: pycolmap reads "
                         f"one format; convert it (colmap model_converter --output_type {fmt.upper()}), or remove it "
                         "to load the model without points")
    points = None
    try:
        rec = _read(pycolmap, model_dir, fmt, have)
    except Exception as err:  # pycolmap raises ValueError/RuntimeError with a C++ message
        check_text_model(model_dir)  # a text model: the file, line and value, when these checks find them
        rec = _without_tracks(pycolmap, model_dir, fmt, have) if fmt in have["points3D"] else None
        if rec is None:
            raise ValueError(f"cannot read the COLMAP model in {model_dir}: {err}") from None
        points = _point_positions(model_dir / f"points3D.{fmt}")
        warnings.warn(f"{model_dir}: pycolmap cannot read the model with its points3D.{fmt} ({err}): its tracks name "
                      "images or 2D points the images file does not have (frames deleted from the model by hand, or "
                      f"2D points stripped); the cameras and images are read without it, and its "
                      f"{0 if points is None else len(points)} points' "
                      "positions and colours are kept, their tracks not used", stacklevel=3)
    if fmt == "txt":
        _check_image_lines(model_dir / "images.txt", len(rec.images))
    return rec, points


def _without_tracks(pycolmap, model_dir: Path, fmt: str, have: dict):
    """The model read with an empty points file, or None when pycolmap refuses it even so (the
    fault is not in the points)."""
    try:
        return _read(pycolmap, model_dir, fmt, {**have, "points3D": []})
    except Exception:
        return None


def _point_positions(file: Path) -> Optional[PointCloud]:
    """Positions and colours of a points3D file's points, read without pycolmap (their tracks are
    skipped): for a model whose tracks do not match its images (_read_model). None for a file
    with no points."""
    xyz, rgb = [], []
    if file.suffix == ".bin":
        r = _Reader(file)
        for i in range(r.u64("the record count")):
            head = _point_record(r, i)
            xyz.append(struct.unpack("<3d", head[8:32]))
            rgb.append(tuple(head[32:35]))
    else:
        for number, fields in _text_lines(file):
            if len(fields) < 8:
                raise ValueError(f"{file}:{number}: a point needs POINT3D_ID X Y Z R G B ERROR TRACK[], got "
                                 f"{len(fields)} field(s)")
            _finite_fields(file, number, fields[1:4], f"the position of point {fields[0]}")
            _finite_fields(file, number, fields[4:7], f"the colour of point {fields[0]}")
            colour = [int(float(v)) for v in fields[4:7]]
            if not all(0 <= c <= 255 for c in colour):
                raise ValueError(f"{file}:{number}: point {fields[0]}'s colour {fields[4:7]} is not three values "
                                 "in [0, 255]")
            xyz.append(tuple(float(v) for v in fields[1:4]))
            rgb.append(colour)
    if not xyz:
        return None
    return PointCloud(xyz=torch.tensor(xyz, dtype=torch.float64), rgb=torch.tensor(rgb, dtype=torch.float64) / 255.0)


def _check_image_lines(file: Path, read: int) -> None:
    """Raise when images.txt holds more image records than pycolmap read. COLMAP's text format
    follows every image line with one line of its 2D points (empty when it has none); a file
    written by hand without those lines loads every other image, the others taken for points,
    and pycolmap says nothing. A record: an integer id, seven numbers, an integer camera id and
    a name that is not a number (a line of 2D points is numbers only). Only the first eleven
    fields of a line are split, so a model with long point lines is read once, quickly."""
    with open(file, encoding="utf-8", errors="replace") as fh:
        records = sum(_image_record(line.split(maxsplit=10)) for line in fh)
    if records > read:
        raise ValueError(f"{file}: {records} lines look like image records (IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME) "
                         f"but pycolmap read {read} images: {POINTS_LINE_HINT}")


POINTS_LINE_HINT = ("COLMAP's text format follows every image line with a line of its 2D points, an empty line when it "
                    "has none; without it the next image is read as points. Add an empty line after each image line")


def _image_record(fields: Sequence[str]) -> bool:
    """Whether a split images.txt line is an image record: an integer id, seven fields, an
    integer camera id and a name that is not a number."""
    if len(fields) < 10 or fields[0].startswith("#") or not (fields[0].isdigit() and fields[8].isdigit()):
        return False
    try:
        float(fields[9])
    except ValueError:
        return True
    return False


def _read(pycolmap, model_dir: Path, fmt: str, have: dict):
    """pycolmap's reading of the model, with an empty points file in place of its own when it
    has none (``have["points3D"]`` empty: _without_tracks asks so of a model that has one)."""
    if fmt in have["points3D"]:
        return pycolmap.Reconstruction(str(model_dir))
    with tempfile.TemporaryDirectory(prefix="mvgs_colmap_") as tmp:
        for f in model_dir.iterdir():
            # the model's points file is not linked: the empty one below would be written through the link
            if f.is_file() and f.suffix == f".{fmt}" and f.stem != "points3D":
                try:  # the model's files as they are (images.bin may be large)
                    os.symlink(f.resolve(), Path(tmp) / f.name)
                except OSError:  # no symlinks here (some Windows setups)
                    shutil.copyfile(f, Path(tmp) / f.name)
        if fmt == "bin":
            (Path(tmp) / "points3D.bin").write_bytes(struct.pack("<Q", 0))
        else:
            (Path(tmp) / "points3D.txt").write_text("")
        return pycolmap.Reconstruction(tmp)


def _intrinsics(cam) -> tuple[np.ndarray, Distortion]:
    """K [3,3] and the lens distortion of a pycolmap camera: the pinhole models, and SIMPLE_RADIAL,
    RADIAL, OPENCV, FULL_OPENCV without its rational terms (k4 = k5 = k6 = 0) and the fisheye models
    OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, SIMPLE_FISHEYE and FISHEYE (the last two
    equidistant, without distortion terms), whose images are undistorted when read; other models
    are refused."""
    model = getattr(cam, "model_name", None) or cam.model.name
    p = [float(v) for v in cam.params]
    dist = Distortion()
    if model == "PINHOLE":
        fx, fy, cx, cy = p
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = p
        fy = fx
    elif model == "SIMPLE_RADIAL":
        fx, cx, cy, k = p
        fy, dist = fx, Distortion(k1=k)
    elif model == "RADIAL":
        fx, cx, cy, k1, k2 = p
        fy, dist = fx, Distortion(k1=k1, k2=k2)
    elif model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        dist = Distortion(k1=k1, k2=k2, p1=p1, p2=p2)
    elif model == "FULL_OPENCV" and not any(p[9:12]):
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = p[:9]
        dist = Distortion(k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)
    elif model == "OPENCV_FISHEYE":
        fx, fy, cx, cy, k1, k2, k3, k4 = p
        dist = Distortion(k1=k1, k2=k2, k3=k3, k4=k4, fisheye=True)
    elif model == "SIMPLE_RADIAL_FISHEYE":
        fx, cx, cy, k = p
        fy, dist = fx, Distortion(k1=k, fisheye=True)
    elif model == "RADIAL_FISHEYE":
        fx, cx, cy, k1, k2 = p
        fy, dist = fx, Distortion(k1=k1, k2=k2, fisheye=True)
    elif model == "SIMPLE_FISHEYE":  # the equidistant lens: theta_d = theta
        fx, cx, cy = p
        fy, dist = fx, Distortion(fisheye=True)
    elif model == "FISHEYE":
        fx, fy, cx, cy = p
        dist = Distortion(fisheye=True)
    else:
        # Splatting renders an ideal pinhole; a rational or thin-prism lens is not resampled here.
        why = " with rational terms k4..k6" if model == "FULL_OPENCV" else ""
        raise ValueError(
            f"camera model {model}{why}: supported are PINHOLE, SIMPLE_PINHOLE, and SIMPLE_RADIAL, RADIAL, OPENCV, "
            "FULL_OPENCV with k4 = k5 = k6 = 0, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, SIMPLE_FISHEYE, "
            "FISHEYE (undistorted when read). Undistort the images first: colmap image_undistorter "
            "--image_path <images> --input_path <sparse/0> --output_path <out> "
            "(then load <out>, which has images/ and sparse/)")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), dist


def _downscaled(K: np.ndarray, width: int, height: int, size: tuple, file: Path, owner: str) -> tuple:
    """(K, width, height) of a camera for its image at ``size``, a copy of the camera's image
    downscaled alike on both axes (Mip-NeRF 360's images_2/4/8: the rounded size of each side over
    one factor); each row of K scales with its axis, as Camera.scaled does. ValueError otherwise,
    naming ``owner`` (what the full size is of: "its camera 3")."""
    w, h = size
    sx, sy = w / width, h / height
    # one factor s for both sides, each rounded or cut to whole pixels: |width / s - w| <= 1 and
    # |height / s - h| <= 1, i.e. the ranges of 1 / s the two sides allow overlap
    if w <= width and h <= height and max((w - 1) / width, (h - 1) / height) <= min((w + 1) / width, (h + 1) / height):
        return np.diag([sx, sy, 1.0]) @ K, w, h
    raise ValueError(f"image {file} is {w}x{h} but {owner} is {width}x{height}, and it is not a copy "
                     f"downscaled alike on both axes (x {sx:.4g}, y {sy:.4g}); give the folder of full-size images, or "
                     "one downscaled by one factor (e.g. images_4)")


def _world_to_camera(image) -> np.ndarray:
    rigid = image.cam_from_world
    if callable(rigid):  # a method since pycolmap 3.12 (rigs/frames), a property before
        rigid = rigid()
    T = np.eye(4)
    T[:3, :] = np.asarray(rigid.matrix(), dtype=np.float64)
    # COLMAP normalises the quaternions it reads; pycolmap keeps them as written, so one rounded
    # to a few decimals in images.txt gives a rotation block that is not orthonormal
    x, y, z, w = np.asarray(rigid.rotation.quat, dtype=np.float64)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(norm) and norm > 1e-6):
        raise ValueError(f"its quaternion (qw, qx, qy, qz) = ({w}, {x}, {y}, {z}) has no direction (norm {norm:.3g})")
    import pycolmap

    T[:3, :3] = np.asarray(pycolmap.Rotation3d(np.array([x, y, z, w]) / norm).matrix(), dtype=np.float64)
    return T


def _split(names: Sequence[str], test_every: Optional[int], test_names: Optional[Iterable[str]],
           model_dir: Path) -> set[str]:
    """Names of the test images (``names`` is sorted)."""
    if test_names is not None:
        if isinstance(test_names, (str, bytes)):
            raise ValueError(f"test_names must be a list of names, got the string {test_names!r}")
        wanted = {normalize_name(n) for n in test_names}
        missing = sorted(wanted - set(names))
        if missing:
            raise ValueError(f"{model_dir}: test_names not in the model: {missing[:5]}"
                             + (" ..." if len(missing) > 5 else ""))
        return wanted
    if test_every is None or test_every == 0:
        return set()
    check_int("test_every", test_every, 0)
    # the original 3DGS "llffhold": indices 0, k, 2k, ... of the name-sorted images
    return {n for i, n in enumerate(names) if i % test_every == 0}


def _points(rec, model_dir: Path) -> Optional[PointCloud]:
    pts = list(rec.points3D.values())
    if not pts:
        warnings.warn(f"the COLMAP model in {model_dir} holds 0 3D points (an empty or absent points3D file): the "
                      "scene has no point cloud (the examples' "
                      "--init makes one, by default triangulated from the training views; an adapter given none "
                      "initialises randomly, where the cameras look)", stacklevel=3)
        return None
    xyz = np.array([p.xyz for p in pts], dtype=np.float64)
    rgb = np.array([p.color for p in pts], dtype=np.float64) / 255.0
    return PointCloud(xyz=torch.from_numpy(xyz), rgb=torch.from_numpy(rgb))


def load_colmap(path, images_dir=None, test_every: Optional[int] = 8,
                test_names: Optional[Iterable[str]] = None,
                background: Optional[Sequence[float]] = None) -> Scene:
    """Load a COLMAP scene.

    Args:
        path: scene folder holding ``sparse/0/`` (or ``sparse/``), or the model folder itself.
        images_dir: folder the model's image names are relative to (names may contain
            subfolders, e.g. "train/r_000.png"). Default: ``path/images`` if it exists, else
            ``path``.
        test_every: every k-th image in name order is a test image (indices 0, k, 2k, ...; the
            original 3DGS "llffhold" with k = 8). None or 0: no test images.
        test_names: explicit test image names; overrides ``test_every``.
        background: RGB in [0,1] to composite RGBA images on; None drops the alpha channel.

    Masks (:meth:`Scene.mask`): a ``masks/`` folder beside the images (``masks_K/`` for images in
    ``images_K/``) holds, per image name N, ``N.png`` (COLMAP's convention, "a/1.jpg.png") or N
    with its extension replaced by ".png" (nerfstudio's); each has its image file's size, and an
    image without one counts all its pixels.
    Returns:
        A :class:`Scene`; camera uids are COLMAP image ids, names are the model's image names.
        Only registered images (with a pose) are used. Every image's size is checked against its
        camera from the file header at load time.
    """
    path = Path(path)
    model_dir = find_colmap_model(path)
    if images_dir is None:
        images_dir = path / "images" if (path / "images").is_dir() else path
    images_dir = Path(images_dir)
    if not images_dir.is_dir():
        raise FileNotFoundError(f"images folder not found: {images_dir}")

    import pycolmap

    check_binary_counts(model_dir)
    rec, read_points = _read_model(pycolmap, model_dir)

    records, undistortions, sources, resized = [], {}, {}, {}
    for image_id, image in rec.images.items():
        # unregistered images have no pose to train with ("registered" before pycolmap 3.12)
        if not getattr(image, "has_pose", getattr(image, "registered", True)):
            continue
        name = check_inside(normalize_name(image.name), images_dir, f"{model_dir}: image {image_id}")
        cam = rec.cameras[image.camera_id]
        try:
            K, dist = _intrinsics(cam)
            width, height = int(cam.width), int(cam.height)
            file = images_dir / name
            if file.is_file():  # a missing one is named below
                size = image_size(file)
                if size != (width, height):  # a downscaled copy (images_4/): its intrinsics
                    K, width, height = _downscaled(K, width, height, size, file, f"its camera {image.camera_id}")
                    resized.setdefault((image.camera_id, cam.width, cam.height), set()).add((width, height))
            if dist:
                und = shared_undistortion(undistortions, K, width, height, dist, f"{model_dir}: camera {image.camera_id}")
                K, width, height = und.K_out, und.width_out, und.height_out
                sources[int(image_id)] = UndistortedImage(file, und)
            camera = Camera(uid=int(image_id), name=name, K=K, world_to_camera=_world_to_camera(image),
                            width=width, height=height)
        except ValueError as err:
            raise ValueError(f"{model_dir}: image {name!r}: {err}") from None
        records.append(camera)
    if not records:
        raise ValueError(f"{model_dir}: the model has no registered images")
    records.sort(key=lambda c: c.name)
    names = [c.name for c in records]
    if len(set(names)) != len(names):
        counts = collections.Counter(names)
        name, n = max(counts.items(), key=lambda kv: kv[1])
        hint = (" (COLMAP's text format ends a name at its first space: images.txt cannot hold names with spaces; "
                "write the model as binary)" if (Path(model_dir) / "images.txt").is_file() else "")
        raise ValueError(f"{model_dir}: duplicate image names in the model: {name!r} appears {n} times{hint}")

    test = _split(names, test_every, test_names, model_dir)
    train_cams = [c for c in records if c.name not in test]
    test_cams = [c for c in records if c.name in test]
    if not train_cams:
        rule = ("test_names lists them all" if test_names is not None else
                f"one image in every {test_every} by name is held out, the first included; give more images, or from Python "
                "load_colmap(..., test_every=None)")
        raise ValueError(f"{model_dir}: the train split is empty: every one of its {len(records)} image(s) is a test "
                         f"view ({rule})")
    files = {c.uid: images_dir / c.name for c in records}
    for c in records:
        if not files[c.uid].is_file():
            raise FileNotFoundError(f"image {c.name!r} of {model_dir} not found at {files[c.uid]} "
                                    "(the model's image names are read relative to the scene's images/ folder, or to the scene "
                                    "folder when it has none; from Python, load_colmap(images_dir=...) names another)")
    if resized:
        LOG.info("%s: images in %s are downscaled copies, each camera scaled to its images: %s", model_dir, images_dir,
                 "; ".join(f"camera {i} {w}x{h} -> " + ", ".join(f"{a}x{b}" for a, b in sorted(to))
                           for (i, w, h), to in sorted(resized.items())))
    masks = _masks(path, images_dir, records, files, sources)
    if masks:
        LOG.info("%s: %d of %d images have a mask: the loss and the test metrics count the pixels it keeps",
                 path, len(masks), len(records))
    return Scene(train_cams, test_cams, {uid: sources.get(uid, f) for uid, f in files.items()},
                 points=read_points or _points(rec, model_dir), background=background, source=path, masks=masks)


def _masks(path: Path, images_dir: Path, records: list, files: dict, sources: dict) -> dict:
    """Per camera uid, its mask file (an UndistortedImage when its image is one), from the masks
    folder load_colmap describes; {} when there is none."""
    suffix = images_dir.name[len("images"):] if images_dir.name.startswith("images") else ""
    places = dict.fromkeys(base / name for name in (f"masks{suffix}", "masks") for base in (images_dir.parent, path))
    folder = next((f for f in places if f.is_dir()), None)  # beside the images, then in the scene folder
    if folder is None:
        return {}
    copy_missing = f" (no masks{suffix}/ for the images in {images_dir.name}/ was found)" if suffix and folder.name == "masks" else ""
    out = {}
    for cam in records:
        name = Path(cam.name)
        found = next((f for f in (folder / f"{cam.name}.png", folder / name.with_suffix(".png")) if f.is_file()), None)
        if found is None:
            continue
        size, want = image_size(found), image_size(files[cam.uid])
        if size != want:
            raise ValueError(f"mask {found} is {size[0]}x{size[1]} but its image {files[cam.uid]} is {want[0]}x{want[1]} "
                             f"(a mask has its image's size){copy_missing}")
        src = sources.get(cam.uid)
        out[cam.uid] = UndistortedImage(found, src.undistortion) if isinstance(src, UndistortedImage) else found
    missing = [cam for cam in records if cam.uid not in out]
    if missing:  # a name the folder does not hold: say so, not train on what the mask would hide
        first = Path(missing[0].name)
        expected = f"{folder / (missing[0].name + '.png')} (COLMAP's naming) or {folder / first.with_suffix('.png')}"
        if not out:
            held = sorted(f.relative_to(folder).as_posix() for f in folder.rglob("*") if f.is_file())[:3]
            raise ValueError(f"{folder} holds no mask for any of the {len(records)} images: for {first} it looks for "
                             f"{expected}; the folder holds {', '.join(held) if held else 'nothing'}"
                             f"{', ...' if len(held) == 3 else ''}. Rename the masks, or move the folder away to "
                             "train on every pixel")
        warnings.warn(f"{folder}: {len(missing)} of {len(records)} images have no mask (for {first}: {expected}); "
                      "they count every pixel", stacklevel=3)
    return out
