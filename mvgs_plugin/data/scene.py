"""The Scene record: cameras, lazily loaded images with a per-factor cache, optional points."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Mapping, Optional, Sequence, Union

import torch

from ..camera import Camera, _check_factor
from .distortion import UndistortedImage
from .images import (check_background, downsample, image_size, masked_downsample, may_have_alpha, read_alpha, read_mask,
                     read_rgb)

__all__ = ["Scene", "PointCloud", "camera_normalization"]

# a file, a loaded [H, W, 3] tensor, or a file resampled for a camera with lens distortion
ImageSource = Union[str, Path, torch.Tensor, UndistortedImage]


@dataclasses.dataclass(frozen=True, eq=False)
class PointCloud:
    """Initial points: xyz [P, 3] float32 (world units), rgb [P, 3] float32 in [0, 1]. shell: how
    many of the last rows are the far background shell that load_scene adds
    (background_points), not the scene's own points: sizes taken from the scene's points (the
    Scaffold-GS voxel, the 4DGS deformation box) leave them out."""

    xyz: torch.Tensor
    rgb: torch.Tensor
    shell: int = 0

    def __post_init__(self) -> None:
        xyz = torch.as_tensor(self.xyz).detach().to("cpu", torch.float32)
        rgb = torch.as_tensor(self.rgb).detach().to("cpu", torch.float32)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"xyz must be [P,3], got {list(xyz.shape)}")
        if tuple(rgb.shape) != tuple(xyz.shape):
            raise ValueError(f"rgb must be [P,3] like xyz {list(xyz.shape)}, got {list(rgb.shape)}")
        if not bool(torch.isfinite(xyz).all()):
            raise ValueError("xyz must be finite")
        if rgb.numel() and not (bool(torch.isfinite(rgb).all()) and rgb.min() >= 0 and rgb.max() <= 1):
            raise ValueError(f"rgb must be finite and in [0,1], got range "
                             f"[{float(rgb.min())}, {float(rgb.max())}]")
        if isinstance(self.shell, bool) or not isinstance(self.shell, int) or not 0 <= self.shell <= len(xyz):
            raise ValueError(f"shell must be an int in [0, {len(xyz)}] (rows of xyz), got {self.shell!r}")
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "rgb", rgb)

    def __len__(self) -> int:
        return self.xyz.shape[0]

    @property
    def own(self) -> torch.Tensor:
        """xyz of the scene's own points (the rows before the shell)."""
        return self.xyz[: len(self) - self.shell]


def camera_normalization(cams: Sequence[Camera]) -> tuple[torch.Tensor, float]:
    """Scene centre and extent as the original 3DGS computes them from the training cameras.

    center = mean of the camera centres [3] (float64); extent = 1.1 x the largest distance of a
    centre from that mean. A rig whose centres all coincide (one camera, or a turntable of
    rotations only) has extent 0, which would zero every extent-scaled learning rate and
    threshold; 1.0 is returned instead, with a warning, so the caller can see it and override.
    """
    if not cams:
        raise ValueError("camera_normalization needs at least one camera")
    centers = torch.stack([c.center for c in cams])
    center = centers.mean(dim=0)
    extent = 1.1 * float(torch.linalg.norm(centers - center, dim=1).max())
    if not extent > 0:
        warnings.warn(f"all {len(cams)} training camera centres coincide; scene extent set to 1.0",
                      stacklevel=2)
        extent = 1.0
    return center, extent


def _keeps_some(mask: torch.Tensor, what: str, cam: Camera) -> torch.Tensor:
    """``mask``, refused when it ignores every pixel of its view."""
    if not bool(mask.any()):
        raise ValueError(f"{what} of camera {cam.name!r} ignores every pixel: nothing of this view would count; "
                         "drop the view, or give a mask that keeps some pixels")
    return mask


