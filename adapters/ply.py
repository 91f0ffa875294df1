"""Reading and writing Gaussians in the standard 3DGS PLY layout.

Layout (docs/design.md "PLY"; what the original 3DGS writes and the common viewers read): one
``vertex`` element, binary little-endian, every property a float32, in this order:

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3*K'-1)  opacity  scale_0..2  rot_0..3

with K' = (d+1)^2 - 1 higher-order SH coefficients per colour channel. ``f_rest`` is
channel-major: the K' red coefficients, then the K' green, then the K' blue, so
``f_rest_{c*K' + k}`` is coefficient k of channel c. Values are stored raw, as the model
optimises them: logit opacity, log scale, unnormalised w-x-y-z quaternion. The normals are
written as zeros (3DGS has none; the viewers expect the properties).

Functions here work on tensors and arrays only; they know nothing about adapters.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, List, Union

import numpy as np
import torch
from torch import Tensor

from mvgs_plugin.io import write_atomic

__all__ = ["PlyGaussians", "ply_property_names", "write_gaussian_ply", "read_gaussian_ply",
           "sh_degree_from_rest"]

PathLike = Union[str, os.PathLike]

# Rows per write call: big enough to be fast, small enough that a 5M-Gaussian model does not
# need a second full copy of its bytes in memory.
_ROWS_PER_WRITE = 1 << 16


@dataclass
class PlyGaussians:
    """Raw Gaussian attributes as stored in a 3DGS PLY (float32 CPU tensors).

    means [N, 3]; sh0 [N, 1, 3] (DC); shN [N, K', 3] with K' = (d+1)^2 - 1 (K' may be 0);
    opacities [N] logits; scales [N, 3] logs; quats [N, 4] w-x-y-z, unnormalised.
    """

    means: Tensor
    sh0: Tensor
    shN: Tensor
    opacities: Tensor
    scales: Tensor
    quats: Tensor

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_rest(self.shN.shape[1])


def sh_degree_from_rest(n_rest: int) -> int:
    """SH degree d such that (d+1)^2 - 1 == n_rest (coefficients per channel beyond the DC)."""
    for d in range(0, 4):
        if (d + 1) ** 2 - 1 == n_rest:
            return d
    raise ValueError(f"{n_rest} higher-order SH coefficients per channel is not (d+1)^2-1 for "
                     f"any degree d in 0..3")


def ply_property_names(sh_degree: int) -> List[str]:
    """Vertex property names in file order for SH degree ``sh_degree``."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _as_rows(means, sh0, shN, opacities, scales, quats) -> tuple[np.ndarray, int]:
    """Pack the attributes into the [N, P] float32 row matrix of the file, checking shapes.
    Returns the rows and the SH degree."""
    def arr(name, x):
        x = x.detach().cpu().numpy() if isinstance(x, Tensor) else np.asarray(x)
        x = x.astype(np.float32, copy=False)
        bad = ~np.isfinite(x)
        if bad.any():
            # a NaN in a PLY breaks every viewer that opens it; refuse instead
            row = int(np.argwhere(bad)[0][0]) if x.ndim else 0
            raise ValueError(f"{name} has {int(bad.sum())} non-finite values (first in row {row})")
        return x

    means, sh0, shN = arr("means", means), arr("sh0", sh0), arr("shN", shN)
    opacities, scales, quats = arr("opacities", opacities), arr("scales", scales), arr("quats", quats)
    n = means.shape[0] if means.ndim == 2 else -1
    expected = {"means": (means, (n, 3)), "sh0": (sh0, (n, 1, 3)), "opacities": (opacities, (n,)),
                "scales": (scales, (n, 3)), "quats": (quats, (n, 4))}
    for name, (x, shape) in expected.items():
        if x.shape != shape:
            raise ValueError(f"{name} must be {list(shape)} (N from means {list(means.shape)}), "
                             f"got {list(x.shape)}")
    if shN.ndim != 3 or shN.shape[0] != n or shN.shape[2] != 3:
        raise ValueError(f"shN must be [N,K',3] with N={n}, got {list(shN.shape)}")
    degree = sh_degree_from_rest(shN.shape[1])  # raises on a count no degree has
    # channel-major: [N, K', 3] -> [N, 3, K'] -> [N, 3*K'] (all red, then green, then blue)
    rest = shN.transpose(0, 2, 1).reshape(n, -1)
    normals = np.zeros((n, 3), dtype=np.float32)
    rows = np.concatenate([means, normals, sh0.reshape(n, 3), rest, opacities[:, None], scales, quats],
                          axis=1)
    return np.ascontiguousarray(rows, dtype="<f4"), degree


def _header(n: int, names: List[str]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    lines += [f"property float {name}" for name in names]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _write_rows(f: BinaryIO, rows: np.ndarray) -> None:
    """Write the [N, P] little-endian float32 rows (the vertex data) in blocks."""
    for start in range(0, rows.shape[0], _ROWS_PER_WRITE):
        f.write(rows[start:start + _ROWS_PER_WRITE].tobytes())


def write_gaussian_ply(path: PathLike, means, sh0, shN, opacities, scales, quats) -> None:
    """Write raw Gaussian attributes as a standard 3DGS PLY, atomically.

    Args:
        means [N, 3]; sh0 [N, 1, 3]; shN [N, K', 3]; opacities [N] (logits); scales [N, 3]
        (logs); quats [N, 4] (w-x-y-z) -- tensors or arrays, converted to float32.

    Written with mvgs_plugin.io.write_atomic: readers never see a half-written file, a failed
    write leaves any previous file at ``path`` untouched, and partials of killed writers go.
    """
    path = Path(path)
    rows, degree = _as_rows(means, sh0, shN, opacities, scales, quats)
    names = ply_property_names(degree)

    def write(f):
        f.write(_header(rows.shape[0], names))
        _write_rows(f, rows)

    write_atomic(path, write, binary=True)


def _vertex_element(path: Path, ply):
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: no 'vertex' element (elements: {names}); not a 3DGS PLY")
    return ply["vertex"]


def _column(path: Path, data: np.ndarray, name: str, found: List[str]) -> np.ndarray:
    if name not in found:
        raise ValueError(f"{path}: vertex property {name!r} is missing; a 3DGS PLY needs x y z "
                         f"f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3 (found: {found})")
    return np.asarray(data[name], dtype=np.float32)


def _rest_count(path: Path, found: List[str]) -> int:
    """Number of f_rest_* properties, checking they are f_rest_0..f_rest_{M-1} with no gap."""
    idx = sorted(int(n[len("f_rest_"):]) for n in found
                 if n.startswith("f_rest_") and n[len("f_rest_"):].isdigit())
    for want, got in enumerate(idx):
        if want != got:
            raise ValueError(f"{path}: vertex property 'f_rest_{want}' is missing (f_rest indices "
                             f"found: {idx[0]}..{idx[-1]}, {len(idx)} of them)")
    if len(idx) % 3:
        raise ValueError(f"{path}: {len(idx)} f_rest properties is not a multiple of 3 (channels)")
    try:
        sh_degree_from_rest(len(idx) // 3)
    except ValueError as err:
        raise ValueError(f"{path}: {len(idx)} f_rest properties: {err}") from None
    return len(idx)


def read_gaussian_ply(path: PathLike) -> PlyGaussians:
    """Read a 3DGS PLY (ours or another tool's: properties are found by name, in any order and
    any numeric type; normals and extra properties are ignored).

    Raises ValueError naming the file and what is wrong: not a PLY, a missing property, an
    f_rest count that matches no SH degree, no vertices, NaN or Inf values, zero quaternions.
    """
    from plyfile import PlyData  # local: only reading needs plyfile

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    try:
        ply = PlyData.read(str(path))
    except Exception as err:  # plyfile raises PlyHeaderParseError, PlyElementParseError, ValueError, ...
        raise ValueError(f"{path}: not a readable PLY file ({type(err).__name__}: {err})") from None
    vertex = _vertex_element(path, ply)
    data = vertex.data
    found = list(data.dtype.names or ())
    col = lambda name: _column(path, data, name, found)  # noqa: E731
    n_rest = _rest_count(path, found)
    n = len(data)
    means = np.stack([col("x"), col("y"), col("z")], axis=1)
    sh0 = np.stack([col(f"f_dc_{c}") for c in range(3)], axis=1).reshape(n, 1, 3)
    if n_rest:
        rest = np.stack([col(f"f_rest_{i}") for i in range(n_rest)], axis=1)
        shN = rest.reshape(n, 3, n_rest // 3).transpose(0, 2, 1)  # channel-major -> [N, K', 3]
    else:
        shN = np.zeros((n, 0, 3), dtype=np.float32)
    opacities = col("opacity")
    scales = np.stack([col(f"scale_{i}") for i in range(3)], axis=1)
    quats = np.stack([col(f"rot_{i}") for i in range(4)], axis=1)
    if n == 0:
        raise ValueError(f"{path}: the vertex element is empty (0 Gaussians)")
    used = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0",
            "rot_1", "rot_2", "rot_3"] + [f"f_rest_{i}" for i in range(n_rest)]
    for name in used:
        bad = ~np.isfinite(np.asarray(data[name], dtype=np.float64))
        if bad.any():
            raise ValueError(f"{path}: property {name!r} holds {int(bad.sum())} NaN or Inf values (first: row "
                             f"{int(np.argmax(bad))})")
    flat = np.linalg.norm(quats.astype(np.float64), axis=1) < 1e-12
    if flat.any():
        raise ValueError(f"{path}: {int(flat.sum())} rows have a zero rotation quaternion rot_0..3 (first: row "
                         f"{int(np.argmax(flat))}); a rotation needs a quaternion of non-zero norm")
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return PlyGaussians(means=t(means), sh0=t(sh0), shN=t(shN), opacities=t(opacities),
                        scales=t(scales), quats=t(quats))
