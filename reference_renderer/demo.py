"""Renders a small procedural Gaussian scene from a ring of cameras and writes a PNG.

    python -m mvgs_plugin.reference_renderer.demo --out demo.png

The scene is a torus knot of coloured, view-dependent (SH degree 1) Gaussians over a disc of flat
ones; it exercises the whole pipeline (projection, SH, binning, compositing, backward) and prints
the time of each batch render and of one gradient step.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from .rendering import available_backends, rasterization


def demo_scene(n_knot: int = 3000, n_disc: int = 2000, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(n_knot, generator=g) * 2 * math.pi
    r = 0.6 + 0.25 * torch.cos(3 * t)
    knot = torch.stack([r * torch.cos(2 * t), r * torch.sin(2 * t), 0.45 + 0.25 * torch.sin(3 * t)], -1)
    knot += 0.03 * torch.randn(n_knot, 3, generator=g)
    rho = 1.4 * torch.sqrt(torch.rand(n_disc, generator=g))
    phi = torch.rand(n_disc, generator=g) * 2 * math.pi
    disc = torch.stack([rho * torch.cos(phi), rho * torch.sin(phi), torch.zeros(n_disc)], -1)
    means = torch.cat([knot, disc])
    hue = torch.cat([t / (2 * math.pi), 0.6 + 0.1 * torch.rand(n_disc, generator=g)])
    rgb = 0.5 + 0.45 * torch.stack([torch.cos(2 * math.pi * (hue + k / 3)) for k in range(3)], -1)
    checker = ((disc[:, 0] * 3).floor() + (disc[:, 1] * 3).floor()) % 2
    rgb[n_knot:] = (0.25 + 0.5 * checker)[:, None].expand(-1, 3)
    sh = torch.zeros(len(means), 4, 3)
    sh[:, 0] = (rgb - 0.5) / 0.28209479177387814
    sh[:n_knot, 1:] = 0.15 * torch.randn(n_knot, 3, 3, generator=g)  # some view dependence
    scales = torch.cat([torch.full((n_knot, 3), 0.03), torch.tensor([0.05, 0.05, 0.004]).expand(n_disc, 3)])
    quats = torch.nn.functional.normalize(torch.randn(len(means), 4, generator=g), dim=-1)
    quats[n_knot:] = torch.tensor([1.0, 0, 0, 0])
    opacities = torch.cat([torch.full((n_knot,), 0.8), torch.full((n_disc,), 0.9)])
    return means, quats, scales, opacities, sh


def ring_cameras(n: int, size: int, radius: float = 3.2, height: float = 1.6):
    """World-to-camera matrices (OpenCV axes) on a ring, looking at the origin; z is up."""
    mats = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = torch.tensor([radius * math.cos(a), radius * math.sin(a), height])
        fwd = torch.nn.functional.normalize(-eye, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 0, 1])), dim=0)
        down = torch.linalg.cross(fwd, right)
        R = torch.stack([right, down, fwd])  # rows: camera axes in world coordinates
        w2c = torch.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        mats.append(w2c)
    K = torch.tensor([[1.1 * size, 0, size / 2], [0, 1.1 * size, size / 2], [0, 0, 1]])
    return torch.stack(mats), K.expand(n, 3, 3).clone()


def save_png(path: str, image: np.ndarray) -> None:
    """Writes an 8-bit PNG atomically (a crash never leaves a truncated file at `path`), with the
    mode the umask gives a new file (mvgs_plugin.io.write_atomic)."""
    from PIL import Image

    from mvgs_plugin.io import write_atomic

    pixels = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
    write_atomic(path, lambda f: pixels.save(f, format="PNG"), binary=True, make_folder=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="demo.png")
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--backend", default=None, choices=[None, "cpp", "torch"])
    args = ap.parse_args()

    means, quats, scales, opacities, sh = demo_scene()
    viewmats, Ks = ring_cameras(args.views, args.size)
    bg = torch.full((args.views, 3), 0.05)
    print(f"backends available: {available_backends()}")
    t0 = time.perf_counter()
    with torch.no_grad():
        img, alpha, meta = rasterization(means, quats, scales, opacities, sh, viewmats, Ks, args.size,
                                         args.size, sh_degree=1, backgrounds=bg, backend=args.backend)
    t_render = time.perf_counter() - t0

    params = [p.clone().requires_grad_() for p in (means, quats, scales, opacities, sh)]
    t0 = time.perf_counter()
    out, _, _ = rasterization(*params, viewmats, Ks, args.size, args.size, sh_degree=1, backgrounds=bg,
                              backend=args.backend)
    out.square().mean().backward()
    t_grad = time.perf_counter() - t0

    grid = torch.cat([torch.cat(list(img[i : i + 3]), dim=1) for i in range(0, args.views, 3)], dim=0)
    save_png(args.out, grid.numpy())
    visible = int((meta["radii"][..., 0] > 0).sum())
    print(
        f"rendered {len(means)} Gaussians into {args.views} views of {args.size}x{args.size} "
        f"({visible} Gaussian-view pairs visible) with backend {meta['backend']}: "
        f"{t_render:.3f} s forward, {t_grad:.3f} s forward+backward -> {args.out}"
    )


if __name__ == "__main__":
    main()
