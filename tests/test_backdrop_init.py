"""An object on a backdrop (NeRF-synthetic's kind of capture: RGBA images, or images whose borders
are one colour): no background shell (mvgs_plugin.data.init.background_shell's ``backdrop``), and
random initial points carved to the views' silhouettes (on_silhouettes, hull_candidates,
random_init_points). The images here are an analytic sphere, each pixel's coverage computed by
ray-sphere intersection on a 4 x 4 grid of sub-pixel rays, independently of the package."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mvgs_plugin.cli import common_args, scene_from_args
from mvgs_plugin.data import load_scene
from mvgs_plugin.data.init import background_shell, backdrop_of, on_silhouettes, random_init_points, silhouettes_of
from test_background_shell import constant_images, orbit
from test_forward_init import look

RADIUS = 0.5  # the sphere, at the origin
COLOUR = (0.8, 0.2, 0.1)


def sphere_rig(n=24, distance=3.0, f=40.0, size=32):
    """n cameras on a Fibonacci sphere about the origin (every side, below too), looking at it."""
    cams = []
    for i in range(n):
        z = 1.0 - 2.0 * (i + 0.5) / n
        r = math.sqrt(1.0 - z * z)
        a = math.pi * (1.0 + math.sqrt(5.0)) * i
        cams.append(look((distance * r * math.cos(a), distance * r * math.sin(a), distance * z), (0.0, 0.0, 0.0),
                         f, size, i))
    return cams


def sphere_hits(cam, sub=4):
    """Per sub-pixel ray (a sub x sub grid in each pixel): whether it hits the sphere (|o + t d| =
    RADIUS, t > 0) and where it first does, and a function averaging such a map over each pixel."""
    j, i = np.meshgrid(np.arange(cam.height * sub), np.arange(cam.width * sub), indexing="ij")
    pixels = torch.tensor(np.stack([(i + 0.5) / sub, (j + 0.5) / sub], -1), dtype=torch.float64)
    o, d = cam.rays(pixels)
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - RADIUS ** 2
    hit = (b * b - c > 0) & (-b > 0)
    t = -b - torch.sqrt((b * b - c).clamp_min(0))  # the nearer crossing
    per_pixel = lambda x: x.double().reshape(cam.height, sub, cam.width, sub).mean(dim=(1, 3)).numpy()
    return hit, o + t[..., None] * d, per_pixel


def coverage(cam, sub=4):
    """[H, W] share of each pixel's sub-pixel rays that hit the sphere."""
    hit, _, per_pixel = sphere_hits(cam, sub)
    return per_pixel(hit)


def one_colour(cam):
    """(coverage [H, W], straight colour [H, W, 3]) of the sphere in COLOUR."""
    a = coverage(cam)
    return a, np.array(COLOUR) * (a[..., None] > 0)


