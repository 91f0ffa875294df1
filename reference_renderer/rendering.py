"""rasterization(): gsplat's call shape, classic 3DGS image formation, on the CPU.

Pipeline: validate -> project and colour (SH) -> depth order and tile binning -> compositing.
Two twins implement it. The "torch" backend is plain PyTorch (projection.py, sh.py,
rasterize_torch.py): the readable reference, on any device, with autograd's gradients. The
"cpp" backend runs the same rules in compiled kernels (csrc/) with hand-written backwards: one
fused pass projects and colours all C cameras (the per-Gaussian covariance formed once per call),
then binning and compositing run over (camera, tile) pairs in parallel. The tests check both
against a dense float64 reference, finite differences and each other. When camera gradients are
asked for (viewmats or Ks require grad), the cpp backend projects through the PyTorch twin so
autograd reaches the cameras.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

from . import _cpp, rasterize_torch
from . import _validate as V
from .projection import Projection, project
from .sh import sh_to_rgb

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
BACKENDS = ("cpp", "torch")


def available_backends() -> list:
    """Compositing backends that work here, fastest first: "cpp" (compiled on first use, CPU
    tensors) when a C++ compiler is found, and always "torch" (any device)."""
    return (["cpp"] if _cpp.load() is not None else []) + ["torch"]


def _pick_backend(backend: Optional[str], device: torch.device) -> str:
    if backend is None:
        return "cpp" if device.type == "cpu" and _cpp.load() is not None else "torch"
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS} or None, got {backend!r}")
    if backend == "cpp":
        if device.type != "cpu":
            raise ValueError(f"backend 'cpp' needs CPU tensors, got tensors on {device}")
        if _cpp.load() is None:
            raise RuntimeError(f"backend 'cpp' is unavailable: {_cpp.build_error()}")
    return backend


class _ProjectCpp(torch.autograd.Function):
    """Fused projection and SH colours (csrc/project.cpp) with its hand-written backward."""

    @staticmethod
    def forward(ctx, means, quats, scales, sh, viewmats, Ks, settings):
        args = [x.contiguous() for x in (means, quats, scales)]
        sh_c = None if sh is None else sh.contiguous()
        cams = [viewmats.detach().contiguous(), Ks.detach().contiguous()]
        out = _cpp.project_forward(*args, sh_c, *cams, *settings)
        ctx.save_for_backward(*args, *cams, *([] if sh_c is None else [sh_c]))
        ctx.settings = settings
        ctx.has_sh = sh_c is not None
        ctx.mark_non_differentiable(*out[5:])
        return out

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_comp, g_colors, *_):
        means, quats, scales, viewmats, Ks, *rest = ctx.saved_tensors
        sh = rest[0] if ctx.has_sh else None
        C, N = viewmats.shape[0], means.shape[0]
        z = lambda g, *shape: (torch.zeros(*shape, dtype=means.dtype) if g is None  # noqa: E731
                               else g.contiguous())
        grads = _cpp.project_backward(
            means, quats, scales, sh, viewmats, Ks, *ctx.settings, z(g_means2d, C, N, 2),
            z(g_conics, C, N, 3), z(g_depths, C, N), z(g_comp, C, N),
            z(g_colors, C, N, 3) if ctx.has_sh else None)
        for name, g in zip(("means", "quats", "scales", "sh coefficients"), grads):
            if g is not None and not V.all_finite(g):
                raise FloatingPointError(f"non-finite gradient w.r.t. {name} in the projection backward")
        return (*grads, None, None, None)


def _project(means, quats, scales, colors, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
             tile_size, radius_clip, sh_degree, render_mode, backend):
    """Projection and, when the compiled path fuses them, SH colours [C, N, 3] (else None)."""
    fused = backend == "cpp" and not (viewmats.requires_grad or Ks.requires_grad)
    if not fused:
        return project(means, quats, scales, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
                       tile_size, radius_clip), None
    fuse_sh = sh_degree is not None and colors.dim() == 3 and render_mode != "D" and render_mode != "ED"
    settings = (width, height, float(near_plane), float(far_plane), float(eps2d), tile_size, float(radius_clip),
                sh_degree if fuse_sh else None)
    # the kernel re-projects in double the pairs float32 would get wrong and culls what does not
    # fit the model's dtype (csrc/project.cpp, needs_double); projection.project is the float64 twin
    out = _ProjectCpp.apply(means, quats, scales, colors if fuse_sh else None, viewmats, Ks, settings)
    means2d, conics, depths, comp, rgb, radii, rects, valid = out
    return Projection(means2d, conics, depths, comp, radii, rects, valid), (rgb if fuse_sh else None)


class _CompositeCpp(torch.autograd.Function):
    """Compiled compositing with its hand-written backward (csrc/rasterize.cpp)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, backgrounds, offsets, ids, width, height, tile, absgrad,
                blend=None):
        args = [x.contiguous() for x in (means2d, conics, opacities, colors, backgrounds)]
        color, trans, last, weight, pixels = _cpp.forward(*args, offsets, ids, width, height, tile,
                                                          blend=blend is not None)
        if blend is not None:  # a dict to fill (not an output: nothing to differentiate)
            blend.update(weight=weight, pairs=pixels)
        ctx.save_for_backward(*args, offsets, ids, color, trans, last)
        ctx.size = (width, height, tile)
        # gsplat's convention: the summed |gradient| lands on means2d.absgrad (AbsGS).
        ctx.absgrad_target = means2d if absgrad else None
        return color, (1 - trans).unsqueeze(-1)

    @staticmethod
    def backward(ctx, grad_color, grad_alpha):
        means2d, conics, opacities, colors, backgrounds, offsets, ids, color, trans, last = ctx.saved_tensors
        width, height, tile = ctx.size
        grad_color = grad_color.contiguous()
        grad_alpha = grad_alpha.squeeze(-1).contiguous()
        g_m, g_q, g_o, g_c, absgrad = _cpp.backward(
            means2d, conics, opacities, colors, backgrounds, offsets, ids, color, trans, last,
            grad_color, grad_alpha, width, height, tile,
        )
        g_bg = (grad_color * trans.unsqueeze(-1)).sum(dim=(1, 2))
        checked = [("means2d", g_m), ("conics", g_q), ("opacities", g_o), ("colors", g_c)]
        if ctx.needs_input_grad[4]:  # a learnt background: its gradient is summed here, not in the kernel
            checked.append(("backgrounds", g_bg))
        for name, g in checked:
            if not V.all_finite(g):
                raise FloatingPointError(f"non-finite gradient w.r.t. {name} in the compositing backward")
        if ctx.absgrad_target is not None:
            ctx.absgrad_target.absgrad = absgrad
        return g_m, g_q, g_o, g_c, g_bg, None, None, None, None, None, None, None


