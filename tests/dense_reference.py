"""Dense, float64, autograd-only reference for the image-formation rule.

Written from docs/design.md ("Conventions" -> "Image formation") only; it shares no code with
``reference_renderer``. Clarity over speed: every Gaussian is evaluated against every pixel
([H*W, N] tensors) and the tile rule is applied as a boolean mask, so the only things that
make it "tiled" are the masks, not the loop structure.

Everything that decides *which* terms exist (culling, tile coverage, the 1/255 and 1e-4
thresholds, depth order) is computed without gradient and enters through ``torch.where``;
everything that decides the *value* of a term is plain autograd, so gradients of the
reference are the gradients of the piecewise-smooth function the spec defines.

Public pieces:
    quat_to_rotmat(quats)                        [N,4] w-x-y-z -> [N,3,3] (normalises)
    sh_basis(degree, dirs)                       [..., 3] unit -> [..., (degree+1)^2]
    sh_colors(coeffs, dirs, degree)              3DGS SH colour: max(sum + 0.5, 0)
    project(...)                                 one camera -> dict (means2d, conics, radii, ...)
    dense_render(...)                            one camera -> image [H,W,3], alpha [H,W,1]
"""
from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4

# Real SH normalisation constants (the values used by the original 3DGS sh_utils).
_SH0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
_SH1 = 0.4886025119029199  # sqrt(3 / (4 pi))
_SH2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
        -1.0925484305920792, 0.5462742152960396)
_SH3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
        -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


# ----------------------------------------------------------------------------- geometry
def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N,4] (w, x, y, z), any norm -> rotation matrices [N,3,3].

    Uses R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x for the unit quaternion (w, v).
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, v = q[..., 0], q[..., 1:]
    eye = torch.eye(3, dtype=q.dtype, device=q.device).expand(*q.shape[:-1], 3, 3)
    vx, vy, vz = v.unbind(-1)
    zero = torch.zeros_like(vx)
    cross = torch.stack(
        [torch.stack([zero, -vz, vy], -1),
         torch.stack([vz, zero, -vx], -1),
         torch.stack([-vy, vx, zero], -1)], -2)
    vv = (v * v).sum(-1)
    return ((w * w - vv)[..., None, None] * eye
            + 2.0 * v[..., :, None] * v[..., None, :]
            + 2.0 * w[..., None, None] * cross)


def covariance3d(quats: Tensor, scales: Tensor) -> Tensor:
    """Sigma = R S S^T R^T, [N,3,3]."""
    m = quat_to_rotmat(quats) * scales[..., None, :]  # R @ diag(s)
    return m @ m.transpose(-1, -2)


def camera_centre(viewmat: Tensor) -> Tensor:
    """World position of the camera of a world-to-camera [4,4] matrix."""
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    return -(rot.transpose(0, 1) @ trans)


