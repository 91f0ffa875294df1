"""GS3DConfig.beside_cull (--beside-cull K): a Gaussian beside a view's camera (centre outside
the image widened by 0.3 tan(fov/2) per side, nearer than K x its largest scale) is not drawn
in that view. Checked against pixel coordinates from Camera.project, against a render of the
model without that Gaussian, and through the statistics a training step folds in."""

from __future__ import annotations

import argparse
import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter, GS3DConfig, beside_camera
from mvgs_plugin.camera import Camera, stack_cameras
from mvgs_plugin.cli import common_args, model_config, world_size_arg
from mvgs_plugin.config import MVGSConfig
from mvgs_plugin.testing import check_adapter, look_at


def pinhole(eye, target, uid, width, height, fov_deg):
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = [[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]
    return Camera(uid, f"v{uid}", K, look_at(eye, target), width, height)


def camera(uid=0, size=(40, 30)):
    return pinhole((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), uid, size[0], size[1], 60.0)


def independent_beside(cam, means, scales, k):
    """Per Gaussian, from the projected pixel: outside [-0.15 W, 1.15 W] x [-0.15 H, 1.15 H] (0.3
    tan(fov/2) per side is 0.3 x half the image in pixels), in front, nearer than k x max scale."""
    pix, z = cam.project(means.double())
    w, h = cam.width, cam.height
    out = (pix[:, 0] < -0.15 * w) | (pix[:, 0] > 1.15 * w) | (pix[:, 1] < -0.15 * h) | (pix[:, 1] > 1.15 * h)
    return (z > 0) & out & (z < k * scales.double().amax(-1))


def test_the_mask_is_the_pixel_rule_for_every_camera():
    g = torch.Generator().manual_seed(0)
    means = (torch.rand(4000, 3, generator=g, dtype=torch.float64) - 0.5) * 12.0
    scales = torch.exp(torch.randn(4000, 3, generator=g, dtype=torch.float64))
    cams = [camera(0), pinhole((3.0, 1.0, 2.0), (0.0, 0.5, 0.0), 1, 50, 30, 40.0),
            pinhole((-2.0, 3.0, -1.0), (1.0, 0.0, 0.0), 2, 50, 30, 90.0)]
    for c in cams:
        viewmats, Ks = stack_cameras([c], dtype=torch.float64)
        got = beside_camera(means, scales, viewmats, Ks, c.width, c.height, 3.0)[0]
        want = independent_beside(c, means, scales, 3.0)
        assert 50 < int(want.sum()) < 3000  # both kinds are drawn
        assert torch.equal(got, want)


def model(means, scales, opacities, rgb, beside_cull):
    return GS3DAdapter.from_tensors(torch.tensor(means), scales=torch.tensor(scales), opacities=torch.tensor(opacities),
                                    rgb=torch.tensor(rgb), scene_extent=2.0,
                                    config=GS3DConfig(sh_degree=0, beside_cull=beside_cull))


ON_SCREEN = ([[0.0, 0.0, 0.0], [0.3, 0.2, 0.1]], [[0.3, 0.3, 0.3], [0.2, 0.2, 0.2]], [0.8, 0.6],
             [[0.9, 0.2, 0.1], [0.1, 0.8, 0.3]])
# beside the camera at (0, -4, 0): 0.5 in front of it, 3 to the side (far outside a 60 degree
# frustum), scale 1.5: 3 x 1.5 > 0.5, so it is culled at K = 3; at scale 0.1 it is not
BESIDE = [3.0, -3.5, 0.0]


@pytest.mark.parametrize("size,culled", [(1.5, True), (0.1, False)])
def test_a_culled_gaussian_renders_as_the_model_without_it(size, culled):
    cam = camera()
    means, scales, opac, rgb = ON_SCREEN
    with_it = model(means + [BESIDE], scales + [[size] * 3], opac + [0.9], rgb + [[1.0, 1.0, 1.0]], 3.0)
    without = model(means, scales, opac, rgb, 0.0)
    bg = torch.zeros(1, 3)
    img = with_it.render([cam], bg).images
    assert bool(independent_beside(cam, with_it.params["means"].detach(), with_it.get_scales().detach(), 3.0)[-1]) == culled
    if culled:
        assert torch.allclose(img, without.render([cam], bg).images, atol=1e-6)
        # the same model without the rule draws the smear this rule removes
        plain = model(means + [BESIDE], scales + [[size] * 3], opac + [0.9], rgb + [[1.0, 1.0, 1.0]], 0.0)
        assert float((plain.render([cam], bg).images - img).detach().abs().max()) > 1e-2
    else:
        plain = model(means + [BESIDE], scales + [[size] * 3], opac + [0.9], rgb + [[1.0, 1.0, 1.0]], 0.0)
        assert torch.equal(img, plain.render([cam], bg).images)


def test_a_culled_gaussian_gets_no_gradient_and_no_visit_in_that_view_only():
    means, scales, opac, rgb = ON_SCREEN
    m = model(means + [BESIDE], scales + [[1.5] * 3], opac + [0.9], rgb + [[1.0, 1.0, 1.0]], 3.0)
    far = pinhole((0.0, 9.0, 0.5), (1.0, 0.0, 0.0), 1, 40, 30, 60.0)  # sees it from afar
    for cam, visited in ((camera(), False), (far, True)):
        denom0 = m.denom.clone()
        for p in m.params.values():
            p.grad = None
        res = m.render([cam], torch.zeros(1, 3))
        res.images.sum().backward()
        m.accumulate_stats(res)
        assert (float(m.denom[-1] - denom0[-1]) == 1.0) == visited
        assert (float(m.params["opacities"].grad.reshape(-1)[-1].abs()) > 0) == visited
        assert bool((m.denom[:2] - denom0[:2] == 1).all())  # the others are drawn and visited


def test_the_config_the_flag_and_the_conformance_suite():
    with pytest.raises(ValueError, match="beside_cull must be a finite number >= 0, got -1"):
        GS3DConfig(beside_cull=-1)
    with pytest.raises(ValueError, match="beside_cull must be a finite number >= 0, got nan"):
        GS3DConfig(beside_cull=math.nan)
    ap = world_size_arg(common_args(argparse.ArgumentParser(), out="out"))
    assert ap.parse_args([]).beside_cull is None
    args = ap.parse_args(["--beside-cull", "3"])
    assert model_config(MVGSConfig.default(), 0, beside_cull=args.beside_cull).beside_cull == 3.0
    assert model_config(MVGSConfig.default(), 0).beside_cull == 0.0
    with pytest.raises(SystemExit):
        ap.parse_args(["--beside-cull", "-1"])
    # the protocol holds with the rule on (render, statistics, densify, checkpoint round trip)
    check_adapter(lambda scene: GS3DAdapter.from_scene(scene, GS3DConfig(sh_degree=1, beside_cull=3.0)))
