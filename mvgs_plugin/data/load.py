"""One entry point for a scene folder of any supported format."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import torch

from .colmap import load_colmap
from .images import check_background
from .hypernerf import is_hypernerf, load_hypernerf
from .llff import is_llff, load_llff
from .nerf import is_dynamic, load_dnerf, load_nerf_synthetic
from .scene import Scene

LOG = logging.getLogger("mvgs_plugin")


def scene_layout(path) -> Optional[str]:
    """The layout load_scene reads a folder as: "nerf" (transforms_train.json, or one
    transforms.json in a folder without a COLMAP model), "colmap" (sparse/, or cameras.bin /
    cameras.txt at the top), "hypernerf" (dataset.json and camera/), "llff" (LLFF's
    poses_bounds.npy and none of those), or None."""
    path = Path(path)
    colmap = (path / "sparse").exists() or (path / "cameras.bin").exists() or (path / "cameras.txt").exists()
    if (path / "transforms_train.json").exists() or (not colmap and (path / "transforms.json").exists()):
        return "nerf"
    if colmap:
        return "colmap"
    if is_hypernerf(path):
        return "hypernerf"
    return "llff" if is_llff(path) else None


def load_scene(path, init: Optional[str] = "triangulate", init_points: int = 10_000, init_seed: int = 0,
               init_cache=None, threads: Optional[int] = None, background_points: int = 0,
               background="auto", images=None, backdrop_drawn: bool = True,
               background_radius: Optional[float] = None) -> Scene:
    """A scene folder, its format told by its files: NeRF-synthetic or D-NeRF
    (transforms_train.json, or one transforms.json as instant-ngp and nerfstudio write it; D-NeRF
    when its frames carry a time), COLMAP (sparse/, sparse/0, or cameras.bin / cameras.txt at
    the top) or LLFF's poses_bounds.npy with still images or a multi-camera video's frames
    (DyNeRF / Neu3D, as 4DGS trains on it: :func:`~mvgs_plugin.data.llff.load_llff`), or a
    HyperNeRF / Nerfies capture (dataset.json, camera/, rgb/2x: :mod:`~mvgs_plugin.data.hypernerf`). Raises
    ValueError naming the folder when it does not exist or holds none of them.

    ``background``: "auto" (the NeRF loaders' rule, see :func:`load_nerf_synthetic`: RGBA on
    white, images without alpha on the colour their borders show; a COLMAP scene drops alpha and
    has none), or an RGB colour in [0, 1] that RGBA images are composited on and that is the
    scene's background (``scene.background``, ``scene.background_origin``).

    ``images``: a COLMAP scene's image folder, relative to ``path`` or absolute (default:
    ``path/images`` when it exists, else ``path``); a copy downscaled by one factor (Mip-NeRF
    360's ``images_4``) scales the cameras to it (:func:`load_colmap`). A NeRF-style scene takes
    the name of a downscaled copy of nerfstudio's ``images/`` beside its json (``images_4``), read
    in place of ``images/`` with each camera scaled to it (:func:`load_nerf_synthetic`).

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
    by ``init=None``, gets none; ``background_radius``: the shell's radius in rig radii, None:
    :data:`~mvgs_plugin.data.init.SHELL_RADIUS`), and no point of it that shows only ``scene.background``, the
    colour the renderer draws behind the Gaussians, in every view that sees it (an object on a
    transparent or one-colour backdrop gets none at all). ``backdrop_drawn=False`` keeps those: a
    run that trains in front of random colours (``MVGSConfig(background="random")``) has the
    Gaussians paint the backdrop. What was done is in ``scene.points_origin`` and
    logged to the "mvgs_plugin" logger.
    """
    if isinstance(background_points, bool) or not isinstance(background_points, int) or background_points < 0:
        raise ValueError(f"background_points must be an int >= 0, got {background_points!r}")
    from .init import SHELL_RADIUS, background_shell, is_shell_radius

    if background_radius is not None and not is_shell_radius(background_radius):
        raise ValueError(f"background_radius must be None or a finite number of rig radii > 1, got {background_radius!r}")
    path = Path(path)
    if not path.exists():
        raise ValueError(f"scene folder {path} does not exist")
    if not path.is_dir():
        raise ValueError(f"scene path {path} is a file, expected a folder (COLMAP or NeRF-synthetic)")
    if not (isinstance(background, str) and background == "auto"):
        background = check_background(background)  # a ValueError naming the value
        if background is None:
            raise ValueError("background must be 'auto' or 3 floats in [0,1], got None")
    layout = scene_layout(path)
    if layout == "nerf":
        scene = (load_dnerf if is_dynamic(path) else load_nerf_synthetic)(path, background=background, images=images)
    elif layout == "colmap":
        folder = None if images is None else path / images  # an absolute one stays itself
        if folder is not None and not folder.is_dir():
            raise ValueError(f"images folder {folder} does not exist (images={str(images)!r}, relative to {path})")
        scene = load_colmap(path, images_dir=folder, background=None if background == "auto" else background)
    elif layout in ("llff", "hypernerf"):  # their loaders refuse an images folder outside the scene folder
        scene = (load_llff if layout == "llff" else load_hypernerf)(path, images=images)
        if background not in (None, "auto"):
            scene.background, scene.background_origin = background, "given"
    else:
        raise ValueError(f"{path} is neither a COLMAP scene (sparse/), a NeRF-synthetic one (transforms_train.json, "
                         "or one transforms.json), a HyperNeRF one (dataset.json, camera/) nor an LLFF one (poses_bounds.npy)")
    LOG.info("%s: background %s", path, scene.background_origin)
    if scene.points is None and init is not None:
        from .triangulate import initial_points

        made = initial_points(scene, init, init_points, init_seed, init_cache, threads)
        scene.points, scene.points_origin = made.points, made.description
        LOG.info("%s: %s", path, made.description)
    if background_points and scene.points is not None:
        from .scene import PointCloud
        from .triangulate import synchronized_instant

        views = synchronized_instant(scene.train_cameras) or scene.train_cameras  # a video: its first instant
        xyz, rgb, said = background_shell(views, scene.center, background_points, scene.image,
                                          points=scene.points.xyz, mask=scene.mask,
                                          backdrop=scene.background if backdrop_drawn else None,
                                          radius=SHELL_RADIUS if background_radius is None else background_radius)
        if xyz.shape[0]:
            pts = scene.points  # float32 (PointCloud's dtype)
            scene.points = PointCloud(xyz=torch.cat([pts.xyz, xyz.to(pts.xyz.dtype)]),
                                      rgb=torch.cat([pts.rgb, rgb.to(pts.rgb.dtype)]), shell=pts.shell + len(xyz))
        scene.points_origin = f"{scene.points_origin}; {said}" if scene.points_origin else said
        LOG.info("%s: %s", path, said)
    return scene
