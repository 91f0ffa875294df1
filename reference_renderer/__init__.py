"""Differentiable CPU Gaussian-splatting rasterizer with gsplat's call shape.

Classic 3DGS image formation (EWA projection, 16x16 tiles, front-to-back alpha compositing), so a
model trained with it renders the same under gsplat or the original CUDA rasterizer. It does not
depend on mvgs_plugin.

    from mvgs_plugin.reference_renderer import rasterization
    colors, alphas, meta = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, W, H)
"""

from .projection import Projection, covariance_3d, project, quat_to_rotmat
from .rendering import available_backends, rasterization
from .sh import eval_sh, sh_basis, sh_to_rgb

__all__ = [
    "rasterization",
    "available_backends",
    "project",
    "Projection",
    "quat_to_rotmat",
    "covariance_3d",
    "eval_sh",
    "sh_basis",
    "sh_to_rgb",
]
