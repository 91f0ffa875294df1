"""nerfstudio's downscaled copies (images_2/, masks_2/ beside a transforms.json): read in place
of images/ with every camera scaled to them, checked against the full-size scene's cameras and
the full-size files subsampled."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import skimage.io
import torch

from mvgs_plugin.data import load_scene
from test_masks import TABLETOP, _nerfstudio


@pytest.mark.parametrize("declared", [True, False])
def test_a_nerfstudio_downscaled_copy_is_read_with_its_cameras_scaled(tmp_path, declared):
    """images_2/ and masks_2/ beside a transforms.json whose intrinsics are for the 16 px images:
    the 8 px copies are read, each camera's focal length and principal point halved (written out),
    and a world point lands at half its full-size pixel coordinates."""
    _nerfstudio(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    if not declared:  # the full size then comes from the full-size images' headers
        del meta["w"], meta["h"]
        (tmp_path / "transforms.json").write_text(json.dumps(meta))
    for folder in ("images", "masks"):
        (tmp_path / f"{folder}_2").mkdir()
        for f in (tmp_path / folder).iterdir():
            arr = skimage.io.imread(f)
            skimage.io.imsave(tmp_path / f"{folder}_2" / f.name, arr[::2, ::2], check_contrast=False)
    with pytest.warns(UserWarning, match="held out"):
        full = load_scene(tmp_path, init=None)
    with pytest.warns(UserWarning, match="held out"):
        small = load_scene(tmp_path, init=None, images="images_2")
    for a, b in zip(full.cameras, small.cameras):
        assert (b.width, b.height) == (8, 8) and b.name == a.name.replace("images/", "images_2/")
        assert np.allclose(b.K.numpy(), np.diag([0.5, 0.5, 1.0]) @ a.K.numpy(), atol=1e-12)
        X = torch.tensor([[0.1, -0.2, 0.05]], dtype=torch.float64)
        assert torch.allclose(b.project(X)[0], a.project(X)[0] / 2, atol=1e-9)
        k = int(a.name.split("/f")[1][:-4])
        want = skimage.io.imread(tmp_path / f"images/f{k}.png")[::2, ::2] / 255.0
        assert np.allclose(small.image(b).numpy(), want, atol=1e-6)
        assert np.array_equal(small.mask(b)[..., 0].numpy(),
                              (skimage.io.imread(tmp_path / f"masks/f{k}.png")[::2, ::2] != 0).astype(np.float32))


def test_a_downscaled_copy_of_a_scene_not_under_images_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"images='images_2': a NeRF-style scene takes a downscaled copy"):
        load_scene(TABLETOP, init=None, images="images_2")
    shutil.copytree(TABLETOP, tmp_path / "s")
    (tmp_path / "s" / "images_2").mkdir()
    with pytest.raises(ValueError, match=r"its file_path 'train/r_000' does not lie in images/"):
        load_scene(tmp_path / "s", init=None, images="images_2")


def test_a_copy_flattened_as_nerfstudio_writes_it_is_found(tmp_path):
    """file_path images/cam0/f{k}.png with the copy at images_2/f{k}.png (nerfstudio looks for the
    file's name directly under the copy): read, the same pixels as the sub-path copy."""
    _nerfstudio(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    (tmp_path / "images" / "cam0").mkdir()
    (tmp_path / "images_2").mkdir()
    for f in meta["frames"]:
        name = f["file_path"].split("/")[-1]
        shutil.move(tmp_path / "images" / name, tmp_path / "images" / "cam0" / name)
        f["file_path"] = f"images/cam0/{name}"
        del f["mask_path"]
        arr = skimage.io.imread(tmp_path / "images" / "cam0" / name)
        skimage.io.imsave(tmp_path / "images_2" / name, arr[::2, ::2], check_contrast=False)
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="held out"):
        small = load_scene(tmp_path, init=None, images="images_2")
    for cam in small.cameras:
        name = cam.name.split("/")[-1]
        assert cam.name == f"images_2/{name}" and (cam.width, cam.height) == (8, 8)
        want = skimage.io.imread(tmp_path / "images" / "cam0" / name)[::2, ::2] / 255.0
        assert np.allclose(small.image(cam).numpy(), want, atol=1e-6)
