"""Initial points for the far background of a rig that surrounds its scene
(mvgs_plugin.data.init.background_shell, load_scene(background_points=...), --background-points):
where they go, which are kept, their colour, what a forward-facing rig gets, and bad input."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

import argparse

from mvgs_plugin.cli import BACKGROUND_POINTS, common_args
from mvgs_plugin.data import load_scene
from mvgs_plugin.data.init import SHELL_RADIUS, background_shell
from test_forward_init import look, parallel_rig

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "examples" / "scenes" / "tabletop"
FORWARD = ROOT / "tests" / "data" / "forward64"


def orbit(n=8, radius=3.0, height=1.0, f=40.0, size=32):
    """n cameras on a circle at `height`, all looking at the origin."""
    return [look((radius * math.cos(2 * math.pi * i / n), radius * math.sin(2 * math.pi * i / n), height),
                 (0.0, 0.0, 0.0), f, size, i) for i in range(n)]


def constant_images(colours):
    """An image(camera, factor) callable: camera uid i sees the flat colour colours[i]."""
    def image(cam, factor=1):
        small = cam.scaled(factor) if factor != 1 else cam
        return torch.tensor(colours[cam.uid], dtype=torch.float32).expand(small.height, small.width, 3).clone()
    return image


def sees(cam, p):
    """Independent check: p [3] in front of cam and inside its image (pinhole, OpenCV axes)."""
    x = cam.world_to_camera[:3, :3] @ p + cam.world_to_camera[:3, 3]
    if x[2] <= 0:
        return False
    u = cam.K[0, 0] * x[0] / x[2] + cam.K[0, 2]
    v = cam.K[1, 1] * x[1] / x[2] + cam.K[1, 2]
    return bool(0 <= u <= cam.width and 0 <= v <= cam.height)


def test_shell_points_lie_on_the_sphere_behind_the_cameras_and_each_is_in_some_view():
    cams = orbit()
    centre = torch.stack([c.center for c in cams]).mean(0)
    rig = float(torch.linalg.norm(torch.stack([c.center for c in cams]) - centre, dim=1).max())
    assert rig == pytest.approx(3.0)
    xyz, rgb, said = background_shell(cams, centre, 500, constant_images([(0.5, 0.5, 0.5)] * 8))
    assert 0 < xyz.shape[0] < 500, said  # the sphere's poles are in no view of a level ring
    assert torch.allclose(torch.linalg.norm(xyz - centre, dim=1),
                          torch.full((xyz.shape[0],), SHELL_RADIUS * rig, dtype=torch.float64))
    for p in xyz:
        assert any(sees(c, p) for c in cams)
        # at least (SHELL_RADIUS - 1) rig radii from every camera: none stands among the cameras,
        # where it could cover a new view taken from between them
        for c in cams:
            assert float(torch.linalg.norm(p - c.center)) >= (SHELL_RADIUS - 1.0) * rig - 1e-9
    assert "background shell" in said and str(xyz.shape[0]) in said


def test_the_points_not_kept_are_exactly_those_no_camera_sees():
    cams = orbit(n=6)
    centre = torch.stack([c.center for c in cams]).mean(0)
    n = 400
    xyz, _, _ = background_shell(cams, centre, n, constant_images([(0.2, 0.2, 0.2)] * 6))
    # recompute the lattice independently and count the points some camera sees
    rig = float(torch.linalg.norm(torch.stack([c.center for c in cams]) - centre, dim=1).max())
    golden = math.pi * (3.0 - math.sqrt(5.0))  # the same lattice: azimuth step pi (1 + sqrt 5) mod 2 pi
    seen = 0
    for i in range(n):
        z = 1.0 - 2.0 * (i + 0.5) / n
        r = math.sqrt(1.0 - z * z)
        a = -golden * (i + 0.5)
        p = centre + SHELL_RADIUS * rig * torch.tensor([r * math.cos(a), r * math.sin(a), z], dtype=torch.float64)
        seen += any(sees(c, p) for c in cams)
    assert xyz.shape[0] == seen


def test_each_point_gets_the_mean_colour_of_the_views_that_see_it():
    cams = orbit(n=4, f=20.0)  # wide views: most shell points are seen by two or three cameras
    colours = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 1.0)]
    centre = torch.stack([c.center for c in cams]).mean(0)
    xyz, rgb, _ = background_shell(cams, centre, 300, constant_images(colours))
    assert xyz.shape[0] > 0
    for p, got in zip(xyz, rgb):
        which = [i for i, c in enumerate(cams) if sees(c, p)]
        want = torch.tensor([colours[i] for i in which], dtype=torch.float64).mean(0)
        assert torch.allclose(got, want, atol=1e-6), (p, which, got)


def test_a_forward_facing_rig_and_zero_points_get_none():
    cams = parallel_rig([-1.0, -0.5, 0.0, 0.5, 1.0])
    centre = torch.stack([c.center for c in cams]).mean(0)
    xyz, rgb, said = background_shell(cams, centre, 1000, constant_images([(0.5, 0.5, 0.5)] * 5))
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3) and "forward-facing" in said
    xyz, _, said = background_shell(orbit(), centre, 0, constant_images([(0.5, 0.5, 0.5)] * 8))
    assert xyz.shape == (0, 3) and "0 points" in said


@pytest.mark.parametrize("n", [-1, 2.5, True, "10"])
def test_a_bad_point_count_is_refused_naming_it(n):
    cams = orbit()
    with pytest.raises(ValueError, match=f"n >= 0, got {n!r}".replace(".", r"\.")):
        background_shell(cams, torch.zeros(3), n, constant_images([(0.5, 0.5, 0.5)] * 8))


@pytest.mark.parametrize("radius", [1.0, 0.5, math.inf, math.nan])
def test_a_shell_inside_the_rig_is_refused(radius):
    with pytest.raises(ValueError, match="rig radii > 1"):
        background_shell(orbit(), torch.zeros(3), 10, constant_images([(0.5, 0.5, 0.5)] * 8), radius=radius)


def test_load_scene_appends_the_shell_after_the_scene_points_on_an_orbit_only():
    plain = load_scene(BUNDLED)
    shelled = load_scene(BUNDLED, background_points=2000)
    k = len(shelled.points) - len(plain.points)
    assert 0 < k < 2000
    assert torch.equal(shelled.points.xyz[: len(plain.points)], plain.points.xyz)
    assert torch.equal(shelled.points.rgb[: len(plain.points)], plain.points.rgb)
    far = torch.linalg.norm(shelled.points.xyz[len(plain.points):].double() - shelled.center, dim=1)
    rig = float(torch.linalg.norm(torch.stack([c.center for c in shelled.train_cameras]) - shelled.center,
                                  dim=1).max())
    assert torch.allclose(far, torch.full_like(far, SHELL_RADIUS * rig), rtol=1e-5)
    assert "background shell" in shelled.points_origin and plain.points_origin in shelled.points_origin
    assert shelled.points.shell == k and plain.points.shell == 0  # the shell's rows are counted
    assert torch.equal(shelled.points.own, plain.points.xyz)
    forward = load_scene(FORWARD, background_points=2000)
    assert len(forward.points) == len(load_scene(FORWARD).points)
    assert "forward-facing" in forward.points_origin
    with pytest.raises(ValueError, match="background_points must be an int >= 0, got -3"):
        load_scene(BUNDLED, background_points=-3)


def test_load_scene_puts_the_shell_at_the_radius_asked(tmp_path):
    """background_radius (--background-radius) moves the sphere: its points lie at that many rig
    radii from the centre, computed here from the cameras; the CLI passes its value through."""
    shelled = load_scene(BUNDLED, background_points=500, background_radius=3.5)
    rig = float(torch.linalg.norm(torch.stack([c.center for c in shelled.train_cameras]) - shelled.center,
                                  dim=1).max())
    far = torch.linalg.norm(shelled.points.xyz[-shelled.points.shell:].double() - shelled.center, dim=1)
    assert shelled.points.shell > 0 and torch.allclose(far, torch.full_like(far, 3.5 * rig), rtol=1e-5)
    assert "(3.5 rig radii)" in shelled.points_origin
    ap = common_args(argparse.ArgumentParser(), "out/x")
    ap.add_argument("--data", default=str(BUNDLED))
    args = ap.parse_args(["--background-points", "500", "--background-radius", "3.5", "--out", str(tmp_path)])
    from mvgs_plugin.cli import scene_from_args

    via_cli = scene_from_args(args)
    assert torch.equal(via_cli.points.xyz, shelled.points.xyz)
    assert ap.parse_args([]).background_radius is None  # None: the module's SHELL_RADIUS
    assert torch.equal(load_scene(BUNDLED, background_points=500).points.xyz,
                       load_scene(BUNDLED, background_points=500, background_radius=SHELL_RADIUS).points.xyz)


@pytest.mark.parametrize("bad", [1.0, 0.5, math.nan, math.inf, "4", True])
def test_load_scene_refuses_a_bad_shell_radius_naming_it(bad):
    with pytest.raises(ValueError, match="background_radius must be None or a finite number of rig radii > 1, got "):
        load_scene(BUNDLED, background_points=0, background_radius=bad)  # refused even when no shell is asked for


@pytest.mark.parametrize("bad", ["1", "0.5", "nan", "inf"])
def test_the_cli_refuses_a_shell_radius_inside_the_rig(capsys, bad):
    ap = common_args(argparse.ArgumentParser(), "out/x")
    with pytest.raises(SystemExit):
        ap.parse_args(["--background-radius", bad])
    assert f"expected a finite number > 1, got {bad!r}" in capsys.readouterr().err


def test_the_cli_flag_defaults_to_the_module_value_and_refuses_negatives(capsys):
    ap = common_args(argparse.ArgumentParser(), "out/x")
    assert ap.parse_args([]).background_points == BACKGROUND_POINTS
    assert ap.parse_args(["--background-points", "500"]).background_points == 500
    with pytest.raises(SystemExit):
        ap.parse_args(["--background-points", "-1"])
    assert "expected an int in 0..10000000, got -1" in capsys.readouterr().err


def test_point_cloud_shell_count_is_checked():
    from mvgs_plugin.data import PointCloud

    for bad in (-1, 4, 1.0, True):
        with pytest.raises(ValueError, match=rf"shell must be an int in \[0, 3\] \(rows of xyz\), got {bad!r}"):
            PointCloud(torch.zeros(3, 3), torch.zeros(3, 3), shell=bad)
    assert len(PointCloud(torch.zeros(3, 3), torch.zeros(3, 3), shell=3).own) == 0


def _sparse_scene_with_shell(n_own=60, seed=0):
    """The bundled scene's cameras with a few points of its own in a small cluster (spacing about
    0.05) and the 2000-point shell load_scene adds (spacing about 0.5)."""
    from mvgs_plugin.data import PointCloud

    scene = load_scene(BUNDLED, background_points=2000)
    gen = torch.Generator().manual_seed(seed)
    own = torch.rand(n_own, 3, generator=gen) * 0.2 - 0.1
    shell = scene.points.xyz[len(scene.points) - scene.points.shell:]
    scene.points = PointCloud(torch.cat([own, shell]), torch.rand(n_own + len(shell), 3, generator=gen),
                              shell=len(shell))
    return scene, own


def test_scaffold_takes_its_voxel_from_the_scenes_own_points_not_the_shell():
    """The default voxel is the median over the scene's own points of their RMS distance to
    their 3 nearest others (a plain pairwise-distance computation here), not that of own points
    and shell together, which the shell's spacing would set when it is most of the points."""
    from mvgs_plugin.adapters.scaffold import ScaffoldAdapter, ScaffoldConfig

    scene, own = _sparse_scene_with_shell()
    d = torch.cdist(own.double(), own.double())
    d.fill_diagonal_(float("inf"))
    expected = float(d.topk(3, largest=False).values.pow(2).mean(1).sqrt().median())
    adapter = ScaffoldAdapter.from_scene(scene, ScaffoldConfig())
    assert adapter.voxel_size == pytest.approx(expected, rel=1e-6)
    everything = scene.points.xyz.double()
    d = torch.cdist(everything, everything)
    d.fill_diagonal_(float("inf"))
    with_shell = float(d.topk(3, largest=False).values.pow(2).mean(1).sqrt().median())
    assert with_shell > 3 * expected  # what it took before: the shell's spacing


def test_4dgs_deformation_box_and_extra_points_are_the_scenes_own_not_the_shells():
    """The HexPlane box is the own points' bounding box (widened as bounds_from_points does, by
    hand here), and --init-random's default box is the own points' box widened to a cube: the
    shell, at twice the rig's radius, spans a box 30x wider in which the moving content would get
    a few of the planes' cells."""
    from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig

    scene, own = _sparse_scene_with_shell()
    adapter = GS4DAdapter.from_scene(scene, GS4DConfig())
    lo, hi = own.double().min(0).values, own.double().max(0).values
    assert torch.allclose(adapter.field.bounds.double(), torch.stack([lo, hi]), atol=1e-6)
    extra = GS4DAdapter.from_scene(scene, GS4DConfig(init_random_points=500))
    means = extra.params["means"].detach().double()
    assert len(means) == len(scene.points) + 500
    added = means[len(own): len(own) + 500]  # own points first, then the extra ones, the shell last
    half = float((hi - lo).max()) / 2
    centre = (lo + hi) / 2
    assert bool(((added - centre).abs() <= half + 1e-6).all())
    assert torch.allclose(means[len(own) + 500:], scene.points.xyz[len(own):].double())
