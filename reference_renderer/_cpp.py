"""Build, load and call the compiled compositing kernels (csrc/rasterize.cpp).

The library is compiled on first use with the system C++ compiler and cached, keyed by the
source, the flags, the compiler and the CPU (``-march=native`` code must not run on another CPU).
It exposes a plain C ABI called through ctypes, so it builds in seconds, needs no build step at
install time and works with any torch version. When no compiler is available the renderer falls
back to the pure-PyTorch path (``available_backends()`` then lists only ``"torch"``).

Environment: ``MVGS_CACHE_DIR`` (default ``~/.cache/mvgs_plugin``) holds the built library;
``CXX`` picks the compiler (default ``c++``).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Optional

import torch

_SOURCE = Path(__file__).with_name("csrc") / "rasterize.cpp"
_FLAGS = ["-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-pthread"]
_lock = threading.Lock()
_lib: Optional[ctypes.CDLL] = None
_error: Optional[str] = None

_i64 = ctypes.c_int64
_ptr = ctypes.c_void_p


def _cpu_signature() -> str:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    keep = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags", "Features"))]
    return "\n".join(sorted(set(keep)))


def _cache_dir() -> Path:
    root = os.environ.get("MVGS_CACHE_DIR") or os.path.join(Path.home(), ".cache", "mvgs_plugin")
    return Path(root)


def _build() -> ctypes.CDLL:
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        raise RuntimeError(f"no C++ compiler found (CXX={cxx!r})")
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True).stdout
    key = hashlib.sha256(
        b"\0".join(
            [_SOURCE.read_bytes(), " ".join(_FLAGS).encode(), version.encode(), _cpu_signature().encode()]
        )
    ).hexdigest()[:16]
    target = _cache_dir() / f"mvgs_rasterize_{key}.so"
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        # Compile to a private file and rename: concurrent processes never load a half-written
        # library, and a failed build leaves nothing behind.
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
        os.close(fd)
        try:
            proc = subprocess.run([cxx, *_FLAGS, str(_SOURCE), "-o", tmp], capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"compiling {_SOURCE.name} failed:\n{proc.stderr[-4000:]}")
            os.replace(tmp, target)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    lib = ctypes.CDLL(str(target))
    lib.mvgs_bin_count.restype = _i64
    lib.mvgs_bin_count.argtypes = [_i64, _i64, _i64, _i64, _ptr, _ptr]
    lib.mvgs_bin_fill.restype = None
    lib.mvgs_bin_fill.argtypes = [_i64, _i64, _i64, _i64, _ptr, _ptr, _ptr, _ptr]
    for suffix in ("f32", "f64"):
        fwd = getattr(lib, f"mvgs_forward_{suffix}")
        fwd.restype = None
        fwd.argtypes = [_i64] * 6 + [_ptr] * 10 + [ctypes.c_int]
        bwd = getattr(lib, f"mvgs_backward_{suffix}")
        bwd.restype = None
        bwd.argtypes = [_i64] * 6 + [_ptr] * 17 + [ctypes.c_int]
    return lib


def load() -> Optional[ctypes.CDLL]:
    """The compiled library, building it on first call; None when it cannot be built."""
    global _lib, _error
    with _lock:
        if _lib is None and _error is None:
            try:
                _lib = _build()
            except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
                _error = str(exc)
        return _lib


def build_error() -> Optional[str]:
    """Why the compiled library is unavailable (None when it loaded or was not tried yet)."""
    return _error


def _p(t: torch.Tensor) -> int:
    return t.data_ptr()


def _suffix(dtype: torch.dtype) -> str:
    return {torch.float32: "f32", torch.float64: "f64"}[dtype]


def bin_tiles(rects: torch.Tensor, order: torch.Tensor, tiles_x: int, tiles_y: int):
    """Per-(camera, tile) lists of Gaussians in depth order (counting sort).

    rects: [C, N, 4] int32 (x0, x1, y0, y1) tile ranges; order: [C, N] int64 depth order.
    Returns offsets [C * tiles + 1] int64 and ids [total] int32.
    """
    lib = load()
    C, N = order.shape
    rects = rects.contiguous()
    order = order.contiguous()
    offsets = torch.empty(C * tiles_x * tiles_y + 1, dtype=torch.int64)
    total = lib.mvgs_bin_count(C, N, tiles_x, tiles_y, _p(rects), _p(offsets))
    ids = torch.empty(total, dtype=torch.int32)
    lib.mvgs_bin_fill(C, N, tiles_x, tiles_y, _p(rects), _p(order), _p(offsets), _p(ids))
    return offsets, ids


def forward(means2d, conics, opacities, colors, backgrounds, offsets, ids, width, height, tile):
    """Composite [C, N, ...] splats; returns colour [C,H,W,D], transmittance [C,H,W], last [C,H,W]."""
    lib = load()
    C, N, D = colors.shape
    out_color = torch.empty(C, height, width, D, dtype=colors.dtype)
    out_trans = torch.empty(C, height, width, dtype=colors.dtype)
    out_last = torch.empty(C, height, width, dtype=torch.int32)
    getattr(lib, f"mvgs_forward_{_suffix(colors.dtype)}")(
        C, N, D, width, height, tile,
        _p(means2d), _p(conics), _p(opacities), _p(colors), _p(backgrounds), _p(offsets), _p(ids),
        _p(out_color), _p(out_trans), _p(out_last), torch.get_num_threads(),
    )
    return out_color, out_trans, out_last


def backward(means2d, conics, opacities, colors, backgrounds, offsets, ids, out_trans, out_last,
             grad_color, grad_alpha, width, height, tile):
    """Gradients w.r.t. means2d [C,N,2], conics [C,N,3], opacities [C,N], colours [C,N,D], and
    the summed |d/dmeans2d| per pixel [C,N,2] (AbsGS's "absgrad")."""
    lib = load()
    C, N, D = colors.shape
    z = lambda *shape: torch.zeros(*shape, dtype=colors.dtype)  # noqa: E731
    g_means2d, g_conics, g_opac, g_colors, absgrad = z(C, N, 2), z(C, N, 3), z(C, N), z(C, N, D), z(C, N, 2)
    isect = torch.empty(ids.numel(), 8 + D, dtype=colors.dtype)
    getattr(lib, f"mvgs_backward_{_suffix(colors.dtype)}")(
        C, N, D, width, height, tile,
        _p(means2d), _p(conics), _p(opacities), _p(colors), _p(backgrounds), _p(offsets), _p(ids),
        _p(out_trans), _p(out_last), _p(grad_color), _p(grad_alpha), _p(isect),
        _p(g_means2d), _p(g_conics), _p(g_opac), _p(g_colors), _p(absgrad), torch.get_num_threads(),
    )
    return g_means2d, g_conics, g_opac, g_colors, absgrad