# ----------------------------------------------------------------------------- SH
def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis of the 3DGS convention up to ``degree`` (<= 3) at unit ``dirs``."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _SH0)]
    if degree >= 1:
        out += [-_SH1 * y, _SH1 * z, -_SH1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_SH2[0] * x * y,
                _SH2[1] * y * z,
                _SH2[2] * (2.0 * zz - xx - yy),
                _SH2[3] * x * z,
                _SH2[4] * (xx - yy)]
    if degree >= 3:
        out += [_SH3[0] * y * (3.0 * xx - yy),
                _SH3[1] * x * y * z,
                _SH3[2] * y * (4.0 * zz - xx - yy),
                _SH3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                _SH3[4] * x * (4.0 * zz - xx - yy),
                _SH3[5] * z * (xx - yy),
                _SH3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(out, -1)


def sh_colors(coeffs: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """coeffs [N,K,3] (K >= (degree+1)^2; extra ones ignored), dirs [N,3] (any length).

    colour = max(sum_k Y_k(dir) c_k + 0.5, 0).
    """
    nb = (degree + 1) ** 2
    if coeffs.shape[-2] < nb:
        raise ValueError(f"need >= {nb} SH coefficients for degree {degree}, got {coeffs.shape}")
    unit = dirs / dirs.norm(dim=-1, keepdim=True)
    basis = sh_basis(degree, unit)  # [N, nb]
    rgb = (basis[..., :, None] * coeffs[..., :nb, :]).sum(-2) + 0.5
    return torch.clamp_min(rgb, 0.0)


# ----------------------------------------------------------------------------- projection
def project(means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, K: Tensor,
            width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10,
            eps2d: float = 0.3, tile_size: int = 16) -> dict:
    """EWA projection + radius + tile rectangle of every Gaussian for one camera.

    Returns a dict of
        means_cam [N,3], depths [N], means2d [N,2], cov2d [N,2,2], conics [N,3] (a, b, c of
        the inverse 2D covariance), radii [N] int64 (0 = culled), visible [N] bool,
        tiles [N,4] int64 (x0, x1, y0, y1; half-open ranges of tile indices), det [N]
        (of the 2D covariance including eps2d).
    Values of culled Gaussians are finite but meaningless (computed with safe
    substitutes so that no NaN reaches the gradients).
    """
    dtype = means.dtype
    fx, fy = float(K[0, 0]), float(K[1, 1])
    cx, cy = float(K[0, 2]), float(K[1, 2])

    rot_v, trans_v = viewmat[:3, :3].to(dtype), viewmat[:3, 3].to(dtype)
    p = means @ rot_v.transpose(0, 1) + trans_v  # camera space [N,3]
    x, y, z = p.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # safe z for culled ones

    # Jacobian of the perspective map, with x/z, y/z clamped to the widened frustum.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lo_x, hi_x = -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x
    lo_y, hi_y = -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y
    tx = zs * torch.clamp(x / zs, lo_x, hi_x)
    ty = zs * torch.clamp(y / zs, lo_y, hi_y)
    zero = torch.zeros_like(zs)
    jac = torch.stack([torch.stack([fx / zs, zero, -fx * tx / (zs * zs)], -1),
                       torch.stack([zero, fy / zs, -fy * ty / (zs * zs)], -1)], -2)  # [N,2,3]

    cov_cam = rot_v @ covariance3d(quats, scales) @ rot_v.transpose(0, 1)
    cov2d = jac @ cov_cam @ jac.transpose(-1, -2)
    cov2d = cov2d + eps2d * torch.eye(2, dtype=dtype, device=means.device)
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    ok = in_depth & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)

    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam_max = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        r = torch.ceil(3.0 * torch.sqrt(torch.clamp_min(lam_max, 0.0)))
        r = torch.where(ok, r, torch.zeros_like(r))
        n_tx = (width + tile_size - 1) // tile_size
        n_ty = (height + tile_size - 1) // tile_size
        u = torch.where(ok, means2d[:, 0], torch.zeros_like(r))
        v = torch.where(ok, means2d[:, 1], torch.zeros_like(r))
        x0 = torch.clamp(torch.floor((u - r) / tile_size), 0, n_tx)
        x1 = torch.clamp(torch.floor((u + r + tile_size - 1) / tile_size), 0, n_tx)
        y0 = torch.clamp(torch.floor((v - r) / tile_size), 0, n_ty)
        y1 = torch.clamp(torch.floor((v + r + tile_size - 1) / tile_size), 0, n_ty)
        visible = ok & (x1 > x0) & (y1 > y0)
        radii = torch.where(visible, r, torch.zeros_like(r)).to(torch.int64)
        tiles = torch.stack([x0, x1, y0, y1], -1).to(torch.int64)

    return dict(means_cam=p, depths=z, means2d=means2d, cov2d=cov2d, conics=conics,
                radii=radii, visible=visible, tiles=tiles, det=det)


# ----------------------------------------------------------------------------- rendering
def gaussian_colors(means: Tensor, colors: Tensor, viewmat: Tensor,
                    sh_degree: Optional[int]) -> Tensor:
    """Per-Gaussian RGB [N,3] for this camera: plain colours as given, or SH evaluated."""
    if sh_degree is None:
        return colors
    dirs = means - camera_centre(viewmat.to(means.dtype))
    return sh_colors(colors, dirs, sh_degree)


def dense_render(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                 colors: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int,
                 near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = 0.3,
                 sh_degree: Optional[int] = None, background: Optional[Tensor] = None,
                 tile_size: int = 16, return_meta: bool = False):
    """Render ONE camera densely.

    means [N,3], quats [N,4], scales [N,3], opacities [N], colors [N,3] (sh_degree None)
    or [N,K,3] SH coefficients, viewmat [4,4] world-to-camera, K [3,3], background [3].
    Returns image [H,W,3], alpha [H,W,1] (and the projection dict when return_meta; its
    ``means2d`` is the very tensor the compositing reads, so ``retain_grad()`` on it gives
    d loss / d (u, v)).
    """
    dtype, dev = means.dtype, means.device
    n = means.shape[0]
    proj = project(means, quats, scales, viewmat, K, width, height, near_plane, far_plane,
                   eps2d, tile_size)
    rgb = gaussian_colors(means, colors, viewmat, sh_degree)  # [N,3]

    # Pixel centres, row-major (py, px) -> flat index py*W + px.
    py, px = torch.meshgrid(torch.arange(height, device=dev), torch.arange(width, device=dev),
                            indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)  # [P]
    centre = torch.stack([px, py], -1).to(dtype) + 0.5  # [P,2]

    # Front-to-back order by camera depth, ties by index (stable sort).
    order = torch.sort(proj["depths"].detach(), stable=True).indices
    m2 = proj["means2d"][order]
    con = proj["conics"][order]
    op = opacities[order]
    col = rgb[order]
    tiles = proj["tiles"][order]
    vis = proj["visible"][order]

    # Tile rule as a mask: pixel tile index inside the Gaussian's half-open tile ranges.
    ptx, pty = (px // tile_size)[:, None], (py // tile_size)[:, None]  # [P,1]
    covered = (vis[None, :]
               & (tiles[None, :, 0] <= ptx) & (ptx < tiles[None, :, 1])
               & (tiles[None, :, 2] <= pty) & (pty < tiles[None, :, 3]))  # [P,N]

    d = m2[None, :, :] - centre[:, None, :]  # [P,N,2]
    dx, dy = d[..., 0], d[..., 1]
    sigma = 0.5 * (con[None, :, 0] * dx * dx + con[None, :, 2] * dy * dy) \
        + con[None, :, 1] * dx * dy
    alpha = torch.clamp_max(op[None, :] * torch.exp(-sigma), ALPHA_MAX)

    with torch.no_grad():
        active = covered & (sigma >= 0) & (alpha >= ALPHA_MIN)
        # Transmittance *after* each term if every active term were taken. It only drops
        # at active terms and never rises, so the first term taking it below T_MIN is the
        # one the pixel stops at, and every later term is below T_MIN too.
        t_after = torch.cumprod(1.0 - torch.where(active, alpha, torch.zeros_like(alpha)), 1)
        used = active & (t_after >= T_MIN)

    a = torch.where(used, alpha, torch.zeros_like(alpha))  # [P,N]
    one_minus = 1.0 - a
    if n > 0:
        t_incl = torch.cumprod(one_minus, 1)
        t_before = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], 1)
        t_final = t_incl[:, -1]
    else:
        t_before = one_minus
        t_final = torch.ones(px.shape[0], dtype=dtype, device=dev)
    weight = a * t_before  # [P,N]
    img = weight @ col  # [P,3]
    if background is not None:
        img = img + t_final[:, None] * background.to(dtype)[None, :]
    img = img.reshape(height, width, 3)
    acc = (1.0 - t_final).reshape(height, width, 1)
    if return_meta:
        return img, acc, proj
    return img, acc


