"""One entry point for a scene folder of any supported format."""

from __future__ import annotations

from pathlib import Path

from .colmap import load_colmap
from .nerf import is_dynamic, load_dnerf, load_nerf_synthetic
from .scene import Scene


def load_scene(path) -> Scene:
    """A scene folder, its format told by its files: NeRF-synthetic or D-NeRF
    (transforms_train.json; D-NeRF when its frames carry a time) or COLMAP (sparse/, sparse/0, or
    cameras.bin / cameras.txt at the top). Raises ValueError naming the folder when it does not
    exist or holds neither."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"scene folder {path} does not exist")
    if not path.is_dir():
        raise ValueError(f"scene path {path} is a file, expected a folder (COLMAP or NeRF-synthetic)")
    if (path / "transforms_train.json").exists():
        return load_dnerf(path) if is_dynamic(path) else load_nerf_synthetic(path)
    if (path / "sparse").exists() or (path / "cameras.bin").exists() or (path / "cameras.txt").exists():
        return load_colmap(path)
    raise ValueError(f"{path} is neither a COLMAP scene (sparse/) nor a NeRF-synthetic one (transforms_train.json)")
