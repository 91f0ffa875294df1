"""A model shaped like the original 3DGS code's GaussianModel (graphdeco-inria/gaussian-splatting),
and its single-camera `render`, on our CPU rasterizer.

Written here to the original's interface, so that train_mvgs.py reads as a graphdeco train.py:
raw tensors `_xyz`, `_features_dc` [N, 1, 3], `_features_rest` [N, K-1, 3], `_scaling`,
`_rotation`, `_opacity`; one Adam with a parameter group per attribute (names "xyz", "f_dc",
"f_rest", "opacity", "scaling", "rotation"); `xyz_gradient_accum` / `denom` / `max_radii2D`;
`add_densification_stats(viewspace_point_tensor, update_filter)`, `densify_and_prune(max_grad,
min_opacity, extent, max_screen_size)`, `densification_postfix(...)`, `reset_opacity()`,
`capture()` / `restore()`. The rules are the original's: clone small / split large (2 children at
scale / 1.6) at a mean NDC gradient >= max_grad, prune opacity < min_opacity and, with
max_screen_size, screen radius > max_screen_size or world size > 0.1 x extent; opacity reset to
min(opacity, 0.01); position learning rate log-linear from 1.6e-4 to 1.6e-6 times the extent.
If your code base has its own GaussianModel, train_mvgs.py's loop is what changes; this file is
what it needs from the model.
"""

from __future__ import annotations

import math
from typing import Dict, Optional

import torch
from torch import Tensor

from mvgs_plugin.adapters.gs3d import SH_C0, knn_mean_sq_dist
from mvgs_plugin.camera import Camera, stack_cameras
from mvgs_plugin.reference_renderer import rasterization
from mvgs_plugin.reference_renderer.projection import quat_to_rotmat


def inverse_sigmoid(x: Tensor) -> Tensor:
    return torch.log(x / (1 - x))


