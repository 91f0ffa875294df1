"""The conformance suite (mvgs_plugin.testing) on adapters broken in ways it used to miss or
misname: a trainable group left out of named_gradients(), state_dicts that drop a parameter, a
statistic or a group's Adam moments, renders that are non-finite only at small sizes or in one
pixel, densify drawing from the global torch RNG or from a generator state_dict() leaves out,
and densify restarting Adam's moments.

Each broken adapter is the shipped GS3DAdapter with one method changed; the message must name
what was broken (the group, entry, view size or check), which the test knows from the change it
made, not from the suite's output. Two changed adapters are not broken and must pass: one whose
densify draws from the global RNG, and one that makes a new leaf tensor at each render (as
3DGS's screen-space points), which is no parameter.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from mvgs_plugin.adapters.gs3d import STAT_NAMES, GS3DAdapter
from mvgs_plugin.protocol import DensifyContext
from mvgs_plugin.testing import (CHECKS, check_adapter, check_gradients_reach_every_group, check_state_dict_round_trip,
                                 synthetic_scene)
from test_controller import ForgetsStats  # a resume that starts the window's statistics over

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene()


def suite_error(kind, scene) -> str:
    """The message check_adapter fails with on `kind` (a GS3DAdapter subclass)."""
    with pytest.raises(AssertionError) as info:
        check_adapter(lambda s: kind.from_scene(s), scene)
    return str(info.value)


# ---- 1. every trainable group in named_gradients() ---------------------------------------------

class HidesSh0(GS3DAdapter):
    """Trains its DC colours but does not report their gradient (the NaN guard never sees it)."""

    def named_gradients(self):
        return {k: v for k, v in super().named_gradients().items() if k != "sh0"}


def test_a_group_left_out_of_named_gradients_is_named(scene):
    message = suite_error(HidesSh0, scene)
    n = GS3DAdapter.from_scene(scene).num_primitives()
    assert message.startswith("check_gradients_reach_every_group: named_gradients() ")
    # the omitted group, found as the adapter holds it and as its optimizer names it, with its shape
    assert f"has no gradient for params['sh0'] (optimizer's group 'sh0'), a [{n}, 1, 3] tensor" \
        in message
    assert "'means', 'opacities', 'quats', 'scales', 'shN'" in message


class FreshLeafEachRender(GS3DAdapter):
    """Each render makes a new leaf tensor that requires grad and adds it in (times 0), as 3DGS
    makes its screen-space points to read their gradient: no parameter, nothing to name or save."""

    def render(self, cameras, backgrounds):
        out = super().render(cameras, backgrounds)
        probe = torch.zeros((), requires_grad=True)
        return dataclasses.replace(out, images=out.images + 0 * probe)


def test_a_leaf_made_anew_at_each_render_is_no_parameter(scene):
    for check in (check_gradients_reach_every_group, check_state_dict_round_trip):
        check(lambda s: FreshLeafEachRender.from_scene(s), scene)


# ---- 2. the state_dict round trip ----------------------------------------------------------------

class DropsSh0Moments(GS3DAdapter):
    """state_dict() leaves out the Adam moments of the colour group (a resume restarts them)."""

    def state_dict(self):
        state = super().state_dict()
        index = [g["name"] for g in self.optimizer.param_groups].index("sh0")
        state["optimizer"]["state"].pop(index, None)
        return state


class DropsMaxRadii(GS3DAdapter):
    """state_dict() leaves out the screen-radius statistic (read only by size pruning); loading
    tolerates its absence (zeros), so nothing raises."""

    def state_dict(self):
        state = super().state_dict()
        del state["stats"]["max_radii2D"]
        return state

    def load_state_dict(self, state):
        n = state["params"]["means"].shape[0]
        super().load_state_dict({**state, "stats": {"max_radii2D": torch.zeros(n), **state["stats"]}})


class DropsQuats(GS3DAdapter):
    """state_dict() leaves out the rotations; loading keeps the adapter's own, cycled to the
    saved count."""

    def state_dict(self):
        state = super().state_dict()
        del state["params"]["quats"]
        return state

    def load_state_dict(self, state):
        n = state["params"]["means"].shape[0]
        own = self.params["quats"].detach()
        super().load_state_dict({**state, "params": {**state["params"], "quats": own[torch.arange(n) % len(own)]}})


class ZeroesCoverage(GS3DAdapter):
    """load_state_dict() starts one statistic over: its state_dict() after loading is not the one
    it was given."""

    def load_state_dict(self, state):
        super().load_state_dict(state)
        self.stats["coverage_accum"].zero_()


def test_dropped_adam_moments_are_named(scene):
    message = suite_error(DropsSh0Moments, scene)
    # the saved and the loaded state_dicts agree (both lack the moments); one step later the
    # colours differ, as the loaded adapter stepped them with fresh moments
    assert message.startswith("check_state_dict_round_trip: after one more step ")
    assert "entry ['params']['sh0'] differs between the saved adapter's and the loaded adapter's" in message
    assert "optimizer's moments" in message


def test_a_dropped_statistic_is_named(scene):
    assert "max_radii2D" in STAT_NAMES  # the statistic the subclass drops is one the adapter keeps
    message = suite_error(DropsMaxRadii, scene)
    n = GS3DAdapter.from_scene(scene).num_primitives()
    assert message.startswith(f"check_state_dict_round_trip: state_dict() holds no tensor equal to the adapter's "
                              f"stats['max_radii2D'], a [{n}] tensor accumulate_stats() changes (a statistic)")


def test_a_dropped_parameter_is_named(scene):
    message = suite_error(DropsQuats, scene)
    n = GS3DAdapter.from_scene(scene).num_primitives()
    assert message.startswith(f"check_state_dict_round_trip: state_dict() holds no tensor equal to params['quats'] "
                              f"(optimizer's group 'quats'), a [{n}, 4] tensor every view's loss reaches")


def test_a_statistic_load_state_dict_does_not_restore_is_named(scene):
    message = suite_error(ZeroesCoverage, scene)
    assert message.startswith("check_state_dict_round_trip: ")
    assert ("entry ['stats']['coverage_accum'] differs between the saved state_dict() and the loaded adapter's "
            "state_dict()") in message


# ---- 3, 4. non-finite renders ------------------------------------------------------------------

class NaNWhenSmall(GS3DAdapter):
    """Renders NaN at every size below 8 px but 1 px (a pyramid level's camera)."""

    def render(self, cameras, backgrounds):
        out = super().render(cameras, backgrounds)
        if 1 < cameras[0].width < 8:
            out = dataclasses.replace(out, images=out.images * math.nan)
        return out


class NaNPixel(GS3DAdapter):
    """One NaN value in every render: the first channel of the top-left pixel."""

    def render(self, cameras, backgrounds):
        out = super().render(cameras, backgrounds)
        images = out.images.clone()
        images[:, 0, 0, 0] = math.nan
        return dataclasses.replace(out, images=images)


def test_a_render_non_finite_only_at_a_small_size_fails_check_render(scene):
    small = scene.train_cameras[0].scaled(4)
    assert 1 < small.width < 8  # the size NaNWhenSmall breaks
    message = suite_error(NaNWhenSmall, scene)
    values = small.width * small.height * 3
    assert message.startswith(f"check_render: render() of the view scaled by 1/4 (a pyramid level's camera) gave "
                              f"{values} non-finite value(s) among {values}")
    assert f"{small.width}x{small.height} px" in message


def test_a_nan_pixel_is_reported_as_non_finite_not_as_unseeded(scene):
    cam = scene.train_cameras[0]
    message = suite_error(NaNPixel, scene)
    assert message.startswith(f"check_make_adapter_is_deterministic: render() gave 1 non-finite value(s) among "
                              f"{cam.width * cam.height * 3} (the first: nan at channel 0 of pixel (x=0, y=0) of view "
                              f"{cam.name!r}, {cam.width}x{cam.height} px)")
    assert "seed" not in message and "differently" not in message


# ---- 5. the global torch RNG, and what a densify that differs is told --------------------------

class GlobalJitter(GS3DAdapter):
    """Densify jitters every mean with draws from the global torch RNG (which MVGS's checkpoints
    save and restore)."""

    def densify(self, ctx):
        report = super().densify(ctx)
        with torch.no_grad():
            means = self.params["means"]
            means.add_(1e-3 * torch.randn(means.shape, dtype=means.dtype))
        return report


class HiddenJitter(GS3DAdapter):
    """Densify jitters every mean with draws from a generator of its own that state_dict() leaves
    out: a loaded adapter starts that generator over."""

    def densify(self, ctx):
        report = super().densify(ctx)
        if not hasattr(self, "jitter"):
            self.jitter = torch.Generator().manual_seed(7)
        with torch.no_grad():
            means = self.params["means"]
            means.add_(1e-3 * torch.randn(means.shape, generator=self.jitter, dtype=means.dtype))
        return report


def densified_positions(adapter_seed: int, scene) -> torch.Tensor:
    adapter = GlobalJitter.from_scene(scene)
    torch.manual_seed(adapter_seed)
    with torch.no_grad():
        adapter.densify(DensifyContext(step=1, grad_threshold=math.inf, scene_extent=float(scene.extent)))
    return adapter.positions()


def test_densify_from_the_global_rng_round_trips_and_the_caller_rng_is_kept(scene):
    # the jitter is not inert: two global RNG states put the Gaussians in two places
    assert not torch.equal(densified_positions(1, scene), densified_positions(2, scene))
    torch.manual_seed(123)
    before = torch.get_rng_state()
    check_state_dict_round_trip(lambda s: GlobalJitter.from_scene(s), scene)
    assert torch.equal(torch.get_rng_state(), before)
    assert set(check_adapter(lambda s: GlobalJitter.from_scene(s), scene).values()) == {"ok"}


def test_a_densify_that_lands_elsewhere_is_told_as_such(scene):
    with pytest.raises(AssertionError) as info:
        check_state_dict_round_trip(lambda s: HiddenJitter.from_scene(s), scene)
    message = str(info.value)
    # same counts, other positions: the message says so, and does not claim the counts differ
    assert message.startswith("after one more step, a densify of the loaded adapter went ")
    went = message.split(" went ")[1].split(" as the saved adapter did")[0]
    before, after = (int(v) for v in went.split(" -> "))
    assert after > before
    assert "but put its primitives elsewhere (positions() differ by up to " in message
    assert "where the saved adapter went" not in message
    assert "densify reads something state_dict() does not carry" in message


def test_a_densify_of_other_counts_names_the_counts_and_the_statistic(scene):
    with pytest.raises(AssertionError) as info:
        check_state_dict_round_trip(lambda s: ForgetsStats.from_scene(s), scene)
    message = str(info.value)
    n = GS3DAdapter.from_scene(scene).num_primitives()
    assert message.startswith(f"a densify right after load_state_dict went {n} -> {n} where the saved adapter went "
                              f"{n} -> ")
    assert "right after loading, entry ['stats']['grad_accum'] differs between the saved state_dict()" in message


# ---- densify keeps Adam's moments ----------------------------------------------------------------

class RestartsMoments(GS3DAdapter):
    """Densify drops the optimizer's state: every group starts Adam over."""

    def densify(self, ctx):
        report = super().densify(ctx)
        self.optimizer.state.clear()
        return report


def test_densify_restarting_adam_is_named(scene):
    message = suite_error(RestartsMoments, scene)
    n = GS3DAdapter.from_scene(scene).num_primitives()
    assert message.startswith(f"check_densify_keeps_optimizer_state: a densify with an infinite threshold kept all "
                              f"{n} primitives where they were, yet the next optimizer step moved the model elsewhere")


# ---- the shipped adapter --------------------------------------------------------------------------

def test_the_shipped_3dgs_adapter_passes_every_check(scene):
    report = check_adapter(lambda s: GS3DAdapter.from_scene(s), scene)
    assert report == {name: "ok" for name in [c.__name__ for c in CHECKS] + ["check_distributed_support"]}
