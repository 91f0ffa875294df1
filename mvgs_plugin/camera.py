"""Pinhole cameras in the project's fixed convention.

Convention (see docs/design.md): OpenCV camera axes (x right, y down, z forward), a world-to-camera
rigid transform ``world_to_camera`` [4, 4] and a pinhole matrix ``K`` [3, 3] that maps camera
coordinates to *pixel* coordinates in which pixel (i, j) (column i, row j) has its centre at
(i + 0.5, j + 0.5). The image covers [0, width] x [0, height] in those coordinates.

Storage: ``K`` and ``world_to_camera`` are float64 torch tensors on the CPU. float64 because
poses from COLMAP or Blender are double precision and camera centres far from the origin lose
millimetres in float32; CPU because a camera is metadata, and renderers move what they need with
:func:`stack_cameras` (which also chooses the dtype, float32 by default).
"""

from __future__ import annotations

import dataclasses
import math
import operator
from typing import Optional, Sequence

import numpy as np
import torch

__all__ = ["Camera", "stack_cameras", "scaled_size", "ROTATION_TOL"]

# Largest accepted |R^T R - I| entry. Poses stored in float32 (Blender json) are orthonormal
# to ~1e-7; 1e-4 accepts those and still rejects matrices that carry a scale or shear, which
# the renderers would silently mis-handle.
ROTATION_TOL = 1e-4


def _as_float64_matrix(value, shape: tuple[int, int], what: str) -> torch.Tensor:
    """Return ``value`` as a detached float64 CPU tensor of ``shape``; raise with its shape."""
    if isinstance(value, torch.Tensor):
        t = value.detach().to(device="cpu", dtype=torch.float64)
    else:
        try:
            t = torch.as_tensor(np.asarray(value, dtype=np.float64))
        except (TypeError, ValueError) as err:
            raise ValueError(f"{what} must be a numeric [{shape[0]},{shape[1]}] matrix: {err}") from None
    if tuple(t.shape) != shape:
        got = ",".join(str(d) for d in t.shape)
        raise ValueError(f"{what} must be [{shape[0]},{shape[1]}], got [{got}]")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{what} must be finite, got {t.tolist()}")
    return t.clone()


def _check_K(K: torch.Tensor) -> None:
    """Pinhole only: positive focals, zero skew, last row [0, 0, 1]."""
    fx, fy = float(K[0, 0]), float(K[1, 1])
    if fx <= 0 or fy <= 0:
        raise ValueError(f"K must have positive fx, fy, got fx={fx}, fy={fy}")
    # Renderers read only fx, fy, cx, cy; a skew or a non-canonical last row would be ignored
    # without a word, so reject it here.
    tol = 1e-9 * max(fx, fy, 1.0)
    off = [float(K[0, 1]), float(K[1, 0]), float(K[2, 0]), float(K[2, 1])]
    if any(abs(v) > tol for v in off) or abs(float(K[2, 2]) - 1.0) > 1e-9:
        raise ValueError(f"K must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")


def _check_rigid(T: torch.Tensor, what: str) -> None:
    """A proper rigid transform: orthonormal rotation with det +1, last row [0, 0, 0, 1]."""
    last = T[3]
    if float((last - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype)).abs().max()) > 1e-9:
        raise ValueError(f"{what} must have last row [0,0,0,1], got {last.tolist()}")
    R = T[:3, :3]
    err = float((R.T @ R - torch.eye(3, dtype=T.dtype)).abs().max())
    if err > ROTATION_TOL:
        raise ValueError(
            f"{what} rotation block must be orthonormal (max |R^T R - I| = {err:.6g} > "
            f"{ROTATION_TOL}), got {R.tolist()}"
        )
    det = float(torch.linalg.det(R))
    if det <= 0:
        raise ValueError(f"{what} rotation block must have det +1 (no reflection), got det={det:.6g}")


def _positive_int(value, what: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{what} must be a positive int, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"{what} must be a positive int, got {value!r}") from None
    if v <= 0:
        raise ValueError(f"{what} must be a positive int, got {v}")
    return v


