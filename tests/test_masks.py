"""Masks (nerfstudio's mask_path): which pixels the loss and the test metrics count.

Checked against plain computations: the mask file's pixels, skimage's resize for the pyramid
levels, the PSNR of the kept pixels picked out by boolean indexing, and gradients that must not
change when only ignored pixels of a target change. The training path (the 3DGS example through
its hand-off, densification, opacity reset and a resume) is in the slow test at the end.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import skimage.io
import torch

from mvgs_plugin import MVGS, MVGSConfig
from mvgs_plugin import controller as controller_module
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig
from mvgs_plugin.data import Scene, load_scene
from mvgs_plugin.data.images import read_mask
from mvgs_plugin.metrics import masked_psnr, psnr
from mvgs_plugin.testing import synthetic_scene
from test_example_resume import Crash, _example, record_steps  # the example loader and the simulated kill of the resume tests

ROOT = Path(__file__).resolve().parents[1]
TABLETOP = ROOT / "examples" / "scenes" / "tabletop"


# ---- reading a mask ------------------------------------------------------------------------------

def test_a_mask_file_keeps_every_non_zero_pixel(tmp_path):
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 4, size=(9, 7), dtype=np.uint8) * 60  # 0, 60, 120, 180
    skimage.io.imsave(tmp_path / "m.png", grey, check_contrast=False)
    got = read_mask(tmp_path / "m.png")
    assert got.shape == (9, 7, 1) and got.dtype == torch.float32
    assert np.array_equal(got[..., 0].numpy(), (grey != 0).astype(np.float32))
    # saved as RGB with equal channels (many tools do): the same mask
    skimage.io.imsave(tmp_path / "rgb.png", np.repeat(grey[..., None], 3, axis=2), check_contrast=False)
    assert torch.equal(read_mask(tmp_path / "rgb.png"), got)


def test_a_mask_in_an_alpha_channel_or_a_palette_is_read(tmp_path):
    """A cut-out saved as white with transparent holes keeps the opaque pixels; grey and alpha
    that agree are one mask; grey and alpha that disagree are refused. A palette image keeps
    its non-zero indices (as nerfstudio reads it), whatever colours the palette gives them."""
    from PIL import Image

    hole = np.zeros((6, 8), bool)
    hole[1:4, 2:6] = True
    rgba = np.full((6, 8, 4), 255, np.uint8)
    rgba[..., 3][hole] = 0
    skimage.io.imsave(tmp_path / "cut.png", rgba, check_contrast=False)
    want = (~hole).astype(np.float32)
    assert np.array_equal(read_mask(tmp_path / "cut.png")[..., 0].numpy(), want)
    la = np.stack([np.where(hole, 0, 255), np.where(hole, 0, 255)], -1).astype(np.uint8)
    skimage.io.imsave(tmp_path / "la.png", la, check_contrast=False)
    assert np.array_equal(read_mask(tmp_path / "la.png")[..., 0].numpy(), want)
    la[0, 0, 0] = 0  # the grey drops a pixel the alpha keeps
    skimage.io.imsave(tmp_path / "bad.png", la, check_contrast=False)
    with pytest.raises(ValueError, match=r"bad\.png: its grey values and its alpha channel both vary and disagree on 1 pixels"):
        read_mask(tmp_path / "bad.png")
    indices = np.where(hole, 0, 2).astype(np.uint8)
    img = Image.fromarray(indices, mode="P")
    img.putpalette([255, 255, 255, 0, 0, 0, 200, 0, 0] + [0] * 759)  # index 0 white, 2 red
    img.save(tmp_path / "p.png")
    assert np.array_equal(read_mask(tmp_path / "p.png")[..., 0].numpy(), want)


def test_a_colour_image_is_not_taken_for_a_mask(tmp_path):
    img = np.zeros((5, 5, 3), np.uint8)
    img[2, 3] = (255, 0, 0)
    skimage.io.imsave(tmp_path / "c.png", img, check_contrast=False)
    with pytest.raises(ValueError, match=r"c\.png is a colour image whose channels differ"):
        read_mask(tmp_path / "c.png")


# ---- the metric --------------------------------------------------------------------------------

def test_masked_psnr_is_the_psnr_of_the_kept_pixels():
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(12, 10, 3, generator=g), torch.rand(12, 10, 3, generator=g)
    keep = torch.rand(12, 10, generator=g) > 0.6
    # a plain reference: the PSNR of the pixels boolean indexing picks out
    assert masked_psnr(a, b, keep.float()) == pytest.approx(psnr(a[keep], b[keep]), rel=1e-12)
    assert masked_psnr(a, b, keep.float()[..., None]) == pytest.approx(psnr(a[keep], b[keep]), rel=1e-12)
    # fractional weights: the weighted mean of the squared error, written out
    w = torch.rand(12, 10, generator=g)
    ad, bd, wd = a.double(), b.double(), w.double()
    mse = sum(float(wd[i, j]) * float(((ad[i, j] - bd[i, j]) ** 2).sum()) for i in range(12) for j in range(10))
    mse /= 3 * float(wd.sum())
    assert masked_psnr(a, b, w) == pytest.approx(-10 * math.log10(mse), rel=1e-9)
    c = b.clone()
    c[keep] = a[keep]  # the kept pixels agree, the others do not
    assert masked_psnr(a, c, keep.float()) == math.inf


@pytest.mark.parametrize("weights,message", [
    (torch.zeros(4, 4), "keep no pixel"),
    (torch.ones(4, 5), r"weights \[4, 5, 1\] do not fit images \[4, 4, 3\]"),
    (torch.full((4, 4), 1.5), r"in \[0, 1\]"),
])
def test_masked_psnr_refuses_weights_it_cannot_use(weights, message):
    with pytest.raises(ValueError, match=message):
        masked_psnr(torch.rand(4, 4, 3), torch.rand(4, 4, 3), weights)


# ---- the scene ---------------------------------------------------------------------------------

def _masked_scene(masks: dict, size: int = 24) -> Scene:
    base = synthetic_scene(n_train=4, n_test=2, size=size)
    images = {c.uid: base.image(c) for c in base.cameras}
    return Scene(base.train_cameras, base.test_cameras, images, points=base.points, masks=masks)


def test_scene_masks_at_every_pyramid_level():
    g = torch.Generator().manual_seed(2)
    keep = (torch.rand(24, 24, generator=g) > 0.3).float()
    scene = _masked_scene({1: keep})
    cam, other = scene.camera("view_001"), scene.train_cameras[-1]
    assert scene.has_masks and [c.uid for c in scene.masked()] == [1]
    assert torch.equal(scene.mask(cam)[..., 0], keep)
    # the 1/2 level: the mask resized as skimage resizes an image (antialiased, full frame on full frame)
    from skimage.transform import resize

    ref = resize(keep.numpy().astype(np.float64), (12, 12), order=1, mode="symmetric", anti_aliasing=True,
                 preserve_range=True)
    assert np.allclose(scene.mask(cam, 2)[..., 0].numpy(), ref, atol=1e-6)
    assert 0 < float(scene.mask(cam, 2).min()) < 1  # edges get weights between 0 and 1
    # a camera without a mask counts every pixel; a scene without masks has none
    assert torch.equal(scene.mask(other, 2), torch.ones(12, 12, 1))
    assert synthetic_scene().mask(synthetic_scene().train_cameras[0]) is None
    assert "1 masks" in repr(scene)


def test_the_pyramid_images_of_a_masked_view_take_no_colour_from_ignored_pixels():
    """Changing the pixels a mask ignores changes no level of the image; an all-ones mask gives the
    plain pyramid image; a level's pixel is the weighted mean of the kept pixels under it."""
    base = synthetic_scene(n_train=2, n_test=1, size=24)
    cam = base.train_cameras[0]
    g = torch.Generator().manual_seed(7)
    keep = (torch.rand(24, 24, generator=g) > 0.5).float()
    img = base.image(cam)
    other = torch.where(keep[..., None] > 0, img, torch.rand(24, 24, 3, generator=g))

    def scene(image, mask):
        images = {c.uid: base.image(c) for c in base.cameras}
        images[cam.uid] = image
        return Scene(base.train_cameras, base.test_cameras, images, masks={cam.uid: mask})

    a, b, ones = scene(img, keep), scene(other, keep), scene(img, torch.ones(24, 24))
    for factor in (2, 3, 4):
        assert torch.equal(a.image(cam, factor), b.image(cam, factor)), factor
        torch.testing.assert_close(ones.image(cam, factor), base.image(cam, factor), atol=1e-6, rtol=0)
    # at factor 4 the weighted mean, from skimage's resize of image x mask and of the mask
    from skimage.transform import resize

    def r(x):
        return resize(x.numpy().astype(np.float64), (6, 6, x.shape[2]), order=1, mode="symmetric", anti_aliasing=True,
                      preserve_range=True)

    num, den = r(img * keep[..., None]), r(keep[..., None])
    assert np.allclose(a.image(cam, 4).numpy(), np.clip(num / den, 0, 1), atol=1e-5)


