"""The resolution-aware gradient threshold (MVGSConfig.grad_threshold_width).

The premise is checked on the 3DGS adapter itself: the NDC statistic of a Gaussian of a fixed
size in pixels, for the same error per pixel, halves when the image doubles in width. Then the
pure function and the schedule's use of it (per pyramid level, composed with MVAD).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import GS3DAdapter
from mvgs_plugin import MVADConfig, MVGSConfig, Stage
from mvgs_plugin.camera import Camera
from mvgs_plugin.densify import resolution_threshold
from mvgs_plugin.schedule import ViewSchedule
from mvgs_plugin.testing import look_at, synthetic_scene


def _ndc_statistic(width: int, shift_px: float = 1.0, sigma_px: float = 3.0) -> float:
    """One Gaussian at the image centre, sigma_px pixels wide; the target is the same Gaussian
    shifted by shift_px pixels. Returns the adapter's accumulated NDC gradient norm after the
    backward of a plain L1 mean over the image."""
    f, d = 1.5 * width, 4.0  # focal length (px), camera distance
    cam = Camera(uid=0, name="c", K=[[f, 0, width / 2], [0, f, width / 2], [0, 0, 1]],
                 world_to_camera=look_at((0.0, 0.0, d), up=(0.0, 1.0, 0.0)), width=width, height=width)
    world_px = d / f  # world units per pixel at the Gaussian's depth
    scales = torch.full((1, 3), sigma_px * world_px, dtype=torch.float64)

    def model(x: float) -> GS3DAdapter:
        return GS3DAdapter.from_tensors(torch.tensor([[x, 0.0, 0.0]], dtype=torch.float64), scales=scales,
                                        opacities=torch.tensor([0.9], dtype=torch.float64), scene_extent=1.0,
                                        rgb=torch.tensor([[0.8, 0.5, 0.2]], dtype=torch.float64))

    bg = torch.zeros(1, 3, dtype=torch.float64)
    with torch.no_grad():
        target = model(shift_px * world_px).render([cam], bg).images[0]
    adapter = model(0.0)
    result = adapter.render([cam], bg)
    (result.images[0] - target).abs().mean().backward()
    adapter.accumulate_stats(result)
    return float(adapter.grad_accum[0])


def test_ndc_statistic_of_a_fixed_pixel_size_gaussian_halves_when_the_width_doubles():
    g32, g64, g128 = (_ndc_statistic(w) for w in (32, 64, 128))
    assert g32 > 0
    # Same picture in the central pixels, 4x the pixels in the mean, 2x the NDC factor: 1/2.
    assert g64 / g32 == pytest.approx(0.5, rel=0.02)
    assert g128 / g64 == pytest.approx(0.5, rel=0.02)


def test_resolution_threshold_by_hand():
    assert resolution_threshold(2e-4, 64, None) == 2e-4
    assert resolution_threshold(2e-4, 64, 800) == pytest.approx(2.5e-3)
    assert resolution_threshold(2e-4, 1600, 800) == pytest.approx(1e-4)
    for width, ref in ((0, 800), (64, 0), (float("nan"), 800), (64, float("inf")), (-3, 800)):
        with pytest.raises(ValueError, match="width"):
            resolution_threshold(2e-4, width, ref)


@pytest.mark.parametrize("bad", [0, -800, float("inf"), float("nan"), True, "800"])
def test_config_rejects_a_bad_reference_width(bad):
    with pytest.raises(ValueError, match="grad_threshold_width"):
        MVGSConfig.default(grad_threshold_width=bad)


def test_config_round_trips_the_reference_width():
    cfg = MVGSConfig.default(grad_threshold_width=800)
    assert MVGSConfig.from_dict(cfg.to_dict()).grad_threshold_width == 800


def _thresholds(cfg: MVGSConfig, scene) -> list[tuple[int, float]]:
    sched = ViewSchedule(scene, cfg)
    out = []
    for plan in sched:
        maps = [torch.zeros(c.height, c.width) for c in plan.cameras]
        out.append((plan.factor, sched.densify_context(plan, maps, 100).grad_threshold))
    return out


def test_schedule_scales_the_threshold_per_pyramid_level():
    scene = synthetic_scene(n_train=8, size=32)  # 32 px at factor 1
    stages = (Stage(4, 2, 3), Stage(2, 2, 3), Stage(1, 2, 3))
    base = dict(stages=stages, densify_from=0, densify_every=1, grad_threshold=2e-4)
    plain = _thresholds(MVGSConfig(**base), scene)
    scaled = _thresholds(MVGSConfig(**base, grad_threshold_width=32), scene)
    assert [t for _, t in plain] == [2e-4] * 9
    for factor, t in scaled:  # rendered width 32 / factor: beta * factor
        assert t == pytest.approx(2e-4 * factor), factor
    wide = _thresholds(MVGSConfig(**base, grad_threshold_width=320), scene)
    for factor, t in wide:
        assert t == pytest.approx(2e-4 * 10 * factor)


def test_mvad_halves_the_scaled_threshold():
    scene = synthetic_scene(n_train=8, size=32)  # cameras on a ring: opposite views are 2 apart
    cfg = MVGSConfig(stages=(Stage(1, 8, 2),), densify_from=0, densify_every=1, mvad=MVADConfig(enabled=True, center="scene"),
                     grad_threshold=2e-4, grad_threshold_width=64)
    for _, t in _thresholds(cfg, scene):  # all 8 ring views in every step: the rule fires
        assert t == pytest.approx(2e-4 * 2 / 2)
    off = dataclasses.replace(cfg, mvad=MVADConfig(enabled=False))
    assert all(t == pytest.approx(4e-4) for _, t in _thresholds(off, scene))
    assert not math.isclose(2e-4 * 2 / 2, 4e-4)


def _densify_infos(cfg: MVGSConfig, scene) -> list:
    from mvgs_plugin.adapters.gs3d import GS3DConfig
    from mvgs_plugin import MVGS

    torch.manual_seed(0)
    adapter = GS3DAdapter.from_scene(scene, GS3DConfig(seed=0))
    infos = []
    MVGS(adapter, scene, cfg).fit(progress=False, callback=infos.append)
    return [i for i in infos if i.densify is not None]


def test_controller_hands_the_scaled_threshold_to_the_adapter_and_reports_mvad():
    scene = synthetic_scene(n_train=8, size=32)
    cfg = MVGSConfig(stages=(Stage(2, 8, 4), Stage(1, 8, 4)), densify_from=0, densify_every=2,
                     mvad=MVADConfig(enabled=True), grad_threshold=2e-4, grad_threshold_width=64)
    infos = _densify_infos(cfg, scene)
    assert [i.factor for i in infos] == [2, 2, 1, 1]
    for info in infos:  # width 32 / factor; the eight ring views always hold an opposite pair
        expected = 2e-4 * 64 / (32 / info.factor) / 2
        assert info.mvad_fired and info.threshold == pytest.approx(expected)
        assert info.densify.extra["grad_threshold"] == pytest.approx(expected)  # what the adapter used
    off = _densify_infos(dataclasses.replace(cfg, mvad=MVADConfig(enabled=False)), scene)
    assert not any(i.mvad_fired for i in off)
    assert [i.threshold for i in off] == pytest.approx([2e-4 * 64 / (32 / i.factor) for i in off])


def test_presets_threshold_policy():
    assert MVGSConfig.default().grad_threshold_width == 800
    assert MVGSConfig.paper().grad_threshold_width is None  # the released code: β at every level
    assert MVGSConfig.baseline().grad_threshold_width is None  # 3DGS