def scaled_size(width: int, height: int, s: float) -> tuple[int, int]:
    """Image size at downsampling factor ``s``: ``max(1, floor(n / s + 0.5))`` per axis.

    Round-half-up (not Python's banker's rounding) so the size never depends on the parity of
    the quotient; the original 3DGS uses ``round(W / s)``, identical except on exact ties.
    """
    s = _check_factor(s)
    return max(1, math.floor(width / s + 0.5)), max(1, math.floor(height / s + 0.5))


def _check_factor(s) -> float:
    try:
        s = float(s)
    except (TypeError, ValueError):
        raise ValueError(f"scale factor must be a positive number, got {s!r}") from None
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"scale factor must be a positive finite number, got {s}")
    return s


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """One pinhole view.

    Attributes:
        uid: unique id within a scene (COLMAP image_id, or the frame index for NeRF scenes).
        name: image name relative to the scene's image folder, '/'-separated.
        K: [3, 3] float64 intrinsics in pixel units, pixel centres at +0.5.
        world_to_camera: [4, 4] float64, OpenCV axes.
        width, height: image size in pixels.
        time: frame time in [0, 1] for dynamic scenes, else None.

    Inputs may be numpy arrays, lists or tensors of any dtype; they are validated and stored as
    float64 CPU tensors. Treat the tensors as read-only (a dataclass cannot freeze a tensor).
    Cameras compare by identity; compare ``K`` / ``world_to_camera`` explicitly when needed.
    """

    uid: int
    name: str
    K: torch.Tensor
    world_to_camera: torch.Tensor
    width: int
    height: int
    time: Optional[float] = None

    def __post_init__(self) -> None:
        if isinstance(self.uid, bool):
            raise ValueError(f"uid must be an int, got {self.uid!r}")
        try:
            uid = operator.index(self.uid)
        except TypeError:
            raise ValueError(f"uid must be an int, got {self.uid!r}") from None
        if not isinstance(self.name, str):
            raise ValueError(f"name must be a str, got {self.name!r}")
        K = _as_float64_matrix(self.K, (3, 3), "K")
        _check_K(K)
        w2c = _as_float64_matrix(self.world_to_camera, (4, 4), "world_to_camera")
        _check_rigid(w2c, "world_to_camera")
        width = _positive_int(self.width, "width")
        height = _positive_int(self.height, "height")
        time = self.time
        if time is not None:
            if isinstance(time, bool):
                raise ValueError(f"time must be a float in [0,1] or None, got {time!r}")
            try:
                time = float(time)
            except (TypeError, ValueError):
                raise ValueError(f"time must be a float in [0,1] or None, got {time!r}") from None
            if not (0.0 <= time <= 1.0):  # also rejects NaN
                raise ValueError(f"time must be in [0,1], got {time}")
        # frozen dataclass: normalised values are written through object.__setattr__
        for key, val in dict(uid=uid, K=K, world_to_camera=w2c, width=width,
                             height=height, time=time).items():
            object.__setattr__(self, key, val)

    def __repr__(self) -> str:
        return (f"Camera(uid={self.uid}, name={self.name!r}, {self.width}x{self.height}, "
                f"fx={self.fx:.4g}, fy={self.fy:.4g}, time={self.time})")

    # ---- intrinsics ---------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians, ``2 atan(W / (2 fx))`` (assumes cx = W/2)."""
        return 2.0 * math.atan(0.5 * self.width / self.fx)

    @property
    def fov_y(self) -> float:
        """Vertical field of view in radians, ``2 atan(H / (2 fy))`` (assumes cy = H/2)."""
        return 2.0 * math.atan(0.5 * self.height / self.fy)

    # ---- pose ---------------------------------------------------------------------------
    @property
    def camera_to_world(self) -> torch.Tensor:
        """[4, 4] float64, the exact inverse of ``world_to_camera``."""
        R = self.world_to_camera[:3, :3]
        t = self.world_to_camera[:3, 3]
        # Invert with the general inverse of R, not R^T: the constructor tolerates rotations
        # orthonormal only to ROTATION_TOL and the inverse must undo exactly what we project.
        Rinv = torch.linalg.inv(R)
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = Rinv
        out[:3, 3] = -Rinv @ t
        return out

    @property
    def center(self) -> torch.Tensor:
        """[3] float64 camera centre in world coordinates."""
        return self.camera_to_world[:3, 3]

    # ---- derived cameras and geometry ---------------------------------------------------
    def scaled(self, s: float) -> "Camera":
        """The camera of the image downsampled by factor ``s`` (pyramid level).

        Size: ``W' = max(1, floor(W / s + 0.5))`` (same for H), see :func:`scaled_size`.
        Intrinsics: the x row of K (fx, cx) is multiplied by ``W' / W`` and the y row (fy, cy) by
        ``H' / H``; the principal point is scaled, never re-centred. When ``s`` divides W and H
        (the usual case: 800 px and s = 8) this is exactly fx/s, fy/s, cx/s, cy/s.

        Why the actual size ratio and not 1/s: a downsampled image is the whole frame
        [0, W] x [0, H] resampled onto [0, W'] x [0, H'], so a scene point seen at pixel
        coordinate u lands at ``u * W' / W``; pixel centres stay at +0.5 on both grids. Dividing
        by s while rounding the size would misalign image and K by up to half a coarse pixel at
        the right and bottom edges. This also keeps the field of view, as the original 3DGS does
        when it resizes.
        Same uid, name, pose and time.
        """
        w, h = scaled_size(self.width, self.height, s)
        K = self.K.clone()
        K[0, :] *= w / self.width
        K[1, :] *= h / self.height
        return Camera(uid=self.uid, name=self.name, K=K, world_to_camera=self.world_to_camera,
                      width=w, height=h, time=self.time)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points.

        Args:
            points: [..., 3] world coordinates.
        Returns:
            pixels [..., 2] in K's coordinates (centre of pixel (i, j) at (i+0.5, j+0.5)) and
            depth [..., ] (camera-space z; pixels are meaningless where depth <= 0).
            float64 unless ``points`` is another floating dtype, which is then kept.
        """
        points = torch.as_tensor(points)
        out_dtype = points.dtype if points.is_floating_point() else torch.float64
        p = points.to(torch.float64)
        w2c = self.world_to_camera.to(p.device)
        K = self.K.to(p.device)
        cam = p @ w2c[:3, :3].T + w2c[:3, 3]
        uvw = cam @ K.T
        z = cam[..., 2]
        pix = uvw[..., :2] / z[..., None]
        return pix.to(out_dtype), z.to(out_dtype)

    def rays(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space rays through pixel coordinates.

        Args:
            pixels: [..., 2] (u, v) in K's coordinates; the centre of pixel (i, j) is
                (i + 0.5, j + 0.5).
        Returns:
            origins [..., 3] (the camera centre) and unit directions [..., 3], in the dtype of
            ``pixels`` if floating, else float64, on its device.
        """
        pixels = torch.as_tensor(pixels)
        if pixels.shape[-1:] != (2,):
            raise ValueError(f"pixels must be [...,2], got {list(pixels.shape)}")
        out_dtype = pixels.dtype if pixels.is_floating_point() else torch.float64
        uv = pixels.to(torch.float64)
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        c2w = self.camera_to_world.to(uv.device)
        d = d_cam @ c2w[:3, :3].T
        d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
        o = c2w[:3, 3].expand_as(d)
        return o.to(out_dtype), d.to(out_dtype)


def stack_cameras(cams: Sequence[Camera], dtype: torch.dtype = torch.float32,
                  device: Optional[torch.device | str] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch cameras into the renderer's tensors.

    Args:
        cams: C >= 1 cameras (sizes may differ; image sizes are not part of the output).
    Returns:
        viewmats [C, 4, 4] (world-to-camera) and Ks [C, 3, 3], in ``dtype`` on ``device``.
    """
    cams = list(cams)
    if not cams:
        raise ValueError("stack_cameras needs at least one camera, got 0")
    for i, c in enumerate(cams):
        if not isinstance(c, Camera):
            raise ValueError(f"cams[{i}] must be a Camera, got {type(c).__name__}")
    viewmats = torch.stack([c.world_to_camera for c in cams]).to(device=device, dtype=dtype)
    Ks = torch.stack([c.K for c in cams]).to(device=device, dtype=dtype)
    return viewmats, Ks
