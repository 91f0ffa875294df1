"""One entry point for a scene folder of any supported format."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import torch

from .colmap import load_colmap
from .nerf import is_dynamic, load_dnerf, load_nerf_synthetic
from .scene import Scene

LOG = logging.getLogger("mvgs_plugin")


def load_scene(path, init: Optional[str] = "triangulate", init_points: int = 10_000, init_seed: int = 0,
               init_cache=None, threads: Optional[int] = None, background_points: int = 0) -> Scene:
    """A scene folder, its format told by its files: NeRF-synthetic or D-NeRF
    (transforms_train.json; D-NeRF when its frames carry a time) or COLMAP (sparse/, sparse/0, or
    cameras.bin / cameras.txt at the top). Raises ValueError naming the folder when it does not
    exist or holds neither.

    A scene without a point file (points3d.ply beside the jsons, COLMAP's points3D) gets initial
    points by ``init`` (:func:`~mvgs_plugin.data.triangulate.initial_points`): "triangulate"
    (default: pycolmap from the training views at their poses, the uncovered space filled with
    photo-consistent points, falling back to "random" with the reason when too few tracks are
    found), "random" (the 3DGS cube for rigs around the scene, the training frusta for
    forward-facing ones), "frusta" or "cube"; ``init_points`` of them (tracks beyond it are all
    kept), seeded by ``init_seed``. None leaves ``scene.points`` None (the adapters then draw
    random points themselves). ``init_cache``: a folder to keep the triangulation in for the
    next run (None: a temporary folder; the scene folder is never written). ``threads``:
    pycolmap's threads (default: torch's). ``background_points``: that many more points on a
    shell beyond a rig that surrounds the scene, for its far background
    (:func:`~mvgs_plugin.data.init.background_shell`; 0: none; a forward-facing rig, a scene whose
    points lie mostly beyond the shell (a room shot from its middle), or a scene left without points
    by ``init=None``, gets none). What was done is in ``scene.points_origin`` and
    logged to the "mvgs_plugin" logger.
    """
    if isinstance(background_points, bool) or not isinstance(background_points, int) or background_points < 0:
        raise ValueError(f"background_points must be an int >= 0, got {background_points!r}")
    path = Path(path)
    if not path.exists():
        raise ValueError(f"scene folder {path} does not exist")
    if not path.is_dir():
        raise ValueError(f"scene path {path} is a file, expected a folder (COLMAP or NeRF-synthetic)")
    if (path / "transforms_train.json").exists():
        scene = load_dnerf(path) if is_dynamic(path) else load_nerf_synthetic(path)
    elif (path / "sparse").exists() or (path / "cameras.bin").exists() or (path / "cameras.txt").exists():
        scene = load_colmap(path)
    else:
        raise ValueError(f"{path} is neither a COLMAP scene (sparse/) nor a NeRF-synthetic one (transforms_train.json)")
    if scene.points is None and init is not None:
        from .triangulate import initial_points

        made = initial_points(scene, init, init_points, init_seed, init_cache, threads)
        scene.points, scene.points_origin = made.points, made.description
        LOG.info("%s: %s", path, made.description)
    if background_points and scene.points is not None:
        from .init import background_shell
        from .scene import PointCloud

        xyz, rgb, said = background_shell(scene.train_cameras, scene.center, background_points, scene.image,
                                          points=scene.points.xyz)
        if xyz.shape[0]:
            pts = scene.points  # float32 (PointCloud's dtype)
            scene.points = PointCloud(xyz=torch.cat([pts.xyz, xyz.to(pts.xyz.dtype)]),
                                      rgb=torch.cat([pts.rgb, rgb.to(pts.rgb.dtype)]), shell=pts.shell + len(xyz))
        scene.points_origin = f"{scene.points_origin}; {said}" if scene.points_origin else said
        LOG.info("%s: %s", path, said)
    return scene
