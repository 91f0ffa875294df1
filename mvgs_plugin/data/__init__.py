"""Scene loaders: COLMAP (via pycolmap), NeRF-synthetic and D-NeRF -> cameras + images.

Every loader returns a :class:`Scene`; see ``docs/data.md`` for pointing the package at your
own data.
"""

from .colmap import load_colmap
from .load import load_scene
from .nerf import is_dynamic, load_dnerf, load_nerf_synthetic
from .scene import PointCloud, Scene, camera_normalization

__all__ = ["Scene", "PointCloud", "camera_normalization", "load_colmap", "load_nerf_synthetic",
           "load_dnerf", "is_dynamic", "load_scene"]
