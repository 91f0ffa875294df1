"""Random initialisation where the cameras look (issue 16, part 1): the region for forward-facing
and surrounding rigs, the photo-consistent selection, and a forward-facing scene trained from
random init against its points-initialised run."""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
import torch

from mvgs_plugin import MVGS, MVGSConfig
from mvgs_plugin.camera import Camera
from mvgs_plugin.data import load_nerf_synthetic, load_scene
from mvgs_plugin.data.init import FAR_OVER_NEAR, init_region, photo_consistent, random_init_points

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
BUNDLED = ROOT / "examples" / "scenes" / "tabletop"


def look(center, target, f=50.0, size=64, uid=0):
    """A camera at `center` looking at `target` (OpenCV axes, world z up unless looking along z)."""
    c, t = torch.tensor(center, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    z = (t - c) / torch.linalg.norm(t - c)
    up = torch.tensor([0.0, 1.0, 0.0] if abs(float(z[1])) < 0.9 else [1.0, 0.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(-up, z)
    x = x / torch.linalg.norm(x)
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ c
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float64)
    return Camera(uid=uid, name=f"c{uid}", K=K, world_to_camera=w2c, width=size, height=size)


def parallel_rig(xs, f=50.0, size=64):
    """Cameras at (x, 0, 0) all looking along +z."""
    return [look((x, 0.0, 0.0), (x, 0.0, 1.0), f, size, i) for i, x in enumerate(xs)]


def test_a_forward_rig_gets_the_frusta_between_the_first_depth_half_of_it_sees_and_20x_that():
    xs = [-1.0, -0.6, -0.2, 0.2, 0.6, 1.0]
    cams = parallel_rig(xs)
    centers = torch.stack([c.center for c in cams])
    region = init_region(cams, centers.mean(0), 1.1)
    assert region.kind == "frusta", region.description
    # Analytic: camera x_i sees the axis point (0, 0, z) when |x_i| <= z * tan(half fov), i.e.
    # z >= |x_i| * f / (W / 2); half of the 6 cameras (|x| <= 0.6) see it from z = 0.6 * 50 / 32.
    want = 0.6 * 50.0 / 32.0
    step = 10 ** (7 / 140)  # the search's geometric step
    assert want <= region.near <= want * step * 1.001, (region.near, want)
    assert region.far == pytest.approx(FAR_OVER_NEAR * region.near)
    # every sample lies in some camera's view at a depth in [near, far] along that camera's axis
    pts = region.sample(2000, torch.Generator().manual_seed(0))
    inside_some = torch.zeros(2000, dtype=torch.bool)
    for cam in cams:
        pix, z = cam.project(pts)
        ok = (z >= region.near * (1 - 1e-9)) & (z <= region.far * (1 + 1e-9))
        ok &= (pix[:, 0] >= -1e-6) & (pix[:, 0] <= cam.width + 1e-6) & (pix[:, 1] >= -1e-6) & (pix[:, 1] <= cam.height + 1e-6)
        inside_some |= ok
    assert bool(inside_some.all())
    # uniform in disparity: the median depth is the harmonic middle 2 / (1/near + 1/far)
    depth = pts[:, 2]
    harmonic = 2.0 / (1.0 / region.near + 1.0 / region.far)
    assert float(depth.median()) == pytest.approx(harmonic, rel=0.08)


def test_surrounding_rigs_keep_the_3dgs_cube_and_degenerate_rigs_fall_back_to_it():
    ring = [look((3 * math.cos(a), 3 * math.sin(a), 1.0), (0.0, 0.0, 0.0), uid=i)
            for i, a in enumerate(torch.linspace(0, 2 * math.pi, 13)[:-1].tolist())]
    center = torch.stack([c.center for c in ring]).mean(0)
    region = init_region(ring, center, 3.3)
    assert region.kind == "cube" and region.half == 3.3 and torch.equal(region.center, center)
    pts = region.sample(500, torch.Generator().manual_seed(1))
    assert float((pts - center).abs().max()) <= 3.3
    one = parallel_rig([0.0])  # one camera: no depth cue
    assert init_region(one, one[0].center, 1.0).kind == "cube"
    apart = [look((0, 0, 0), (0, 0, 1), uid=0), look((5, 0, 0), (5, 0, -1), uid=1)]  # back to back
    # nearly parallel? no: opposite axes spread fully, so they count as surrounding
    assert init_region(apart, torch.zeros(3, dtype=torch.float64), 1.0).kind == "cube"


@pytest.mark.parametrize("heading", ["random", "inwards"])
def test_cameras_over_a_ground_tilted_every_way_get_the_frusta_not_the_cube_about_them(heading):
    """An aerial grid: 5 x 4 cameras 6 above a ground, each looking at its own ground point 15 to
    35 degrees off the vertical, in a random direction (the axes meet nowhere in front) or towards
    the middle (they meet near the ground): the axes spread past the forward threshold and share
    a direction. The cube about the camera centres (half = 1.1 x their radius) holds the air they
    stand in and does not reach the ground, so the region is the frusta, whose samples reach the
    ground; a hemisphere looking at one point (whose axes share a direction too, and meet inside
    the cube) keeps the cube."""
    g = torch.Generator().manual_seed(0)
    cams = []
    for i, (x, y) in enumerate((x, y) for x in (-2.0, -1.0, 0.0, 1.0, 2.0) for y in (-1.5, -0.5, 0.5, 1.5)):
        tilt = math.radians(15.0 + 20.0 * float(torch.rand(1, generator=g)))
        toward = 2 * math.pi * float(torch.rand(1, generator=g)) if heading == "random" else math.atan2(-y, -x)
        ground = (x + 6.0 * math.tan(tilt) * math.cos(toward), y + 6.0 * math.tan(tilt) * math.sin(toward), 0.0)
        cams.append(look((x, y, 6.0), ground, f=40.0, uid=i))
    centers = torch.stack([c.center for c in cams])
    centre = centers.mean(0)
    extent = 1.1 * float(torch.linalg.norm(centers - centre, dim=1).max())
    assert float(centre[2]) - extent > 2.0  # the 3DGS cube stays 2 or more above the ground
    region = init_region(cams, centre, extent)
    why = "meet nowhere in front" if heading == "random" else "outside the ball in the 3DGS cube"
    assert region.kind == "frusta" and why in region.description, region.description
    pts = region.sample(4000, torch.Generator().manual_seed(1))
    assert float((pts[:, 2].abs() < 0.5).double().mean()) > 0.01  # samples at the ground (the cube has none)
    hemisphere = [look((4 * math.cos(a) * math.cos(e), 4 * math.sin(a) * math.cos(e), 4 * math.sin(e)), (0.0, 0.0, 0.0), uid=i)
                  for i, (a, e) in enumerate((a, e) for a in torch.linspace(0, 6.0, 8).tolist() for e in (0.4, 0.8, 1.2))]
    h_centers = torch.stack([c.center for c in hemisphere])
    h_centre = h_centers.mean(0)
    assert float(torch.linalg.norm(torch.stack([c.world_to_camera[2, :3] for c in hemisphere]).mean(0))) >= 0.5
    assert init_region(hemisphere, h_centre, 1.1 * float(torch.linalg.norm(h_centers - h_centre, dim=1).max())).kind == "cube"


def test_the_bundled_orbit_keeps_its_cube_and_the_forward_scene_gets_the_frusta():
    orbit = load_nerf_synthetic(BUNDLED)
    assert init_region(orbit.train_cameras, orbit.center, orbit.extent).kind == "cube"
    forward = load_nerf_synthetic(FORWARD)
    region = init_region(forward.train_cameras, forward.center, forward.extent)
    assert region.kind == "frusta"
    # the scene's true surface points (from the renderer's scene description) lie between near and far
    depth = torch.stack([c.project(forward.points.xyz.double())[1] for c in forward.train_cameras])
    assert float(depth.quantile(0.05)) >= region.near and float(depth.quantile(0.95)) <= region.far


def test_photo_consistency_keeps_the_points_on_a_textured_plane():
    """Cameras of a parallel rig see a plane z = 3 whose colour is a known function of (x, y);
    their images are made by exact ray-plane intersection. Candidates on the plane see one
    colour from every view, the others mixed ones: the kept ones must be the plane's."""
    cams = parallel_rig([-0.6, -0.3, 0.0, 0.3, 0.6], f=40.0, size=48)

    def colour(x, y):
        return torch.stack([0.5 + 0.5 * torch.sin(7 * x), 0.5 + 0.5 * torch.cos(5 * y + 1), 0.5 + 0.5 * torch.sin(3 * x + 4 * y)], -1)

    def image(cam, factor):
        assert factor == 1
        j, i = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64), torch.arange(cam.width, dtype=torch.float64),
                              indexing="ij")
        o, d = cam.rays(torch.stack([i + 0.5, j + 0.5], -1))
        hit = o + d * ((3.0 - o[..., 2]) / d[..., 2])[..., None]
        return colour(hit[..., 0], hit[..., 1]).float()

    gen = torch.Generator().manual_seed(2)
    on = torch.cat([torch.rand(300, 2, generator=gen, dtype=torch.float64) * 1.6 - 0.8, torch.full((300, 1), 3.0, dtype=torch.float64)], 1)
    off = torch.cat([torch.rand(3000, 2, generator=gen, dtype=torch.float64) * 1.6 - 0.8,
                     1.5 + 4.0 * torch.rand(3000, 1, generator=gen, dtype=torch.float64)], 1)
    off = off[(off[:, 2] - 3.0).abs() > 0.3]
    xyz, rgb, seen = photo_consistent(torch.cat([on, off]), cams, image, 300, max_width=48)
    assert seen == 300
    on_plane = (xyz[:, 2] - 3.0).abs() < 1e-9
    assert float(on_plane.double().mean()) >= 0.9, float(on_plane.double().mean())
    # and their colour is the plane's there (up to the pixel grid: 1/40 world units per pixel)
    want = colour(xyz[on_plane, 0], xyz[on_plane, 1])
    assert float((rgb[on_plane] - want).abs().median()) < 0.05