class GaussianModel:
    def __init__(self, sh_degree: int = 3):
        self.active_sh_degree = 0
        self.max_sh_degree = sh_degree
        self.percent_dense = 0.01
        self.spatial_lr_scale = 1.0
        self.optimizer: Optional[torch.optim.Adam] = None

    # ---- activated attributes, as the original's properties ----
    @property
    def get_xyz(self) -> Tensor:
        return self._xyz

    @property
    def get_scaling(self) -> Tensor:
        return torch.exp(self._scaling)

    @property
    def get_rotation(self) -> Tensor:
        return torch.nn.functional.normalize(self._rotation, dim=-1)

    @property
    def get_opacity(self) -> Tensor:
        return torch.sigmoid(self._opacity)

    @property
    def get_features(self) -> Tensor:
        return torch.cat((self._features_dc, self._features_rest), dim=1)

    def oneupSHdegree(self) -> None:
        self.active_sh_degree = min(self.active_sh_degree + 1, self.max_sh_degree)

    def create_from_pcd(self, xyz: Tensor, rgb: Tensor, spatial_lr_scale: float) -> None:
        self.spatial_lr_scale = spatial_lr_scale
        n = xyz.shape[0]
        features = torch.zeros((n, (self.max_sh_degree + 1) ** 2, 3))
        features[:, 0] = (rgb - 0.5) / SH_C0
        dist = torch.sqrt(knn_mean_sq_dist(xyz, k=3)).float().clamp_min(1e-7)
        rots = torch.zeros((n, 4))
        rots[:, 0] = 1
        self._xyz = torch.nn.Parameter(xyz.float().clone())
        self._features_dc = torch.nn.Parameter(features[:, :1].contiguous())
        self._features_rest = torch.nn.Parameter(features[:, 1:].contiguous())
        self._scaling = torch.nn.Parameter(torch.log(dist)[:, None].repeat(1, 3))
        self._rotation = torch.nn.Parameter(rots)
        self._opacity = torch.nn.Parameter(inverse_sigmoid(torch.full((n, 1), 0.1)))
        self.max_radii2D = torch.zeros(n)

    def training_setup(self, iterations: int, position_lr_init: float = 1.6e-4, position_lr_final: float = 1.6e-6,
                       feature_lr: float = 2.5e-3, opacity_lr: float = 2.5e-2, scaling_lr: float = 5e-3,
                       rotation_lr: float = 1e-3) -> None:
        # opacity_lr 2.5e-2 is graphdeco's arguments today; its first release (2023), gsplat's simple_trainer
        # and the package's GS3DAdapter use 5e-2 (train_mvgs.py --opacity-lr)
        n = self._xyz.shape[0]
        self.xyz_gradient_accum = torch.zeros((n, 1))
        self.denom = torch.zeros((n, 1))
        groups = [
            {"params": [self._xyz], "lr": position_lr_init * self.spatial_lr_scale, "name": "xyz"},
            {"params": [self._features_dc], "lr": feature_lr, "name": "f_dc"},
            {"params": [self._features_rest], "lr": feature_lr / 20.0, "name": "f_rest"},
            {"params": [self._opacity], "lr": opacity_lr, "name": "opacity"},
            {"params": [self._scaling], "lr": scaling_lr, "name": "scaling"},
            {"params": [self._rotation], "lr": rotation_lr, "name": "rotation"},
        ]
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        self._lr = (position_lr_init * self.spatial_lr_scale, position_lr_final * self.spatial_lr_scale, iterations)

    def update_learning_rate(self, iteration: int) -> float:
        """Position learning rate, log-linear from init to final over the run."""
        start, end, length = self._lr
        t = min(max(iteration / length, 0.0), 1.0)
        lr = math.exp(math.log(start) * (1 - t) + math.log(end) * t)
        for group in self.optimizer.param_groups:
            if group["name"] == "xyz":
                group["lr"] = lr
        return lr

    # ---- densification, as the original ----
    def add_densification_stats(self, viewspace_point_tensor: Tensor, update_filter: Tensor) -> None:
        self.xyz_gradient_accum[update_filter] += torch.norm(viewspace_point_tensor.grad[update_filter, :2], dim=-1,
                                                             keepdim=True)
        self.denom[update_filter] += 1

    def _attributes(self) -> Dict[str, torch.nn.Parameter]:
        return {"xyz": self._xyz, "f_dc": self._features_dc, "f_rest": self._features_rest,
                "opacity": self._opacity, "scaling": self._scaling, "rotation": self._rotation}

    def _set_attributes(self, tensors: Dict[str, Tensor]) -> None:
        self._xyz, self._features_dc, self._features_rest = tensors["xyz"], tensors["f_dc"], tensors["f_rest"]
        self._opacity, self._scaling, self._rotation = tensors["opacity"], tensors["scaling"], tensors["rotation"]

    def _swap(self, make, names=None) -> Dict[str, torch.nn.Parameter]:
        """Replace the parameter of every group (or of those in `names`) by make(name, old
        tensor, is_state) (Adam moments follow: make is called on them with is_state True)."""
        out = {}
        for group in self.optimizer.param_groups:
            if names is not None and group["name"] not in names:
                continue
            old = group["params"][0]
            state = self.optimizer.state.pop(old, None)
            new = torch.nn.Parameter(make(group["name"], old.detach(), False).requires_grad_(True))
            if state is not None:
                for key in ("exp_avg", "exp_avg_sq"):
                    state[key] = make(group["name"], state[key], True)
                self.optimizer.state[new] = state
            group["params"][0] = new
            out[group["name"]] = new
        return out

    def replace_tensor_to_optimizer(self, tensor: Tensor, name: str) -> Dict[str, torch.nn.Parameter]:
        return self._swap(lambda n, t, st: torch.zeros_like(tensor) if st else tensor, names=(name,))

    def prune_points(self, mask: Tensor) -> None:
        keep = ~mask
        self._set_attributes(self._swap(lambda n, t, st: t[keep]))
        self.xyz_gradient_accum = self.xyz_gradient_accum[keep]
        self.denom = self.denom[keep]
        self.max_radii2D = self.max_radii2D[keep]

    def densification_postfix(self, new_xyz, new_features_dc, new_features_rest, new_opacities, new_scaling,
                              new_rotation) -> None:
        new = {"xyz": new_xyz, "f_dc": new_features_dc, "f_rest": new_features_rest, "opacity": new_opacities,
               "scaling": new_scaling, "rotation": new_rotation}
        self._set_attributes(self._swap(lambda n, t, st: torch.cat([t, torch.zeros_like(new[n]) if st else new[n]])))
        n = self._xyz.shape[0]
        self.xyz_gradient_accum = torch.zeros((n, 1))
        self.denom = torch.zeros((n, 1))
        self.max_radii2D = torch.zeros(n)

    def _rows(self, mask: Tensor, repeat: int = 1):
        return [t.detach()[mask].repeat(repeat, *[1] * (t.dim() - 1)) for t in self._attributes().values()]

    def densify_and_split(self, grads: Tensor, grad_threshold: float, scene_extent: float, N: int = 2) -> None:
        n = self._xyz.shape[0]
        padded = torch.zeros(n)
        padded[:grads.shape[0]] = grads.squeeze()
        sel = (padded >= grad_threshold) & (self.get_scaling.max(dim=1).values > self.percent_dense * scene_extent)
        stds = self.get_scaling[sel].repeat(N, 1)
        samples = torch.normal(mean=torch.zeros_like(stds), std=stds)
        rots = quat_to_rotmat(self.get_rotation[sel]).repeat(N, 1, 1)
        xyz, f_dc, f_rest, opacity, _, rotation = self._rows(sel, N)
        new_xyz = torch.bmm(rots, samples[..., None])[..., 0] + xyz
        new_scaling = torch.log(self.get_scaling[sel].repeat(N, 1) / (0.8 * N))
        self.densification_postfix(new_xyz, f_dc, f_rest, opacity, new_scaling.detach(), rotation)
        self.prune_points(torch.cat([sel, torch.zeros(N * int(sel.sum()), dtype=torch.bool)]))

    def densify_and_clone(self, grads: Tensor, grad_threshold: float, scene_extent: float) -> None:
        sel = (torch.norm(grads, dim=-1) >= grad_threshold) & (
            self.get_scaling.max(dim=1).values <= self.percent_dense * scene_extent)
        self.densification_postfix(*self._rows(sel))

    def densify_and_prune(self, max_grad: float, min_opacity: float, extent: float,
                          max_screen_size: Optional[float]) -> None:
        grads = self.xyz_gradient_accum / self.denom
        grads[grads.isnan()] = 0.0
        self.densify_and_clone(grads, max_grad, extent)
        self.densify_and_split(grads, max_grad, extent)
        prune = (self.get_opacity < min_opacity).squeeze()
        if max_screen_size:
            prune = prune | (self.max_radii2D > max_screen_size) | (self.get_scaling.max(dim=1).values > 0.1 * extent)
        self.prune_points(prune)

    def reset_opacity(self) -> None:
        value = inverse_sigmoid(torch.min(self.get_opacity, torch.ones_like(self.get_opacity) * 0.01))
        self._opacity = self.replace_tensor_to_optimizer(value.detach(), "opacity")["opacity"]

    # ---- checkpoints, as the original's capture / restore ----
    def capture(self):
        return (self.active_sh_degree, self._xyz.detach(), self._features_dc.detach(), self._features_rest.detach(),
                self._scaling.detach(), self._rotation.detach(), self._opacity.detach(), self.max_radii2D,
                self.xyz_gradient_accum, self.denom, self.optimizer.state_dict(), self.spatial_lr_scale)

    def restore(self, model_args, iterations: int, **lrs) -> None:
        """As the original's restore(model_args, training_args): lrs are training_setup's."""
        (self.active_sh_degree, xyz, f_dc, f_rest, scaling, rotation, opacity, max_radii2D, accum, denom, opt_state,
         self.spatial_lr_scale) = model_args
        self._xyz, self._features_dc, self._features_rest = (torch.nn.Parameter(t.clone()) for t in (xyz, f_dc, f_rest))
        self._scaling, self._rotation, self._opacity = (torch.nn.Parameter(t.clone()) for t in (scaling, rotation, opacity))
        self.training_setup(iterations, **lrs)
        self.xyz_gradient_accum, self.denom, self.max_radii2D = accum.clone(), denom.clone(), max_radii2D.clone()
        self.optimizer.load_state_dict(opt_state)


