"""Adapter conformance checks anyone can run on their own adapter.

    from mvgs_plugin.testing import check_adapter
    check_adapter(lambda scene: MyAdapter.from_scene(scene))       # raises AssertionError on failure

Adapters that implement the optional DistributedAdapter methods (training over several
processes) also get check_distributed_support.

`make_adapter(scene)` must return a fresh adapter for the scene (same seed -> same model). The
scene defaults to `synthetic_scene()`: a few coloured points seen by a ring of small cameras,
with smooth synthetic target images (no renderer needed to make them). Each check is also a
function of its own, so a test suite can run them one by one.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Callable, Dict, List, Optional

import torch

from .camera import Camera
from .data.scene import PointCloud, Scene
from .losses import photometric_loss
from .protocol import Adapter, DensifyContext, DistributedAdapter, RenderResult, check_is_adapter

MakeAdapter = Callable[[Scene], Adapter]


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """World-to-camera [4, 4] (OpenCV axes) of a camera at `eye` looking at `target`."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up), dim=0)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


def synthetic_scene(n_train: int = 6, n_test: int = 2, size: int = 24, n_points: int = 300,
                    seed: int = 0, time: bool = False) -> Scene:
    """A small scene: points on a sphere of radius 0.6, cameras on a ring at distance 3 looking
    at the origin, target images with a smooth colour gradient per view. With time=True every
    camera carries a time in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.nn.functional.normalize(torch.randn(n_points, 3, generator=g, dtype=torch.float64), dim=-1) * 0.6
    rgb = torch.rand(n_points, 3, generator=g)
    K = [[1.2 * size, 0, size / 2], [0, 1.2 * size, size / 2], [0, 0, 1]]
    cams, images = [], {}
    n = n_train + n_test
    yy, xx = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (3 * math.cos(a), 3 * math.sin(a), 0.8 + 0.3 * math.sin(3 * a))
        cam = Camera(uid=i, name=f"view_{i:03d}", K=K, world_to_camera=look_at(eye), width=size, height=size,
                     time=(i / max(1, n - 1)) if time else None)
        cams.append(cam)
        c = torch.rand(3, generator=g)
        images[i] = torch.stack([c[0] * xx, c[1] * yy, c[2] * (1 - xx) * yy], -1).clamp(0, 1)
    test_ids = set(range(0, n, max(1, n // max(1, n_test)))[:n_test])
    train = [c for c in cams if c.uid not in test_ids]
    test = [c for c in cams if c.uid in test_ids]
    return Scene(train, test, images, points=PointCloud(pts.float(), rgb))


PLANE_HALF = 1.5  # plane_scene's textured square is [-PLANE_HALF, PLANE_HALF]^2 at z = 0


def plane_texture(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """[..., 3] colour of plane_scene's square at (x, y): a few low-frequency waves per channel."""
    r = 0.5 + 0.3 * torch.sin(2.1 * x) * torch.cos(1.7 * y)
    g = 0.5 + 0.3 * torch.cos(1.3 * x + 0.4) * torch.sin(2.4 * y + 0.2)
    b = 0.45 + 0.25 * torch.sin(1.1 * (x + y))
    return torch.stack([r, g, b], dim=-1)


def plane_image(cam: Camera, supersample: int = 3) -> torch.Tensor:
    """[H, W, 3] the textured square seen by `cam` on black, by exact ray-plane intersection
    (supersample x supersample rays per pixel, box-filtered): independent of any rasterizer."""
    s = supersample
    offs = (torch.arange(s, dtype=torch.float64) + 0.5) / s
    v = (torch.arange(cam.height, dtype=torch.float64)[:, None] + offs[None, :]).reshape(-1)
    u = (torch.arange(cam.width, dtype=torch.float64)[:, None] + offs[None, :]).reshape(-1)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    o, d = cam.rays(torch.stack([uu, vv], dim=-1).reshape(-1, 2))
    o, d = o.to(torch.float64), d.to(torch.float64)
    t = -o[..., 2] / d[..., 2]
    p = o + t[..., None] * d
    hit = (t > 0) & (p[..., 0].abs() <= PLANE_HALF) & (p[..., 1].abs() <= PLANE_HALF)
    rgb = plane_texture(p[..., 0], p[..., 1]) * hit[..., None]
    return rgb.reshape(cam.height, s, cam.width, s, 3).mean(dim=(1, 3)).float()