def dense_render_batch(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                       near_plane=0.01, far_plane=1e10, eps2d=0.3, sh_degree=None,
                       backgrounds=None, tile_size=16):
    """C cameras via C calls of dense_render; colors may be [C,N,3] (per camera).

    Returns images [C,H,W,3], alphas [C,H,W,1], list of per-camera projection dicts.
    """
    imgs, accs, metas = [], [], []
    per_camera = sh_degree is None and colors.dim() == 3
    for ci in range(viewmats.shape[0]):
        img, acc, meta = dense_render(
            means, quats, scales, opacities, colors[ci] if per_camera else colors,
            viewmats[ci], Ks[ci], width, height, near_plane, far_plane, eps2d, sh_degree,
            None if backgrounds is None else backgrounds[ci], tile_size, return_meta=True)
        imgs.append(img)
        accs.append(acc)
        metas.append(meta)
    return torch.stack(imgs), torch.stack(accs), metas


# ----------------------------------------------------------------------------- scenes
def look_at(eye, target, up=(0.0, -1.0, 0.0), dtype=torch.float64) -> Tensor:
    """World-to-camera [4,4] for an OpenCV camera at ``eye`` looking at ``target``."""
    eye_t = torch.tensor(eye, dtype=dtype)
    fwd = torch.tensor(target, dtype=dtype) - eye_t
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, torch.tensor(up, dtype=dtype))
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    rot = torch.stack([right, down, fwd])  # rows: camera axes in world coordinates
    m = torch.eye(4, dtype=dtype)
    m[:3, :3] = rot
    m[:3, 3] = -(rot @ eye_t)
    return m