def render(viewpoint_camera: Camera, pc: GaussianModel, bg_color: Tensor) -> Dict[str, Tensor]:
    """One camera, as the original's render(): {"render" [3, H, W], "viewspace_points" [N, 3]
    whose .grad after backward holds the screen-space gradient in NDC units (the original CUDA
    rasterizer's: our rasterizer's pixel gradient times W/2 and H/2), "visibility_filter" [N],
    "radii" [N]}."""
    viewmats, Ks = stack_cameras([viewpoint_camera])
    w, h = viewpoint_camera.width, viewpoint_camera.height
    image, _, meta = rasterization(pc.get_xyz, pc.get_rotation, pc.get_scaling, pc.get_opacity.squeeze(-1),
                                   pc.get_features, viewmats, Ks, w, h, sh_degree=pc.active_sh_degree,
                                   backgrounds=bg_color[None])
    viewspace = torch.zeros_like(pc.get_xyz)
    if meta["means2d"].requires_grad:
        scale = torch.tensor([w / 2.0, h / 2.0])

        def to_ndc(grad: Tensor) -> None:
            viewspace.grad = torch.cat([grad[0] * scale, torch.zeros_like(grad[0, :, :1])], dim=-1)

        meta["means2d"].register_hook(to_ndc)
    radii = meta["radii"][0].max(dim=-1).values
    return {"render": image[0].permute(2, 0, 1), "viewspace_points": viewspace, "visibility_filter": radii > 0,
            "radii": radii}