def _guard(t: Tensor, name: str) -> Tensor:
    """t itself, or (when it requires grad) an alias whose backward hook raises
    FloatingPointError naming `name` if the gradient this call sends it is not finite."""
    if not t.requires_grad:
        return t
    alias = t.view_as(t)

    def check(grad: Optional[Tensor]) -> None:
        if grad is not None and not V.all_finite(grad):
            raise FloatingPointError(f"non-finite gradient w.r.t. {name} in the renderer's backward")

    alias.register_hook(check)
    return alias


def rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = False,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,
    render_mode: str = "RGB",
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    camera_model: str = "pinhole",
    backend: Optional[str] = None,
    *,
    blend_stats: bool = False,
    sparse_grad: bool = False,
    channel_chunk: int = 32,
    distributed: bool = False,
    segmented: bool = False,
    covars: Optional[Tensor] = None,
    with_ut: bool = False,
    with_eval3d: bool = False,
    radial_coeffs: Optional[Tensor] = None,
    tangential_coeffs: Optional[Tensor] = None,
    thin_prism_coeffs: Optional[Tensor] = None,
    ftheta_coeffs=None,
    rolling_shutter=None,
    viewmats_rs: Optional[Tensor] = None,
) -> Tuple[Tensor, Tensor, Dict]:
    """Renders N 3D Gaussians into C pinhole cameras (classic 3DGS image formation).

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations w-x-y-z (normalised here; a zero row is an error).
        scales: [N, 3] activated scales (>= 0).
        opacities: [N] or [C, N] activated opacities in [0, 1].
        colors: [N, D] or [C, N, D] colours (used as given) when sh_degree is None;
            [N, K, 3] or [C, N, K, 3] SH coefficients with K >= (sh_degree+1)^2 otherwise
            (colour = SH(view dir from the camera centre) + 0.5, clamped at 0).
        viewmats: [C, 4, 4] world-to-camera (OpenCV axes: x right, y down, z forward).
        Ks: [C, 3, 3] pinhole intrinsics; pixel (i, j) has its centre at (i + 0.5, j + 0.5).
        width, height: image size in pixels.
        near_plane, far_plane: Gaussians with camera depth <= near or >= far are culled.
        radius_clip: Gaussians whose screen radius (pixels) is <= this are culled.
        eps2d: added to the diagonal of every 2D covariance (the 0.3 px low-pass of 3DGS).
        sh_degree: None for plain colours, else 0..3.
        packed: accepted for gsplat compatibility; only False (dense [C, N] outputs) is supported.
        tile_size: tile edge in pixels (16 as the CUDA rasterizers).
        backgrounds: [C, D] colour added with the final transmittance (black when None).
        render_mode: "RGB", "D" (accumulated depth), "ED" (expected depth), "RGB+D", "RGB+ED".
        absgrad: also store sum over pixels of |d loss / d means2d| in meta["means2d"].absgrad
            (compiled backend only), as gsplat does for AbsGS.
        rasterize_mode: "classic", or "antialiased" (opacity times the eps2d compensation).
        camera_model: only "pinhole".
        backend: "cpp", "torch", or None for the fastest available (see available_backends()).
        blend_stats: (this renderer's own, not gsplat's) also return, per camera and Gaussian,
            what the image formation blended: meta["blend_weight"] [C,N], its weight alpha x T
            summed over the pixels (its share of their colours; the weights of a pixel add up to
            its alpha), and meta["blend_pixels"] [C,N], how many pixels it was blended at (alpha
            >= 1/255 before the pixel stopped). Not differentiable; both backends.
        sparse_grad, channel_chunk, distributed, segmented, covars, with_ut, with_eval3d,
        radial_coeffs, tangential_coeffs, thin_prism_coeffs, ftheta_coeffs, rolling_shutter,
        viewmats_rs: gsplat 1.5.3's other keywords, so a call written for gsplat runs unchanged.
            Their defaults (and any channel_chunk, a memory knob) are accepted; a value asking
            for what this renderer does not do (packed sparse gradients, gsplat's own
            multi-GPU split, precomputed covariances, the unscented transform, 3D evaluation,
            lens distortion, rolling shutter) is refused naming the alternative.

    Returns:
        render_colors [C, H, W, D'], render_alphas [C, H, W, 1], meta with means2d [C,N,2] (call
        .retain_grad() before backward for the screen-space gradient densification uses), radii
        [C,N,2] int32 (both entries the square radius; 0 = culled), depths [C,N], conics
        [C,N,3], opacities [C,N], width, height, n_cameras, tile_size, tile_width, tile_height,
        isect_offsets, flatten_ids, gaussian_ids (None: not packed), backend.
    """
    _check_gsplat_options(sparse_grad, channel_chunk, distributed, segmented, covars, with_ut, with_eval3d,
                          radial_coeffs, tangential_coeffs, thin_prism_coeffs, ftheta_coeffs, rolling_shutter,
                          viewmats_rs)
    means, C, N = _check_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane,
        radius_clip, eps2d, sh_degree, packed, tile_size, backgrounds, render_mode, absgrad,
        rasterize_mode, camera_model,
    )
    backend = _pick_backend(backend, means.device)
    if absgrad and backend != "cpp":
        raise ValueError("absgrad=True needs backend 'cpp' (the PyTorch path has no per-pixel gradients)")

    # Off the compiled path (PyTorch backend, or camera gradients) every differentiable input's
    # gradient is checked in backward: autograd would otherwise hand a NaN on silently. The
    # compiled kernels check the gradients they produce themselves.
    if backend != "cpp" or viewmats.requires_grad or Ks.requires_grad:
        means, quats, scales, opacities, colors, viewmats, Ks = (
            _guard(t, name) for t, name in ((means, "means"), (quats, "quats"), (scales, "scales"),
                                            (opacities, "opacities"), (colors, "colors"), (viewmats, "viewmats"),
                                            (Ks, "Ks")))
        backgrounds = None if backgrounds is None else _guard(backgrounds, "backgrounds")
    proj, rgb = _project(means, quats, scales, colors, viewmats, Ks, width, height, near_plane, far_plane,
                         eps2d, tile_size, radius_clip, sh_degree, render_mode, backend)
    feats = _features(means, colors, viewmats, sh_degree, render_mode, proj.depths, C, rgb)
    opac = opacities.expand(C, N) if opacities.dim() == 1 else opacities
    if rasterize_mode == "antialiased":
        opac = opac * proj.compensation
    D = feats.shape[-1]
    bg = torch.zeros(C, D, dtype=means.dtype, device=means.device)
    if backgrounds is not None:
        n_bg, n_col = backgrounds.shape[-1], D - (render_mode != "RGB")
        if n_bg not in {D, n_col} - {0}:
            raise ValueError(f"backgrounds must be [C,{n_col}] (or [C,{D}] with a depth entry) for "
                             f"{D}-channel render_mode {render_mode!r}, got {V.shape_str(backgrounds)}")
        bg = torch.cat([backgrounds, bg[:, n_bg:]], dim=-1)

    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    with torch.no_grad():
        if backend == "cpp":
            offsets, ids = _cpp.bin_by_depth(proj.rects, proj.depths, proj.valid, tiles_x, tiles_y)
        else:
            key = torch.where(proj.valid, proj.depths, torch.full_like(proj.depths, float("inf")))
            order = torch.argsort(key, dim=-1, stable=True)
            offsets, ids = rasterize_torch.bin_tiles(proj.rects, order, tiles_x, tiles_y)

    blend = {} if blend_stats else None
    if backend == "cpp":
        img, alpha = _CompositeCpp.apply(proj.means2d, proj.conics, opac, feats, bg, offsets, ids,
                                         width, height, tile_size, absgrad, blend)
    else:
        img, alpha = rasterize_torch.composite(proj.means2d, proj.conics, opac, feats, bg, offsets, ids,
                                               width, height, tile_size, stats=blend)
    if render_mode in ("ED", "RGB+ED"):
        img = torch.cat([img[..., :-1], img[..., -1:] / alpha.clamp_min(1e-10)], dim=-1)
    if not V.all_finite(img) or not V.all_finite(alpha):
        raise FloatingPointError("the renderer produced a non-finite pixel; please report this input")

    meta = {
        "means2d": proj.means2d,
        "radii": torch.stack([proj.radii, proj.radii], dim=-1),
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": opac,
        "width": width,
        "height": height,
        "n_cameras": C,
        "tile_size": tile_size,
        "tile_width": tiles_x,
        "tile_height": tiles_y,
        "isect_offsets": offsets[:-1].reshape(C, tiles_y, tiles_x),
        "flatten_ids": ids,
        "gaussian_ids": None,
        "camera_ids": None,
        "backend": backend,
    }
    if blend is not None:
        meta.update(blend_weight=blend["weight"].detach(), blend_pixels=blend["pairs"].detach())
    return img, alpha, meta