def plane_scene(n_train: int = 24, n_test: int = 4, size: int = 64, n_points: int = 1500, seed: int = 0) -> Scene:
    """One flat textured square seen from a ring of cameras 3.2 units away at 35-65 degrees
    elevation; initial points uniform on the square with the texture's colour. The simplest
    scene there is: what it needs is a measure of what densification adds on its own."""
    K = [[1.2 * size, 0, size / 2], [0, 1.2 * size, size / 2], [0, 0, 1]]
    cams, images = [], {}
    n = n_train + n_test
    for i in range(n):
        a = 2 * math.pi * i / n
        elev = math.radians(50 + 15 * math.sin(3 * a))
        eye = (3.2 * math.cos(elev) * math.cos(a), 3.2 * math.cos(elev) * math.sin(a), 3.2 * math.sin(elev))
        cam = Camera(uid=i, name=f"view_{i:03d}", K=K, world_to_camera=look_at(eye), width=size, height=size)
        cams.append(cam)
        images[i] = plane_image(cam)
    test_ids = set(range(0, n, max(1, n // max(1, n_test)))[:n_test])
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n_points, 2, generator=g, dtype=torch.float64) * 2 - 1) * PLANE_HALF
    xyz = torch.cat([xy, torch.zeros(n_points, 1, dtype=torch.float64)], dim=-1)
    return Scene([c for c in cams if c.uid not in test_ids], [c for c in cams if c.uid in test_ids], images,
                 points=PointCloud(xyz, plane_texture(xy[:, 0], xy[:, 1]).clamp(0, 1)))


def _check_finite(images: torch.Tensor, cams: List[Camera], what: str = "") -> None:
    """AssertionError naming the first non-finite value of a render of `cams` (its view, size,
    pixel and channel; `what` says which render it was) and how many there are."""
    bad = ~torch.isfinite(images)
    if not bool(bad.any()):
        return
    first = [int(i) for i in bad.nonzero()[0]]
    value = float(images[tuple(first)])
    if len(first) == 4 and first[0] < len(cams):
        cam = cams[first[0]]
        where = (f"channel {first[3]} of pixel (x={first[2]}, y={first[1]}) of view {cam.name!r}, "
                 f"{cam.width}x{cam.height} px")
    else:
        where = f"index {first} of images {list(images.shape)}"
    which = f"render() of {what}" if what else "render()"
    raise AssertionError(f"{which} gave {int(bad.sum())} non-finite value(s) among {images.numel()} (the first: "
                         f"{value} at {where}); every pixel of a render must be finite")


def _render(adapter: Adapter, cams: List[Camera], backgrounds: torch.Tensor) -> RenderResult:
    """adapter.render, its images checked finite. Every render the checks make is checked: here,
    or by _check_finite in check_render, or (the empty view, the hard cameras) with a message
    that says what the view tests."""
    result = adapter.render(cams, backgrounds)
    images = getattr(result, "images", None)
    if isinstance(images, torch.Tensor):
        _check_finite(images.detach(), cams)
    return result


def _loss(adapter: Adapter, scene: Scene, cams: List[Camera]) -> torch.Tensor:
    result = _render(adapter, cams, torch.zeros(len(cams), 3))
    gts = [scene.image(c) for c in cams]
    return sum(photometric_loss(result.images[i], gts[i].to(result.images)) for i in range(len(cams))), result


def _with_stats(make_adapter: MakeAdapter, scene: Scene, cams: List[Camera]) -> Adapter:
    """A fresh adapter at step 1 that rendered `cams` one at a time, backpropagated each and
    folded in their statistics."""
    adapter = make_adapter(scene)
    adapter.set_step(1)
    for cam in cams:
        loss, result = _loss(adapter, scene, [cam])
        loss.backward()
        adapter.accumulate_stats(result)
    return adapter


def check_protocol_methods(make_adapter: MakeAdapter, scene: Scene) -> None:
    """The adapter has every method of the Adapter protocol (the controller calls some only late:
    reset_opacity at the first opacity reset)."""
    try:
        check_is_adapter(make_adapter(scene), "make_adapter(scene)")
    except TypeError as err:
        raise AssertionError(str(err)) from None


def check_make_adapter_is_deterministic(make_adapter: MakeAdapter, scene: Scene) -> None:
    """Two calls of make_adapter build the same model (the checks after this one compare
    adapters built by separate calls, and a resume rebuilds the model before it loads). A
    non-finite render is reported as such, not as a difference between the two."""
    renders = []
    for _ in range(2):
        adapter = make_adapter(scene)
        adapter.set_step(1)
        with torch.no_grad():
            renders.append(_render(adapter, scene.train_cameras[:1], torch.zeros(1, 3)).images)
    assert torch.equal(renders[0], renders[1]), (
        f"two calls of make_adapter built models that render differently (by up to "
        f"{float((renders[0] - renders[1]).abs().max()):.3g}): make_adapter must build the same model every call "
        "(seed its random initialisation, e.g. torch.manual_seed(0) inside it)")


def check_render(make_adapter: MakeAdapter, scene: Scene) -> None:
    """Render shapes, dtype and ranges; a chunk of views of one size renders as a batch; every
    pixel is finite, at full size and at a pyramid level's size (1/4)."""
    adapter = make_adapter(scene)
    adapter.set_step(1)
    cams = scene.train_cameras[:2]
    result = adapter.render(cams, torch.zeros(2, 3))
    assert isinstance(result, RenderResult), f"render must return RenderResult, got {type(result).__name__}"
    H, W = cams[0].height, cams[0].width
    assert tuple(result.images.shape) == (2, H, W, 3), f"images must be [2,{H},{W},3], got {list(result.images.shape)}"
    _check_finite(result.images.detach(), cams)
    if result.alphas is not None:
        assert tuple(result.alphas.shape) == (2, H, W, 1), f"alphas must be [2,{H},{W},1], got {list(result.alphas.shape)}"
        assert result.alphas.min() >= 0 and result.alphas.max() <= 1, "alphas must be in [0, 1]"
    assert result.images.requires_grad, "render output must be differentiable w.r.t. the model"
    small = cams[0].scaled(4)
    img = adapter.render([small], torch.ones(1, 3)).images
    assert tuple(img.shape) == (1, small.height, small.width, 3), (
        f"a pyramid camera ({small.width}x{small.height} px, the view scaled by 1/4) must render at its own size, "
        f"got images {list(img.shape)}")
    _check_finite(img.detach(), [small], "the view scaled by 1/4 (a pyramid level's camera)")


def check_gradients_reach_every_group(make_adapter: MakeAdapter, scene: Scene) -> None:
    """After one backward (the views' loss plus regularization(step), as the controller's step),
    every trainable group named by named_gradients() has a finite, non-zero gradient
    (late-activated parts are switched on by a large set_step first), and named_gradients()
    reports the gradient of every trainable tensor that backward reaches: the leaves of the
    loss's autograd graph that two steps' losses share, found by walking the graphs, not by
    asking the adapter (a leaf made anew at each render, as 3DGS's screen-space points, is no
    parameter). The controller's NaN/Inf guard, and distributed training, see only the groups
    named_gradients() names."""
    adapter = make_adapter(scene)
    adapter.set_step(100_000)
    # Two optimizer steps first: a fresh model can be symmetric (isotropic Gaussians have no
    # gradient w.r.t. their rotation) in ways training immediately breaks.
    leaves: List[torch.Tensor] = []
    for i in range(3):
        adapter.zero_grad()
        loss, _ = _loss(adapter, scene, scene.train_cameras[:3])
        reg = adapter.regularization(100_000)
        if reg is not None:
            loss = loss + reg
        found = _graph_leaves(loss)
        leaves = [t for t in found if any(t is u for u in leaves)] if i == 2 else found
        loss.backward()
        if i < 2:
            adapter.optimizer_step()
    grads = adapter.named_gradients()
    assert grads, "named_gradients() must name at least one group"
    for name, g in grads.items():
        assert g is not None, f"group {name!r} received no gradient"
        assert torch.isfinite(g).all(), f"group {name!r} has non-finite gradients"
        assert g.abs().sum() > 0, f"group {name!r} has an all-zero gradient"
    reported = [g for g in grads.values() if isinstance(g, torch.Tensor)]
    for leaf in leaves:
        g = leaf.grad
        if g is None or any(r is g or (r.shape == g.shape and torch.equal(r, g)) for r in reported):
            continue
        raise AssertionError(
            f"named_gradients() (it names {sorted(grads)}) has no gradient for {_tensor_name(adapter, leaf)}, a "
            f"{list(leaf.shape)} tensor every step's loss reaches, whose .grad the backward filled: it must report "
            "every trainable group (the controller's NaN/Inf guard checks only the groups it names)")
    adapter.zero_grad()
    for name, g in adapter.named_gradients().items():
        assert g is None or not bool(g.abs().sum() > 0), f"zero_grad() left a gradient in group {name!r}"


def _graph_leaves(output: torch.Tensor) -> List[torch.Tensor]:
    """The leaf tensors of output's autograd graph: those whose .grad a backward of it fills."""
    leaves: Dict[int, torch.Tensor] = {}
    seen, stack = set(), [output.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        leaf = getattr(node, "variable", None)  # an AccumulateGrad node holds the leaf it fills
        if isinstance(leaf, torch.Tensor):
            leaves[id(leaf)] = leaf
        stack.extend(nxt for nxt, _ in node.next_functions)
    return list(leaves.values())


def _tensor_name(adapter: Adapter, tensor: torch.Tensor) -> str:
    """How the adapter holds `tensor`, for messages: its attribute path (params['sh0'],
    mlps.color.0.weight) and the name of the optimizer group that steps it, when found among the
    adapter's attributes (modules, optimizers, and dicts, lists and tuples nested up to three
    levels deep)."""
    paths, groups = [], []

    def visit(obj, path: str, depth: int) -> None:
        if obj is tensor:
            paths.append(path)
        elif isinstance(obj, torch.optim.Optimizer):
            for i, group in enumerate(obj.param_groups):
                if any(p is tensor for p in group["params"]):
                    groups.append(f"{path}'s group {group.get('name', i)!r}")
        elif isinstance(obj, torch.nn.Module):
            paths.extend(f"{path}.{n}" for n, p in obj.named_parameters() if p is tensor)
        elif depth < 3 and isinstance(obj, dict):
            for k, v in obj.items():
                visit(v, f"{path}[{k!r}]", depth + 1)
        elif depth < 3 and isinstance(obj, (list, tuple)):
            for i, v in enumerate(obj):
                visit(v, f"{path}[{i}]", depth + 1)

    for attr, value in vars(adapter).items() if hasattr(adapter, "__dict__") else ():
        visit(value, attr, 1)
    if paths and groups:
        return f"{paths[0]} ({groups[0]})"
    return (paths + groups + ["a tensor not found among the adapter's attributes"])[0]


def check_optimizer_descends(make_adapter: MakeAdapter, scene: Scene, steps: int = 10) -> None:
    """A few optimizer steps on the same views lower their loss (an update of the wrong sign, or
    one that misses the parameters the renderer reads, does not)."""
    adapter = make_adapter(scene)
    adapter.set_step(1)
    cams = scene.train_cameras[:3]
    with torch.no_grad():
        before = float(_loss(adapter, scene, cams)[0])
    for _ in range(steps):
        loss, _ = _loss(adapter, scene, cams)
        loss.backward()
        adapter.optimizer_step()
        adapter.zero_grad()
    with torch.no_grad():
        after = float(_loss(adapter, scene, cams)[0])
    assert after < before, (f"{steps} optimizer steps on the same 3 views did not lower their loss "
                            f"({before:.6g} -> {after:.6g}): the update goes the wrong way or misses what render() reads")


def check_summed_equals_accumulated(make_adapter: MakeAdapter, scene: Scene, rtol: float = 1e-5) -> None:
    """Backward of views one at a time accumulates exactly the gradient of their summed loss."""
    cams = scene.train_cameras[:3]
    a = make_adapter(scene)
    a.set_step(100_000)
    loss, _ = _loss(a, scene, cams)
    loss.backward()
    joint = {k: v.clone() for k, v in a.named_gradients().items() if v is not None}
    b = make_adapter(scene)
    b.set_step(100_000)
    for cam in cams:
        loss, _ = _loss(b, scene, [cam])
        loss.backward()
    acc = b.named_gradients()
    for name, g in joint.items():
        h = acc[name]
        scale = g.abs().max().clamp_min(1e-30)
        err = float((g - h).abs().max() / scale)
        assert err <= rtol, f"group {name!r}: accumulated gradient differs from the summed one by {err:.3g} (relative)"


def check_stats_and_densify(make_adapter: MakeAdapter, scene: Scene) -> None:
    """Statistics accumulate (a zero threshold grows the model, an infinite one does not) and
    densification keeps parameters and optimizer state aligned (a step after it works)."""
    for threshold, grows in ((math.inf, False), (0.0, True)):
        adapter = _with_stats(make_adapter, scene, scene.train_cameras[:3])
        adapter.optimizer_step()  # as in training: the optimizer holds state (Adam's moments) when densify comes
        adapter.zero_grad()
        n0 = adapter.num_primitives()
        ctx = DensifyContext(step=1, grad_threshold=threshold, scene_extent=float(scene.extent),
                             cameras=tuple(scene.train_cameras[:3]))
        with torch.no_grad():
            report = adapter.densify(ctx)
        n1 = adapter.num_primitives()
        assert report.before == n0 and report.after == n1, f"DensifyReport says {report.before}->{report.after}, model has {n0}->{n1}"
        if grows:
            assert n1 > n0, (f"threshold 0 must densify the visible primitives, got {n0} -> {n1} (a model that "
                             "can only grow where its primitives left their initial cells, as Scaffold-GS's anchors, "
                             "has nothing to grow when fresh: let make_adapter return one that can, e.g. "
                             "ScaffoldConfig(offset_init_std=1.0) as tests/test_adapter_scaffold.py does)")
        else:
            assert n1 <= n0, f"an infinite threshold must not grow the model, got {n0} -> {n1}"
        assert adapter.positions().shape == (n1, 3), f"positions() must be [{n1},3], got {list(adapter.positions().shape)}"
        with torch.no_grad():  # the call reset the statistics: nothing is left to grow from
            again = adapter.densify(dataclasses.replace(ctx, grad_threshold=1e-12))
        assert again.after <= again.before, (f"a second densify right after the first (no view rendered in between, "
                                             f"threshold 1e-12) grew {again.before} -> {again.after}: densify must "
                                             "reset the statistics it used")
        adapter.optimizer_step()
        adapter.zero_grad()
        loss, result = _loss(adapter, scene, scene.train_cameras[:1])
        loss.backward()
        _check_optimizer_state_shapes(adapter, n0, n1)  # before the step: torch's fused Adam may abort on a mismatch
        try:
            adapter.optimizer_step()  # shapes of optimizer state and parameters must agree
        except RuntimeError as err:
            raise AssertionError(
                f"the optimizer step after a densify that went {n0} -> {n1} failed ({err}): the optimizer's state "
                "(e.g. Adam's exp_avg / exp_avg_sq) must be cut and extended with the parameters' rows") from err
        adapter.zero_grad()
        with torch.no_grad():
            after = _render(adapter, scene.train_cameras[:1], torch.zeros(1, 3)).images
        assert not torch.equal(after, result.images.detach()), (
            "after densify, an optimizer step with gradients changed nothing the view renders: the optimizer "
            "still holds the tensors from before densify (its state must follow the new parameters)")


def check_densify_keeps_optimizer_state(make_adapter: MakeAdapter, scene: Scene) -> None:
    """A densify that changes no row leaves the optimizer's state (Adam's moments and step
    counts) as it was: of two adapters built and trained alike (statistics of 3 views, one
    optimizer step), one densifies with an infinite threshold; when that kept the count and every
    position, one more step on the same view must move both to the same render, bit for bit (an
    adapter that restarts its moments at every densify trains, worse). A densify that prunes or
    moves rows here leaves nothing to compare, and the check says nothing."""
    cams = scene.train_cameras[:3]
    twins = []
    for _ in range(2):
        adapter = _with_stats(make_adapter, scene, cams)
        adapter.optimizer_step()
        adapter.zero_grad()
        twins.append(adapter)
    kept, densified = twins
    n0 = densified.num_primitives()
    with torch.no_grad():
        densified.densify(DensifyContext(step=1, grad_threshold=math.inf, scene_extent=float(scene.extent),
                                         cameras=tuple(cams)))
    if densified.num_primitives() != n0 or not torch.equal(densified.positions(), kept.positions()):
        return
    images = []
    for adapter in twins:
        adapter.set_step(2)
        loss, _ = _loss(adapter, scene, cams[:1])
        loss.backward()
        adapter.optimizer_step()
        adapter.zero_grad()
        with torch.no_grad():
            images.append(_render(adapter, scene.train_cameras[-1:], torch.zeros(1, 3)).images)
    assert torch.equal(images[0], images[1]), (
        f"a densify with an infinite threshold kept all {n0} primitives where they were, yet the next optimizer step "
        f"moved the model elsewhere than the same step without that densify (renders differ by up to "
        f"{float((images[0] - images[1]).abs().max()):.3g}): densify must keep the optimizer's state (Adam's moments "
        "and step counts) of the rows it keeps")


def _check_optimizer_state_shapes(adapter: Adapter, n0: int, n1: int) -> None:
    """For an adapter that keeps its torch optimizer(s) as `optimizer` (or a dict `optimizers`,
    gsplat's layout): every per-parameter state tensor (Adam's moments) has its parameter's shape.
    Checked before the step, as torch's multi-tensor Adam can end the process on a mismatch
    rather than raise; other layouts are checked by the step itself."""
    found = getattr(adapter, "optimizer", None)
    optimizers = list(found.values()) if isinstance(found, dict) else [found]
    more = getattr(adapter, "optimizers", None)
    optimizers += list(more.values()) if isinstance(more, dict) else [more]
    for opt in (o for o in optimizers if isinstance(o, torch.optim.Optimizer)):
        for group in opt.param_groups:
            for param in group["params"]:
                for key, value in opt.state.get(param, {}).items():
                    if isinstance(value, torch.Tensor) and value.dim() > 0 and value.shape != param.shape:
                        name = group.get("name", f"group {opt.param_groups.index(group)}")
                        raise AssertionError(
                            f"after a densify that went {n0} -> {n1}, the optimizer's {key!r} of {name!r} has shape "
                            f"{list(value.shape)} where its parameter has {list(param.shape)}: the optimizer's state "
                            "(e.g. Adam's exp_avg / exp_avg_sq) must be cut and extended with the parameters' rows")


def check_the_cap_holds(make_adapter: MakeAdapter, scene: Scene) -> None:
    """DensifyContext.max_primitives bounds the count after a densify call, whether the call
    would grow past it (threshold 0) or the model is already above it (it must shrink)."""
    for share in (1.0, 0.5):
        adapter = _with_stats(make_adapter, scene, scene.train_cameras[:3])
        n0 = adapter.num_primitives()
        cap = max(1, int(share * n0))
        ctx = DensifyContext(step=1, grad_threshold=0.0, scene_extent=float(scene.extent),
                             cameras=tuple(scene.train_cameras[:3]), max_primitives=cap)
        with torch.no_grad():
            report = adapter.densify(ctx)
        n1 = adapter.num_primitives()
        assert n1 <= cap, f"densify with max_primitives={cap} (the model had {n0}) left {n1}"
        assert report.after == n1, f"DensifyReport says {report.after} after, the model has {n1}"
        adapter.zero_grad()


def check_background(make_adapter: MakeAdapter, scene: Scene) -> None:
    """A view with nothing in it shows each view's own background colour."""
    base = scene.train_cameras[0]
    away = Camera(904, "away", base.K, look_at((300.0, 0.0, 0.0), (600.0, 0.0, 0.0)), base.width, base.height, base.time)
    adapter = make_adapter(scene)
    adapter.set_step(1)
    colours = torch.tensor([[0.2, 0.5, 0.9], [0.9, 0.1, 0.3]])
    with torch.no_grad():
        images = adapter.render([away, away], colours).images
    assert torch.isfinite(images).all(), ("a view with nothing in it (the camera looks away from every "
                                          "primitive) rendered non-finite pixels: a division by the view's coverage "
                                          "or alpha, 0 there, is the usual cause")
    for i in range(2):
        err = float((images[i] - colours[i].to(images)).abs().max())
        assert err <= 1e-3, (f"an empty view rendered with background {colours[i].tolist()} is off it by {err:.3g}: "
                             "render() must composite over the backgrounds it is given")


def check_state_dict_round_trip(make_adapter: MakeAdapter, scene: Scene) -> None:
    """state_dict -> load_state_dict into a fresh adapter (even of another size) restores it
    exactly. A state taken between densifications (views rendered, their statistics folded in)
    holds every parameter and every statistic, and densifies alike after loading. A state taken
    after a densify and a step: the loaded adapter's state_dict() holds what the saved one holds
    (the same entries, every tensor of the same shape, dtype and values), it renders the same,
    and one more step and a densify leave both adapters with equal state_dicts. After the save,
    each adapter goes on from the same global torch RNG state, as a resumed MVGS run does (its
    checkpoints carry that state); the caller's RNG state is restored afterwards."""
    with torch.random.fork_rng(devices=[]):  # the CPU generator: the one MVGS's checkpoints save
        _round_trip_between_densifications(make_adapter, scene)
        _round_trip_after_a_step(make_adapter, scene)


def _round_trip_between_densifications(make_adapter: MakeAdapter, scene: Scene) -> None:
    """The statistics are part of "everything to resume". What the parameters and statistics are
    is found without asking the adapter: the leaves every view's loss reaches, and the tensors
    among its attributes that accumulate_stats() changes; the saved state must hold each."""
    a = make_adapter(scene)
    a.set_step(1)
    leaves, stats = None, set()
    for view in scene.train_cameras[:3]:
        loss, result = _loss(a, scene, [view])
        found = _graph_leaves(loss)  # the parameters: the leaves every view's loss reaches
        leaves = found if leaves is None else [t for t in leaves if any(t is u for u in found)]
        loss.backward()
        before = {path: t.detach().clone() for path, t in _attribute_tensors(a)}
        a.accumulate_stats(result)
        stats.update(path for path, t in _attribute_tensors(a) if path not in before or not _same(before[path], t))
    state = copy.deepcopy(a.state_dict())
    for leaf in leaves:
        assert _holds(state, leaf.detach()), (
            f"state_dict() holds no tensor equal to {_tensor_name(a, leaf)}, a {list(leaf.shape)} tensor every "
            "view's loss reaches (a trainable parameter): it must hold every parameter, or a loaded adapter keeps "
            "its own")
    now = dict(_attribute_tensors(a))
    for path in sorted(stats):
        if path in now:
            assert _holds(state, now[path].detach()), (
                f"state_dict() holds no tensor equal to the adapter's {path}, a {list(now[path].shape)} tensor "
                "accumulate_stats() changes (a statistic): it must hold every statistic, or a resumed run "
                "densifies or prunes from other values")
    rng = torch.get_rng_state()
    b = make_adapter(scene)
    b.load_state_dict(copy.deepcopy(state))
    differs = _state_difference(state, b.state_dict(), "the saved state_dict()", "the loaded adapter's state_dict()")
    ctx = DensifyContext(step=1, grad_threshold=1e-12, scene_extent=float(scene.extent),
                         cameras=tuple(scene.train_cameras[:3]))
    reports = []
    for m in (a, b):
        torch.set_rng_state(rng)
        with torch.no_grad():
            reports.append(m.densify(ctx))
    _check_densified_alike(a, b, *reports, "a densify right after load_state_dict", differs,
                           "state_dict must carry the densification statistics gathered since the last densify "
                           "(a resumed run would otherwise densify differently)")
    assert differs is None, (
        f"after load_state_dict of a state taken between densifications (the statistics of 3 views folded in), "
        f"{differs}: load_state_dict() must restore exactly what state_dict() gave")


def _round_trip_after_a_step(make_adapter: MakeAdapter, scene: Scene) -> None:
    """A state taken after a densify and an optimizer step (Adam's moments filled) loads to an
    equal state_dict, renders alike, and steps and densifies alike."""
    a = _with_stats(make_adapter, scene, scene.train_cameras[:2])
    with torch.no_grad():
        a.densify(DensifyContext(step=1, grad_threshold=0.0, scene_extent=float(scene.extent)))
    loss, _ = _loss(a, scene, scene.train_cameras[:1])
    loss.backward()
    a.optimizer_step()
    a.zero_grad()
    state = copy.deepcopy(a.state_dict())
    rng = torch.get_rng_state()
    b = make_adapter(scene)
    b.load_state_dict(copy.deepcopy(state))
    differs = _state_difference(state, b.state_dict(), "the saved state_dict()", "the loaded adapter's state_dict()")
    assert differs is None, (
        f"after load_state_dict into a fresh adapter, {differs}: state_dict() must hold everything to resume "
        "(every parameter, the optimizer's state of every group, every statistic densify reads) and "
        "load_state_dict() must restore exactly what it is given")
    assert b.num_primitives() == a.num_primitives(), (
        f"the loaded adapter has {b.num_primitives()} primitives, the saved one {a.num_primitives()}")
    cam = scene.train_cameras[-1:]
    ctx = DensifyContext(step=2, grad_threshold=0.0, scene_extent=float(scene.extent), cameras=tuple(cam))
    images, stepped, reports = [], [], []
    for m in (a, b):
        torch.set_rng_state(rng)
        m.set_step(2)
        loss, result = _loss(m, scene, cam)
        images.append(result.images.detach())
        loss.backward()
        m.accumulate_stats(result)
        m.optimizer_step()
        m.zero_grad()
        stepped.append(copy.deepcopy(m.state_dict()))
        with torch.no_grad():
            reports.append(m.densify(ctx))
    assert torch.equal(images[0], images[1]), (
        f"a loaded adapter must render exactly like the saved one (they differ by up to "
        f"{float((images[0] - images[1]).abs().max()):.3g})")
    differs = _state_difference(stepped[0], stepped[1], "the saved adapter's", "the loaded adapter's")
    assert differs is None, (
        f"after one more step (render, backward, statistics, optimizer step) of both, {differs}: state_dict() "
        "must carry everything the step reads (e.g. the optimizer's moments and step counts of every group)")
    _check_densified_alike(a, b, *reports, "after one more step, a densify of the loaded adapter", None,
                           "state_dict() must carry everything densify reads")


def _attribute_tensors(adapter: Adapter):
    """(path, tensor) for the tensors that do not require grad among the adapter's attributes and
    the dicts, lists and tuples they hold (stats['denom'], max_radii): where adapters keep their
    statistics."""
    for attr, value in (vars(adapter).items() if hasattr(adapter, "__dict__") else ()):
        yield from ((path, t) for path, t in _tensors(value, attr) if not t.requires_grad)


def _holds(state, value: torch.Tensor) -> bool:
    """Whether some tensor in the nested state has value's shape and values (NaN equal to NaN;
    a state tensor of another dtype compares after a cast to value's)."""
    return any(tuple(t.shape) == tuple(value.shape) and _same(t.detach().to(value.dtype), value)
               for _, t in _tensors(state))


def _check_densified_alike(a: Adapter, b: Adapter, ra, rb, when: str, loaded_differs: Optional[str],
                           counts_reason: str) -> None:
    """AssertionError unless the saved adapter `a` and the loaded `b` densified alike (reports ra,
    rb): the same counts, then the same positions(), then equal state_dicts; the message says
    which of them differs and why it may (loaded_differs: how b's state_dict differed from the
    saved one right after loading, None when it did not)."""
    if loaded_differs is not None:
        why = f"right after loading, {loaded_differs}"
    else:
        why = ("the two adapters held equal state_dicts and densified from the same global torch RNG state, so densify "
               "reads something state_dict() does not carry (a random generator of the adapter's own, say: save its "
               "state)")
    went = f"{when} went {rb.before} -> {rb.after}"
    if (ra.before, ra.after) != (rb.before, rb.after):
        raise AssertionError(f"{went} where the saved adapter went {ra.before} -> {ra.after}: {counts_reason}; {why}")
    pa, pb = a.positions().detach(), b.positions().detach()
    if pa.shape != pb.shape:
        raise AssertionError(f"{went} as the saved adapter did, but its positions() are {list(pb.shape)} where the "
                             f"saved adapter's are {list(pa.shape)}")
    if not torch.equal(pa, pb):
        raise AssertionError(f"{went} as the saved adapter did, but put its primitives elsewhere (positions() differ "
                             f"by up to {float((pa - pb).abs().max()):.3g}): {why}")
    differs = _state_difference(a.state_dict(), b.state_dict(), "the saved adapter's", "the loaded adapter's")
    if differs is not None:
        raise AssertionError(f"{went} as the saved adapter did, to the same positions, but then {differs}: {why}")


def check_hard_cameras(make_adapter: MakeAdapter, scene: Scene) -> None:
    """No NaN/Inf in images or gradients for cameras inside the model, far away, looking away,
    tiny and non-square."""
    base = scene.train_cameras[0]
    K = base.K.clone()
    hard = [
        ("inside the model", Camera(900, "inside", K, look_at((0.05, 0.02, 0.01), (1.0, 0.0, 0.0)), base.width,
                                    base.height, base.time)),
        ("far away", Camera(901, "far", K, look_at((300.0, 0.0, 0.0)), base.width, base.height, base.time)),
        ("looking away", Camera(902, "away", K, look_at((3.0, 0.0, 0.0), (6.0, 0.0, 0.0)), base.width, base.height,
                                base.time)),
        ("1x1 px", base.scaled(base.width)),
        ("40x6 px", Camera(903, "wide", [[10.0, 0, 20], [0, 10.0, 3], [0, 0, 1]], base.world_to_camera, 40, 6,
                           base.time)),
    ]
    adapter = make_adapter(scene)
    adapter.set_step(100_000)
    for label, cam in hard:
        out = adapter.render([cam], torch.rand(1, 3))
        assert torch.isfinite(out.images).all(), f"non-finite pixels for the {label} camera ({cam.name!r})"
        (out.images.sum() + (0 if out.alphas is None else out.alphas.sum())).backward()
        for name, g in adapter.named_gradients().items():
            assert g is None or torch.isfinite(g).all(), \
                f"non-finite gradient in {name!r} for the {label} camera ({cam.name!r})"
        adapter.zero_grad()


def check_distributed_support(make_adapter: MakeAdapter, scene: Scene, rtol: float = 1e-5) -> None:
    """For adapters with the optional DistributedAdapter methods (distributed training):
    gradient_parameters() holds the tensors whose .grad named_gradients() reports; the statistics
    of two adapters that rendered disjoint views, combined as statistics() declares ("sum" or
    "max"), equal those of one adapter that rendered all of them; load_statistics() restores
    them."""
    cams = scene.train_cameras[:3]
    whole, first, rest = (_with_stats(make_adapter, scene, views) for views in (cams, cams[:1], cams[1:]))
    params, grads = whole.gradient_parameters(), whole.named_gradients()
    assert set(params) == set(grads), \
        f"gradient_parameters() names {sorted(params)} but named_gradients() names {sorted(grads)}"
    for name, p in params.items():
        assert p.grad is grads[name], f"gradient_parameters()[{name!r}].grad is not named_gradients()[{name!r}]"
    stats = whole.statistics()
    assert stats, "statistics() must name at least one statistic"
    a, b = first.statistics(), rest.statistics()
    combined_stats = {}
    for name, (t, op) in stats.items():
        assert op in ("sum", "max"), f"statistic {name!r} combines by {op!r}; expected 'sum' or 'max'"
        assert name in a and name in b, f"statistic {name!r} is missing from another adapter's statistics()"
        combined = a[name][0] + b[name][0] if op == "sum" else torch.maximum(a[name][0], b[name][0])
        combined_stats[name] = combined
        scale = float(t.abs().max()) if t.numel() else 0.0
        err = float((combined - t).abs().max()) / max(scale, 1e-30) if t.numel() else 0.0
        assert err <= rtol, (f"statistic {name!r}: the {op} over two adapters that rendered disjoint views "
                             f"differs from one adapter that rendered all by {err:.3g} (relative)")
    fresh = make_adapter(scene)
    fresh.load_statistics({name: t.clone() for name, (t, _) in stats.items()})
    for name, (t, _) in fresh.statistics().items():
        assert torch.equal(t, stats[name][0]), f"load_statistics() did not restore {name!r}"
    # One step as two ranks take it (mvgs_plugin.distributed): the .grad of every tensor
    # gradient_parameters() names summed over the ranks, the statistics combined, then each rank
    # steps. It must leave the state one adapter that rendered every view reaches; a trainable
    # group gradient_parameters() leaves out keeps one rank's gradient, so its update and its
    # optimizer moments differ.
    ranks = (first, rest)
    for name in params:
        grads_r = [r.gradient_parameters()[name].grad for r in ranks]
        present = [g for g in grads_r if g is not None]
        if present:
            total = torch.stack(present).sum(dim=0)
            for r in ranks:
                r.gradient_parameters()[name].grad = total.clone()
    first.load_statistics(combined_stats)
    for adapter in (whole, first):
        adapter.optimizer_step()
    want, got = dict(_tensors(whole.state_dict())), dict(_tensors(first.state_dict()))
    assert set(want) == set(got), f"state_dict() holds other tensors after the step: {sorted(set(want) ^ set(got))}"
    for key, t in want.items():
        u = got[key]
        if not t.is_floating_point():
            assert torch.equal(t, u), f"state_dict(){key} differs after a step taken as two ranks take it"
            continue
        scale = max(float(t.abs().max()) if t.numel() else 0.0, 1e-12)
        err = float((t - u).abs().max()) / scale if t.numel() else 0.0
        assert tuple(t.shape) == tuple(u.shape) and err <= 1e-3, (
            f"after one step taken as two ranks take it (the gradients of gradient_parameters() summed), "
            f"state_dict(){key} differs from one adapter that rendered every view by {err:.3g} (relative): "
            f"gradient_parameters() must name every trainable tensor (it names {sorted(params)})")


def _leaves(obj, key: str = ""):
    """(path, value) for every value in a nested dict / list / tuple (a state_dict): tensors and
    everything else that is not a non-empty container (an empty one is a value of its own)."""
    if isinstance(obj, dict) and obj:
        for k, v in obj.items():
            yield from _leaves(v, f"{key}[{k!r}]")
    elif isinstance(obj, (list, tuple)) and obj:
        for i, v in enumerate(obj):
            yield from _leaves(v, f"{key}[{i}]")
    else:
        yield key, obj


def _tensors(obj, key: str = ""):
    """(path, tensor) for every tensor in a nested dict / list / tuple (a state_dict)."""
    for path, value in _leaves(obj, key):
        if isinstance(value, torch.Tensor):
            yield path, value


_PLAIN = (bool, int, float, complex, str, bytes, type(None))


def _equal_entries(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Elementwise x == y of two tensors of one shape and dtype, on the CPU, NaN equal to NaN."""
    x, y = x.detach().cpu(), y.detach().cpu()
    same = x == y
    if x.is_floating_point() or x.is_complex():
        same |= x.isnan() & y.isnan()
    return same


def _same(x: torch.Tensor, y: torch.Tensor) -> bool:
    """Same dtype, shape and values (NaN equal to NaN)."""
    return x.dtype == y.dtype and x.shape == y.shape and bool(_equal_entries(x, y).all())


def _short(value) -> str:
    """A value as a message names it: a tensor by dtype and shape, a plain value by repr."""
    if isinstance(value, torch.Tensor):
        return f"a {str(value.dtype).replace('torch.', '')} tensor {list(value.shape)}"
    text = repr(value) if isinstance(value, _PLAIN + (dict, list, tuple)) else f"a {type(value).__name__}"
    return text if len(text) <= 60 else text[:57] + "..."


def _state_difference(want, got, want_label: str, got_label: str) -> Optional[str]:
    """None when two state_dicts hold the same entries (the same paths; tensors of the same shape,
    dtype and values, NaN equal to NaN; numbers, strings and None equal; other objects of the
    same type), else a phrase naming the first entry, in want's order, that differs."""
    w, g = dict(_leaves(want)), dict(_leaves(got))
    for key in list(w) + [k for k in g if k not in w]:
        if key not in g:
            return f"entry {key} ({_short(w[key])}) is in {want_label} but not in {got_label}"
        if key not in w:
            return f"entry {key} ({_short(g[key])}) is in {got_label} but not in {want_label}"
        x, y = w[key], g[key]
        if isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor):
            if x.dtype != y.dtype or x.shape != y.shape:
                return f"entry {key} is {_short(x)} in {want_label} but {_short(y)} in {got_label}"
            same = _equal_entries(x, y)
            if not bool(same.all()):
                gap = (x.detach().cpu() - y.detach().cpu())[~same].abs().max() if x.is_floating_point() else None
                by = "" if gap is None else f", by up to {float(gap):.3g}"
                return (f"entry {key} differs between {want_label} and {got_label} (in {int((~same).sum())} of "
                        f"{x.numel()} values{by})")
        elif isinstance(x, _PLAIN) and isinstance(y, _PLAIN):
            nan = isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)
            if not (nan or x == y):
                return f"entry {key} is {_short(x)} in {want_label} but {_short(y)} in {got_label}"
        elif type(x) is not type(y):
            return f"entry {key} is {_short(x)} in {want_label} but {_short(y)} in {got_label}"
    return None


CHECKS = [
    check_protocol_methods,
    check_make_adapter_is_deterministic,
    check_render,
    check_background,
    check_gradients_reach_every_group,
    check_optimizer_descends,
    check_summed_equals_accumulated,
    check_stats_and_densify,
    check_densify_keeps_optimizer_state,
    check_the_cap_holds,
    check_state_dict_round_trip,
    check_hard_cameras,
]


def check_adapter(make_adapter: MakeAdapter, scene: Optional[Scene] = None) -> Dict[str, str]:
    """Runs every conformance check; raises AssertionError naming the first that fails (an
    error the adapter raised inside a check is reported the same way, with its type).
    Returns {check name: "ok"}. scene: synthetic_scene() when None, whose cameras have no
    time; a time-dependent model (4DGS) needs synthetic_scene(time=True)."""
    if not callable(make_adapter) or isinstance(make_adapter, Adapter):
        raise TypeError(f"check_adapter takes make_adapter, a function scene -> a fresh adapter, got "
                        f"{type(make_adapter).__name__} (e.g. check_adapter(lambda scene: MyAdapter.from_scene(scene)))")
    scene = synthetic_scene() if scene is None else scene
    checks = list(CHECKS)
    if isinstance(make_adapter(scene), DistributedAdapter):  # optional: only adapters that support it
        checks.append(check_distributed_support)
    done = {}
    for check in checks:
        try:
            check(make_adapter, scene)
        except AssertionError as exc:
            raise AssertionError(f"{check.__name__}: {exc}") from exc
        except Exception as exc:
            hint = ""
            if "time" in str(exc) and all(c.time is None for c in scene.train_cameras):
                hint = (" (the scene's cameras have no time; for a time-dependent model pass one that has: "
                        "check_adapter(make_adapter, synthetic_scene(time=True)))")
            raise AssertionError(f"{check.__name__}: the adapter raised {type(exc).__name__}: {exc}{hint}") from exc
        done[check.__name__] = "ok"
    return done