def _train(scene, random_cube: bool = False, budget: float = 600):
    from mvgs_plugin.cli import model_config

    from mvgs_plugin.adapters.gs3d import GS3DAdapter

    config = MVGSConfig.default().with_budget(budget)
    model = model_config(config, 0)
    if random_cube:  # the original 3DGS cube: centre of the cameras ± extent
        model = dataclasses.replace(model, random_init_half_size=float(scene.extent))
    trainer = MVGS(GS3DAdapter.from_scene(scene, model), scene, config)
    trainer.fit(progress=False)
    return trainer.evaluate().psnr


def _run(kind: str, bare: Path) -> tuple[float, str | None]:
    """One of forward_runs' trainings, in its own process (one torch thread): "points" (the
    scene's own points), "random", "cube" (the scene without points) or "triangulate". Returns
    the test PSNR and where the init points came from (None: no points)."""
    torch.set_num_threads(1)
    if kind == "triangulate":
        scene = load_scene(bare, init="triangulate", threads=1)
    else:
        scene = load_nerf_synthetic(FORWARD if kind == "points" else bare)
    origin = None if scene.points is None else scene.points_origin
    return _train(scene, random_cube=kind == "cube"), origin


@pytest.fixture(scope="module")
def forward_runs(tmp_path_factory):
    bare = tmp_path_factory.mktemp("forward_no_points")
    for name in ("train", "test"):
        shutil.copytree(FORWARD / name, bare / name)
        shutil.copy(FORWARD / f"transforms_{name}.json", bare)
    # four independent trainings, two at a time (one thread each), the longest first
    kinds = ("triangulate", "points", "random", "cube")
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        runs = dict(zip(kinds, [pool.submit(_run, kind, bare) for kind in kinds]))
        runs = {kind: run.result() for kind, run in runs.items()}
    assert runs["random"][1] is None and runs["cube"][1] is None  # trained without points
    assert runs["points"][1] is not None
    assert runs["triangulate"][1].startswith("triangulated"), runs["triangulate"][1]
    return {kind: psnr for kind, (psnr, _) in runs.items()}