@pytest.mark.parametrize("mask,message", [
    (torch.ones(24, 23), r"must be \[24,24\] or \[24,24,1\], got \[24, 23\]"),
    (torch.full((24, 24), -0.5), r"finite weights in \[0,1\]"),
    (torch.zeros(24, 24), "ignores every pixel"),
])
def test_a_bad_mask_tensor_is_refused_naming_the_camera(mask, message):
    with pytest.raises(ValueError, match=message):
        _masked_scene({1: mask})


def test_a_mask_for_a_camera_the_scene_lacks_is_refused():
    with pytest.raises(ValueError, match="camera uid 99"):
        _masked_scene({99: torch.ones(24, 24)})


# ---- the loader --------------------------------------------------------------------------------

def _nerfstudio(root: Path, n: int = 9, size: int = 16, k1: float = 0.0) -> list:
    """A transforms.json folder (nerfstudio's keys) of n views: image k random, mask k a block."""
    rng = np.random.default_rng(3)
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    frames = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = np.array([3 * math.cos(a), 3 * math.sin(a), 0.5])
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([right, up, -fwd], axis=1)  # OpenGL: x right, y up, looking down -z
        c2w[:3, 3] = eye
        skimage.io.imsave(root / f"images/f{k}.png", rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
                          check_contrast=False)
        m = np.full((size, size), 255, np.uint8)
        m[2 + k % 5: 8 + k % 5, 3:9] = 0
        skimage.io.imsave(root / f"masks/f{k}.png", m, check_contrast=False)
        frames.append({"file_path": f"images/f{k}.png", "mask_path": f"masks/f{k}.png", "transform_matrix": c2w.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 14.0, "fl_y": 14.0, "cx": size / 2, "cy": size / 2, "w": size, "h": size,
            "k1": k1, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return frames


def test_nerfstudio_mask_path_becomes_the_scene_mask(tmp_path):
    frames = _nerfstudio(tmp_path)
    del frames[4]["mask_path"]  # a frame without one counts all its pixels
    (tmp_path / "transforms.json").write_text(json.dumps({**json.loads((tmp_path / "transforms.json").read_text()),
                                                          "frames": frames}))
    with pytest.warns(UserWarning, match="held out"):
        scene = load_scene(tmp_path, init=None)
    assert scene.has_masks and len(scene.masked()) == 8
    for cam in scene.cameras:
        k = int(cam.name.split("/f")[1][:-4])
        want = np.ones((16, 16), np.float32) if k == 4 else (skimage.io.imread(tmp_path / f"masks/f{k}.png") != 0)
        assert np.array_equal(scene.mask(cam)[..., 0].numpy(), want.astype(np.float32)), cam.name


def test_a_distorted_capture_resamples_its_masks_as_its_images(tmp_path):
    """With lens distortion (k1) the mask is resampled as an image is (the same capture with
    its masks painted in as images, loaded without masks, gives the same pixels), and an image
    is resampled as the weighted mean of its kept pixels: painted white where its mask keeps a
    pixel and magenta where it does not, every pixel with weight is white, on the mask's edge too."""
    _nerfstudio(tmp_path / "a", k1=-0.08)
    _nerfstudio(tmp_path / "b", k1=-0.08)
    meta = json.loads((tmp_path / "b/transforms.json").read_text())
    for f in meta["frames"]:
        del f["mask_path"]
    (tmp_path / "b/transforms.json").write_text(json.dumps(meta))
    for k in range(9):
        keep = skimage.io.imread(tmp_path / f"a/masks/f{k}.png") != 0
        magenta = np.where(keep[..., None], 255, np.array([255, 0, 255])).astype(np.uint8)
        skimage.io.imsave(tmp_path / f"a/images/f{k}.png", magenta, check_contrast=False)
        skimage.io.imsave(tmp_path / f"b/images/f{k}.png", np.repeat(np.where(keep, 255, 0)[..., None], 3, 2).astype(np.uint8),
                          check_contrast=False)
    with pytest.warns(UserWarning):
        masked, painted = load_scene(tmp_path / "a", init=None), load_scene(tmp_path / "b", init=None)
    edges = 0
    for cam, other in zip(masked.cameras, painted.cameras):
        mask, image = masked.mask(cam)[..., 0], masked.image(cam)
        assert 0 < float(mask.mean()) < 1
        assert torch.allclose(mask, painted.image(other)[..., 0], atol=1.5 / 255), cam.name
        kept = mask > 0
        assert torch.allclose(image[kept], torch.ones_like(image[kept]), atol=1e-5), cam.name
        assert float(image[~kept].abs().max()) == 0.0
        edges += int(((mask > 0.05) & (mask < 0.95)).sum())
    assert edges > 50  # the resampling does make edge pixels, and none of them takes magenta


@pytest.mark.parametrize("edit,error,message", [
    (lambda f: f.update(mask_path="masks/none.png"), FileNotFoundError, r"mask_path 'masks/none.png' names .*none.png"),
    (lambda f: f.update(mask_path=3), ValueError, "'mask_path' must be a file name, got 3"),
    (lambda f: f.update(mask_path="masks/big.png"), ValueError, r"its mask .*big.png is 20x16 but its image .* is 16x16"),
])
def test_a_bad_mask_path_is_named(tmp_path, edit, error, message):
    frames = _nerfstudio(tmp_path)
    skimage.io.imsave(tmp_path / "masks/big.png", np.full((16, 20), 255, np.uint8), check_contrast=False)
    edit(frames[2])
    meta = json.loads((tmp_path / "transforms.json").read_text())
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
    with pytest.warns(UserWarning), pytest.raises(error, match=message):
        load_scene(tmp_path, init=None)


def test_a_colmap_folder_reads_masks_by_either_naming(tmp_path):
    """The bundled scene's COLMAP model with a masks/ folder: "train/r_000.png.png" (COLMAP's
    naming) and "train/r_001.png" (nerfstudio's, the extension replaced) are read; other images
    count every pixel; a mask of another size is refused naming both sizes."""
    from mvgs_plugin.data import load_colmap

    shutil.copytree(TABLETOP, tmp_path / "s")
    (tmp_path / "s" / "masks" / "train").mkdir(parents=True)
    m0 = np.full((128, 128), 255, np.uint8)
    m0[:40] = 0
    m1 = np.full((128, 128), 255, np.uint8)
    m1[:, 90:] = 0
    skimage.io.imsave(tmp_path / "s/masks/train/r_000.png.png", m0, check_contrast=False)
    skimage.io.imsave(tmp_path / "s/masks/train/r_001.png", m1, check_contrast=False)
    with pytest.warns(UserWarning, match=r"masks: 58 of 60 images have no mask \(for test/r_000.png: .*test/r_000.png.png"):
        scene = load_colmap(tmp_path / "s")
    assert sorted(c.name for c in scene.masked()) == ["train/r_000.png", "train/r_001.png"]
    assert np.array_equal(scene.mask(scene.camera("train/r_000.png"))[..., 0].numpy(), (m0 != 0).astype(np.float32))
    assert np.array_equal(scene.mask(scene.camera("train/r_001.png"))[..., 0].numpy(), (m1 != 0).astype(np.float32))
    assert float(scene.mask(scene.camera("train/r_002.png")).min()) == 1.0
    skimage.io.imsave(tmp_path / "s/masks/train/r_001.png", np.full((64, 128), 255, np.uint8), check_contrast=False)
    with pytest.raises(ValueError, match=r"r_001.png is 128x64 but its image .*r_001.png is 128x128"):
        load_colmap(tmp_path / "s")


def test_a_colmap_masks_folder_that_matches_no_image_is_refused(tmp_path):
    """Masks named as their images (JPEG masks under the image's own name, another layout) match
    neither naming: the folder is refused naming what was looked for, not silently unused."""
    from mvgs_plugin.data import load_colmap

    shutil.copytree(TABLETOP, tmp_path / "s")
    (tmp_path / "s" / "masks" / "train").mkdir(parents=True)
    skimage.io.imsave(tmp_path / "s/masks/train/r_000.jpg", np.full((128, 128), 255, np.uint8), check_contrast=False)
    with pytest.raises(ValueError, match=r"masks holds no mask for any of the \d+ images: for test/r_000.png it looks "
                                         r"for .*test/r_000.png.png \(COLMAP's naming\) or .*; the folder holds train/r_000.jpg\. "):
        load_colmap(tmp_path / "s")


def test_the_automatic_background_reads_only_kept_border_pixels():
    from mvgs_plugin.data.images import uniform_border

    images, masks = [], []
    for k in range(6):
        img = torch.ones(16, 16, 3)
        m = torch.ones(16, 16, 1)
        if k < 3:  # something magenta fills these views' borders; their masks hide it
            img[:, :, 1] = 0.0
            img[4:12, 4:12] = 1.0
            m[:] = 0.0
            m[4:12, 4:12] = 1.0
        images.append(img)
        masks.append(m)
    assert uniform_border(images) is None  # half the border pixels are magenta
    assert uniform_border(images, masks) == (1.0, 1.0, 1.0)
    assert uniform_border(images, [None] * 3 + masks[3:]) is None


def test_initial_colours_skip_pixels_a_mask_ignores():
    """view_colours: a point counts as seen by a view only where that view's mask keeps the
    pixel it lands on; the count and mean written out by projecting each point by hand."""
    from mvgs_plugin.data.init import view_colours

    base = synthetic_scene(n_train=6, n_test=1, size=24)
    g = torch.Generator().manual_seed(8)
    keep = {c.uid: (torch.rand(24, 24, generator=g) > 0.5).float() for c in base.train_cameras}
    scene = Scene(base.train_cameras, base.test_cameras, {c.uid: base.image(c) for c in base.cameras}, masks=keep)
    pts = base.points.xyz[:50].double()
    mean, _, count = view_colours(pts, scene.train_cameras, scene.image, max_width=64, mask=scene.mask)
    want_count = torch.zeros(50, dtype=torch.float64)
    want_sum = torch.zeros(50, 3, dtype=torch.float64)
    for cam in scene.train_cameras:
        pix, z = cam.project(pts)
        for i in range(50):
            u, v = float(pix[i, 0]), float(pix[i, 1])
            if z[i] > 0 and 0 <= u < 24 and 0 <= v < 24 and keep[cam.uid][int(v), int(u)] > 0:
                want_count[i] += 1
                want_sum[i] += scene.image(cam)[int(v), int(u)].double()
    assert torch.equal(count, want_count) and int(count.sum()) > 0
    seen = count > 0
    torch.testing.assert_close(mean[seen], want_sum[seen] / want_count[seen, None], atol=1e-6, rtol=0)
    _, _, unmasked = view_colours(pts, scene.train_cameras, scene.image, max_width=64)
    assert bool((unmasked >= count).all()) and float(unmasked.sum()) > float(count.sum())


def test_a_level_below_full_resolution_holds_only_that_level(tmp_path):
    """A scene loaded from files (the automatic background reads every training image's border)
    and read at 1/2: the full-resolution images and masks are read and let go, never held; asked
    for at full resolution, they are."""
    _nerfstudio(tmp_path)
    with pytest.warns(UserWarning, match="held out"):
        scene = load_scene(tmp_path, init=None)
    assert "borders" in scene.background_origin  # it did read them
    for cam in scene.cameras:
        scene.image(cam, 2), scene.mask(cam, 2)
    held = [k for k in list(scene._cache) + list(scene._mask_cache) if k[1] == 1.0]
    assert held == [], held
    cam = scene.train_cameras[0]
    first = scene.image(cam)
    assert scene.image(cam) is first and (cam.uid, 1.0) in scene._cache


# ---- the loss and the metrics --------------------------------------------------------------------

def _one_step_gradients(scene: Scene) -> dict:
    torch.manual_seed(0)
    config = MVGSConfig.from_preset("baseline", seed=0).with_views(2).with_total_steps(10)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig.for_run(config))
    trainer = MVGS(adapter, scene, config)
    plan = trainer.schedule.next()
    timer = controller_module.PhaseTimer("render", "backward", "comm", "loss", "adapter")
    trainer._render_and_backward(plan, list(range(len(plan.views))), None, timer)
    return {k: g.clone() for k, g in adapter.named_gradients().items() if g is not None}


def _two_versions(base: Scene, cameras, seed: int, fill) -> tuple[dict, dict, dict]:
    """Random masks for `cameras` (about half their pixels kept), the base scene's images, and the
    same images with the pixels the masks ignore replaced by fill(generator)."""
    g = torch.Generator().manual_seed(seed)
    keep = {c.uid: (torch.rand(20, 20, generator=g) > 0.5).float() for c in cameras}
    images = {c.uid: base.image(c) for c in base.cameras}
    other = dict(images)
    for uid, k in keep.items():
        other[uid] = torch.where(k[..., None] > 0, images[uid], fill(g))
    return keep, images, other


@pytest.mark.filterwarnings("ignore::UserWarning")  # a 10-step run densifies at no step: it is one step here
def test_ignored_pixels_do_not_reach_the_gradients():
    """Two scenes that differ only in pixels the masks ignore give the same gradients; without the
    masks they differ (so the pixels changed are ones the views see)."""
    base = synthetic_scene(n_train=2, n_test=1, size=20)
    keep, clean, noisy = _two_versions(base, base.train_cameras, 4, lambda g: torch.rand(20, 20, 3, generator=g))

    def scene(images, masks):
        return Scene(base.train_cameras, base.test_cameras, images, points=base.points, masks=masks)

    a, b = _one_step_gradients(scene(clean, keep)), _one_step_gradients(scene(noisy, keep))
    assert a.keys() == b.keys() and a
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-7)
    c, d = _one_step_gradients(scene(clean, None)), _one_step_gradients(scene(noisy, None))
    assert any(not torch.allclose(c[k], d[k], atol=1e-6) for k in c)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_evaluate_counts_the_kept_pixels():
    """Per view, the PSNR of the kept pixels picked out by boolean indexing; test images that
    differ only where the masks ignore them give the same metrics."""
    base = synthetic_scene(n_train=3, n_test=2, size=20)
    keep, images, other = _two_versions(base, base.test_cameras, 5, lambda g: torch.ones(20, 20, 3))
    results = []
    for imgs in (images, other):
        scene = Scene(base.train_cameras, base.test_cameras, imgs, points=base.points, masks=keep)
        config = MVGSConfig.from_preset("baseline").with_total_steps(10)
        trainer = MVGS(GS3DAdapter.from_scene(scene, GS3DConfig.for_run(config)), scene, config)
        results.append(trainer.evaluate())
        for row, cam in zip(results[-1].per_view, scene.test_cameras):
            img, gt, k = row["image"], scene.image(cam), keep[cam.uid] > 0
            assert row["psnr"] == pytest.approx(psnr(img[k], gt[k]), rel=1e-9)  # the kept pixels, picked out
    assert [r["psnr"] for r in results[0].per_view] == [r["psnr"] for r in results[1].per_view]
    assert results[0].ssim == results[1].ssim