def write_rgba_scene(folder: Path, cams, n_test=4, paint=one_colour):
    """A NeRF-synthetic folder: the sphere as ``paint(camera)`` gives it (its coverage as straight
    alpha and its colour), on a transparent backdrop; the last n_test cameras are the test split."""
    splits = {"train": cams[:-n_test], "test": cams[-n_test:]}
    for split, group in splits.items():
        (folder / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for k, cam in enumerate(group):
            a, straight = paint(cam)
            rgba = np.zeros((cam.height, cam.width, 4), dtype=np.uint8)
            rgba[..., :3] = np.round(straight * 255).astype(np.uint8)
            rgba[..., 3] = np.round(a * 255).astype(np.uint8)
            Image.fromarray(rgba, "RGBA").save(folder / split / f"r_{k:03d}.png")
            c2w = torch.linalg.inv(cam.world_to_camera) @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0],
                                                                                 dtype=torch.float64))
            frames.append({"file_path": f"{split}/r_{k:03d}", "transform_matrix": c2w.tolist()})
        cam = group[0]
        (folder / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": 2 * math.atan(0.5 * cam.width / float(cam.K[0, 0])), "frames": frames}))
    return folder


@pytest.fixture(scope="module")
def rgba_scene(tmp_path_factory):
    return write_rgba_scene(tmp_path_factory.mktemp("sphere"), sphere_rig())


def framed_images(inner, border, cams, width=2):
    """image(camera, factor): the colour `inner` with a frame `width` px wide of colour `border`
    (border may be a callable of (camera uid) for a frame of many colours)."""
    def image(cam, factor=1):
        small = cam.scaled(factor) if factor != 1 else cam
        img = torch.tensor(inner, dtype=torch.float32).expand(small.height, small.width, 3).clone()
        ring = torch.tensor(border(cam.uid) if callable(border) else border, dtype=torch.float32)
        img[:width], img[-width:], img[:, :width], img[:, -width:] = ring, ring, ring, ring
        return img
    return image


def test_no_shell_when_every_border_shows_the_backdrop_the_renderer_draws():
    cams = orbit()
    centre = torch.stack([c.center for c in cams]).mean(0)
    on_white = framed_images((0.3, 0.6, 0.2), (1.0, 1.0, 1.0), cams)
    xyz, rgb, said = background_shell(cams, centre, 500, on_white, backdrop=(1.0, 1.0, 1.0))
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    assert "borders show only the backdrop [1.0, 1.0, 1.0]" in said
    # the same images without a backdrop colour, or with another one: the shell as before
    plain, _, _ = background_shell(cams, centre, 500, on_white)
    assert plain.shape[0] > 0
    other, _, _ = background_shell(cams, centre, 500, on_white, backdrop=(0.0, 0.0, 0.0))
    assert torch.equal(other, plain)
    # borders of many colours (a photograph's) keep the shell even when one of them is the backdrop
    many = framed_images((0.3, 0.6, 0.2), lambda uid: (uid / 8.0, 1.0 - uid / 8.0, 0.5), cams)
    kept, _, _ = background_shell(cams, centre, 500, many, backdrop=(0.0, 1.0, 0.5))
    assert torch.equal(kept, plain)
    # within the border rule's tolerance (8/255) of the backdrop is the backdrop; beyond it is not
    near = framed_images((0.3, 0.6, 0.2), (1.0 - 7.0 / 255.0,) * 3, cams)
    assert background_shell(cams, centre, 500, near, backdrop=(1.0, 1.0, 1.0))[0].shape[0] == 0
    far = framed_images((0.3, 0.6, 0.2), (1.0 - 10.0 / 255.0,) * 3, cams)
    assert torch.equal(background_shell(cams, centre, 500, far, backdrop=(1.0, 1.0, 1.0))[0], plain)


def test_on_silhouettes_keeps_the_inside_of_the_sphere_and_nothing_far_from_it():
    cams = sphere_rig()
    images = {cam.uid: torch.tensor(1.0 - coverage(cam)[..., None] * (1.0 - np.array(COLOUR)), dtype=torch.float32)
              for cam in cams}  # straight colour over white by coverage

    def image(cam, factor=1):
        assert factor == 1  # 32 px images: read whole
        return images[cam.uid]

    gen = torch.Generator().manual_seed(0)
    dirs = torch.randn(400, 3, generator=gen, dtype=torch.float64)
    dirs = dirs / torch.linalg.norm(dirs, dim=1, keepdim=True)
    radii = torch.rand(400, 1, generator=gen, dtype=torch.float64)
    inside = dirs * radii * 0.9 * RADIUS
    assert on_silhouettes(inside, cams, image, (1.0, 1.0, 1.0)).all()
    # from 24 views on every side the hull of a sphere is the sphere, widened by the cones between
    # the views and about a pixel (a pixel at the sphere is 3 / 40 = 0.075 across): 1.5 x is out
    outside = dirs * RADIUS * (1.5 + 2.0 * radii)
    assert not on_silhouettes(outside, cams, image, (1.0, 1.0, 1.0)).any()
    # and with a backdrop of another colour every pixel is content: everything in the frames is in
    anywhere = on_silhouettes(outside, cams, image, (0.0, 0.0, 1.0))
    frames = torch.stack([torch.tensor([bool(z > 0 and 0 <= p[0] < c.width and 0 <= p[1] < c.height)
                                        for p, z in zip(*c.project(outside))]) for c in cams]).double().mean(0)
    assert torch.equal(anywhere, frames >= 0.5)


def test_a_scene_on_a_transparent_backdrop_gets_points_on_its_object_and_no_shell(rgba_scene):
    scene = load_scene(rgba_scene, init="random", background_points=2000)
    assert backdrop_of(scene) == (1.0, 1.0, 1.0)
    distance = torch.linalg.norm(scene.points.xyz.double(), dim=1)
    assert len(scene.points) == 10_000 and scene.points.shell == 0
    assert float(distance.max()) < 1.5 * RADIUS  # the cube is 3 x 3 x 3 about the rig: 1/3000 of it is the sphere
    # one colour all over: photo-consistency cannot tell the surface from the inside, so the points
    # fill the hull, which is the sphere up to the cones between the views and a pixel's smoothing
    assert float((distance < 1.2 * RADIUS).double().mean()) > 0.9
    assert torch.allclose(scene.points.rgb.double().median(0).values, torch.tensor(COLOUR, dtype=torch.float64),
                          atol=0.05)
    assert "carved to the training views' silhouettes" in scene.points_origin
    assert "no background shell: the training images' borders show only the backdrop" in scene.points_origin
    # composited on another colour, the backdrop is that colour and the same holds
    on_black = load_scene(rgba_scene, init="random", background=(0.0, 0.0, 0.0))
    assert backdrop_of(on_black) == (0.0, 0.0, 0.0)
    assert float(torch.linalg.norm(on_black.points.xyz.double(), dim=1).max()) < 1.5 * RADIUS
    # training in front of random colours: the Gaussians paint the backdrop, so the shell stays
    painted = load_scene(rgba_scene, init="random", background_points=2000, backdrop_drawn=False)
    assert painted.points.shell > 0 and "background shell:" in painted.points_origin


def test_the_cli_keeps_the_shell_for_random_backgrounds_only(rgba_scene, tmp_path):
    ap = common_args(argparse.ArgumentParser(), str(tmp_path / "out"))
    ap.add_argument("--data", type=Path)  # as the example scripts add it
    for flag, shell in (("auto", False), ("random", True)):
        args = ap.parse_args(["--data", str(rgba_scene), "--init", "random", "--background", flag,
                              "--out", str(tmp_path / flag)])
        scene = scene_from_args(args)
        assert (scene.points.shell > 0) == shell, scene.points_origin


def test_a_scene_of_photographs_keeps_the_3dgs_cube():
    # borders of many colours: no backdrop, so the 3DGS cube, not carved (since 2026-12-01 swept
    # along pixel rays, tests/test_sweep_init.py; this one colour inside every frame ties every
    # depth, and ties go to random depths)
    cams = orbit()
    scene = argparse.Namespace(train_cameras=cams, background=(1.0, 1.0, 1.0), center=torch.zeros(3), extent=3.0,
                               image=framed_images((0.3, 0.6, 0.2), lambda uid: (uid / 8.0, 0.2, 0.9), cams))
    assert backdrop_of(scene) is None
    xyz, _, said = random_init_points(scene, 500, torch.Generator().manual_seed(0))
    assert "carved" not in said and said.startswith("random init: cube")
    assert float(xyz.abs().max()) > 2.5  # spread over the cube, not gathered anywhere


def test_fill_points_on_a_backdrop_stay_inside_the_silhouettes(rgba_scene):
    from mvgs_plugin.data.triangulate import fill_points

    scene = load_scene(rgba_scene, init=None)
    # tracks on one side of the sphere: the views facing the other side see no track, so the fill
    # draws rays through their pixels, most of which show the backdrop
    gen = torch.Generator().manual_seed(1)
    dirs = torch.randn(300, 3, generator=gen, dtype=torch.float64)
    dirs = dirs[dirs[:, 0] > 0.3]
    tracks = RADIUS * dirs / torch.linalg.norm(dirs, dim=1, keepdim=True)
    xyz, rgb, said = fill_points(scene, tracks, 500, torch.Generator().manual_seed(0))
    assert 0 < len(xyz) <= 500 and "inside the views' silhouettes (read from their alpha) on the backdrop [1.0, 1.0, 1.0]" in said
    assert float(torch.linalg.norm(xyz, dim=1).max()) < 1.5 * RADIUS
    # without a backdrop (a colour no border shows) the same draw fills the air too: the rule is what keeps it out
    scene.background = (0.0, 0.0, 0.0)
    assert backdrop_of(scene) is None
    air, _, said = fill_points(scene, tracks, 500, torch.Generator().manual_seed(0))
    assert "silhouettes" not in said and float(torch.linalg.norm(air, dim=1).max()) > 2 * RADIUS


def test_a_moving_scene_on_a_backdrop_is_not_carved(rgba_scene):
    # silhouettes at different times bound no one shape: a D-NeRF scene keeps the cube (and gets no shell)
    import dataclasses

    scene = load_scene(rgba_scene, init=None)
    moving = argparse.Namespace(
        train_cameras=[dataclasses.replace(c, time=k / 19) for k, c in enumerate(scene.train_cameras)],
        background=scene.background, center=scene.center, extent=scene.extent, image=scene.image)
    assert backdrop_of(moving) == (1.0, 1.0, 1.0) and silhouettes_of(moving) is None
    assert silhouettes_of(scene) == (1.0, 1.0, 1.0)
    xyz, _, said = random_init_points(moving, 2000, torch.Generator().manual_seed(0))
    assert "carved" not in said and float(torch.linalg.norm(xyz, dim=1).max()) > 2.0


# A sphere whose lower half (z < 0) is black, on a transparent backdrop composited on black: the
# lower half is the backdrop's colour, so only the images' alpha tells it from the backdrop.

def two_tone(cam, sub=4):
    """([H, W] coverage of each pixel by the sphere, [H, W] share of its sub-pixel rays that hit the
    upper half)."""
    hit, landing, per_pixel = sphere_hits(cam, sub)
    return per_pixel(hit), per_pixel(hit & (landing[..., 2] > 0))


@pytest.fixture(scope="module")
def two_tone_scene(tmp_path_factory):
    """A NeRF-synthetic folder of the two-tone sphere (straight colour: COLOUR where the covered
    part is the upper half, black where it is the lower), and its training images' alpha at full
    size (as the PNG holds it, 8 bits)."""
    def paint(cam):
        a, up = two_tone(cam)
        return a, np.where(a > 0, up / np.maximum(a, 1e-12), 0.0)[..., None] * np.array(COLOUR)

    cams = sphere_rig()
    folder = write_rgba_scene(tmp_path_factory.mktemp("two_tone"), cams, paint=paint)
    alphas = {k: np.round(two_tone(cam)[0] * 255) / 255.0 for k, cam in enumerate(cams[:-4])}
    return folder, alphas


def test_scene_coverage_is_the_files_alpha_downsampled_as_the_image(two_tone_scene, tmp_path):
    from skimage.transform import resize

    folder, alphas = two_tone_scene
    scene = load_scene(folder, init=None, background=(0.0, 0.0, 0.0))
    for k, cam in enumerate(scene.train_cameras[:3]):
        full = scene.coverage(cam)
        assert full.shape == (cam.height, cam.width, 1)
        assert np.allclose(full[..., 0].numpy(), alphas[k], atol=1e-6)
        half = scene.coverage(cam, 2)
        ref = resize(alphas[k], (cam.height // 2, cam.width // 2), order=1, anti_aliasing=True)
        assert half.shape == (cam.height // 2, cam.width // 2, 1)
        assert np.allclose(half[..., 0].numpy(), ref, atol=1e-5)
    # no alpha to read: alpha dropped (no background), an opaque file, an image given as a tensor
    from mvgs_plugin.data import Scene

    cams = scene.train_cameras[:2]
    files = {c.uid: scene.image_file(c) for c in cams}
    assert Scene(cams, [], files, background=None).coverage(cams[0]) is None
    opaque = tmp_path / "opaque"
    opaque.mkdir()
    for split in ("train", "test"):
        (opaque / split).mkdir()
        for png in (folder / split).glob("*.png"):
            rgba = np.asarray(Image.open(png)).copy()
            rgba[..., 3] = 255
            Image.fromarray(rgba, "RGBA").save(opaque / split / png.name)
        (opaque / f"transforms_{split}.json").write_text((folder / f"transforms_{split}.json").read_text())
    on_black = load_scene(opaque, init=None, background=(0.0, 0.0, 0.0))
    assert on_black.coverage(on_black.train_cameras[0]) is None
    given = Scene(cams, [], {c.uid: scene.image(c) for c in cams}, background=(0.0, 0.0, 0.0))
    assert given.coverage(cams[0]) is None
    assert Scene(cams, [], files, background=(0.0, 0.0, 0.0)).coverage(cams[0]) is not None


def test_silhouettes_from_alpha_keep_a_part_in_the_backdrops_colour(two_tone_scene):
    folder, _ = two_tone_scene
    scene = load_scene(folder, init=None, background=(0.0, 0.0, 0.0))
    assert backdrop_of(scene) == (0.0, 0.0, 0.0)
    gen = torch.Generator().manual_seed(0)
    dirs = torch.randn(2000, 3, generator=gen, dtype=torch.float64)
    dirs = dirs / torch.linalg.norm(dirs, dim=1, keepdim=True)
    radii = torch.rand(2000, 1, generator=gen, dtype=torch.float64)
    inside = dirs * radii * 0.9 * RADIUS
    lower = inside[:, 2] < -0.2 * RADIUS  # clear of the seam
    by_alpha = on_silhouettes(inside, scene.train_cameras, scene.image, (0.0, 0.0, 0.0), coverage=scene.coverage)
    by_colour = on_silhouettes(inside, scene.train_cameras, scene.image, (0.0, 0.0, 0.0))
    assert bool(by_alpha.all())  # the whole sphere, its black half too
    # read by colour the black half is backdrop in the views that see it, and is cut away
    assert float(by_colour[lower].double().mean()) < 0.2
    outside = dirs * RADIUS * (1.5 + 2.0 * radii)
    assert not on_silhouettes(outside, scene.train_cameras, scene.image, (0.0, 0.0, 0.0), coverage=scene.coverage).any()


def test_a_scene_without_points_starts_on_both_halves_of_the_two_tone_sphere(two_tone_scene):
    folder, _ = two_tone_scene
    scene = load_scene(folder, init="random", background=(0.0, 0.0, 0.0))
    xyz = scene.points.xyz.double()
    assert len(scene.points) == 10_000 and float(torch.linalg.norm(xyz, dim=1).max()) < 1.5 * RADIUS
    # uniform in a hull symmetric about z = 0: half of the points below the seam
    assert 0.4 < float((xyz[:, 2] < 0).double().mean()) < 0.6
    assert "silhouettes (read from their alpha) on the backdrop [0.0, 0.0, 0.0]" in scene.points_origin
    # coloured by the views: inside the sphere a point lands on both halves, the lower ones mostly on black
    red = scene.points.rgb.double()[:, 0]
    assert float(red[xyz[:, 2] < -0.2 * RADIUS].mean()) < 0.6 * float(red[xyz[:, 2] > 0.2 * RADIUS].mean())


def test_views_without_alpha_are_read_by_colour_beside_those_with_it(two_tone_scene):
    from mvgs_plugin.data.init import _silhouettes_read

    folder, _ = two_tone_scene
    scene = load_scene(folder, init=None, background=(0.0, 0.0, 0.0))
    cams = scene.train_cameras
    half = {c.uid for c in cams[::2]}

    def some(cam, factor):  # alpha for every other view only
        return scene.coverage(cam, factor) if cam.uid in half else None

    assert _silhouettes_read(cams, some) == f" (read from the alpha of {len(half)} of {len(cams)} views, the others' by colour)"
    assert _silhouettes_read(cams, scene.coverage) == " (read from their alpha)" and _silhouettes_read(cams, None) == ""
    # each view votes by what it has: a point of the black half is content in the views with alpha only
    gen = torch.Generator().manual_seed(2)
    dirs = torch.randn(500, 3, generator=gen, dtype=torch.float64)
    inside = 0.8 * RADIUS * dirs / torch.linalg.norm(dirs, dim=1, keepdim=True) * torch.rand(500, 1, generator=gen,
                                                                                              dtype=torch.float64)
    lower = inside[inside[:, 2] < -0.2 * RADIUS]
    all_alpha = on_silhouettes(lower, cams, scene.image, (0.0, 0.0, 0.0), coverage=scene.coverage)
    mixed = on_silhouettes(lower, cams, scene.image, (0.0, 0.0, 0.0), coverage=some)
    colour = on_silhouettes(lower, cams, scene.image, (0.0, 0.0, 0.0))
    assert bool(all_alpha.all()) and int(colour.sum()) <= int(mixed.sum()) < len(lower)