@pytest.mark.slow
def test_a_forward_facing_scene_trains_from_random_init_close_to_its_points_run(forward_runs):
    """The default recipe on a budget of 600 view renders at 64 px. Measured when written:
    points 29.7 dB, random init where the cameras look 25.3 dB, the 3DGS cube 15.4 dB; with the
    forward rig's disparity step rule (GS3DConfig.means_lr_rule="auto", 2026-11-26): points
    31.14, random 29.72, cube 15.63."""
    r = forward_runs
    assert r["random"] >= r["points"] - 5.0, r
    assert r["random"] >= r["cube"] + 5.0, r


@pytest.mark.slow
def test_triangulated_init_trains_no_worse_than_random_on_the_64px_scene(forward_runs):
    """The default init (pycolmap tracks from the posed views plus photo-consistent fill) on the
    64 px forward scene, default recipe, budget 600. Measured when written: points 29.77 dB,
    triangulate 26.04, random 26.00, cube 15.40. At 64 px SIFT finds 210 tracks and the fill
    carries the init, so issue 25's bar (within 3 dB of points) is missed here (-3.7 dB; -4.0 with
    the baseline at 1000 steps); it holds on the 128 px forward scenes (docs/data.md). With the
    forward rig's disparity step rule (2026-11-26): points 31.14, triangulate 29.55, random 29.72,
    cube 15.63, so the bar holds here too (-1.6 dB): far points now move to their depth."""
    r = forward_runs
    assert r["triangulate"] >= r["random"] - 0.5, r
    assert r["triangulate"] >= r["cube"] + 5.0, r


