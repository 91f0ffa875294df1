"""Build, load and call the compiled kernels: compositing (csrc/rasterize.cpp) and the fused
projection with SH colours (csrc/project.cpp).

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

_SOURCES = [Path(__file__).with_name("csrc") / name for name in ("rasterize.cpp", "project.cpp")]
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
            [*(src.read_bytes() for src in _SOURCES), " ".join(_FLAGS).encode(), version.encode(),
             _cpu_signature().encode()]
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
            proc = subprocess.run([cxx, *_FLAGS, *map(str, _SOURCES), "-o", tmp], capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"compiling {[src.name for src in _SOURCES]} failed:\n{proc.stderr[-4000:]}")
            os.replace(tmp, target)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    lib = ctypes.CDLL(str(target))
    # name: (return type, argument types); f32 and f64 variants alike
    signatures = {
        "mvgs_bin_depth_count": (_i64, [_i64] * 4 + [_ptr] * 3),
        "mvgs_bin_depth_fill": (None, [_i64] * 4 + [_ptr] * 5),
        "mvgs_forward": (None, [_i64] * 6 + [_ptr] * 13),
        "mvgs_backward": (None, [_i64] * 6 + [_ptr] * 18),
        "mvgs_project_forward": (None, [_ptr] * 16),
        "mvgs_project_backward": (None, [_ptr] * 17),
    }
    for name, (restype, argtypes) in signatures.items():
        for suffix in ("f32", "f64"):
            fn = getattr(lib, f"{name}_{suffix}")
            fn.restype = restype
            fn.argtypes = argtypes + [ctypes.c_int]  # the last argument: number of threads
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


def bin_by_depth(rects: torch.Tensor, depths: torch.Tensor, valid: torch.Tensor, tiles_x: int, tiles_y: int):
    """Per-(camera, tile) lists of the valid Gaussians in depth order (ties by index), as
    bin_tiles on a stable argsort of the depths gives, without the sort over all N.

    rects: [C, N, 4] int32; depths: [C, N] float; valid: [C, N] bool.
    Returns offsets [C * tiles + 1] int64 and ids [total] int32.
    """
    lib = load()
    C, N = depths.shape
    rects, depths, valid = rects.contiguous(), depths.detach().contiguous(), valid.contiguous()
    sfx, threads = _suffix(depths.dtype), torch.get_num_threads()
    offsets = torch.empty(C * tiles_x * tiles_y + 1, dtype=torch.int64)
    total = getattr(lib, f"mvgs_bin_depth_count_{sfx}")(C, N, tiles_x, tiles_y, _p(rects), _p(valid), _p(offsets),
                                                         threads)
    ids = torch.empty(total, dtype=torch.int32)
    getattr(lib, f"mvgs_bin_depth_fill_{sfx}")(C, N, tiles_x, tiles_y, _p(rects), _p(depths), _p(valid),
                                               _p(offsets), _p(ids), threads)
    return offsets, ids


def forward(means2d, conics, opacities, colors, backgrounds, offsets, ids, width, height, tile, blend=False):
    """Composite [C, N, ...] splats; returns colour [C,H,W,D], transmittance [C,H,W], last [C,H,W],
    and with blend=True also each Gaussian's blend weight (alpha x T summed over the pixels it is
    blended at) and that pixel count, [C,N] each (else None, None)."""
    lib = load()
    C, N, D = colors.shape
    out_color = torch.empty(C, height, width, D, dtype=colors.dtype)
    out_trans = torch.empty(C, height, width, dtype=colors.dtype)
    out_last = torch.empty(C, height, width, dtype=torch.int32)
    isect = weight = pixels = None
    if blend:
        isect = torch.empty(ids.numel(), 2, dtype=colors.dtype)
        weight, pixels = torch.zeros(C, N, dtype=colors.dtype), torch.zeros(C, N, dtype=colors.dtype)
    getattr(lib, f"mvgs_forward_{_suffix(colors.dtype)}")(
        C, N, D, width, height, tile,
        _p(means2d), _p(conics), _p(opacities), _p(colors), _p(backgrounds), _p(offsets), _p(ids),
        _p(out_color), _p(out_trans), _p(out_last), *(_p(t) if blend else None for t in (isect, weight, pixels)),
        torch.get_num_threads(),
    )
    return out_color, out_trans, out_last, weight, pixels


def backward(means2d, conics, opacities, colors, backgrounds, offsets, ids, out_color, out_trans, out_last,
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
        _p(out_color), _p(out_trans), _p(out_last), _p(grad_color), _p(grad_alpha), _p(isect),
        _p(g_means2d), _p(g_conics), _p(g_opac), _p(g_colors), _p(absgrad), torch.get_num_threads(),
    )
    return g_means2d, g_conics, g_opac, g_colors, absgrad


def _settings(C, N, width, height, tile, K, sh_degree, near, far, eps2d, radius_clip):
    ints = torch.tensor([C, N, width, height, tile, K, -1 if sh_degree is None else sh_degree], dtype=torch.int64)
    reals = torch.tensor([near, far, eps2d, radius_clip], dtype=torch.float64)
    return ints, reals


def project_forward(means, quats, scales, sh, viewmats, Ks, width, height, near, far, eps2d, tile,
                    radius_clip, sh_degree):
    """Fused projection (+ SH colours when sh_degree is not None; sh [N, K, 3]) of N Gaussians
    into C cameras. Returns means2d [C,N,2], conics [C,N,3], depths [C,N], compensation [C,N],
    colours [C,N,3] (empty without SH), radii [C,N] int32, rects [C,N,4] int32, valid [C,N] bool."""
    lib = load()
    C, N = viewmats.shape[0], means.shape[0]
    K = 0 if sh is None else sh.shape[1]
    ints, reals = _settings(C, N, width, height, tile, K, sh_degree, near, far, eps2d, radius_clip)
    e = lambda *shape, dtype=means.dtype: torch.empty(*shape, dtype=dtype)  # noqa: E731
    means2d, conics, depths, comp = e(C, N, 2), e(C, N, 3), e(C, N), e(C, N)
    colors = e(C, N, 3) if sh is not None else e(0)
    radii, rects, valid = e(C, N, dtype=torch.int32), e(C, N, 4, dtype=torch.int32), e(C, N, dtype=torch.bool)
    getattr(lib, f"mvgs_project_forward_{_suffix(means.dtype)}")(
        _p(ints), _p(reals), _p(means), _p(quats), _p(scales), None if sh is None else _p(sh), _p(viewmats),
        _p(Ks), _p(means2d), _p(conics), _p(depths), _p(comp), _p(colors), _p(radii), _p(rects), _p(valid),
        torch.get_num_threads(),
    )
    return means2d, conics, depths, comp, colors, radii, rects, valid


def project_backward(means, quats, scales, sh, viewmats, Ks, width, height, near, far, eps2d, tile,
                     radius_clip, sh_degree, g_means2d, g_conics, g_depths, g_comp, g_colors):
    """Gradients w.r.t. means [N,3], quats [N,4], scales [N,3] and sh [N,K,3] (None without SH)
    from those w.r.t. the outputs of project_forward (all contiguous, same dtype)."""
    lib = load()
    C, N = viewmats.shape[0], means.shape[0]
    K = 0 if sh is None else sh.shape[1]
    ints, reals = _settings(C, N, width, height, tile, K, sh_degree, near, far, eps2d, radius_clip)
    d_means, d_quats, d_scales = torch.empty_like(means), torch.empty_like(quats), torch.empty_like(scales)
    d_sh = None if sh is None else torch.zeros_like(sh)
    getattr(lib, f"mvgs_project_backward_{_suffix(means.dtype)}")(
        _p(ints), _p(reals), _p(means), _p(quats), _p(scales), None if sh is None else _p(sh), _p(viewmats),
        _p(Ks), _p(g_means2d), _p(g_conics), _p(g_depths), _p(g_comp),
        _p(g_colors) if sh is not None else None, _p(d_means), _p(d_quats), _p(d_scales),
        None if d_sh is None else _p(d_sh), torch.get_num_threads(),
    )
    return d_means, d_quats, d_scales, d_sh
