"""Where to put random initial points when a scene has none: where the cameras look.

The original 3DGS draws them uniformly in a cube about the mean camera centre, with half-size
the camera extent. That works for rigs that surround the scene (an orbit, a hemisphere, a
turntable): the cube holds what every camera sees. For a forward-facing rig (LLFF-like: cameras
on a small patch, all looking one way) that cube sits around the cameras, not the scene, and a
run from it trains to nothing (12 dB where points give 34 dB).

:func:`init_region` tells them apart by how much the optical axes spread and where they point:

* ``cube``: the axes spread (the smallest eigenvalue of mean(I - d dᵀ) over the unit viewing
  directions d is at least ``CONVERGING_SPREAD``: a full orbit gives about 0.65) and look in
  at one place (:func:`look_convergence` at least ``CONVERGING_COSINE``); when they share a
  direction (a hemisphere), that place (:func:`axes_meeting_point`) must lie inside the cube:
  the 3DGS cube, unchanged.
* ``frusta``: nearly parallel axes (a forward-facing rig gives about 0.01), or axes that spread
  and share a direction but meet outside the cube or nowhere in front (cameras over a ground
  tilted every way, a fan of views), where the cube about the cameras holds the air they stand
  in (an aerial town: 15.6 dB from it, 19.0 from the frusta, docs/data.md): points in the union
  of the training views' frusta, uniform in disparity (1/depth) between ``near`` and ``far``,
  as NeRF samples LLFF scenes. ``near`` is the first depth along the mean viewing axis that at
  least half of the cameras see (nearer content is in too few views to be reconstructed);
  ``far`` = ``FAR_OVER_NEAR`` x near. :func:`random_init_points` then draws 20 candidates per
  point there and keeps the most photo-consistent ones (:func:`photo_consistent`: the colour a
  candidate lands on agrees across the views that see it) with their mean colour: the
  images carry the depth that the rig's geometry cannot.
* ``cube+frusta`` for a rig whose axes spread every way but do not meet (no shared direction,
  :func:`look_convergence` below ``CONVERGING_COSINE``): a room shot from its middle, where the
  cube sits among the cameras and the content stands around them, but also a walk through a
  scene or two orbits about two objects, where the content lies among the cameras. The rig
  cannot tell these apart, so half of the candidates come from the cube and half from the
  training frusta (``near`` = the radius of the camera centres, ``far`` = ``FAR_OVER_NEAR`` x
  near), and photo-consistency keeps the ones the views agree on.
* a rig with nearly parallel axes but one camera centre, or no depth that half of the cameras
  see, falls back to the cube and says so (as does a rig that looks every way from one centre).

The choice and its numbers are in :attr:`InitRegion.description` (the adapters log it).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import torch

from ..camera import Camera
from ..densify.mvad import camera_axes

__all__ = ["InitRegion", "init_region", "random_init_points", "photo_consistent", "axis_spread",
           "is_forward_facing", "look_convergence", "axes_meeting_point", "background_shell", "is_shell_radius", "view_colours", "CONVERGING_SPREAD",
           "CONVERGING_COSINE", "FAR_OVER_NEAR", "SHELL_RADIUS", "backdrop_of", "silhouettes_of", "on_silhouettes",
           "hull_candidates", "ray_sweep", "sweep_rays", "sweep_span", "pose_distance", "SWEEP_DEPTHS"]

# Smallest eigenvalue of mean(I - d d^T) at and above which the rig counts as surrounding the
# scene: about sin^2 of the axes' angular spread (0.05 ~ axes within +-13 degrees of each
# other are "parallel"; a full orbit gives ~0.65, the bundled forward rig ~0.01).
CONVERGING_SPREAD = 0.05
# far / near of the frusta region. LLFF captures bound their content by near/far ratios of
# about 5 to 20; disparity-uniform sampling puts half of the points within 2 x near.
FAR_OVER_NEAR = 20.0
# the depth search along the mean axis: geometric steps from 1e-3 to 1e4 rig radii
_DEPTH_STEPS = 141
# frusta init: candidates drawn per kept point, the image width they are scored at, and the
# fewest views a candidate must be seen in to be scored
CANDIDATES_PER_POINT = 20
PHOTO_WIDTH = 64
MIN_VIEWS = 3
# background shell: its radius in rig radii (the largest distance of a training camera centre from
# the rig's centre). Twice the rig puts every shell point behind the cameras that stand near it
# and, with ~2000 points on the sphere, spaces them about 0.16 rig radii apart, small enough for
# the 3DGS size rule (0.1 x extent = 0.11 rig radii after the first split) to leave their children.
SHELL_RADIUS = 2.0
# look_convergence at and above which a rig with spread axes looks in at one place (an orbit, a
# hemisphere, rings: 1.00 on every generated 360-degree rig); below it the axes do not meet (0.10
# on the generator's room, whose cameras look out every way from its middle)
CONVERGING_COSINE = 0.5
# random init of an object on a backdrop (its training images' borders one colour): candidates
# are drawn inside the visual hull of the views' silhouettes, found first on a grid of HULL_GRID
# cells a side over the cube; a point is in the hull when at least HULL_FRAMED of the views frame
# it and at least HULL_SHARE of those show content where it projects (a few may show a patch of
# the backdrop's colour on the object itself)
HULL_GRID = 64
# random init in the cube of a rig round a still scene (ray_sweep): candidates per pixel ray (48
# keep the slices about as long as 32 were over the cube, before the search took the ball round it
# below; 32 and 48 trained within 0.2 dB of each other on three scenes), and the nearest one's
# distance from its camera in half sizes of the cube
SWEEP_DEPTHS = 48
SWEEP_NEAR = 0.02
# ... searched inside the ball about the cube's centre that holds the cube whichever way it is
# turned (radius sqrt(3) half sizes): a world frame's axes are arbitrary (COLMAP's are wherever its
# reconstruction started), and the axis-aligned cube's reach along a ray would change with them
# (plain 3DGS from --init random on the generated arc, 1000 steps: 27.51 dB, turned 45 degrees
# about the vertical 26.14, about an oblique axis 26.97; with the ball 29.16, 29.02, 28.90)
SWEEP_BALL = math.sqrt(3.0)
# ... and the views a candidate is scored in: the ray's camera's nearest (pose_distance), as a
# multi-view stereo method picks its source views; the far side of an orbit sees other surfaces
SWEEP_NEIGHBOURS = 12
HULL_FRAMED = 0.5
HULL_SHARE = 0.9


@dataclasses.dataclass(frozen=True)
class InitRegion:
    """A region to draw random initial points from.

    kind "cube": uniform in center ± half. kind "frusta": a training camera at random, a pixel
    uniform in its image, a depth uniform in disparity between near and far. kind
    "cube+frusta": half of the points from each (for photo-consistency to choose between).
    """

    kind: str
    description: str
    center: Optional[torch.Tensor] = None
    half: float = 0.0
    near: float = 0.0
    far: float = 0.0
    cameras: tuple = ()

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, 3] float64 points, drawn with ``generator`` (kind "cube+frusta": the first n // 2
        from the cube, the rest from the frusta)."""
        if self.kind == "cube+frusta":
            cube = dataclasses.replace(self, kind="cube").sample(n // 2, generator)
            return torch.cat([cube, dataclasses.replace(self, kind="frusta").sample(n - n // 2, generator)])
        if self.kind == "cube":
            u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
            return torch.as_tensor(self.center, dtype=torch.float64) + (2.0 * u - 1.0) * self.half
        pick = torch.randint(len(self.cameras), (n,), generator=generator)
        uv = torch.rand(n, 2, generator=generator, dtype=torch.float64)
        disparity = 1.0 / self.far + torch.rand(n, generator=generator, dtype=torch.float64) * (
            1.0 / self.near - 1.0 / self.far)
        out = torch.empty(n, 3, dtype=torch.float64)
        for i, cam in enumerate(self.cameras):
            rows = (pick == i).nonzero().flatten()
            if rows.numel() == 0:
                continue
            pixels = uv[rows] * torch.tensor([cam.width, cam.height], dtype=torch.float64)
            origin, direction = cam.rays(pixels)
            # a unit ray at depth z (camera-space) is z / cos of its angle to the optical axis away
            axis = cam.camera_to_world[:3, 2] / torch.linalg.norm(cam.camera_to_world[:3, 2])
            cos = (direction @ axis).clamp_min(1e-6)
            out[rows] = origin + direction * (1.0 / disparity[rows] / cos)[:, None]
        return out


def _photo_level(cam: Camera, max_width: int) -> int:
    """The pyramid factor that brings ``cam``'s image to at most ``max_width`` pixels across."""
    return max(1, -(-cam.width // max_width))


def _lookups(points: torch.Tensor, cameras: Sequence[Camera], image, max_width: int, mask=None, coverage=None):
    """Per camera, what the points [P, 3] land on in its image downsampled to at most ``max_width``
    pixels across (``image(camera, factor)``): (the colour of the pixel each projects into [P, 3]
    float32, clamped to the frame; whether it lies in front of the camera and inside the frame [P];
    whether ``mask(camera, factor)`` keeps that pixel, weight 1/2 or more, [P], all True without
    a mask; the content's coverage of that pixel [P] from ``coverage(camera, factor)``
    (:meth:`~mvgs_plugin.data.Scene.coverage`), None when it is not given or gives None)."""
    # float32 is plenty for a pixel lookup at <= 64 px
    pts = points.to(torch.float32)
    for cam in cameras:
        factor = _photo_level(cam, max_width)
        small = cam.scaled(factor)
        img = image(cam, factor).to(torch.float32).reshape(-1, 3)
        w2c = small.world_to_camera.to(torch.float32)
        cam_xyz = pts @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam_xyz[:, 2]
        zs = z.clamp_min(1e-12)
        px = small.fx * cam_xyz[:, 0] / zs + small.cx
        py = small.fy * cam_xyz[:, 1] / zs + small.cy
        inside = (z > 0) & (px >= 0) & (px < small.width) & (py >= 0) & (py < small.height)
        at = py.clamp(0, small.height - 1).to(torch.int64) * small.width + px.clamp(0, small.width - 1).to(torch.int64)
        weights = None if mask is None else mask(cam, factor)
        kept = torch.ones_like(inside) if weights is None else weights.reshape(-1)[at] >= 0.5
        alpha = None if coverage is None else coverage(cam, factor)
        yield img[at], inside, kept, (None if alpha is None else alpha.reshape(-1)[at])


def view_colours(points: torch.Tensor, cameras: Sequence[Camera], image,
                 max_width: int = PHOTO_WIDTH, mask=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What each point [P, 3] lands on in the training views: every point is projected into every
    camera (its image downsampled to at most ``max_width`` pixels across by ``image(camera,
    factor)``). Returns (mean colour [P, 3] float64 over the views that see the point, the variance
    of those colours [P] (summed over the channels), how many views see it [P]); a point no view
    sees has mean and variance 0. ``mask``: optionally ``mask(camera, factor)``, the view's pixel
    weights [H', W', 1] or None (:meth:`~mvgs_plugin.data.Scene.mask`): a point that lands on a
    pixel the mask ignores (weight below 1/2 at that level) counts as not seen by that view."""
    p = points.shape[0]
    total = torch.zeros(p, 3, dtype=torch.float64)
    squares = torch.zeros(p, dtype=torch.float64)
    count = torch.zeros(p, dtype=torch.float64)
    for colour, inside, kept, _ in _lookups(points, cameras, image, max_width, mask):
        inside &= kept  # an ignored pixel says nothing of what the point is
        colour = (colour * inside[:, None]).to(torch.float64)
        total += colour
        squares += (colour * colour).sum(1)
        count += inside.to(torch.float64)
    mean = total / count.clamp_min(1)[:, None]
    variance = squares / count.clamp_min(1) - (mean * mean).sum(1)
    return mean, variance, count


def photo_consistent(candidates: torch.Tensor, cameras: Sequence[Camera], image, n: int,
                     max_width: int = PHOTO_WIDTH, mask=None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The n candidates whose colour agrees best across the training views, and that colour.

    The score of a candidate [P, 3] is the variance of the colours it lands on over the views that
    see it (:func:`view_colours`; a crude plane sweep: a point on a surface sees one colour from
    everywhere, a point in free space sees several). Candidates seen by fewer than ``MIN_VIEWS``
    views rank last. Returns (xyz [n, 3] float64, rgb [n, 3] in [0, 1] the mean colour, how many
    of the n are seen by at least MIN_VIEWS views). ``mask``: as :func:`view_colours`'.
    """
    mean, variance, count = view_colours(candidates, cameras, image, max_width, mask)
    keep = _photo_rank(variance, count)[:n]
    return candidates[keep], mean[keep].clamp(0.0, 1.0), int((count[keep] >= MIN_VIEWS).sum())


def _photo_rank(variance: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """Indices from the most to the least photo-consistent (lowest colour variance first; points
    seen by fewer than MIN_VIEWS views last)."""
    return torch.argsort(torch.where(count >= MIN_VIEWS, variance, torch.full_like(variance, math.inf)))


def backdrop_of(scene) -> Optional[tuple[float, float, float]]:
    """The colour the scene's training images show around their content, when there is one: the
    scene's background (what its RGBA images are composited on, or what its borders were found to
    show, or a colour given) when the borders of every training view show it and nothing else
    (:func:`~mvgs_plugin.data.images.uniform_border`); None for a scene of photographs, or one
    without a background colour or training cameras."""
    background, cameras = getattr(scene, "background", None), getattr(scene, "train_cameras", None)
    if background is None or not cameras or not _borders_show(cameras, scene.image, background,
                                                               getattr(scene, "mask", None)):
        return None
    return tuple(float(v) for v in background)


def silhouettes_of(scene) -> Optional[tuple[float, float, float]]:
    """The backdrop to carve ``scene``'s initial points to its silhouettes by (:func:`backdrop_of`),
    or None: also None for a moving scene (training views at more than one time), whose
    silhouettes at different times do not bound one shape (the hull of a moving arm across its
    frames is the part that never moves)."""
    cameras = getattr(scene, "train_cameras", None) or ()
    if len({c.time for c in cameras}) > 1:
        return None
    return backdrop_of(scene)


def on_silhouettes(points: torch.Tensor, cameras: Sequence[Camera], image, backdrop: Sequence[float],
                   max_width: int = PHOTO_WIDTH, mask=None, coverage=None) -> torch.Tensor:
    """[P] bool: the points [P, 3] inside the visual hull of the training views' silhouettes,
    the content of views that show it on a one-colour ``backdrop``. A point is in when at least
    HULL_FRAMED of the views have it in their frame (a backdrop at the borders says the content
    lies inside nearly every frame; a point near the cameras, in front of the object in the few
    views that frame it, is not) and at least HULL_SHARE of those show content where it projects
    (a pixel off the backdrop by more than ``BORDER_TOLERANCE`` in some channel, in the image read
    as :func:`view_colours` reads it, whose smoothing widens a silhouette by about a pixel). A
    view that does not frame the point does not vote on its content, so a part of the object that
    leaves some frames is kept; the share, not every view, so that a patch of the object in the
    backdrop's colour seen in a few views does not cut a hole through it. ``mask``: as
    :func:`view_colours`' (a view that ignores the pixel does not vote at all). ``coverage``:
    optionally ``coverage(camera, factor)``, the view's alpha [H', W', 1] or None
    (:meth:`~mvgs_plugin.data.Scene.coverage`): a view that has one shows content where its
    coverage is above ``BORDER_TOLERANCE``, whatever the colour there (a part in the backdrop's
    colour is content too); the others are read by colour."""
    from .images import BORDER_TOLERANCE

    colour = torch.tensor([float(v) for v in backdrop], dtype=torch.float32)
    votes = torch.zeros(points.shape[0], dtype=torch.int64)  # views that do not ignore the pixel
    seen = torch.zeros(points.shape[0], dtype=torch.int64)  # ... and frame the point
    content = torch.zeros(points.shape[0], dtype=torch.int64)  # ... and show content there
    for shown, inside, kept, alpha in _lookups(points, cameras, image, max_width, mask, coverage):
        votes += kept
        seen += kept & inside
        shows = (shown - colour).abs().amax(dim=1) > BORDER_TOLERANCE if alpha is None else alpha > BORDER_TOLERANCE
        content += kept & inside & shows
    return (seen >= MIN_VIEWS) & (seen >= HULL_FRAMED * votes) & (content >= HULL_SHARE * seen)


def hull_candidates(region: "InitRegion", cameras: Sequence[Camera], image, backdrop: Sequence[float], count: int,
                    generator: torch.Generator, mask=None, coverage=None) -> tuple[torch.Tensor, str]:
    """Up to ``count`` points drawn uniformly in the part of the cube ``region`` inside the
    silhouettes' visual hull (:func:`on_silhouettes`): the cube cut into HULL_GRID cells a side,
    the cells whose centre is in the hull and their neighbours kept (a part thinner than a cell
    keeps the cell it passes through), ``count`` points drawn in them, and those in the hull
    kept. ``mask``, ``coverage``: as :func:`on_silhouettes`'. Returns (points [k, 3] float64,
    what was done)."""
    center = torch.as_tensor(region.center, dtype=torch.float64)
    g, half = HULL_GRID, float(region.half)
    step = 2.0 * half / g
    axis = (torch.arange(g, dtype=torch.float64) + 0.5) * step - half  # cell centres about the cube's centre
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3) + center
    inside = on_silhouettes(grid, cameras, image, backdrop, mask=mask, coverage=coverage).reshape(1, 1, g, g, g).float()
    cells = torch.nn.functional.max_pool3d(inside, 3, stride=1, padding=1).reshape(-1) > 0
    corners = grid[cells] - 0.5 * step
    if corners.shape[0] == 0:
        return torch.zeros(0, 3, dtype=torch.float64), f"no cell of a {g}^3 grid over the cube is inside the silhouettes"
    pick = torch.randint(corners.shape[0], (count,), generator=generator)
    points = corners[pick] + step * torch.rand(count, 3, generator=generator, dtype=torch.float64)
    points = points[on_silhouettes(points, cameras, image, backdrop, mask=mask, coverage=coverage)]
    return points, (f"carved to the training views' silhouettes{_silhouettes_read(cameras, coverage)} "
                    f"on the backdrop {_rounded(backdrop)} "
                    f"({int(inside.sum())} of {g ** 3} cells of a {g}^3 grid over the cube inside them, "
                    f"{points.shape[0]} of {count} candidates drawn near those inside)")


def _silhouettes_read(cameras: Sequence[Camera], coverage) -> str:
    """How many views' silhouettes come from their alpha (for the log), or ""."""
    if coverage is None:
        return ""
    by_alpha = sum(coverage(cam, _photo_level(cam, PHOTO_WIDTH)) is not None for cam in cameras)
    if not by_alpha:
        return ""
    return (" (read from their alpha)" if by_alpha == len(cameras) else
            f" (read from the alpha of {by_alpha} of {len(cameras)} views, the others' by colour)")


def random_init_points(scene, n: int, generator: torch.Generator,
                       half_size: Optional[float] = None) -> tuple[torch.Tensor, torch.Tensor, str]:
    """n initial points (xyz, rgb [n, 3] float64) for a scene without a point cloud, and what
    was done (for the log). Cube, round a still scene: one point per pixel ray of the training
    views, at the depth the other views agree on (:func:`ray_sweep`); with a ``half_size``, or
    views at several times (a moving scene): uniform in the cube, colours uniform in [0, 1] (the
    original 3DGS). Frusta: CANDIDATES_PER_POINT x n candidates in the region, the n most photo-consistent
    kept with their mean colour (photo_consistent). ``half_size`` (or a scene-like object
    without training cameras) asks for the cube about scene.center instead of init_region."""
    cameras = getattr(scene, "train_cameras", None)
    if half_size is not None or not cameras:
        half = float(scene.extent) if half_size is None else float(half_size)
        region = _cube(scene.center, half, "no cameras: scene.extent" if half_size is None else "a given half size")
    else:
        region = init_region(cameras, scene.center, float(scene.extent))
    backdrop = silhouettes_of(scene) if region.kind == "cube" and half_size is None and cameras else None
    if backdrop is not None:  # an object on a backdrop: where the silhouettes say it is
        candidates, carved = hull_candidates(region, cameras, scene.image, backdrop, CANDIDATES_PER_POINT * n,
                                             generator, mask=getattr(scene, "mask", None),
                                             coverage=getattr(scene, "coverage", None))
        if candidates.shape[0] >= n:
            # the first n: uniform in the hull, as 3DGS's are in its cube. Not the most photo-consistent:
            # inside an object of one colour every point is, and they would all go there (on the
            # generator's object scene 78 % in the red ball, none in the textured box)
            xyz = candidates[:n]
            rgb = view_colours(xyz, cameras, scene.image, mask=getattr(scene, "mask", None))[0].clamp(0.0, 1.0)
            return xyz, rgb, (f"{region.description}; {carved}; the first {n} kept, coloured by the views")
        region = dataclasses.replace(region, description=f"{region.description} (the silhouettes left {candidates.shape[0]} "
                                                         f"candidates, fewer than {n}: {carved}; not carved)")
    if region.kind == "cube":
        if half_size is None and cameras and len({c.time for c in cameras}) == 1:
            xyz, rgb, swept = ray_sweep(region, cameras, scene.image, n, generator, mask=getattr(scene, "mask", None))
            return xyz, rgb, f"{region.description}; {swept}"
        xyz = region.sample(n, generator)
        why = "" if half_size is not None or not cameras else " (views at several times: no colour to sweep by)"
        return xyz, torch.rand(n, 3, generator=generator, dtype=torch.float64), region.description + why
    candidates = region.sample(CANDIDATES_PER_POINT * n, generator)
    xyz, rgb, seen = photo_consistent(candidates, scene.train_cameras, scene.image, n, mask=getattr(scene, "mask", None))
    return xyz, rgb, (f"{region.description}; kept the {n} of {candidates.shape[0]} candidates whose colour agrees "
                      f"best across the views ({seen} seen by >= {MIN_VIEWS} views)")


def sweep_span(origins: torch.Tensor, directions: torch.Tensor, region: InitRegion) -> tuple[torch.Tensor, torch.Tensor]:
    """The part of rays [R, 3] (unit directions) a sweep searches about the cube ``region``: inside
    the ball of radius SWEEP_BALL x its half size about its centre (which holds the cube however
    the world's axes are turned), from where each ray enters it, but no nearer than SWEEP_NEAR x
    the half size, to where it leaves; a ray that misses the ball gets twice the half size past
    that start. (near, far) [R]."""
    center, half = torch.as_tensor(region.center, dtype=torch.float64), float(region.half)
    offset = origins - center
    b = (offset * directions).sum(1)
    disc = b * b - ((offset * offset).sum(1) - (SWEEP_BALL * half) ** 2)
    root = disc.clamp_min(0.0).sqrt()
    near = (-b - root).clamp_min(SWEEP_NEAR * half)
    t_out = -b + root
    return near, torch.where((disc > 0) & (t_out > near), t_out, near + 2.0 * half)


def pose_distance(cameras: Sequence[Camera]) -> torch.Tensor:
    """[V, V] how far apart two views are: centre distance over the rig's median spacing plus
    the angle between their optical axes (radians): near views first, whichever way the rig is
    laid out (an orbit, a grid, a walk)."""
    centres = torch.stack([c.center for c in cameras]).to(torch.float64)
    axes = camera_axes(cameras).to(torch.float64)
    axes = axes / torch.linalg.norm(axes, dim=1, keepdim=True)
    d = torch.cdist(centres, centres)
    off = d[~torch.eye(len(cameras), dtype=torch.bool)]
    scale = float(off.median()) if off.numel() and float(off.median()) > 0 else 1.0
    angle = torch.arccos((axes @ axes.T).clamp(-1.0, 1.0))
    return d / scale + angle


def ray_sweep(region: InitRegion, cameras: Sequence[Camera], image, n: int, generator: torch.Generator,
              max_width: int = PHOTO_WIDTH, mask=None, depths: int = SWEEP_DEPTHS,
              neighbours: int = SWEEP_NEIGHBOURS) -> tuple[torch.Tensor, torch.Tensor, str]:
    """n initial points about the cube ``region``, one on each of n pixel rays of the training
    views, at the depth its neighbouring views agree on (a plane sweep with one winner per ray).

    A ray: a training camera and a pixel, both uniform. Along it, ``depths`` candidates, one in
    each of as many equal slices of the part :func:`sweep_span` gives (from SWEEP_NEAR x half off
    the camera to where it leaves the ball round the cube, which does not turn with the world's
    axes). A candidate is scored by the colours it lands on in the ``neighbours`` views
    nearest the ray's camera (:func:`pose_distance`; :func:`view_colours`' lookups at
    ``max_width``): the squared difference from the ray's own pixel in each of them that sees it,
    of which the smaller half (at least two) are averaged, so the views that see the candidate's
    place hidden behind something else do not count against it; seen by fewer than MIN_VIEWS - 1
    of them: not scored. The best-scored candidate of each ray is kept, coloured by its pixel and
    the views of that smaller half; a ray none of whose candidates can be scored keeps one at
    random (3DGS's cube along that ray) with its pixel's colour (a ray through a pixel a mask
    ignores is not scored, and its point takes the mean colour of the views that see it, grey
    when none does).

    Why one per ray and not the n best of all candidates (the frusta rule): a candidate in free
    space in front of the sky, or anywhere over a plain wall, is as consistent as one on a
    textured surface, and a global ranking gathers the points there (on three of the generator's
    360-degree scenes, four times as many rays with the best quarter of their winners kept put
    2-17 % of the points within 5 % of the extent of the scene's own surface points, one per ray
    41-61 %). Rays spread the points over what the images show; the sweep places each along its
    ray. ``mask``: as :func:`view_colours`' (a view that ignores the pixel does not see the
    candidate). Returns (xyz [n, 3] float64, rgb [n, 3] in [0, 1], what was done)."""
    pick = torch.randint(len(cameras), (n,), generator=generator)
    uv = torch.rand(n, 2, generator=generator, dtype=torch.float64)
    pixels = torch.empty(n, 2, dtype=torch.float64)
    near, far = torch.empty(n, dtype=torch.float64), torch.empty(n, dtype=torch.float64)
    for i, cam in enumerate(cameras):
        rows = (pick == i).nonzero().flatten()
        if rows.numel():
            pixels[rows] = uv[rows] * torch.tensor([cam.width, cam.height], dtype=torch.float64)
            near[rows], far[rows] = sweep_span(*cam.rays(pixels[rows]), region)
    xyz, rgb, scored = sweep_rays(cameras, image, pick, pixels, near, far, generator, max_width=max_width, mask=mask,
                                  depths=depths, neighbours=neighbours)
    return xyz, rgb, (
        f"one point on each of {n} pixel rays of the {len(cameras)} training views, at the depth of {depths} in the ball "
        f"round the cube whose colour the {min(neighbours, len(cameras) - 1)} nearest views agree on best "
        f"({int(scored.sum())} rays scored, the rest at a random depth)")


def sweep_rays(cameras: Sequence[Camera], image, pick: torch.Tensor, pixels: torch.Tensor, near: torch.Tensor,
               far: torch.Tensor, generator: torch.Generator, disparity: bool = False, max_width: int = PHOTO_WIDTH,
               mask=None, depths: int = SWEEP_DEPTHS, neighbours: int = SWEEP_NEIGHBOURS
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One point on each ray (camera ``pick`` [n], pixel ``pixels`` [n, 2] in its K's
    coordinates), between distances ``near`` and ``far`` [n] from the camera along it: ``depths``
    candidates, one in each of as many equal slices of that interval (of its inverse with
    ``disparity``), scored and chosen as :func:`ray_sweep` says. Returns (xyz [n, 3] float64, rgb
    [n, 3] in [0, 1], [n] whether the ray's point was scored)."""
    n, v = pick.shape[0], len(cameras)
    near_views = torch.topk(pose_distance(cameras).fill_diagonal_(math.inf), min(neighbours, v - 1), dim=1,
                            largest=False).indices if v > 1 else torch.zeros(v, 0, dtype=torch.int64)
    slices = (torch.arange(depths, dtype=torch.float64) + torch.rand(n, depths, generator=generator, dtype=torch.float64)) / depths
    fallback = torch.randint(depths, (n,), generator=generator)
    tie_break = torch.rand(n, depths, generator=generator, dtype=torch.float64)
    xyz = torch.empty(n, 3, dtype=torch.float64)
    rgb = torch.empty(n, 3, dtype=torch.float64)
    scored = torch.zeros(n, dtype=torch.bool)
    for i, cam in enumerate(cameras):
        rows = (pick == i).nonzero().flatten()
        r = rows.numel()
        if r == 0:
            continue
        origins, directions = cam.rays(pixels[rows])
        lo, hi = near[rows, None], far[rows, None]
        t = 1.0 / (1.0 / hi + slices[rows] * (1.0 / lo - 1.0 / hi)) if disparity else lo + slices[rows] * (hi - lo)
        candidates = (origins[:, None, :] + directions[:, None, :] * t[..., None]).reshape(-1, 3)
        views = [cam] + [cameras[int(j)] for j in near_views[i]]
        colours, seen, keeps = [], [], []
        for colour, inside, kept, _ in _lookups(candidates, views, image, max_width, mask):
            colours.append(colour)
            seen.append(inside & kept)
            keeps.append(kept)
        own, own_kept = colours[0], keeps[0]  # the ray's pixel, at the lookups' level, and whether a mask keeps it
        colours = torch.stack(colours[1:], 1) if v > 1 else own.new_zeros(own.shape[0], 0, 3)  # [r x depths, neighbours, 3]
        others = torch.stack(seen[1:], 1) if v > 1 else torch.zeros(own.shape[0], 0, dtype=torch.bool)
        count = others.sum(1)
        gap = torch.where(others, ((colours - own[:, None, :]) ** 2).sum(-1), torch.full(others.shape, math.inf))
        gap, order = gap.sort(1)
        used = (count // 2).clamp_min(2)
        within = torch.arange(gap.shape[1])[None, :] < used[:, None]
        score = torch.where(within, gap, torch.zeros_like(gap)).sum(1) / used
        score = torch.where((count >= MIN_VIEWS - 1) & own_kept, score, torch.full_like(score, math.inf)).reshape(r, depths)
        best = score.min(1).values
        ok = torch.isfinite(best)
        # ties (a plain wall, the sky, a synthetic colour field) go to a random one of them, not the nearest
        at = torch.where(score <= best[:, None], tie_break[rows], torch.full_like(score, -1.0)).argmax(1)
        chosen = torch.arange(r) * depths + torch.where(ok, at, fallback[rows])
        agreeing = (within & torch.isfinite(gap))[chosen] & ok[:, None]
        # a ray through a pixel a mask ignores is not scored, and takes its colour from the views that see its point
        agreeing |= ~own_kept[chosen, None] & others[chosen].gather(1, order[chosen])
        picked = colours[chosen][torch.arange(r)[:, None], order[chosen]]
        mine = own_kept[chosen].to(own.dtype)
        total = own[chosen] * mine[:, None] + (picked * agreeing[..., None]).sum(1)
        weight = mine + agreeing.sum(1)
        mean = torch.where(weight[:, None] > 0, total / weight.clamp_min(1)[:, None], torch.full_like(total, 0.5))
        xyz[rows], rgb[rows], scored[rows] = candidates[chosen], mean.to(torch.float64), ok
    return xyz, rgb.clamp(0.0, 1.0), scored


def _cube(center, half: float, why: str) -> InitRegion:
    """The original 3DGS region: the cube center ± half."""
    center = torch.as_tensor(center, dtype=torch.float64)
    return InitRegion("cube", f"random init: cube centre {[round(float(v), 3) for v in center]} ± {half:.4g} ({why})",
                      center=center, half=float(half))


def _seen_fraction(cameras: Sequence[Camera], points: torch.Tensor) -> torch.Tensor:
    """[P] fraction of the cameras that see each point (in front, inside the image)."""
    seen = torch.zeros(points.shape[0], dtype=torch.float64)
    for cam in cameras:
        pix, z = cam.project(points)
        inside = (z > 0) & (pix[:, 0] >= 0) & (pix[:, 0] <= cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] <= cam.height)
        seen += inside.to(torch.float64)
    return seen / len(cameras)


def axis_spread(cameras: Sequence[Camera]) -> float:
    """How far the optical axes of a rig spread: the smallest eigenvalue of mean(I - d dᵀ) over
    the unit viewing directions d (about sin² of their angular spread; 0 for parallel axes, 2/3
    for directions spread evenly over the sphere)."""
    if not cameras:
        raise ValueError("axis_spread needs at least one camera")
    d = camera_axes(cameras)
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    return float(torch.linalg.eigvalsh(torch.eye(3, dtype=torch.float64) - d.T @ d / len(cameras))[0])


def axes_meeting_point(cameras: Sequence[Camera]) -> torch.Tensor:
    """[3] float64: the point nearest all the optical axes (least squares over the lines, the
    pseudo-inverse's choice when they are parallel)."""
    if not cameras:
        raise ValueError("axes_meeting_point needs at least one camera")
    d = camera_axes(cameras).to(torch.float64)
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    centers = torch.stack([c.center for c in cameras]).to(d)
    across = torch.eye(3, dtype=d.dtype) - d[:, :, None] * d[:, None, :]  # projects out each axis
    return torch.linalg.pinv(across.sum(0)) @ (across @ centers[:, :, None]).sum(0)[:, 0]


def look_convergence(cameras: Sequence[Camera], point: Optional[torch.Tensor] = None) -> float:
    """How much a rig looks at one place: the mean, over the cameras, of the cosine between a
    camera's optical axis and the direction from its centre to the point nearest all the axes
    (least squares over the lines; `point` when the caller has it). 1 for cameras that all look
    at one point; about 0 or below for cameras that stand together and look out in every
    direction; a camera at that point counts 0. Meaningful for axes that spread (axis_spread >=
    CONVERGING_SPREAD, as its callers check first): nearly parallel axes have no nearest point,
    and the pseudo-inverse's choice then depends on where the world origin is."""
    if not cameras:
        raise ValueError("look_convergence needs at least one camera")
    d = camera_axes(cameras)
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    centers = torch.stack([c.center for c in cameras]).to(d)
    to_point = (axes_meeting_point(cameras) if point is None else point).to(d) - centers
    length = torch.linalg.norm(to_point, dim=1)
    at_point = length <= 1e-9 * (1.0 + float(centers.abs().max()))  # rounding leaves ~1e-16, not 0
    cos = torch.where(at_point, torch.zeros_like(length), (to_point * d).sum(1) / length.clamp_min(1e-300))
    return float(cos.mean())


def is_forward_facing(cameras: Sequence[Camera]) -> bool:
    """Whether a rig looks one way (LLFF-like, a walk-through looking ahead) rather than around
    the scene: axis_spread below CONVERGING_SPREAD."""
    return axis_spread(cameras) < CONVERGING_SPREAD


def init_region(cameras: Sequence[Camera], center: torch.Tensor, extent: float,
                kind: Optional[str] = None) -> InitRegion:
    """Where random initial points should go for this rig (see the module docstring).

    Args:
        cameras: the training cameras.
        center, extent: the scene normalisation (:func:`~mvgs_plugin.data.camera_normalization`),
            the cube of the original 3DGS.
        kind: None (the rig decides), or "frusta" to use the frusta whatever the axis spread
            (the cube is still returned, with the reason, when no depth is seen by half of the
            cameras or the axes have no common direction).
    """
    if kind not in (None, "frusta"):
        raise ValueError(f"init_region kind must be None or 'frusta', got {kind!r}")
    if not cameras:
        raise ValueError("init_region needs at least one camera")
    cube = lambda why: _cube(center, extent, why)  # noqa: E731
    d = camera_axes(cameras)
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)  # unit viewing directions
    spread = axis_spread(cameras)
    centers = torch.stack([c.center for c in cameras])
    radius = float(torch.linalg.norm(centers - centers.mean(0), dim=1).max())
    shared = float(torch.linalg.norm(d.mean(0))) >= 0.5  # the axes share a direction
    one_sided = None
    if spread >= CONVERGING_SPREAD:
        meet = axes_meeting_point(cameras)
        convergence = look_convergence(cameras, meet)
        if not shared and convergence < CONVERGING_COSINE:
            if not radius > 1e-6 * (1.0 + float(centers.mean(0).abs().max())):
                return cube(f"the cameras look every way (look convergence {convergence:.2f} < {CONVERGING_COSINE}) "
                            "from one centre: no depth cue")
            near = radius
            return InitRegion(
                "cube+frusta",
                f"random init: half in the 3DGS cube (centre {[round(float(v), 3) for v in center]} ± {extent:.4g}), half "
                f"in the {len(cameras)} training frusta between depth {near:.4g} and {FAR_OVER_NEAR * near:.4g}, uniform in "
                f"disparity (the axes spread every way but do not meet: look convergence {convergence:.2f} < "
                f"{CONVERGING_COSINE}; the content may lie among the cameras, as along a walk, or around them, as in a "
                "room shot from its middle, and photo-consistency chooses; near = the radius of the camera centres)",
                center=torch.as_tensor(center, dtype=torch.float64), half=float(extent),
                near=near, far=FAR_OVER_NEAR * near, cameras=tuple(cameras))
        if kind is None:
            # the cameras surround what they look at when they look in at one place inside the
            # cube about their centres (a rig without a shared direction that converges always
            # does: the convex hull of the centres lies in the cube). A rig that shares a direction
            # and meets outside the cube, or nowhere in front, stands on one side of what it sees,
            # as cameras over a ground: the cube would hold the air they stand in. Inside: within
            # the ball the cube holds however it is turned (radius: its half size), so the world's
            # axes do not decide it (the generator's rigs meet within 0.81 half sizes or beyond 4.1;
            # a drone grid looking in at the ground meets between 1 and sqrt(3): the ball that holds
            # the cube would take it for a rig round the scene)
            inside = float(torch.linalg.norm(meet - torch.as_tensor(center, dtype=torch.float64))) <= extent
            if not shared or (convergence >= CONVERGING_COSINE and inside):
                return cube(f"the cameras surround the scene: axis spread {spread:.3f} >= {CONVERGING_SPREAD}"
                            + (", the axes meet inside the ball in the cube" if shared else ""))
            one_sided = (f"the axes spread ({spread:.3f}) and share a direction but "
                         + (f"meet at {[round(float(v), 3) for v in meet]}, outside the ball in the 3DGS cube "
                            f"about the camera centres (radius {extent:.4g})" if convergence >= CONVERGING_COSINE else
                            f"meet nowhere in front (look convergence {convergence:.2f} < {CONVERGING_COSINE})")
                         + ": the cameras stand on one side of what they see, as over a ground")
    if not shared:
        return cube(f"frusta asked for, but the optical axes share no direction (axis spread {spread:.3f})")
    if not radius > 0:
        return cube(f"nearly parallel axes (spread {spread:.3f}) but one camera centre: no depth cue")
    mean_axis = d.mean(0)
    mean_axis = mean_axis / torch.linalg.norm(mean_axis)
    depths = radius * torch.logspace(-3, 4, _DEPTH_STEPS, dtype=torch.float64)
    seen = _seen_fraction(cameras, centers.mean(0) + depths[:, None] * mean_axis)
    ok = (seen >= 0.5).nonzero().flatten()
    if ok.numel() == 0:
        return cube(f"nearly parallel axes (spread {spread:.3f}) but no depth that half of the cameras see")
    near = float(depths[int(ok[0])])
    far = FAR_OVER_NEAR * near
    return InitRegion(
        "frusta", f"random init: the {len(cameras)} training frusta between depth {near:.4g} and {far:.4g}, "
                  f"uniform in disparity ("
                  + (f"forward-facing rig: axis spread {spread:.3f} < {CONVERGING_SPREAD}" if spread < CONVERGING_SPREAD
                     else one_sided if one_sided else f"asked for; axis spread {spread:.3f}")
                  + "; near = the first depth half of the cameras see)",
        near=near, far=far, cameras=tuple(cameras))



def _borders_show(cameras: Sequence[Camera], image, backdrop, mask=None, max_width: int = PHOTO_WIDTH) -> bool:
    """Whether the borders of the views, read as :func:`view_colours` reads them, are one colour
    (:func:`~mvgs_plugin.data.images.uniform_border`) within ``BORDER_TOLERANCE`` of ``backdrop``
    in every channel."""
    from .images import BORDER_TOLERANCE, check_background, uniform_border

    colour = check_background(backdrop)
    levels = [_photo_level(cam, max_width) for cam in cameras]
    found = uniform_border([image(cam, f) for cam, f in zip(cameras, levels)],
                           None if mask is None else [mask(cam, f) for cam, f in zip(cameras, levels)])
    return found is not None and max(abs(a - b) for a, b in zip(found, colour)) <= BORDER_TOLERANCE


def _rounded(colour) -> list[float]:
    return [round(float(v), 3) for v in colour]


def is_shell_radius(radius) -> bool:
    """Whether `radius` is a background shell's radius: a finite number (not a bool) of rig radii
    above 1, so the sphere lies beyond every camera."""
    return (not isinstance(radius, bool) and isinstance(radius, (int, float)) and math.isfinite(radius)
            and radius > 1.0)


def background_shell(cameras: Sequence[Camera], center: torch.Tensor, n: int, image,
                     radius: float = SHELL_RADIUS, points: Optional[torch.Tensor] = None, mask=None,
                     backdrop: Optional[Sequence[float]] = None) -> tuple[torch.Tensor, torch.Tensor, str]:
    """Initial points for what lies beyond a rig that surrounds its scene (sky, horizon, far walls).

    Points from a capture (SfM, a scene's point file, triangulation) stop where matching stops:
    nothing stands for the far background, so densification grows it from the nearest content
    outwards and leaves it where gradients stall, at the cameras' own distance from the centre.
    There it is a haze of small Gaussians between the training cameras, outside their frusta, that
    fills any new view taken from among them. This puts ``n`` points on a sphere of ``radius`` rig
    radii about ``center`` (a Fibonacci lattice, so evenly spaced and the same for every run),
    keeps those that at least one training view sees (in front of it, inside its image), and gives
    each the mean colour it lands on in those views (:func:`view_colours` at ``PHOTO_WIDTH`` px). A forward-facing rig gets none (its frusta init already reaches
    ``FAR_OVER_NEAR`` x its near depth, and a sphere about its few centres is not behind them).
    Nor does a rig whose content lies beyond the sphere, as in a room shot from its middle, where
    the sphere would stand in front of every view: with the scene's ``points`` [P, 3], when their
    median distance from ``center`` exceeds the sphere's radius; without them (None or empty),
    when the rig does not look in at one place (:func:`look_convergence` below ``CONVERGING_COSINE``).
    ``mask``: as :func:`view_colours`' (a masked pixel colours no point).
    ``backdrop``: the RGB colour in [0, 1] the renderer draws behind the Gaussians, or None. When
    the training images' borders show that colour and nothing else (the test the NeRF loaders find
    a backdrop with, :func:`~mvgs_plugin.data.images.uniform_border`, on the images as
    :func:`view_colours` reads them), there is none: on a rig round the scene a far background
    reaches the frame's edges, so borders that are all backdrop mean an object on a transparent or
    one-colour backdrop (NeRF-synthetic's kind), with nothing beyond it to model; the shell there
    would be Gaussians that only repeat the backdrop, and a third of the initial model.

    Returns (xyz [k, 3] float64, rgb [k, 3] float64 in [0, 1], what was done), k <= n.
    """
    if isinstance(n, bool) or int(n) != n or n < 0:
        raise ValueError(f"background_shell needs a point count n >= 0, got {n!r}")
    if not is_shell_radius(radius):
        raise ValueError(f"background_shell radius must be a finite number of rig radii > 1, got {radius!r}")
    empty = torch.zeros(0, 3, dtype=torch.float64)
    if n == 0:
        return empty, empty.clone(), "no background shell (0 points asked for)"
    if not cameras:
        raise ValueError("background_shell needs at least one camera")
    spread = axis_spread(cameras)
    if spread < CONVERGING_SPREAD:
        return empty, empty.clone(), (f"no background shell: forward-facing rig (axis spread {spread:.3f} < "
                                      f"{CONVERGING_SPREAD})")
    center = torch.as_tensor(center, dtype=torch.float64)
    centers = torch.stack([c.center for c in cameras])
    rig = float(torch.linalg.norm(centers - center, dim=1).max())
    if not rig > 0:
        return empty, empty.clone(), "no background shell: all camera centres coincide (no rig radius)"
    if points is not None and len(points):
        median = float(torch.linalg.norm(torch.as_tensor(points, dtype=torch.float64) - center, dim=1).median())
        if median > radius * rig:
            return empty, empty.clone(), (
                f"no background shell: the scene's points lie beyond its sphere (median distance {median:.4g} from the "
                f"centre > {radius * rig:.4g}, {radius:g} rig radii), which would stand in front of them in every view")
    else:
        convergence = look_convergence(cameras)
        if convergence < CONVERGING_COSINE:
            return empty, empty.clone(), (
                f"no background shell: the cameras do not look in at one place (look convergence {convergence:.2f} < "
                f"{CONVERGING_COSINE}) and no points say where the scene lies")
    if backdrop is not None and _borders_show(cameras, image, backdrop, mask):
        return empty, empty.clone(), (
            f"no background shell: the training images' borders show only the backdrop {_rounded(backdrop)} the "
            "renderer draws behind the Gaussians (an object on a backdrop: nothing beyond it to model)")
    i = torch.arange(n, dtype=torch.float64) + 0.5
    polar = torch.acos(1.0 - 2.0 * i / n)
    azimuth = math.pi * (1.0 + math.sqrt(5.0)) * i
    dirs = torch.stack([torch.cos(azimuth) * torch.sin(polar), torch.sin(azimuth) * torch.sin(polar),
                        torch.cos(polar)], dim=1)
    shell = center + radius * rig * dirs
    mean, variance, count = view_colours(shell, cameras, image, mask=mask)
    seen = count > 0
    if not seen.any():
        return empty, empty.clone(), f"no background shell: none of {n} points at {radius:g} rig radii is in a view"
    # listed in photo-consistency order, the order every measurement of docs/data.md was made with
    # (training is sensitive to the order of its initial points, not to the set alone)
    order = _photo_rank(variance[seen], count[seen])
    xyz, rgb = shell[seen][order], mean[seen][order].clamp(0.0, 1.0)
    return xyz, rgb, (f"background shell: {xyz.shape[0]} of {n} points on a sphere of radius {radius * rig:.4g} "
                      f"({radius:g} rig radii) about {[round(float(v), 3) for v in center]} are seen by a training "
                      f"view, coloured by the views")