def test_random_init_logs_what_it_chose(caplog):
    forward = load_nerf_synthetic(FORWARD)
    bare = type("S", (), {"train_cameras": forward.train_cameras, "center": forward.center,
                          "extent": forward.extent, "image": forward.image})()
    with caplog.at_level("INFO", logger="mvgs_plugin"):
        from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig

        GS3DAdapter._random_points(bare, GS3DConfig(random_init=200))
    assert any("training frusta between depth" in r.getMessage() and "candidates" in r.getMessage()
               for r in caplog.records), [r.getMessage() for r in caplog.records]
    xyz, rgb, _ = random_init_points(bare, 200, torch.Generator().manual_seed(0))
    assert xyz.shape == (200, 3) and float(rgb.min()) >= 0 and float(rgb.max()) <= 1


def test_dynamic_scenes_without_points_use_the_same_rule():
    """The 4DGS adapter initialises its canonical Gaussians through GS3DAdapter.from_scene, so a
    D-NeRF-style scene without points gets the same answer: a ring of timed cameras keeps the
    cube, a timed forward-facing rig gets points in front of its cameras."""
    from mvgs_plugin.adapters.gs4d import GS4DAdapter, GS4DConfig
    from mvgs_plugin.adapters.gs3d import GS3DConfig
    from mvgs_plugin.data import Scene
    from mvgs_plugin.testing import synthetic_scene

    ring = synthetic_scene(n_train=6, n_test=1, size=16, time=True)
    bare = Scene(ring.train_cameras, ring.test_cameras, {c.uid: ring.image(c) for c in ring.cameras}, points=None)
    config = GS4DConfig(canonical=GS3DConfig(random_init=300))
    model = GS4DAdapter.from_scene(bare, config)
    off = (model.positions().double() - bare.center).abs()
    assert model.num_primitives() == 300 and float(off.max()) <= bare.extent and float(off.max()) > 0.9 * bare.extent

    cams = [dataclasses.replace(c, time=i / 5) for i, c in enumerate(parallel_rig([-0.6, -0.3, 0.0, 0.3, 0.6, 0.9]))]
    images = {c.uid: torch.rand(c.height, c.width, 3, generator=torch.Generator().manual_seed(c.uid)) for c in cams}
    forward = Scene(cams[:5], cams[5:], images, points=None)
    model = GS4DAdapter.from_scene(forward, config)
    depth = torch.stack([c.project(model.positions().double())[1] for c in forward.train_cameras])
    assert model.num_primitives() == 300 and bool((depth.max(0).values > 0).all())  # in front of a camera
