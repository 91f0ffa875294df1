"""benchmarks/probe_view_cells.py cuts a step's views to cells of their images. Checked here: the
cells of a step tile the frame exactly once, each target is the slice of its image, and a cell's
camera renders what the whole camera renders in that slice (the full render, sliced, is the
independent computation)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import probe_view_cells as probe  # noqa: E402
from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig  # noqa: E402
from mvgs_plugin.camera import Camera  # noqa: E402


def camera(uid: int, width: int = 48, height: int = 32) -> Camera:
    # looking down +z from z = -4, turned a little about y so that views differ
    c, s = math.cos(0.1 * uid), math.sin(0.1 * uid)
    R = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)
    K = torch.tensor([[40.0, 0, 23.0], [0, 41.0, 17.5], [0, 0, 1]], dtype=torch.float64)
    return Camera(uid=uid, name=f"v{uid}", K=K, world_to_camera=w2c, width=width, height=height)


def plan_of(m: int, with_masks: bool = True):
    cams = [camera(i) for i in range(m)]
    images = [torch.rand(32, 48, 3, generator=torch.Generator().manual_seed(i)) for i in range(m)]
    masks = [torch.rand(32, 48, 1, generator=torch.Generator().manual_seed(10 + i)) for i in range(m)] if with_masks else None
    return SimpleNamespace(views=list(range(m)), cameras=cams, images=images, masks=masks)


@pytest.mark.parametrize("m", [2, 4])
def test_a_steps_cells_tile_the_frame_once_and_cut_their_own_image(m):
    plan = plan_of(m)
    images, masks = list(plan.images), list(plan.masks)
    out = probe.cut_to_cells(plan, torch.Generator().manual_seed(3), "grid")
    hits = torch.zeros(32, 48, dtype=torch.int64)
    for i, (cam, img, mask) in enumerate(zip(out.cameras, out.images, out.masks)):
        x0, y0 = 23.0 - float(cam.cx), 17.5 - float(cam.cy)  # the principal point moved by the corner
        assert x0 == int(x0) and y0 == int(y0)
        x0, y0 = int(x0), int(y0)
        assert float(cam.fx) == 40.0 and float(cam.fy) == 41.0
        assert torch.equal(cam.world_to_camera, camera(i).world_to_camera)
        assert torch.equal(img, images[i][y0:y0 + cam.height, x0:x0 + cam.width])
        assert torch.equal(mask, masks[i][y0:y0 + cam.height, x0:x0 + cam.width])
        hits[y0:y0 + cam.height, x0:x0 + cam.width] += 1
    assert bool((hits == 1).all())


def test_one_view_gets_one_quarter_and_the_draws_reach_every_quarter():
    seen = set()
    gen = torch.Generator().manual_seed(0)
    for _ in range(40):
        out = probe.cut_to_cells(plan_of(1, with_masks=False), gen, "one")
        cam = out.cameras[0]
        assert (cam.width, cam.height) == (24, 16) and out.masks is None
        seen.add((23.0 - float(cam.cx), 17.5 - float(cam.cy)))
    assert seen == {(0.0, 0.0), (24.0, 0.0), (0.0, 16.0), (24.0, 16.0)}


def test_other_plans_are_left_as_they_are():
    for m, mode in ((1, "grid"), (3, "grid"), (2, "one")):
        plan = plan_of(m)
        cams = list(plan.cameras)
        assert probe.cut_to_cells(plan, torch.Generator(), mode).cameras == cams


def test_an_image_that_does_not_split_evenly_is_refused_with_its_size():
    with pytest.raises(ValueError, match="47x32"):
        probe.cells_of(47, 32, 2, 2)


def test_a_cell_camera_renders_the_slice_of_the_whole_render():
    """Gaussians well inside the view (the renderer's frustum guard band does not reach them in any
    cell), so the cell's render must be the whole render's pixels, forward and backward."""
    g = torch.Generator().manual_seed(1)
    n = 60
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 1.6,
                       (torch.rand(n, 1, generator=g, dtype=torch.float64) - 0.5) * 0.5], 1)
    ad = GS3DAdapter.from_tensors(means, scales=torch.full((n, 3), 0.06, dtype=torch.float64),
                                  opacities=torch.full((n,), 0.7, dtype=torch.float64),
                                  rgb=torch.rand(n, 3, generator=g, dtype=torch.float64), scene_extent=1.0,
                                  config=GS3DConfig(sh_degree=0), dtype=torch.float64)
    cam = camera(0)
    bg = torch.ones(1, 3, dtype=torch.float64)
    whole = ad.render([cam], bg).images[0]
    weights = torch.rand(whole.shape, generator=g, dtype=torch.float64)
    (whole * weights).sum().backward()
    grad_whole = ad.params["means"].grad.clone()
    ad.zero_grad()
    grad_cells = torch.zeros_like(grad_whole)
    for x0, y0, w, h in probe.cells_of(48, 32, 2, 2):
        part = ad.render([probe.cell_camera(cam, x0, y0, w, h)], bg).images[0]
        torch.testing.assert_close(part, whole.detach()[y0:y0 + h, x0:x0 + w], rtol=0, atol=1e-9)
        (part * weights[y0:y0 + h, x0:x0 + w]).sum().backward()
        grad_cells += ad.params["means"].grad
        ad.zero_grad()
    torch.testing.assert_close(grad_cells, grad_whole, rtol=1e-7, atol=1e-9)