def _file_source(cam: Camera, src, check_size: bool, what: str):
    """An image (or mask) source given as a file, or as a file resampled through a lens model,
    checked against its camera: the size the camera expects (the file's header, read when
    check_size), and the undistorted size."""
    if isinstance(src, UndistortedImage):
        und = src.undistortion
        if (cam.width, cam.height) != (und.width_out, und.height_out):
            raise ValueError(f"camera {cam.name!r} is {cam.width}x{cam.height} but its undistorted {what} is "
                             f"{und.width_out}x{und.height_out}")
        file, size = src.path, (und.width, und.height)
    else:
        src = file = Path(src)
        size = (cam.width, cam.height)
    if check_size:
        w, h = image_size(file)
        if (w, h) != size:
            raise ValueError(f"{what} {file} is {w}x{h} but its camera {cam.name!r} expects {size[0]}x{size[1]}")
    return src


def default_cache_bytes() -> int:
    """How many bytes of decoded images a Scene holds by default: half the machine's memory
    (8 GiB where the system does not say). A scene whose images do not fit (a multi-camera video,
    a capture at full resolution) reads the least recently used ones again when asked."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (AttributeError, ValueError, OSError):
        return 8 << 30


def _check_cache_bytes(value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"cache_bytes must be an int >= 0 (bytes of decoded images to hold), got {value!r}")
    return value


def _from_file(sources: Mapping, key: tuple) -> bool:
    """Whether the cached image ``key`` = (uid, factor) can be made again from a file: any level
    below full resolution, and a full-resolution image not given in memory."""
    return key[1] != 1.0 or not isinstance(sources[key[0]], torch.Tensor)


class Scene:
    """Cameras and images of one scene.

    Args:
        train_cameras, test_cameras: lists of :class:`Camera` (uids unique across both).
        images: per camera uid, an image file path (decoded lazily on first use, then cached),
            an already loaded float [H, W, 3] tensor in [0, 1], or an
            :class:`~mvgs_plugin.data.distortion.UndistortedImage` (a file taken with lens
            distortion, resampled for the camera given here, its undistorted pinhole).
        points: optional initial :class:`PointCloud`.
        background: RGB in [0, 1] that images with alpha were composited on, or None (alpha
            dropped / no alpha). Renderers should use the same colour behind the Gaussians.
        check_sizes: read every image file's header now and raise if its size differs from its
            camera's (cheap: PNG and JPEG headers are parsed, not decoded).
        masks: optional, per camera uid (any subset), which pixels the loss and the metrics count:
            a mask file (:func:`~mvgs_plugin.data.images.read_mask`: non-zero keeps a pixel,
            nerfstudio's ``mask_path``), a float [H, W] or [H, W, 1] tensor of weights in [0, 1],
            or an :class:`~mvgs_plugin.data.distortion.UndistortedImage` (a mask file taken with
            the lens distortion of its image). A camera without one counts every pixel.
        cache_bytes: decoded images read from files held at most (None:
            :func:`default_cache_bytes`, half the machine's memory); beyond it the least recently
            used are let go and read again when asked. Images given in memory are always held.

    Attributes:
        center: [3] float64 and extent (float): see :func:`camera_normalization`.
        points_origin: where ``points`` came from, for logs and metrics.json ("N points given
            with the scene", or what :func:`~mvgs_plugin.data.load_scene` made for a scene without).
        background_origin: how ``background`` was chosen ("given", "none", or what the NeRF
            loaders found in the images).
    """

    def __init__(self, train_cameras: Sequence[Camera], test_cameras: Sequence[Camera],
                 images: Mapping[int, ImageSource], points: Optional[PointCloud] = None,
                 background: Optional[Sequence[float]] = None, check_sizes: bool = True,
                 source: Optional[Path] = None, masks: Optional[Mapping[int, ImageSource]] = None,
                 cache_bytes: Optional[int] = None) -> None:
        self.train_cameras = list(train_cameras)
        self.test_cameras = list(test_cameras)
        self.points = points
        # how the initial points came to be (load_scene sets it when it made them)
        self.points_origin = "no points" if points is None else f"{len(points)} points given with the scene"
        self.background = check_background(background)
        # how the background came to be (the NeRF loaders say more; logged and in metrics.json)
        self.background_origin = "given" if self.background is not None else "none"
        self.source = None if source is None else Path(source)
        if not self.train_cameras:
            where = f" {self.source}" if self.source is not None else ""
            raise ValueError(f"scene{where} has no training cameras")
        self._by_uid: dict[int, Camera] = {}
        for cam in self.train_cameras + self.test_cameras:
            if not isinstance(cam, Camera):
                raise ValueError(f"cameras must be Camera instances, got {type(cam).__name__}")
            if cam.uid in self._by_uid:
                raise ValueError(f"duplicate camera uid {cam.uid} ({cam.name!r} and "
                                 f"{self._by_uid[cam.uid].name!r})")
            self._by_uid[cam.uid] = cam
        self._sources: dict[int, ImageSource] = {}
        # decoded images by (uid, factor), least recently used first; those read from files are let
        # go beyond cache_bytes (read again when asked), those given in memory stay
        self._cache: OrderedDict[tuple[int, float], torch.Tensor] = OrderedDict()
        self._cache_used = 0  # bytes of the file-read images held
        self.cache_bytes = default_cache_bytes() if cache_bytes is None else _check_cache_bytes(cache_bytes)
        self._digests: dict[int, str] = {}  # image_digest(), per camera uid
        for uid, cam in self._by_uid.items():
            if uid not in images:
                raise ValueError(f"no image given for camera {cam.name!r} (uid {uid})")
            self._add_source(cam, images[uid], check_sizes)
        self._mask_sources: dict[int, ImageSource] = {}
        self._mask_cache: dict[tuple[int, float], torch.Tensor] = {}
        self._coverage_cache: dict[tuple[int, float], Optional[torch.Tensor]] = {}
        for uid, src in (masks or {}).items():
            if uid not in self._by_uid:
                raise ValueError(f"a mask is given for camera uid {uid!r}, which is not one of the scene's cameras")
            self._add_mask_source(self._by_uid[uid], src, check_sizes)
        self.center, self.extent = camera_normalization(self.train_cameras)

    def _add_source(self, cam: Camera, src: ImageSource, check_size: bool) -> None:
        if isinstance(src, torch.Tensor):
            img = src.detach().to("cpu", torch.float32)
            if tuple(img.shape) != (cam.height, cam.width, 3):
                raise ValueError(f"image for camera {cam.name!r} must be [{cam.height},{cam.width},3], "
                                 f"got {list(img.shape)}")
            if not (bool(torch.isfinite(img).all()) and img.min() >= 0 and img.max() <= 1):
                raise ValueError(f"image for camera {cam.name!r} must be finite and in [0,1]")
            self._cache[(cam.uid, 1.0)] = img
        else:
            src = _file_source(cam, src, check_size, "image")
        self._sources[cam.uid] = src

    def _add_mask_source(self, cam: Camera, src: ImageSource, check_size: bool) -> None:
        if isinstance(src, torch.Tensor):
            m = src.detach().to("cpu", torch.float32)
            m = m[:, :, None] if m.ndim == 2 else m
            if tuple(m.shape) != (cam.height, cam.width, 1):
                raise ValueError(f"mask for camera {cam.name!r} must be [{cam.height},{cam.width}] or "
                                 f"[{cam.height},{cam.width},1], got {list(src.shape)}")
            if not (bool(torch.isfinite(m).all()) and m.min() >= 0 and m.max() <= 1):
                raise ValueError(f"mask for camera {cam.name!r} must be finite weights in [0,1]")
            self._mask_cache[(cam.uid, 1.0)] = _keeps_some(m, "mask", cam)
        else:
            src = _file_source(cam, src, check_size, "mask")
        self._mask_sources[cam.uid] = src

    def _level(self, cam: Camera, factor) -> tuple[Camera, float]:
        """The scene's own camera for ``cam`` (its full-resolution camera) and the checked factor."""
        base = self._by_uid.get(getattr(cam, "uid", None))
        if base is None:
            raise KeyError(f"camera {cam!r} is not part of this scene")
        if (cam.width, cam.height) != (base.width, base.height):
            raise ValueError(f"pass the full-resolution camera ({base.width}x{base.height}) and a "
                             f"factor, got a {cam.width}x{cam.height} camera")
        return base, _check_factor(factor)

    @property
    def has_masks(self) -> bool:
        """Whether any camera has a mask (then :meth:`mask` gives one for every camera)."""
        return bool(self._mask_sources)

    def masked(self, cameras: Optional[Sequence[Camera]] = None) -> list[Camera]:
        """The cameras (default: all) that have a mask of their own."""
        return [c for c in (self.cameras if cameras is None else cameras) if c.uid in self._mask_sources]

    def mask(self, cam: Camera, factor: float = 1) -> Optional[torch.Tensor]:
        """The pixel weights of ``cam``'s image at ``factor`` as float32 [H', W', 1] in [0, 1]:
        its mask, downsampled as the image is (a pixel on a mask's edge gets a weight between 0
        and 1), ones for a camera without a mask in a scene that has masks, and None when the
        scene has none. Cached; do not modify the result in place."""
        if not self._mask_sources:
            return None
        base, factor = self._level(cam, factor)
        key = (base.uid, factor)
        if key not in self._mask_cache:
            if base.uid not in self._mask_sources:
                small = base.scaled(factor) if factor != 1.0 else base
                self._mask_cache[key] = torch.ones(small.height, small.width, 1)
            elif factor == 1.0:
                self._mask_cache[key] = self._full_mask(base)
            else:
                small = base.scaled(factor)
                self._mask_cache[key] = downsample(self._full_mask(base, keep=False), small.width,
                                                   small.height).clamp(0.0, 1.0)
        return self._mask_cache[key]

    def coverage(self, cam: Camera, factor: float = 1) -> Optional[torch.Tensor]:
        """How much of each pixel of ``cam``'s image at ``factor`` its content covers, float32
        [H', W', 1] in [0, 1]: the image file's alpha channel (what :meth:`image` composites on
        ``background``), downsampled as the image is; None when the scene has no background
        (alpha dropped), the file has no alpha or is opaque everywhere, or the image was given as
        a tensor or is read through a lens model. Where it is not None it tells content from
        backdrop whatever their colours (a black part on a black backdrop); the initial points'
        silhouettes use it (:func:`~mvgs_plugin.data.init.on_silhouettes`). Cached; do not modify
        the result in place."""
        base, factor = self._level(cam, factor)
        key = (base.uid, factor)
        if key not in self._coverage_cache:
            src = self._sources[base.uid]
            alpha = None
            if self.background is not None and isinstance(src, Path) and may_have_alpha(src):
                alpha = read_alpha(src)
            if alpha is not None and tuple(alpha.shape) != (base.height, base.width, 1):
                raise ValueError(f"image {src} is {alpha.shape[1]}x{alpha.shape[0]} but its camera {base.name!r} "
                                 f"expects {base.width}x{base.height}")
            if alpha is not None and factor != 1.0:
                small = base.scaled(factor)
                alpha = downsample(alpha, small.width, small.height).clamp(0.0, 1.0)
            self._coverage_cache[key] = alpha
        return self._coverage_cache[key]

    def _full_mask(self, cam: Camera, keep: bool = True) -> torch.Tensor:
        """The full-resolution mask, cached when ``keep`` (else read and not held)."""
        key = (cam.uid, 1.0)
        if key not in self._mask_cache:
            src = self._mask_sources[cam.uid]
            m = src.read_mask() if isinstance(src, UndistortedImage) else read_mask(src)
            if tuple(m.shape) != (cam.height, cam.width, 1):
                raise ValueError(f"mask {src} is {m.shape[1]}x{m.shape[0]} but its camera {cam.name!r} expects "
                                 f"{cam.width}x{cam.height}")
            _keeps_some(m, f"mask {src}", cam)
            if not keep:
                return m
            self._mask_cache[key] = m
        return self._mask_cache[key]

    @property
    def cameras(self) -> list[Camera]:
        """Train then test cameras."""
        return self.train_cameras + self.test_cameras

    def camera(self, name: str) -> Camera:
        """The camera whose image name is ``name``."""
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"no camera named {name!r}")

    def image(self, cam: Camera, factor: float = 1) -> torch.Tensor:
        """The image of ``cam`` downsampled by ``factor`` (1 = full resolution).

        ``cam`` is the scene's full-resolution camera (its uid selects the image); the result is
        float32 [H', W', 3] in [0, 1] with (W', H') = ``cam.scaled(factor)``'s size, made once
        per (camera, factor) with :func:`~mvgs_plugin.data.images.downsample` and cached (within
        ``cache_bytes``: one let go is made again when asked).
        The cached tensor itself is returned: do not modify it in place. Asked for a level
        below full resolution, only that level is kept: the full image is read, downsampled
        and let go (a 4K capture trained at 1/4 holds 1/16 of its pixels). An image with a mask
        (:meth:`mask`) is downsampled as a weighted mean, downsample(image x mask) /
        downsample(mask), so a pixel the mask ignores gives no colour to any level (0 where a
        level's pixel has no kept pixel under it).
        """
        base, factor = self._level(cam, factor)
        key = (base.uid, factor)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        if factor == 1.0:
            return self._full(base)
        full = self._full(base, keep=False)
        small = base.scaled(factor)
        if base.uid in self._mask_sources:
            mean, _ = masked_downsample(full, self._full_mask(base, keep=False),
                                        lambda x: downsample(x, small.width, small.height))
            img = mean.clamp(0.0, 1.0)
        else:
            img = downsample(full, small.width, small.height)
        return self._remember(key, img)

    def _remember(self, key: tuple[int, float], img: torch.Tensor) -> torch.Tensor:
        """Cache an image read from a file, letting the least recently used such images go while
        the held ones exceed ``cache_bytes`` (the one just made stays)."""
        self._cache[key] = img
        self._cache_used += img.numel() * img.element_size()
        if self._cache_used > self.cache_bytes:
            for old in [k for k in self._cache if k != key]:
                if self._cache_used <= self.cache_bytes:
                    break
                if _from_file(self._sources, old):
                    gone = self._cache.pop(old)
                    self._cache_used -= gone.numel() * gone.element_size()
        return img

    def read(self, cam: Camera) -> torch.Tensor:
        """The full-resolution image of ``cam``, read now and not cached (a cached one is returned
        as it is): for a look at every image at load time (the border colour, triangulation)
        that does not hold them all in memory."""
        return self._full(self._level(cam, 1)[0], keep=False)

    def read_mask(self, cam: Camera) -> Optional[torch.Tensor]:
        """:meth:`read` for the mask: the full-resolution mask of ``cam``, not cached (ones for a
        camera without one, None in a scene without masks)."""
        base, _ = self._level(cam, 1)
        if not self._mask_sources:
            return None
        if base.uid not in self._mask_sources:
            return torch.ones(base.height, base.width, 1)
        return self._full_mask(base, keep=False)

    def _full(self, cam: Camera, keep: bool = True) -> torch.Tensor:
        """The full-resolution image, cached when ``keep`` (else read and not held)."""
        key = (cam.uid, 1.0)
        if key in self._cache:
            self._cache.move_to_end(key)
        else:
            src, mask = self._sources[cam.uid], self._mask_sources.get(cam.uid)
            if isinstance(src, UndistortedImage):
                img = src.read_masked(self.background, mask) if isinstance(mask, UndistortedImage) else src.read(self.background)
            else:
                img = read_rgb(src, self.background)
            if tuple(img.shape) != (cam.height, cam.width, 3):
                raise ValueError(f"image {self._sources[cam.uid]} is {img.shape[1]}x{img.shape[0]} "
                                 f"but its camera {cam.name!r} expects {cam.width}x{cam.height}")
            if not keep:
                return img
            return self._remember(key, img)
        return self._cache[key]

    def image_file(self, cam: Camera) -> Optional[Path]:
        """The file the image of ``cam`` is read from, or None for an image given as a tensor (a
        file taken with lens distortion holds the distorted image: see :meth:`undistortion`)."""
        base = self._by_uid.get(getattr(cam, "uid", None))
        if base is None:
            raise KeyError(f"camera {cam!r} is not part of this scene")
        src = self._sources[base.uid]
        if isinstance(src, UndistortedImage):
            return src.path
        return None if isinstance(src, torch.Tensor) else Path(src)

    def image_digest(self, cam: Camera) -> str:
        """A digest of the content ``cam``'s image comes from: the bytes of its file (a file taken
        with lens distortion: the distorted file), or of its tensor given in memory; 16 hex
        digits of SHA-1, computed once. A checkpoint records the training views' digests, so
        resuming it on other images with the same cameras (another render of a rig, a folder of
        re-exposed photos) is refused rather than trained on silently. The file is hashed as it
        is, not decoded: the same pixels saved again in another format give another digest."""
        base, _ = self._level(cam, 1)
        if base.uid not in self._digests:
            src = self._sources[base.uid]
            h = hashlib.sha1()
            if isinstance(src, torch.Tensor):
                h.update(self._cache[(base.uid, 1.0)].numpy().tobytes())
            else:
                with open(src.path if isinstance(src, UndistortedImage) else src, "rb") as f:
                    for block in iter(lambda: f.read(1 << 20), b""):
                        h.update(block)
            self._digests[base.uid] = h.hexdigest()[:16]
        return self._digests[base.uid]

    def mask_file(self, cam: Camera) -> Optional[Path]:
        """The file the mask of ``cam`` is read from (a mask taken with lens distortion: the
        distorted file), or None for a camera without a mask or with one given as a tensor."""
        base, _ = self._level(cam, 1)
        src = self._mask_sources.get(base.uid)
        if isinstance(src, UndistortedImage):
            return src.path
        return None if src is None or isinstance(src, torch.Tensor) else Path(src)

    def undistortion(self, cam: Camera):
        """The :class:`~mvgs_plugin.data.distortion.Undistortion` the image of ``cam`` is
        resampled with (its file holds the distorted image), or None when the file is the
        camera's image as it is."""
        base = self._by_uid.get(getattr(cam, "uid", None))
        if base is None:
            raise KeyError(f"camera {cam!r} is not part of this scene")
        src = self._sources[base.uid]
        return src.undistortion if isinstance(src, UndistortedImage) else None

    def subset(self, cameras: Sequence[Camera], untimed: bool = False) -> "Scene":
        """A scene whose training views are ``cameras`` (some of this scene's, any split) and with
        no test views, reading the same image and mask sources with the same background (no
        points). ``untimed``: the cameras without their time (a synchronized rig's views of one
        instant, seen as a still scene)."""
        cams = []
        for cam in cameras:
            base = self._by_uid.get(getattr(cam, "uid", None))
            if base is None:
                raise KeyError(f"camera {cam!r} is not part of this scene")
            cams.append(dataclasses.replace(base, time=None) if untimed else base)
        images = {c.uid: (self._full(c) if isinstance(self._sources[c.uid], torch.Tensor) else self._sources[c.uid])
                  for c in cams}
        masks = {c.uid: self._mask_sources[c.uid] for c in cams if c.uid in self._mask_sources}
        sub = Scene(cams, [], images, background=self.background, check_sizes=False, source=self.source, masks=masks)
        sub.background_origin = self.background_origin
        return sub

    def clear_cache(self) -> None:
        """Forget decoded images, masks and coverage loaded from files (in-memory ones are kept)."""
        self._cache = OrderedDict((k, v) for k, v in self._cache.items() if not _from_file(self._sources, k))
        self._cache_used = 0
        self._mask_cache = {k: v for k, v in self._mask_cache.items()
                            if k[1] == 1.0 and isinstance(self._mask_sources.get(k[0]), torch.Tensor)}
        self._coverage_cache = {}

    def __repr__(self) -> str:
        pts = "no points" if self.points is None else f"{len(self.points)} points"
        masks = f", {len(self._mask_sources)} masks" if self._mask_sources else ""
        return (f"Scene({self.source or 'in memory'}: {len(self.train_cameras)} train, "
                f"{len(self.test_cameras)} test, {pts}{masks}, extent={self.extent:.4g})")