# ---- the training path ---------------------------------------------------------------------------

def _occluded_tabletop(root: Path, with_masks: bool, occluded: bool = True) -> Path:
    """The bundled scene with a block of one saturated colour pasted into every training image at a
    place that moves from view to view (a person, a tripod leg), and masks zero on it."""
    shutil.copytree(TABLETOP, root)
    meta = json.loads((root / "transforms_train.json").read_text())
    rng = np.random.default_rng(6)
    for k, frame in enumerate(meta["frames"]):
        file = root / (frame["file_path"] + ".png")
        img = skimage.io.imread(file)
        y, x = rng.integers(0, 128 - 48, size=2)
        if occluded:
            img[y:y + 48, x:x + 48] = (255, 0, 255)
            skimage.io.imsave(file, img, check_contrast=False)
        if with_masks:
            m = np.full((128, 128), 255, np.uint8)
            m[y:y + 48, x:x + 48] = 0
            (root / "masks").mkdir(exist_ok=True)
            skimage.io.imsave(root / f"masks/m{k:03d}.png", m, check_contrast=False)
            frame["mask_path"] = f"masks/m{k:03d}.png"
    (root / "transforms_train.json").write_text(json.dumps(meta))
    return root


@pytest.mark.slow
def test_training_with_masks_ignores_what_they_hide_through_every_phase(tmp_path, monkeypatch):
    """The 3DGS example on the bundled scene at 1/8 resolution, its training images occluded by a
    magenta block that moves from view to view. With the masks that hide the block, the run ends
    where the run on the clean images with the same masks ends (what the masks hide no longer
    matters), and well above the run on the occluded images without masks. It passes the hand-off,
    densification and an opacity reset, and a resumed run ends where it would have."""
    steps, every = 400, 150
    base = ["--preset", "default", "--steps", str(steps), "--threads", "1", "--no-progress", "--resolution-scale", "8",
            "--threshold-width", "0", "--min-densify-per-reset", "10"]
    example = _example("train_3dgs.py")
    step = controller_module.MVGS.step  # the real one, for the crash and the resume below
    infos = record_steps(monkeypatch)
    runs = {}
    for name, masks, occluded in (("clean", True, False), ("masked", True, True), ("unmasked", False, True)):
        data = _occluded_tabletop(tmp_path / name, with_masks=masks, occluded=occluded)
        infos.clear()
        runs[name] = example.main(base + ["--data", str(data), "--out", str(tmp_path / f"out_{name}")])
        if name == "masked":
            phases = list(infos)
    assert len({i.stage for i in phases}) == 2  # the hand-off from 1/2 to full resolution
    assert any(i.densify is not None and i.densify.after > i.densify.before for i in phases)
    assert any(i.opacity_reset for i in phases)
    saved = json.loads((tmp_path / "out_masked" / "metrics.json").read_text())
    assert saved["masks"].startswith("48 of 48 training and 0 of 12 test views have a mask")
    clean, masked, unmasked = (runs[k]["psnr"] for k in ("clean", "masked", "unmasked"))
    assert masked == clean and runs["masked"]["num_gaussians"] == runs["clean"]["num_gaussians"], (clean, masked)
    assert (tmp_path / "out_masked" / "point_cloud.ply").read_bytes() == (tmp_path / "out_clean" / "point_cloud.ply").read_bytes()
    assert masked > unmasked + 2.0, (clean, masked, unmasked)

    def crashing(self):
        if self.step_count == 2 * every - 20:
            raise Crash("simulated kill")
        return step(self)

    data = ["--data", str(tmp_path / "masked")]
    monkeypatch.setattr(controller_module.MVGS, "step", crashing)
    with pytest.raises(Crash):
        example.main(base + data + ["--out", str(tmp_path / "cut"), "--checkpoint-every", str(every)])
    monkeypatch.setattr(controller_module.MVGS, "step", step)
    resumed = example.main(base + data + ["--out", str(tmp_path / "resumed"), "--resume",
                                          str(tmp_path / "cut" / "checkpoint.pt")])
    for key in ("psnr", "ssim", "num_gaussians"):
        assert resumed[key] == runs["masked"][key], key