def _features(means, colors, viewmats, sh_degree, render_mode, depths, C, rgb=None) -> Tensor:
    """Per-camera features [C, N, D] to composite: colours (from SH if asked, or the fused
    projection's `rgb`) and/or depth."""
    feats = []
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        if rgb is not None:
            feats.append(rgb)
        elif sh_degree is None:
            feats.append(colors.expand(C, *colors.shape) if colors.dim() == 2 else colors)
        else:
            R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
            centers = -(R.transpose(1, 2) @ t.unsqueeze(-1)).squeeze(-1)  # [C,3]
            dirs = torch.nn.functional.normalize(means[None] - centers[:, None], dim=-1)  # [C,N,3]
            coeffs = colors[None] if colors.dim() == 3 else colors
            feats.append(sh_to_rgb(sh_degree, coeffs, dirs))
    if render_mode != "RGB":
        feats.append(depths.unsqueeze(-1))
    return torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]


def _check_gsplat_options(sparse_grad, channel_chunk, distributed, segmented, covars, with_ut, with_eval3d,
                          radial_coeffs, tangential_coeffs, thin_prism_coeffs, ftheta_coeffs, rolling_shutter,
                          viewmats_rs) -> None:
    """gsplat 1.5.3's keywords this renderer takes only at their defaults (see rasterization)."""
    V.check_positive_int("channel_chunk", channel_chunk)  # a memory knob of gsplat's, unused here
    refused = (
        ("sparse_grad", sparse_grad, False, "sparse gradients come with packed=True, which this renderer does not "
                                            "have: pass sparse_grad=False (dense [N] gradients)"),
        ("distributed", distributed, False, "for several processes use mvgs_plugin.distributed (each rank renders "
                                            "its share of the views): pass distributed=False"),
        ("segmented", segmented, False, "segmented sorting comes with packed=True: pass segmented=False"),
        ("with_ut", with_ut, False, "the unscented transform is not implemented: pass with_ut=False (EWA projection)"),
        ("with_eval3d", with_eval3d, False, "3D Gaussian evaluation is not implemented: pass with_eval3d=False"),
    )
    for name, value, default, why in refused:
        if value != default:
            raise ValueError(f"{name}={value!r} is not supported: {why}")
    for name, value in (("covars", covars), ("radial_coeffs", radial_coeffs), ("tangential_coeffs", tangential_coeffs),
                        ("thin_prism_coeffs", thin_prism_coeffs), ("ftheta_coeffs", ftheta_coeffs),
                        ("viewmats_rs", viewmats_rs)):
        if value is not None:
            why = ("pass quats and scales instead of precomputed covariances" if name == "covars" else
                   "lens distortion and rolling shutter are not modelled: undistort the images (pinhole cameras) "
                   f"and pass {name}=None")
            raise ValueError(f"{name} is not supported: {why}")
    if rolling_shutter is not None and getattr(rolling_shutter, "name", rolling_shutter) != "GLOBAL":
        raise ValueError(f"rolling_shutter={rolling_shutter!r} is not supported: only a global shutter "
                         "(None or RollingShutterType.GLOBAL)")


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                  far_plane, radius_clip, eps2d, sh_degree, packed, tile_size, backgrounds,
                  render_mode, absgrad, rasterize_mode, camera_model):
    V.check_tensor("means", means, (None, 3), "[N,3]")
    N = means.shape[0]
    V.check_tensor("viewmats", viewmats, (None, 4, 4), "[C,4,4]")
    C = viewmats.shape[0]
    if C == 0:
        raise ValueError("viewmats must hold at least one camera, got [0,4,4]")
    V.check_tensor("quats", quats, (N, 4), f"[N,4] with N={N}")
    V.check_tensor("scales", scales, (N, 3), f"[N,3] with N={N}")
    if opacities.dim() == 2 if isinstance(opacities, Tensor) else False:
        V.check_tensor("opacities", opacities, (C, N), f"[N] or [C,N] with C={C}, N={N}")
    else:
        V.check_tensor("opacities", opacities, (N,), f"[N] or [C,N] with C={C}, N={N}")
    V.check_tensor("Ks", Ks, (C, 3, 3), f"[C,3,3] with C={C}")
    if sh_degree is not None:
        if isinstance(sh_degree, bool) or sh_degree not in (0, 1, 2, 3):
            raise ValueError(f"sh_degree must be None or 0..3, got {sh_degree!r}")
        k = (sh_degree + 1) ** 2
        lead = (C, N) if isinstance(colors, Tensor) and colors.dim() == 4 else (N,)
        want = f"[N,K,3] or [C,N,K,3] with K >= {k} for sh_degree={sh_degree} (C={C}, N={N})"
        V.check_tensor("colors", colors, lead + (None, 3), want)
        if colors.shape[-2] < k:
            raise ValueError(f"colors must be {want}, got {V.shape_str(colors)}")
    else:
        lead = (C, N) if isinstance(colors, Tensor) and colors.dim() == 3 else (N,)
        V.check_tensor("colors", colors, lead + (None,), f"[N,D] or [C,N,D] (C={C}, N={N}; SH needs sh_degree)")
    if backgrounds is not None:
        V.check_tensor("backgrounds", backgrounds, (C, None), f"[C,D] with C={C}")
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
               "viewmats": viewmats, "Ks": Ks, "backgrounds": backgrounds}
    V.check_same(tensors)
    for name, t in tensors.items():
        if t is not None:
            V.check_finite(name, t)
    V.check_quats(quats)
    V.check_scales(scales)
    V.check_range("opacities", opacities, 0.0, 1.0, "in [0, 1] (activated, not logits)")
    V.check_viewmats(viewmats)
    V.check_Ks(Ks)
    V.check_positive_int("width", width)
    V.check_positive_int("height", height)
    V.check_positive_int("tile_size", tile_size)
    near = V.check_scalar("near_plane", near_plane, V.NEAR_PLANE_FLOOR)
    if V.check_scalar("far_plane", far_plane) <= near:
        raise ValueError(f"far_plane must be > near_plane={near_plane}, got {far_plane!r}")
    V.check_scalar("radius_clip", radius_clip, 0.0)
    V.check_scalar("eps2d", eps2d, 0.0, finite=True)  # an infinite low-pass has no finite conic
    if packed:
        raise ValueError("packed=True is not supported: pass packed=False (outputs are dense [C, N])")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    if camera_model != "pinhole":
        raise ValueError(f"camera_model must be 'pinhole' (the only one supported), got {camera_model!r}")
    return means, C, N