def intrinsics(fx, fy, cx, cy, dtype=torch.float64) -> Tensor:
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def random_scene(seed: int, n: int, width: int, height: int, n_cameras: int = 2,
                 sh_degree: Optional[int] = None, sh_k: Optional[int] = None,
                 per_camera_colors: bool = False, opacity_range=(0.05, 0.95),
                 scale_range=(0.05, 0.5), extra_culled: bool = True,
                 opaque_stack: int = 0, stack_opacity: float = 0.97,
                 color_range=(0.0, 1.0), background: bool = True) -> dict:
    """A seeded float64 scene: Gaussians in front of camera 0, some near or over the image
    borders, cameras with non-centred principal points and fx != fy.

    With ``extra_culled`` the last three Gaussians are: one behind the camera 0 near plane,
    one far outside every frustum (no covered tile), one well inside (so N stays as given).
    With ``opaque_stack`` = k the first k Gaussians are large, opacity ``stack_opacity``,
    stacked in depth over the image centre (each centred on a pixel centre of camera 0),
    so pixels there reach the T < 1e-4 stop (and, with opacity 1, the 0.999 clamp).
    """
    g = torch.Generator().manual_seed(seed)

    def uni(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)

    f = 1.1 * width
    Ks = torch.stack([intrinsics(f * (1.0 + 0.07 * c), f * (0.93 + 0.05 * c),
                                 0.43 * width + 1.7 + c, 0.56 * height - 1.3 - 0.5 * c)
                      for c in range(n_cameras)])
    viewmats = torch.stack([look_at((0.4 * c, -0.25 * c, -0.15 * c), (0.05, 0.02, 4.0))
                            for c in range(n_cameras)])
    # Sample in camera 0's image (with a 20% margin beyond the borders) and back-project.
    k0, v0 = Ks[0], viewmats[0]
    u = uni(-0.2 * width, 1.2 * width, n)
    v = uni(-0.2 * height, 1.2 * height, n)
    z = uni(2.0, 6.0, n)
    cam = torch.stack([(u - k0[0, 2]) / k0[0, 0] * z, (v - k0[1, 2]) / k0[1, 1] * z, z], -1)
    if extra_culled and n >= 4:
        cam[-3] = torch.tensor([0.1, 0.1, -1.0], dtype=torch.float64)  # behind camera 0
        cam[-2] = torch.tensor([60.0, -40.0, 3.0], dtype=torch.float64)  # outside frustum
    rot0, tr0 = v0[:3, :3], v0[:3, 3]
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(uni(math.log(scale_range[0]), math.log(scale_range[1]), n, 3))
    opacities = uni(opacity_range[0], opacity_range[1], n)
    for i in range(opaque_stack):
        zi = 2.2 + 0.31 * i
        ui = torch.floor(k0[0, 2] + uni(-2.0, 2.0, 1)[0]) + 0.5
        vi = torch.floor(k0[1, 2] + uni(-2.0, 2.0, 1)[0]) + 0.5
        cam[i] = torch.stack([(ui - k0[0, 2]) / k0[0, 0] * zi, (vi - k0[1, 2]) / k0[1, 1] * zi,
                              torch.tensor(zi, dtype=torch.float64)])
        scales[i] = uni(0.25, 0.4, 3)
        opacities[i] = stack_opacity
    means = (cam - tr0) @ rot0  # camera -> world: R^T (p - t)
    if sh_degree is None:
        shape = (n_cameras, n, 3) if per_camera_colors else (n, 3)
        colors = uni(color_range[0], color_range[1], *shape)  # used as given, no clamp
    else:
        k = sh_k if sh_k is not None else (sh_degree + 1) ** 2
        colors = 0.35 * torch.randn(n, k, 3, generator=g, dtype=torch.float64)
        colors[:, 0, :] = uni(-1.0, 1.2, n, 3)  # DC; some colours clamp at 0
    backgrounds = uni(0.1, 0.9, n_cameras, 3) if background else None
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                viewmats=viewmats, Ks=Ks, width=width, height=height, sh_degree=sh_degree,
                backgrounds=backgrounds)


