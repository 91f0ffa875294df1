"""Lens distortion: an ideal pinhole camera, and its images, from a distorted one.

Splatting renders an ideal pinhole. A capture whose camera model has lens distortion (COLMAP's
SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV without its rational terms; nerfstudio's
``k1``..``k4``, ``p1``, ``p2``; and the fisheye models OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE,
RADIAL_FISHEYE, SIMPLE_FISHEYE, FISHEYE) is loaded as the pinhole camera with the same focal
lengths whose image is the largest axis-aligned rectangle every pixel of which the distorted
image saw, and each image is resampled onto it (bilinear) when it is read. COLMAP's
image_undistorter follows the same idea (same focal lengths, the border sampled at pixel
centres; its crop is placed about the principal point, so it is not the same rectangle); here
it happens in memory, so the scene folder stays as it is and nothing is written. An image with
a mask is resampled as the weighted mean of its kept pixels.

The model, in normalised camera coordinates (x, y) = (X / Z, Y / Z), r² = x² + y²:

    radial = 1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸
    x_d = x radial + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y

and the pixel is (fx x_d + cx, fy y_d + cy), pixel centres at +0.5 (COLMAP's, and this
package's, convention). A fisheye lens (OpenCV's fisheye model, Kannala-Brandt; ``fisheye=True``)
bends the angle from the axis instead, θ = atan(r):

    θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸),   (x_d, y_d) = (θ_d / r) (x, y)

A pinhole holds rays up to 90° from the axis only, and a wide one stretches its edges: the
pinhole kept is the rectangle the distorted image's edge midpoints enclose, refused when that
is more than twice the capture's size per axis (COLMAP's undistorter bounds its scale alike).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

__all__ = ["Distortion", "Undistortion", "UndistortedImage", "shared_undistortion"]

_NEWTON_STEPS = 50
_INVERSE_TOLERANCE = 1e-10  # in normalised coordinates: 1e-7 px at a focal length of 1000 px
# an output larger, or smaller, than this many times the input per axis is refused (a lens whose
# inverse runs away, or coefficients in the wrong units: k1 = 100 in pixels would keep 6 % of a
# 96 px image); COLMAP's undistorter bounds its scale alike (0.2 to 2 by default)
_MAX_GROWTH = 2.0


@dataclasses.dataclass(frozen=True)
class Distortion:
    """Radial (k1..k4) and tangential (p1, p2) lens distortion coefficients; with fisheye=True
    the k's bend the angle from the axis (OpenCV's fisheye model; p1 = p2 = 0)."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    fisheye: bool = False

    def __post_init__(self) -> None:
        for f in _COEFFICIENTS:
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"distortion coefficient {f} must be a finite number, got {v!r}")
        if not isinstance(self.fisheye, bool):
            raise ValueError(f"fisheye must be True or False, got {self.fisheye!r}")
        if self.fisheye and (self.p1 or self.p2):
            raise ValueError(f"a fisheye lens has no tangential terms (OpenCV's fisheye model), got p1={self.p1:g}, "
                             f"p2={self.p2:g}")

    def __bool__(self) -> bool:  # a fisheye with k = 0 is the equidistant lens, not a pinhole
        return self.fisheye or any(getattr(self, f) != 0.0 for f in _COEFFICIENTS)

    def describe(self) -> str:
        terms = ", ".join(f"{f}={getattr(self, f):g}" for f in _COEFFICIENTS if getattr(self, f) != 0.0)
        if self.fisheye:
            return f"fisheye ({terms or 'equidistant'})"
        return terms or "none"

    def _angle(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fisheye model's θ_d(θ) and dθ_d/dθ at the angles ``t`` from the axis."""
        t2 = t * t
        poly = 1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4)))
        dpoly = 1.0 + t2 * (3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4)))
        return t * poly, dpoly

    def _not_invertible(self) -> ValueError:
        return ValueError(f"lens distortion {self.describe()}: it cannot be inverted over the image (the model "
                          "folds over itself there, or its coefficients are not in normalised units)")

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates of undistorted ones (float64 arrays)."""
        if self.fisheye:
            r = np.hypot(x, y)
            td, _ = self._angle(np.arctan(r))
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(r > 1e-12, td / r, 1.0)  # θ_d / r -> 1 on the axis
            return x * scale, y * scale
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def _jacobian(self, x: np.ndarray, y: np.ndarray):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))
        dradial = self.k1 + r2 * (2.0 * self.k2 + r2 * (3.0 * self.k3 + r2 * 4.0 * self.k4))  # d radial / d r²
        xx = radial + 2.0 * x * x * dradial + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        xy = 2.0 * x * y * dradial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        yy = radial + 2.0 * y * y * dradial + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return xx, xy, xy, yy  # d xd/dx, d xd/dy, d yd/dx, d yd/dy

    def undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates of distorted ones, by Newton's method from
        (xd, yd); ValueError when it does not converge (a lens model that folds over itself
        inside the image). A fisheye's ray 90° or more from the axis has no pinhole coordinates:
        it comes back as infinite (x, y) along its direction."""
        if self.fisheye:
            return self._undistort_fisheye(np.asarray(xd, dtype=np.float64), np.asarray(yd, dtype=np.float64))
        x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
        for _ in range(_NEWTON_STEPS):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            if np.abs(ex).max(initial=0.0) < _INVERSE_TOLERANCE and np.abs(ey).max(initial=0.0) < _INVERSE_TOLERANCE:
                return x, y
            a, b, c, d = self._jacobian(x, y)
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                x, y = x - (d * ex - b * ey) / det, y - (a * ey - c * ex) / det
            if not (np.isfinite(x).all() and np.isfinite(y).all()):
                break
        raise self._not_invertible()

    def _undistort_fisheye(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """θ from θ_d = hypot(x_d, y_d) by Newton's method on the (radial, monotone) lens
        polynomial; then r = tan θ along (x_d, y_d)."""
        target = np.hypot(xd, yd)
        t = target.copy()
        for _ in range(_NEWTON_STEPS):
            td, dpoly = self._angle(t)
            err = td - target
            if np.abs(err).max(initial=0.0) < _INVERSE_TOLERANCE:
                break
            if not (dpoly > 0).all():  # the polynomial turns back: two angles land on one radius
                raise self._not_invertible()
            t = t - err / dpoly
        else:
            raise self._not_invertible()
        if not np.isfinite(t).all():
            raise self._not_invertible()
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(t < 0.5 * math.pi, np.tan(np.minimum(t, 0.5 * math.pi - 1e-12)), np.inf)
            scale = np.where(target > 1e-12, r / target, 1.0)
        return xd * scale, yd * scale


_COEFFICIENTS = ("k1", "k2", "k3", "k4", "p1", "p2")


class Undistortion:
    """The pinhole camera a distorted one becomes, and the resampling of its images.

    ``K``, ``width``, ``height``: the distorted camera. ``K_out``, ``width_out``,
    ``height_out``: the pinhole camera, with K's focal lengths and the largest rectangle whose
    pixels all lie inside the distorted image. Shared by every image of one camera; the sampling
    grid is made on first use.
    """

    def __init__(self, K: np.ndarray, width: int, height: int, distortion: Distortion, where: str = "") -> None:
        self.K = np.asarray(K, dtype=np.float64)
        self.width, self.height, self.distortion = int(width), int(height), distortion
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        prefix = f"{where}: " if where else ""
        # the outer ring of pixel centres, undistorted; the inner rectangle of what they enclose
        u = np.arange(self.width, dtype=np.float64) + 0.5
        v = np.arange(self.height, dtype=np.float64) + 0.5
        edges = {"left": (np.full_like(v, u[0]), v), "right": (np.full_like(v, u[-1]), v),
                 "top": (u, np.full_like(u, v[0])), "bottom": (u, np.full_like(u, v[-1]))}
        try:
            inner = {k: distortion.undistort((pu - cx) / fx, (pv - cy) / fy) for k, (pu, pv) in edges.items()}
        except ValueError as err:
            raise ValueError(f"{prefix}{err}") from None
        x0, x1 = inner["left"][0].max(), inner["right"][0].min()
        y0, y1 = inner["top"][1].max(), inner["bottom"][1].min()
        if not all(np.isfinite(v) for v in (x0, x1, y0, y1)):  # an edge ray at or beyond 90 degrees off the axis
            raise ValueError(f"{prefix}lens distortion {distortion.describe()}: the capture sees 180 degrees or more "
                             f"across its {self.width}x{self.height} px; no pinhole image holds that view (crop the "
                             "capture, or split it into narrower views)")
        w_out, h_out = math.floor((x1 - x0) * fx), math.floor((y1 - y0) * fy)
        if not (self.width / _MAX_GROWTH <= w_out <= _MAX_GROWTH * self.width
                and self.height / _MAX_GROWTH <= h_out <= _MAX_GROWTH * self.height):
            raise ValueError(f"{prefix}lens distortion {distortion.describe()}: the undistorted image would be "
                             f"{w_out}x{h_out} px for a {self.width}x{self.height} px capture; are the coefficients "
                             "in normalised units (as COLMAP and OpenCV write them)?")
        self.width_out, self.height_out = w_out, h_out
        # centred in the rectangle: a half-pixel margin left over splits between both sides
        self.K_out = np.array([[fx, 0.0, -(x0 + 0.5 * (x1 - x0 - w_out / fx)) * fx],
                               [0.0, fy, -(y0 + 0.5 * (y1 - y0 - h_out / fy)) * fy],
                               [0.0, 0.0, 1.0]])
        self._grid: Optional[torch.Tensor] = None

    def source_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """[H_out, W_out] pixel coordinates in the distorted image of every output pixel centre."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        i = np.arange(self.width_out, dtype=np.float64) + 0.5
        j = np.arange(self.height_out, dtype=np.float64) + 0.5
        x = (i[None, :] - self.K_out[0, 2]) / fx
        y = (j[:, None] - self.K_out[1, 2]) / fy
        xd, yd = self.distortion.distort(*np.broadcast_arrays(x, y))
        return fx * xd + cx, fy * yd + cy

    def grid(self) -> torch.Tensor:
        """[1, H_out, W_out, 2] sampling grid for ``torch.nn.functional.grid_sample``
        (align_corners=False: -1 and 1 are the image's outer edges)."""
        if self._grid is None:
            su, sv = self.source_pixels()
            g = np.stack([2.0 * su / self.width - 1.0, 2.0 * sv / self.height - 1.0], axis=-1)
            self._grid = torch.from_numpy(g).to(torch.float32)[None]
        return self._grid

    def apply(self, image: torch.Tensor) -> torch.Tensor:
        """The pinhole image [H_out, W_out, C] of a distorted one [H, W, C] (bilinear; C = 3 for
        an image, 1 for a mask)."""
        if image.ndim != 3 or tuple(image.shape[:2]) != (self.height, self.width) or image.shape[2] < 1:
            raise ValueError(f"an image for this camera must be [{self.height}, {self.width}, C], got {list(image.shape)}")
        out = torch.nn.functional.grid_sample(image.permute(2, 0, 1)[None].to(torch.float32), self.grid(),
                                              mode="bilinear", padding_mode="border", align_corners=False)
        return out[0].permute(1, 2, 0).clamp(0.0, 1.0).contiguous()


def shared_undistortion(cache: dict, K: np.ndarray, width: int, height: int, distortion: Distortion,
                        where: str = "") -> Undistortion:
    """The Undistortion of a camera from ``cache``, made on its first image: one resampling grid
    per distinct camera (intrinsics, size, lens), shared by all its images."""
    key = (np.asarray(K, dtype=np.float64).tobytes(), int(width), int(height), distortion)
    if key not in cache:
        cache[key] = Undistortion(K, width, height, distortion, where)
    return cache[key]


@dataclasses.dataclass(frozen=True)
class UndistortedImage:
    """A :class:`~mvgs_plugin.data.Scene` image source: the file as the pinhole camera of
    ``undistortion`` sees it."""

    path: Path
    undistortion: Undistortion

    def read(self, background: Optional[Sequence[float]]) -> torch.Tensor:
        from .images import read_rgb

        return self.undistortion.apply(read_rgb(self.path, background))

    def read_mask(self) -> torch.Tensor:
        """The file read as a mask (:func:`~mvgs_plugin.data.images.read_mask`), resampled as
        the image: a pixel on the mask's edge gets a weight between 0 and 1."""
        from .images import read_mask

        return self.undistortion.apply(read_mask(self.path))

    def read_masked(self, background: Optional[Sequence[float]], mask: "UndistortedImage") -> torch.Tensor:
        """:meth:`read` for an image with a mask (``mask``, of the same camera): the weighted mean
        of its kept pixels, resample(image x mask) / resample(mask), so a pixel on the mask's edge
        takes no colour from the ignored side (0 where no kept pixel reaches)."""
        from .images import masked_downsample, read_mask, read_rgb

        image, weights = read_rgb(self.path, background), read_mask(mask.path)
        if image.shape[:2] != weights.shape[:2]:
            raise ValueError(f"mask {mask.path} is {weights.shape[1]}x{weights.shape[0]} but its image {self.path} is "
                             f"{image.shape[1]}x{image.shape[0]} (a mask has its image's size)")
        return masked_downsample(image, weights, self.undistortion.apply)[0]