def test_colmap_masks_for_a_downscaled_copy_come_from_its_own_folder(tmp_path):
    """images_2/ read with only the full-size masks/ beside it: refused naming both sizes and
    the masks_2/ folder looked for; with masks_2/ (the halved masks) every mask is read from it."""
    from mvgs_plugin.data import load_colmap
    from test_data_colmap import H, W, write_model

    write_model(tmp_path)
    for f in (tmp_path / "images").rglob("*.png"):
        rel = f.relative_to(tmp_path / "images")
        for folder, arr in (("images_2", skimage.io.imread(f)[::2, ::2]),
                            ("masks", np.full((H, W), 255, np.uint8)), ("masks_2", np.full((H // 2, W // 2), 255, np.uint8))):
            out = tmp_path / folder / (str(rel) + (".png" if folder != "images_2" else ""))
            out.parent.mkdir(parents=True, exist_ok=True)
            skimage.io.imsave(out, arr, check_contrast=False)
    small = tmp_path / "images_2"
    masks_2 = tmp_path / "masks_2"
    masks_2.rename(tmp_path / "held")
    with pytest.raises(ValueError, match=rf"is {W}x{H} but its image .* is {W // 2}x{H // 2} \(a mask has its image's "
                                         r"size\) \(no masks_2/ for the images in images_2/ was found\)"):
        load_colmap(tmp_path, images_dir=small)
    (tmp_path / "held").rename(masks_2)
    scene = load_colmap(tmp_path, images_dir=small)
    assert len(scene.masked()) == len(scene.cameras)
    assert all(Path(scene.mask_file(c)).relative_to(masks_2) for c in scene.cameras)