def tile_border_scene(seed: int, n: int = 12, width: int = 48, height: int = 40,
                      tile_size: int = 16, n_cameras: int = 2) -> dict:
    """Opaque, axis-elongated Gaussians whose edge u + r or u - r (or v +- r) in camera 0
    lies just past a tile border, so the tile rule visibly cuts them there: the cut pixels
    are at about 3 sigma, where alpha is still ~0.005-0.01 > 1/255. Another tile rule
    (ceil instead of floor, a tile more or less, no tiling, another radius) changes the
    image.
    """
    s = random_scene(seed, n, width, height, n_cameras=n_cameras, opacity_range=(0.93, 1.0),
                     extra_culled=False)
    g = torch.Generator().manual_seed(seed + 1000)
    k0, v0 = s["Ks"][0], s["viewmats"][0]
    rot0, tr0 = v0[:3, :3], v0[:3, 3]
    # Rotation camera 0 -> world: Gaussians with it are axis-aligned in camera 0.
    q_cam = torch.tensor(_rotmat_to_quat(rot0.T), dtype=torch.float64)
    quats = q_cam.repeat(n, 1)
    scales = torch.empty(n, 3, dtype=torch.float64)
    cam = torch.empty(n, 3, dtype=torch.float64)
    for i in range(n):
        horizontal = i % 2 == 0
        z = 2.5 + 3.0 * torch.rand(1, generator=g, dtype=torch.float64).item()
        long_ax = (0.06 + 0.05 * torch.rand(1, generator=g, dtype=torch.float64).item()) * z
        short = 0.25 * long_ax
        scales[i] = torch.tensor([long_ax, short, short] if horizontal else
                                 [short, long_ax, short], dtype=torch.float64)
        u = (0.15 + 0.7 * torch.rand(1, generator=g, dtype=torch.float64).item()) * width
        v = (0.15 + 0.7 * torch.rand(1, generator=g, dtype=torch.float64).item()) * height
        frac = 0.2 + 0.6 * torch.rand(1, generator=g, dtype=torch.float64).item()
        for _ in range(3):  # move the edge onto a border; r is an integer, so this settles
            p = torch.tensor([(u - k0[0, 2]) / k0[0, 0] * z, (v - k0[1, 2]) / k0[1, 1] * z, z],
                             dtype=torch.float64)
            world = (p - tr0) @ rot0
            m = project(world[None], quats[i:i + 1], scales[i:i + 1], v0, k0, width, height,
                        tile_size=tile_size)
            r = float(m["radii"][0])
            if i % 4 < 2:  # far edge just past a border: the spec's floor rule cuts there
                if horizontal:
                    u = tile_size * max(1, round((u + r) / tile_size)) + frac - r
                else:
                    v = tile_size * max(1, round((v + r) / tile_size)) + frac - r
            else:  # near edge just past a border: the tile before it stays uncovered
                if horizontal:
                    u = tile_size * max(1, round((u - r) / tile_size)) + 0.5 * frac + r
                else:
                    v = tile_size * max(1, round((v - r) / tile_size)) + 0.5 * frac + r
        cam[i] = torch.tensor([(u - k0[0, 2]) / k0[0, 0] * z, (v - k0[1, 2]) / k0[1, 1] * z, z],
                              dtype=torch.float64)
    s.update(means=(cam - tr0) @ rot0, quats=quats, scales=scales)
    return s


def _rotmat_to_quat(m: Tensor):
    """Rotation matrix -> (w, x, y, z) (w > 0 branch is enough for the scenes here)."""
    w = math.sqrt(max(0.0, 1.0 + float(m[0, 0] + m[1, 1] + m[2, 2]))) / 2.0
    return [w, float(m[2, 1] - m[1, 2]) / (4 * w), float(m[0, 2] - m[2, 0]) / (4 * w),
            float(m[1, 0] - m[0, 1]) / (4 * w)]


def renderer_backends() -> list:
    """Backends of reference_renderer to parametrize the comparison tests over; an unusable
    renderer yields one entry whose test then fails (never a silent skip)."""
    try:
        import mvgs_plugin.reference_renderer as reference_renderer

        names = list(reference_renderer.available_backends())
    except Exception as exc:  # noqa: BLE001 - reported through the failing entry
        return [f"renderer-unavailable: {type(exc).__name__}: {exc}"]
    return names or ["renderer-unavailable: available_backends() is empty"]
