#!/usr/bin/env python3
"""Render a small tabletop scene with Mitsuba 3 as ground truth for mvgs-plugin.

The scene is rendered by an independent path tracer (Mitsuba 3), never by our own Gaussian
renderer, so that fitting it proves something. One run writes the same cameras in two layouts:

* NeRF-synthetic: ``transforms_{train,test}.json`` (OpenGL camera-to-world, ``camera_angle_x``
  plus explicit ``fl_x, fl_y, cx, cy, w, h``), images ``train/r_000.png`` / ``test/r_000.png``
  (8-bit sRGB, converted the way ``mitsuba.Bitmap.convert(srgb_gamma=True)`` does it) and
  ``points3d.ply`` (x y z red green blue).
* COLMAP: ``sparse/0/{cameras,images,points3D}.bin`` written by pycolmap (version 4 also
  writes ``rigs.bin`` and ``frames.bin``; readers of the classic three files ignore them); one
  PINHOLE camera; image names point at the same PNG files; poses are world-to-camera in OpenCV
  axes; points are sampled on the analytic surfaces, with tracks in the train views that see
  them.

World frame: z up, the table top is the plane z = 0, the scene centre is ``TARGET``.

Mitsuba's ``perspective`` sensor looks along its local +z with local +x pointing LEFT and +y
pointing UP in the image; OpenCV looks along +z with x right and y down. So the Mitsuba
``to_world`` is the OpenCV camera-to-world times diag(-1, -1, 1, 1). ``--check-projection``
verifies this on rendered markers.

Variants (``--variant``):

* ``default``: diffuse red ball, rough gold sphere, tiled box, blue cylinder on a checker
  ground; sky map plus a directional sun. 48 train + 12 test views on a hemisphere rig.
* ``reflective``: the same shapes as a mirror ball, rough copper and aluminium, and glossy
  plastic; sky light only (a delta sun would cause caustic fireflies through the mirrors).
* ``sparse``: the default scene seen by 10 train views 36 degrees apart in azimuth, alternating
  between 18 and 50 degrees elevation; test views lie between them.
* ``moving``: D-NeRF layout. The objects translate and rotate with time; every frame has a
  ``time`` in [0, 1] that runs along the rig, so test views are unseen (camera, time) pairs;
  ``transforms_val.json`` equals test. Its sparse points lie on the static ground only.
* ``multicam``: a multi-camera video in DyNeRF's (Neu3D's) layout: the moving objects filmed by
  9 fixed cameras on a 100 degree arc in front of them (3.6 away, 18 / 34 degrees high,
  alternating), each 12 frames at times k / 11; ``poses_bounds.npy`` (LLFF's rows, one per
  camera) and ``camNN/images/NNNN.png``; cam00, the middle camera, is the held-out one, as in
  DyNeRF. No points, no jsons, no COLMAP model (DyNeRF ships none). ``--n-train`` is the
  training cameras, ``--n-test`` the frames.
* ``forward``: forward-facing (LLFF-like) capture of the default scene in front of a vertical
  brick back wall (value-noise mottled, behind the objects, so every view sees geometry
  everywhere, no sky). 32 train + 8 test views on a jittered 8 x 5 grid, 1.4 wide x 0.7 high,
  3.3-3.6 from the scene, each looking at a point near ``TARGET`` (axes within 9 degrees of
  their mean: nearly parallel, not an orbit); test views take interleaved grid slots. Sun and
  sky as default.
* ``forward-clutter``: the clutter scene's primitives, materials, sun and sky seen by the
  forward rig (32 train + 8 test views), with no back wall: sky behind the objects, a second
  forward-facing scene whose content differs from ``forward``'s.
* ``corridor``: a deep hallway open to the sky (tiled floor, brick side walls 2 apart, a marble
  end wall 16 deep) with five primitives at depths 2.4 to 12 from the cameras; a forward rig at
  its mouth (32 train + 8 test views on a 0.8 x 0.4 grid) looks down it. Content spans a depth
  ratio of about 7 and the walls run from beside the cameras to the far end: a third
  forward-facing geometry, deep where the other two are shallow.
* ``clutter``: a second 360-degree scene: 12 primitives (spheres, yawed cubes, cylinders) of
  varied sizes scattered on the ground disc without overlap (fixed seed), in diffuse colours,
  value-noise textures, plastic, rough Cu / Al / Cr and one glass (dielectric) sphere; sun
  from the other side (azimuth -132 degrees, 35 degrees high). 48 train + 12 test views on two
  interleaved rings at 8-16 and 20-28 degrees elevation, distance 3.0-3.8, looking at points
  near ``TARGET``.
* ``room``: an inside-out capture. A closed room (5 x 5, 2.4 high: checker floor, brick walls on
  two sides, marble and spotted walls on the others, a plain ceiling) lit only by a square
  ceiling lamp, with seven primitives standing near the walls; 48 train + 12 test cameras stand
  within 0.35 of the room's centre at 0.95-1.25 high and look outwards, their azimuths spread
  round the full circle, slightly downwards. The cameras surround nothing: what they see lies
  around them, 1-3.5 away, the rig kind no other variant has.
* ``arc``: the clutter scene's primitives, materials, sun and sky seen by a handheld sweep round
  its front: 48 train + 12 test views in order along a 120 degree arc of azimuth, 8-40 degrees
  high, 2.4-4.2 from the scene (close-ups and wide views alternate), in **4:3 landscape images**
  (width ``--size``, height 3/4 of it, the same horizontal field). The back of the scene is never
  seen: a partial orbit, the rig of most handheld object captures, with non-square images.
* ``aerial``: the clutter scene seen from above by a drone survey: 48 train + 12 test cameras
  flown row by row over a jittered grid 3 x 2 wide, 3.6-4.4 above the ground, each tilted 0-20
  degrees from straight down towards the scene's middle, in **3:4 portrait images** (height
  ``--size``, width 3/4 of it). Nearly parallel axes like a forward rig's, looking down.
* ``thin``: the default scene fenced in: 12 dark posts (0.03 across, about 1.2 px at 128 px)
  on a circle of radius 1.35 round the objects, joined by three rings of pale wire (0.016
  across, about 0.6 px), on the default's hemisphere rig. Structure thinner than a pixel, in
  front of the objects in every view: at the pyramid's 1/4 level it is a quarter of that.
* ``object``: the default scene's four objects floating with no ground (the cylinder closed
  below), lit by the default's sky and sun, on a **transparent backdrop** (the sky lights them but
  no camera ray shows it): RGBA PNGs with straight alpha, the NeRF-synthetic kind of capture.
  48 train + 12 test views over the sphere's band from 40 degrees below the objects' middle to
  75 above (golden-angle azimuth, elevation even in sine), 2.8-3.3 away: the only rig that looks
  up at its scene. Its points lie on the objects only.
* ``object-reflective``: ``object`` with the reflective variant's materials and sky light (a mirror
  ball that shows the hidden sky, rough copper and aluminium, glossy plastic).
* ``object-dark``: ``object`` with a near-black matte ball (albedo 0.01) and a black glossy plastic
  cylinder (diffuse 0.01 under a specular coat): parts as dark as a black backdrop
  (``--background black``, 3DGS's default for NeRF-synthetic) where the sun does not reach them,
  which only the images' alpha tells from the backdrop.
* ``room-walk``: the same room seen by cameras that walk a loop of radius ROOM_WALK_RADIUS about
  its middle, each looking ahead along the loop (yaw jittered by up to 30 degrees either way):
  the axes spread every way and meet nowhere, as for the room, but the objects near the walls
  stand as close to the cameras as the middle of the room does.

Examples::

    python tools/make_scene.py --out examples/scenes/tabletop
    python tools/make_scene.py --variant moving --out scenes/moving
    python tools/make_scene.py --variant forward --out scenes/forward --check-projection
    python tools/make_scene.py --out examples/scenes/tabletop --no-render \\
        --check-projection --check-noise
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

VARIANTS = ("default", "reflective", "sparse", "moving", "multicam", "forward", "clutter", "forward-clutter", "corridor",
            "room", "room-walk", "arc", "aerial", "thin", "object", "object-reflective", "object-dark")
FORWARD_VARIANTS = ("forward", "forward-clutter", "corridor")
ROOM_VARIANTS = ("room", "room-walk")
MOVING_VARIANTS = ("moving", "multicam")  # the objects move with time
# multicam: fixed cameras on an arc in front of the moving objects, filming together
MULTICAM_ARC_DEG, MULTICAM_ELEV_DEG, MULTICAM_DIST, MULTICAM_FRAMES = 100.0, (18.0, 34.0), 3.6, 12
CLUTTER_CONTENT = ("clutter", "forward-clutter", "arc", "aerial")  # the clutter scene's primitives and light
ALPHA_VARIANTS = ("object", "object-reflective", "object-dark")  # RGBA images: the backdrop (the hidden sky) is transparent
REFLECTIVE_MATERIALS = ("reflective", "object-reflective")  # a mirror ball, rough metals, glossy plastic
TARGET = np.array([0.0, 0.0, 0.3])  # the point every camera looks at
GROUND_RADIUS = 2.5
FOV_X_DEG = 45.0
TEXTURE_SEED = 1234  # textures are part of the scene, not of the Monte Carlo noise

# Marker points for --check-projection: off-centre on purpose, so a flipped axis shows.
MARKERS = np.array([[0.9, -0.7, 0.1], [-0.8, 0.6, 0.9], [0.3, 0.9, 0.5]])
MARKER_RADIUS = 0.03
BORDER_PX = 3.0  # markers whose centre projects closer than this to the image edge are not measured

RIG_SEED = 4321  # camera jitter of the forward and clutter rigs

# forward: the camera patch's centre seen from TARGET, and the back wall behind the objects
FORWARD_AZ_DEG, FORWARD_ELEV_DEG, FORWARD_DIST = 20.0, 16.0, 3.4
FORWARD_PATCH = (1.4, 0.7)  # width, height of the camera grid
WALL_DIST = 1.3  # from the z axis, on the far side from the cameras (objects reach ~1.05)
WALL_HALF_WIDTH = 3.6
WALL_Z = (-1.0, 3.0)  # below the floor too: views past the disc's rim still hit the wall

# corridor: a hallway along +y (floor z = 0, side walls at x = +-half width, an end wall at y =
# CORRIDOR_END), open to the sky; the camera grid's centre, its width x height, and the sun
CORRIDOR_HALF_WIDTH, CORRIDOR_HEIGHT, CORRIDOR_START, CORRIDOR_END = 1.0, 2.0, -2.0, 14.0
CORRIDOR_EYE = np.array([0.0, -1.0, 0.9])
CORRIDOR_PATCH = (0.8, 0.4)
CORRIDOR_SUN = (math.radians(-60.0), math.radians(62.0))

# room: half width (x and y), height, the lamp's half width and radiance, the cameras' stand
ROOM_HALF, ROOM_HEIGHT = 2.5, 2.4
ROOM_LAMP_HALF, ROOM_LAMP_RADIANCE = 0.8, (9.0, 8.4, 7.6)
ROOM_EYE_RADIUS, ROOM_EYE_Z = 0.35, (0.95, 1.25)
ROOM_WALK_RADIUS = 1.2

# arc: a sweep round the front of the clutter scene (azimuth span and centre, degrees), the
# cameras' distance range from TARGET, and the images' height over width (landscape 4:3)
ARC_SPAN_DEG, ARC_CENTRE_DEG = 120.0, 30.0
ARC_DIST = (2.4, 4.2)
ARC_ASPECT = 0.75

# aerial: a survey grid over the clutter scene (columns x rows, its half extents in x and y, the
# cameras' heights above the ground) in portrait images (width over height)
AERIAL_GRID = (10, 6)
AERIAL_HALF = (1.5, 1.0)
AERIAL_Z = (3.6, 4.4)
AERIAL_ASPECT = 0.75

# thin: a fence round the default scene's objects: FENCE_POSTS posts of FENCE_POST_RADIUS on a
# circle of FENCE_RADIUS, FENCE_POST_HEIGHT high, joined by wires of FENCE_WIRE_RADIUS at
# FENCE_WIRE_HEIGHTS (at 128 px and the rig's distance a pixel is about 0.026 wide: the posts
# are about 1.2 px across, the wires 0.6 px, a quarter of that at the pyramid's 1/4 level)
FENCE_POSTS, FENCE_RADIUS, FENCE_POST_HEIGHT = 12, 1.35, 1.1
FENCE_POST_RADIUS, FENCE_WIRE_RADIUS = 0.015, 0.008
FENCE_WIRE_HEIGHTS = (0.35, 0.7, 1.05)

# object: a rig over the whole sphere about the objects, from below their middle to near the
# zenith (elevation range, degrees), and its distance range from TARGET
OBJECT_ELEV_DEG = (-40.0, 75.0)
OBJECT_DIST = (2.8, 3.3)

# clutter: primitive layout seed and the sun (azimuth, elevation) in radians
CLUTTER_SEED = 2024
CLUTTER_SUN = (math.radians(-132.0), math.radians(35.0))


# ----------------------------------------------------------------------------- cameras
@dataclass
class View:
    """One camera: OpenCV world-to-camera, pinhole K, its split, index and time."""

    split: str  # "train" or "test"
    index: int  # index within the split (r_000 ...)
    w2c: np.ndarray  # [4, 4] OpenCV world-to-camera
    K: np.ndarray  # [3, 3]
    width: int
    height: int
    time: float = 0.0
    camera: int = -1  # multicam: the camera (its folder camNN), and index is the frame

    @property
    def name(self) -> str:
        if self.camera >= 0:
            return f"cam{self.camera:02d}/images/{self.index:04d}"
        return f"{self.split}/r_{self.index:03d}"

    @property
    def c2w(self) -> np.ndarray:
        return np.linalg.inv(self.w2c)


def intrinsics(size: int, fov_x_deg: float = FOV_X_DEG, height: Optional[int] = None) -> np.ndarray:
    """Square pixels, principal point at the image centre (pixel centres at +0.5); ``size`` is the
    width, ``height`` (None: the width) the image's height."""
    fx = 0.5 * size / math.tan(0.5 * math.radians(fov_x_deg))
    h = size if height is None else height
    return np.array([[fx, 0.0, 0.5 * size], [0.0, fx, 0.5 * h], [0.0, 0.0, 1.0]])


def look_at_w2c(centre: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV world-to-camera for a camera at ``centre`` looking at ``target`` (z up)."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))  # right in the image
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)  # down in the image
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ centre
    return w2c


def radical_inverse(k: int, base: int) -> float:
    """Van der Corput sequence: a low-discrepancy value in [0, 1)."""
    out, f = 0.0, 1.0 / base
    while k > 0:
        out += f * (k % base)
        k //= base
        f /= base
    return out


def azimuth_deg(c: np.ndarray) -> float:
    """The azimuth of a camera centre about TARGET, in degrees in (-180, 180]."""
    return math.degrees(math.atan2(c[1] - TARGET[1], c[0] - TARGET[0]))


def azimuth_gap_deg(centres: list[np.ndarray]) -> float:
    """The widest gap, in degrees, between the azimuths of `centres`, round the circle."""
    az = np.sort([azimuth_deg(c) % 360.0 for c in centres])
    return float(np.max(np.diff(np.append(az, az[0] + 360.0))))


def dense_test_slots(rig: list, slots: set[int], n_test: int) -> set[int]:
    """Test slots on the golden-angle rig: the evenly spaced slots of the rig's order, unless their
    azimuths bunch (a widest gap over twice an even share of the circle: for 20 + 12 views the
    12 spaced slots step 6.7 degrees round and leave a 250-degree arc; 48 + 12 step 32.5 and keep
    their slots); then the evenly spaced slots of the rig sorted by azimuth."""
    if n_test < 2 or azimuth_gap_deg([rig[k][0] for k in slots]) <= 2 * 360.0 / n_test:
        return slots
    order = sorted(range(len(rig)), key=lambda k: azimuth_deg(rig[k][0]))
    return {order[k] for k in pick_test_slots(len(rig), n_test)}


def pick_test_slots(n_total: int, n_test: int) -> set[int]:
    """Rig slots given to test views: spread evenly, so test interleaves with train."""
    if n_test == 0:
        return set()
    slots = {int(round((j + 0.5) * n_total / n_test - 0.5)) for j in range(n_test)}
    if len(slots) != n_test:
        raise ValueError(f"cannot interleave {n_test} test views among {n_total}")
    return slots


def rig_dense(n_total: int) -> list[np.ndarray]:
    """Upper-hemisphere rig: golden-angle azimuth, low-discrepancy elevation and distance."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    lo, hi = math.sin(math.radians(12.0)), math.sin(math.radians(65.0))
    centres = []
    for k in range(n_total):
        az = k * golden
        frac = (radical_inverse(k, 3) + 0.5 / n_total) % 1.0
        elev = math.asin(lo + (hi - lo) * frac)
        dist = 4.0 + 0.6 * (radical_inverse(k, 5) - 0.5)
        centres.append(TARGET + dist * np.array(
            [math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)]))
    return centres


def rig_object(n_total: int) -> list[np.ndarray]:
    """A rig round an object seen from every side, below it too (NeRF-synthetic's kind of capture,
    over more of the sphere): golden-angle azimuth, elevation uniform in sine over
    OBJECT_ELEV_DEG (so evenly spread over that band of the sphere), distance in OBJECT_DIST."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    lo, hi = (math.sin(math.radians(e)) for e in OBJECT_ELEV_DEG)
    centres = []
    for k in range(n_total):
        az = k * golden
        elev = math.asin(lo + (hi - lo) * (k + 0.5) / n_total)
        dist = OBJECT_DIST[0] + (OBJECT_DIST[1] - OBJECT_DIST[0]) * radical_inverse(k, 3)
        centres.append(TARGET + dist * np.array(
            [math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)]))
    return centres


def rig_sparse(n_train: int, n_test: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Few train views spread evenly in azimuth (alternating low/high), test views between."""
    def at(az, elev_deg, dist):
        e = math.radians(elev_deg)
        return TARGET + dist * np.array([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az),
                                         math.sin(e)])
    train = [at(2 * math.pi * i / n_train, 18.0 if i % 2 == 0 else 50.0, 3.6)
             for i in range(n_train)]
    test = [at(2 * math.pi * (j + 0.5) / max(n_test, 1) + 0.37, 33.0, 4.0)
            for j in range(n_test)]
    return train, test


def forward_axes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors of the forward rig: ``back`` from TARGET to the patch centre, and the
    patch's ``right`` and ``up`` (image right / up of a camera at the centre)."""
    a, e = math.radians(FORWARD_AZ_DEG), math.radians(FORWARD_ELEV_DEG)
    back = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    right = np.cross(-back, [0.0, 0.0, 1.0])
    right = right / np.linalg.norm(right)
    up = np.cross(right, -back)
    return back, right, up


def rig_forward(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """LLFF-like (centre, look-at) pairs: a jittered grid on a plane facing the scene, row by
    row from the top left. Each camera looks at a point near TARGET: 0.4 of its own offset in
    the patch plus a small jitter, so the axes converge only far behind TARGET (nearly
    parallel, within about 9 degrees of the mean) instead of orbiting it."""
    rows = max(1, round((1 + math.sqrt(1 + 8 * n_total)) / 4))  # cols - 1 ~ 2 (rows - 1)
    cols = math.ceil(n_total / rows)
    back, right, up = forward_axes()
    width, height = FORWARD_PATCH
    rng = np.random.default_rng(RIG_SEED)
    rig = []
    for k in range(n_total):
        r, c = divmod(k, cols)
        in_row = min(cols, n_total - r * cols)  # a short last row spreads over the width
        x = (c / (in_row - 1) - 0.5) * width if in_row > 1 else 0.0
        y = (0.5 - r / (rows - 1)) * height if rows > 1 else 0.0
        jit = rng.uniform(-1.0, 1.0, 6)
        x, y = x + 0.03 * jit[0], y + 0.03 * jit[1]
        offset = x * right + y * up
        centre = TARGET + (FORWARD_DIST + 0.12 * jit[2]) * back + offset
        rig.append((centre, TARGET + 0.4 * offset + 0.06 * jit[3:]))
    return rig


def rig_corridor(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Forward (centre, look-at) pairs at the corridor's mouth: a jittered grid of
    CORRIDOR_PATCH about CORRIDOR_EYE, row by row from the top left, each camera looking down
    the corridor at a point on the end wall 0.5 x its own offset from the axis (axes within a
    few degrees: a forward-facing rig)."""
    rows = max(1, round((1 + math.sqrt(1 + 8 * n_total)) / 4))
    cols = math.ceil(n_total / rows)
    width, height = CORRIDOR_PATCH
    rng = np.random.default_rng(RIG_SEED + 2)
    rig = []
    for k in range(n_total):
        r, c = divmod(k, cols)
        in_row = min(cols, n_total - r * cols)
        x = (c / (in_row - 1) - 0.5) * width if in_row > 1 else 0.0
        z = (0.5 - r / (rows - 1)) * height if rows > 1 else 0.0
        jit = rng.uniform(-1.0, 1.0, 5)
        centre = CORRIDOR_EYE + np.array([x + 0.02 * jit[0], 0.08 * jit[1], z + 0.02 * jit[2]])
        look = np.array([0.5 * x + 0.15 * jit[3], CORRIDOR_END, CORRIDOR_EYE[2] + 0.5 * z + 0.15 * jit[4]])
        rig.append((centre, look))
    return rig


def rig_rings(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Two interleaved low rings around TARGET (even slots 8-16, odd 20-28 degrees up),
    distance 3.0-3.8, each camera looking at TARGET plus a small jitter."""
    rng = np.random.default_rng(RIG_SEED + 1)
    rig = []
    for k in range(n_total):
        az = 2 * math.pi * k / n_total + 0.3
        base = 12.0 if k % 2 == 0 else 24.0
        elev = math.radians(base + 8.0 * (radical_inverse(k // 2, 3) - 0.5))
        dist = 3.0 + 0.8 * radical_inverse(k, 5)
        centre = TARGET + dist * np.array([math.cos(elev) * math.cos(az),
                                           math.cos(elev) * math.sin(az), math.sin(elev)])
        rig.append((centre, TARGET + rng.uniform(-0.08, 0.08, 3)))
    return rig


def rig_room(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Inside-out (centre, look-at) pairs: centres uniform in a disc of ROOM_EYE_RADIUS about the
    room's axis at heights ROOM_EYE_Z, each looking outwards at azimuth 2 pi k / n (plus a small
    jitter), 5-19 degrees below the horizon (a radical-inverse sequence), so consecutive views
    overlap by about two thirds of their 45 degree field."""
    rng = np.random.default_rng(RIG_SEED + 3)
    rig = []
    for k in range(n_total):
        r, a = ROOM_EYE_RADIUS * math.sqrt(rng.random()), rng.uniform(0.0, 2 * math.pi)
        z = ROOM_EYE_Z[0] + (ROOM_EYE_Z[1] - ROOM_EYE_Z[0]) * rng.random()
        centre = np.array([r * math.cos(a), r * math.sin(a), z])
        az = 2 * math.pi * k / n_total + 0.3 + rng.uniform(-0.05, 0.05)
        elev = math.radians(-12.0 + 14.0 * (radical_inverse(k, 3) - 0.5))
        rig.append((centre, centre + np.array([math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az),
                                               math.sin(elev)])))
    return rig


def rig_room_walk(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, look-at) pairs on a walk round the room: centres on a circle of ROOM_WALK_RADIUS
    about its axis at heights ROOM_EYE_Z, in order round it, each looking along the direction
    of travel (counter-clockwise) turned by a yaw jitter of up to 30 degrees, 5-19 degrees below
    the horizon."""
    rng = np.random.default_rng(RIG_SEED + 4)
    rig = []
    for k in range(n_total):
        a = 2 * math.pi * k / n_total
        z = ROOM_EYE_Z[0] + (ROOM_EYE_Z[1] - ROOM_EYE_Z[0]) * rng.random()
        centre = np.array([ROOM_WALK_RADIUS * math.cos(a), ROOM_WALK_RADIUS * math.sin(a), z])
        heading = a + math.pi / 2 + math.radians(rng.uniform(-30.0, 30.0))
        elev = math.radians(-12.0 + 14.0 * (radical_inverse(k, 3) - 0.5))
        rig.append((centre, centre + np.array([math.cos(elev) * math.cos(heading),
                                               math.cos(elev) * math.sin(heading), math.sin(elev)])))
    return rig


def rig_arc(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, look-at) pairs of a handheld sweep round the front of the scene: azimuths in order
    over ARC_SPAN_DEG about ARC_CENTRE_DEG (jittered by a fifth of a step), elevations 8-40
    degrees and distances over ARC_DIST from TARGET (radical-inverse sequences, so close-ups and
    wide views alternate), each looking at a point within 0.25 of TARGET. The back of the
    scene is never seen and the views converge only over the arc's third of the circle."""
    rng = np.random.default_rng(RIG_SEED + 5)
    rig = []
    step = math.radians(ARC_SPAN_DEG) / max(n_total - 1, 1)
    for k in range(n_total):
        az = math.radians(ARC_CENTRE_DEG - 0.5 * ARC_SPAN_DEG) + k * step + rng.uniform(-0.2, 0.2) * step
        elev = math.radians(8.0 + 32.0 * radical_inverse(k, 3))
        dist = ARC_DIST[0] + (ARC_DIST[1] - ARC_DIST[0]) * radical_inverse(k, 5)
        centre = TARGET + dist * np.array([math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az),
                                           math.sin(elev)])
        rig.append((centre, TARGET + rng.uniform(-0.25, 0.25, 3)))
    return rig


def rig_aerial(n_total: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, look-at) pairs of a drone survey: n_total cameras in rows over a jittered
    AERIAL_GRID-like lattice covering +-AERIAL_HALF, at heights AERIAL_Z, flown row by row;
    each looks down at the ground point halfway between the point below it and the scene's
    centre, plus a jitter (tilts of 0-20 degrees off nadir, towards the middle): the axes nearly
    share a direction, as a forward rig's do, but they look down and converge a little."""
    rng = np.random.default_rng(RIG_SEED + 6)
    cols = max(2, round(math.sqrt(n_total * AERIAL_GRID[0] / AERIAL_GRID[1])))
    rows = -(-n_total // cols)
    rig = []
    for k in range(n_total):
        r, c = divmod(k, cols)
        c = c if r % 2 == 0 else cols - 1 - c  # boustrophedon, as a survey flies
        x = AERIAL_HALF[0] * (2 * (c + 0.5) / cols - 1) + rng.uniform(-0.1, 0.1)
        y = AERIAL_HALF[1] * (2 * (r + 0.5) / rows - 1) + rng.uniform(-0.1, 0.1)
        z = AERIAL_Z[0] + (AERIAL_Z[1] - AERIAL_Z[0]) * rng.random()
        look = np.array([0.5 * x, 0.5 * y, 0.0]) + np.append(rng.uniform(-0.15, 0.15, 2), 0.0)
        rig.append((np.array([x, y, z]), look))
    return rig


def image_size(variant: str, size: int) -> tuple[int, int]:
    """(width, height) of the variant's images: ``size`` wide and square but for arc (landscape
    4:3, ``size`` wide) and aerial (portrait 3:4, ``size`` high)."""
    if variant == "arc":
        return size, max(8, round(ARC_ASPECT * size))
    if variant == "aerial":
        return max(8, round(AERIAL_ASPECT * size)), size
    return size, size


def views_multicam(n_train: int, frames: int, K, width: int, height: int) -> list[View]:
    """A synchronized rig: ``n_train`` + 1 fixed cameras on an arc of MULTICAM_ARC_DEG in front of
    the scene (elevations alternating), each filming ``frames`` frames at times k / (frames - 1);
    the middle camera is cam00, the held-out one (DyNeRF's convention), the others cam01, ...
    in order along the arc."""
    n = n_train + 1
    order = [n // 2] + [k for k in range(n) if k != n // 2]  # arc slot of cam00, cam01, ...
    views = []
    for cam, slot in enumerate(order):
        az = math.radians(-MULTICAM_ARC_DEG / 2 + MULTICAM_ARC_DEG * slot / max(n - 1, 1))
        el = math.radians(MULTICAM_ELEV_DEG[slot % 2])
        c = TARGET + MULTICAM_DIST * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        w2c = look_at_w2c(c, TARGET)
        for k in range(frames):
            views.append(View("test" if cam == 0 else "train", k, w2c, K, width, height,
                              k / max(frames - 1, 1), camera=cam))
    return views


def make_views(variant: str, n_train: int, n_test: int, size: int) -> list[View]:
    width, height = image_size(variant, size)
    K = intrinsics(width, height=height)
    views: list[View] = []
    if variant == "multicam":
        return views_multicam(n_train, n_test, K, width, height)
    if variant == "sparse":
        train, test = rig_sparse(n_train, n_test)
        for i, c in enumerate(train):
            views.append(View("train", i, look_at_w2c(c, TARGET), K, size, size))
        for j, c in enumerate(test):
            views.append(View("test", j, look_at_w2c(c, TARGET), K, size, size))
        return views
    n_total = n_train + n_test
    slots = pick_test_slots(n_total, n_test)
    counts = {"train": 0, "test": 0}
    if variant in ("forward", "forward-clutter"):
        rig = rig_forward(n_total)
    elif variant == "corridor":
        rig = rig_corridor(n_total)
    elif variant == "clutter":
        rig = rig_rings(n_total)
    elif variant == "room":
        rig = rig_room(n_total)
    elif variant == "room-walk":
        rig = rig_room_walk(n_total)
    elif variant == "arc":
        rig = rig_arc(n_total)
    elif variant == "aerial":
        rig = rig_aerial(n_total)
    elif variant in ALPHA_VARIANTS:
        rig = [(c, TARGET) for c in rig_object(n_total)]
        slots = dense_test_slots(rig, slots, n_test)
    else:
        rig = [(c, TARGET) for c in rig_dense(n_total)]
        slots = dense_test_slots(rig, slots, n_test)
    # a camera looking (nearly) straight down takes "up" in its image from the world's +y
    up = (0.0, 1.0, 0.0) if variant == "aerial" else (0.0, 0.0, 1.0)
    for k, (c, look) in enumerate(rig):
        split = "test" if k in slots else "train"
        # Moving scene: time runs along the rig, so a test view gets a time between the times
        # of its train neighbours, at a camera no train view has: an unseen (camera, time) pair.
        t = k / max(n_total - 1, 1) if variant == "moving" else 0.0
        views.append(View(split, counts[split], look_at_w2c(c, look, up=up), K, width, height, t))
        counts[split] += 1
    return views


# ----------------------------------------------------------------------------- textures
def value_noise(res: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth periodic value noise in [0, 1], [res, res]."""
    grid = rng.random((cells, cells))
    t = np.arange(res) * cells / res
    i0 = np.floor(t).astype(int)
    f = t - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    a = grid[i0][:, i0] * (1 - f)[None, :] + grid[i0][:, i1] * f[None, :]
    b = grid[i1][:, i0] * (1 - f)[None, :] + grid[i1][:, i1] * f[None, :]
    return a * (1 - f)[:, None] + b * f[:, None]


def ground_texture(res: int = 512) -> np.ndarray:
    """Checkerboard with mottled noise and fine grain, linear RGB albedo [res, res, 3]."""
    rng = np.random.default_rng(TEXTURE_SEED)
    u = (np.arange(res) + 0.5) / res
    checks = 10  # cells across the ground's diameter
    cu = np.floor(u * checks).astype(int)
    board = (cu[:, None] + cu[None, :]) % 2
    light = np.array([0.62, 0.56, 0.46])
    dark = np.array([0.16, 0.20, 0.26])
    tex = np.where(board[..., None] == 1, light, dark)
    noise = 0.5 * value_noise(res, 8, rng) + 0.3 * value_noise(res, 32, rng) \
        + 0.2 * value_noise(res, 128, rng)
    tex = tex * (0.7 + 0.6 * noise)[..., None]
    return np.clip(tex, 0.0, 0.95).astype(np.float32)


def box_texture(res: int = 256) -> np.ndarray:
    """Coloured tiles with dark grout: gives the box sharp, view-checkable detail."""
    rng = np.random.default_rng(TEXTURE_SEED + 1)
    tiles = 6
    palette = np.array([[0.75, 0.55, 0.1], [0.1, 0.45, 0.6], [0.7, 0.7, 0.65], [0.5, 0.15, 0.35],
                        [0.2, 0.55, 0.25]])
    choice = rng.integers(0, len(palette), (tiles, tiles))
    idx = (np.arange(res) * tiles // res)
    tex = palette[choice[idx][:, idx]]
    frac = (np.arange(res) * tiles / res) % 1.0
    grout = (np.minimum(frac, 1 - frac) < 0.06)
    tex[grout[:, None] | grout[None, :]] = 0.05
    return tex.astype(np.float32)


def wall_texture(res: int = 512) -> np.ndarray:
    """Staggered bricks with light mortar, mottled by value noise (the forward back wall).

    Image rows run along the wall's height: 18 courses of 16 bricks, about 0.45 x 0.22 world
    units each on the 7.2 x 4 wall, mortar about 0.025 wide (one pixel at 128 px).
    """
    rng = np.random.default_rng(TEXTURE_SEED + 2)
    rows, cols = 18, 16
    t = (np.arange(res) + 0.5) / res
    row = np.floor(t * rows).astype(int)  # [res]: brick course of each image row
    uc = t[None, :] * cols + 0.5 * (row % 2)[:, None]  # [res, res]: staggered by half a brick
    col = np.floor(uc).astype(int) % cols
    palette = np.array([[0.56, 0.22, 0.13], [0.62, 0.30, 0.17], [0.46, 0.18, 0.12],
                        [0.66, 0.46, 0.32], [0.40, 0.26, 0.20]])
    choice = rng.integers(0, len(palette), (rows, cols))
    tint = rng.uniform(0.8, 1.15, (rows, cols))
    tex = palette[choice[row[:, None], col]] * tint[row[:, None], col][..., None]
    fu, fv = uc % 1.0, (t * rows) % 1.0
    mortar = (np.minimum(fu, 1 - fu) < 0.03) | (np.minimum(fv, 1 - fv) < 0.06)[:, None]
    tex[mortar] = [0.58, 0.56, 0.52]
    noise = 0.6 * value_noise(res, 16, rng) + 0.4 * value_noise(res, 128, rng)
    tex = tex * (0.75 + 0.5 * noise)[..., None]
    return np.clip(tex, 0.0, 0.95).astype(np.float32)


def marble_texture(seed: int, a, b, res: int = 256) -> np.ndarray:
    """Wavy bands between colours ``a`` and ``b``, the waves bent by value noise."""
    rng = np.random.default_rng(seed)
    noise = 0.6 * value_noise(res, 4, rng) + 0.3 * value_noise(res, 16, rng) \
        + 0.1 * value_noise(res, 64, rng)
    u = (np.arange(res) + 0.5) / res
    band = (0.5 + 0.5 * np.sin(2 * math.pi * (3 * u[None, :] + 3 * noise))) ** 2
    tex = np.asarray(a) * (1 - band)[..., None] + np.asarray(b) * band[..., None]
    return np.clip(tex, 0.0, 0.95).astype(np.float32)


def spots_texture(seed: int, a, b, res: int = 256) -> np.ndarray:
    """Soft-edged blobs of colour ``b`` on ``a`` (thresholded value noise) with fine grain."""
    rng = np.random.default_rng(seed)
    noise = 0.7 * value_noise(res, 8, rng) + 0.3 * value_noise(res, 32, rng)
    m = np.clip((noise - 0.5) * 8 + 0.5, 0, 1)
    tex = np.asarray(a) * (1 - m)[..., None] + np.asarray(b) * m[..., None]
    tex = tex * (0.85 + 0.3 * value_noise(res, 128, rng))[..., None]
    return np.clip(tex, 0.0, 0.95).astype(np.float32)


def sky_texture(height: int = 128, glow_phi: float = 0.9) -> np.ndarray:
    """Equirectangular sky in Mitsuba's envmap frame (row 0 = local +y, i.e. the zenith).

    ``glow_phi`` is the longitude of a broad brightening; with the envmap rotated as in
    :meth:`SceneBuilder.scene_dict` it faces world azimuth pi/2 - glow_phi.
    """
    width = 2 * height
    theta = (np.arange(height) + 0.5) / height * math.pi  # 0 at zenith
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    cos_t = np.cos(theta)[:, None, None] * np.ones((1, width, 1))
    zenith = np.array([0.18, 0.35, 0.80])
    horizon = np.array([0.70, 0.72, 0.75])
    ground = np.array([0.3, 0.27, 0.22])
    up = np.clip(cos_t, 0, 1) ** 0.5
    sky = horizon * (1 - up) + zenith * up
    # a soft, broad brightening towards the sun's azimuth keeps the lighting asymmetric
    dphi = (phi - glow_phi + math.pi) % (2 * math.pi) - math.pi
    glow = 0.35 * np.exp(-dphi ** 2 / 0.8)[None, :, None]
    sky = sky * (1.0 + glow * (cos_t > 0))
    env = np.where(cos_t > 0, sky, ground)
    return env.astype(np.float32)


# ----------------------------------------------------------------------------- scene
@dataclass
class Objects:
    """Analytic geometry at one time; shared by the renderer and the point sampler."""

    ball_centre: np.ndarray
    ball_radius: float
    metal_centre: np.ndarray
    metal_radius: float
    box_centre: np.ndarray
    box_half: float
    box_yaw_deg: float
    cyl_base: np.ndarray
    cyl_radius: float
    cyl_height: float


def fence_segments() -> list[tuple[np.ndarray, np.ndarray, float, str]]:
    """The thin variant's fence: (p0, p1, radius, "post" | "wire") per cylinder, posts first."""
    angles = [2 * math.pi * (k + 0.5) / FENCE_POSTS for k in range(FENCE_POSTS)]
    foot = [np.array([FENCE_RADIUS * math.cos(a), FENCE_RADIUS * math.sin(a), 0.0]) for a in angles]
    out = [(f, f + np.array([0.0, 0.0, FENCE_POST_HEIGHT]), FENCE_POST_RADIUS, "post") for f in foot]
    for h in FENCE_WIRE_HEIGHTS:
        up = np.array([0.0, 0.0, h])
        out += [(foot[k] + up, foot[(k + 1) % FENCE_POSTS] + up, FENCE_WIRE_RADIUS, "wire")
                for k in range(FENCE_POSTS)]
    return out


def sample_segments(n: int, segments, rng: np.random.Generator) -> np.ndarray:
    """n points on the side surfaces of the cylinders (p0, p1, radius, _), area-weighted."""
    areas = np.array([2 * math.pi * r * np.linalg.norm(p1 - p0) for p0, p1, r, _ in segments])
    which = rng.choice(len(segments), size=n, p=areas / areas.sum())
    out = np.empty((n, 3))
    for i, k in enumerate(which):
        p0, p1, r, _ = segments[k]
        axis = (p1 - p0) / np.linalg.norm(p1 - p0)
        u = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        a = rng.uniform(0, 2 * math.pi)
        out[i] = p0 + rng.random() * (p1 - p0) + r * (math.cos(a) * u + math.sin(a) * v)
    return out


def objects_at(variant: str, t: float) -> Objects:
    obj = Objects(
        ball_centre=np.array([0.55, -0.40, 0.35]), ball_radius=0.35,
        metal_centre=np.array([-0.60, -0.45, 0.30]), metal_radius=0.30,
        box_centre=np.array([-0.25, 0.55, 0.28]), box_half=0.28, box_yaw_deg=30.0,
        cyl_base=np.array([0.60, 0.55, 0.0]), cyl_radius=0.18, cyl_height=0.75)
    if variant in MOVING_VARIANTS:
        # translate and rotate over t in [0, 1]; everything stays on or above the table
        obj.ball_centre = obj.ball_centre + np.array([-0.35 * t, 0.25 * math.sin(math.pi * t), 0.0])
        obj.metal_centre = obj.metal_centre + np.array([0.0, 0.0, 0.45 * math.sin(math.pi * t)])
        obj.box_centre = obj.box_centre + np.array([0.3 * t, 0.0, 0.0])
        obj.box_yaw_deg = 30.0 + 120.0 * t
    return obj


def cube_to_world(centre: np.ndarray, half: float, yaw_deg: float) -> np.ndarray:
    """[4, 4] map from Mitsuba's cube [-1, 1]^3 to a cube of half edge ``half`` turned by
    ``yaw_deg`` about z."""
    a = math.radians(yaw_deg)
    R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    M = np.eye(4)
    M[:3, :3] = R * half
    M[:3, 3] = centre
    return M


def box_to_world(obj: Objects) -> np.ndarray:
    """[4, 4] map from Mitsuba's cube [-1, 1]^3 to the world."""
    return cube_to_world(obj.box_centre, obj.box_half, obj.box_yaw_deg)


def wall_to_world() -> np.ndarray:
    """[4, 4] map from Mitsuba's rectangle [-1, 1]^2 x {0} (normal +z) to the forward back wall:
    vertical, its normal pointing (horizontally) at the cameras, WALL_DIST behind the z axis."""
    back, _, _ = forward_axes()
    n = np.array([back[0], back[1], 0.0])
    n = n / np.linalg.norm(n)  # towards the cameras
    z = np.array([0.0, 0.0, 1.0])
    r = np.cross(z, n)  # r x z = n: a proper rotation, so the front face looks at the cameras
    M = np.eye(4)
    M[:3, 0] = WALL_HALF_WIDTH * r
    M[:3, 1] = 0.5 * (WALL_Z[1] - WALL_Z[0]) * z
    M[:3, 2] = n
    M[:3, 3] = -WALL_DIST * n + 0.5 * (WALL_Z[0] + WALL_Z[1]) * z
    return M


@dataclass
class Prim:
    """One primitive of the clutter scene, resting on the ground."""

    kind: str  # "sphere", "cube" or "cylinder"
    centre: np.ndarray  # sphere / cube centre; the cylinder's base centre (z = 0)
    size: float  # sphere / cylinder radius, cube half edge
    material: str
    height: float = 0.0  # cylinder
    yaw_deg: float = 0.0  # cube

    @property
    def footprint(self) -> float:
        """Radius of a disc around the centre that holds the ground footprint at any yaw."""
        return self.size * math.sqrt(2.0) if self.kind == "cube" else self.size

    @property
    def area(self) -> float:
        if self.kind == "sphere":
            return 4 * math.pi * self.size ** 2
        if self.kind == "cube":
            return 24 * self.size ** 2
        return 2 * math.pi * self.size * self.height + math.pi * self.size ** 2


# (kind, material) of the clutter primitives, in placement (and random draw) order
CLUTTER_TABLE = (
    ("sphere", "red"), ("cube", "marble"), ("cylinder", "copper"), ("sphere", "glass"),
    ("cube", "green_plastic"), ("cylinder", "spots"), ("sphere", "aluminium"), ("cube", "ivory"),
    ("cylinder", "violet_plastic"), ("sphere", "spots"), ("cube", "chrome"), ("cylinder", "teal"),
)


def corridor_prims() -> list[Prim]:
    """The corridor's primitives, near to far, alternating sides."""
    return [Prim("sphere", np.array([-0.45, 1.4, 0.28]), 0.28, "red"),
            Prim("cube", np.array([0.5, 3.6, 0.26]), 0.26, "marble", yaw_deg=30.0),
            Prim("cylinder", np.array([-0.5, 6.0, 0.0]), 0.22, "spots", height=1.1),
            Prim("sphere", np.array([0.4, 8.6, 0.45]), 0.45, "copper"),
            Prim("cube", np.array([-0.3, 11.2, 0.4]), 0.4, "green_plastic", yaw_deg=15.0)]


def rect(u, v, centre) -> np.ndarray:
    """[4, 4] map from Mitsuba's rectangle [-1, 1]^2 x {0} (normal +z) to the rectangle centre
    + a u + b v (a, b in [-1, 1]); its normal is u x v, normalised."""
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = u, v, np.cross(u, v) / np.linalg.norm(np.cross(u, v)), centre
    return M


def corridor_rects() -> dict[str, np.ndarray]:
    """[4, 4] maps from Mitsuba's rectangle [-1, 1]^2 x {0} (normal +z) to the corridor's floor,
    side walls and end wall, each normal pointing into the corridor."""
    w, h, y0, y1 = CORRIDOR_HALF_WIDTH, CORRIDOR_HEIGHT, CORRIDOR_START, CORRIDOR_END
    half_len, mid = 0.5 * (y1 - y0), 0.5 * (y0 + y1)
    return {"floor": rect([w, 0, 0], [0, half_len, 0], [0, mid, 0]),
            "left": rect([0, half_len, 0], [0, 0, h / 2], [-w, mid, h / 2]),
            "right": rect([0, -half_len, 0], [0, 0, h / 2], [w, mid, h / 2]),
            "end": rect([w, 0, 0], [0, 0, h / 2], [0, y1, h / 2])}


def room_rects() -> dict[str, np.ndarray]:
    """The room's floor, ceiling and four walls as rectangle maps (see rect), each normal
    pointing into the room, and the lamp just below the ceiling, facing down."""
    a, h = ROOM_HALF, ROOM_HEIGHT
    return {"floor": rect([a, 0, 0], [0, a, 0], [0, 0, 0]),
            "ceiling": rect([0, a, 0], [a, 0, 0], [0, 0, h]),
            "west": rect([0, a, 0], [0, 0, h / 2], [-a, 0, h / 2]),
            "east": rect([0, -a, 0], [0, 0, h / 2], [a, 0, h / 2]),
            "south": rect([-a, 0, 0], [0, 0, h / 2], [0, -a, h / 2]),
            "north": rect([a, 0, 0], [0, 0, h / 2], [0, a, h / 2]),
            "lamp": rect([0, ROOM_LAMP_HALF, 0], [ROOM_LAMP_HALF, 0, 0], [0, 0, h - 0.01])}


def room_prims() -> list[Prim]:
    """The room's primitives, standing near its walls all round."""
    return [Prim("sphere", np.array([1.6, 0.9, 0.35]), 0.35, "red"),
            Prim("cube", np.array([-1.7, 1.2, 0.3]), 0.3, "ivory", yaw_deg=25.0),
            Prim("cylinder", np.array([0.8, -1.8, 0.0]), 0.25, "copper", height=0.9),
            Prim("sphere", np.array([-1.2, -1.6, 0.28]), 0.28, "aluminium"),
            Prim("cube", np.array([1.9, -1.0, 0.25]), 0.25, "green_plastic", yaw_deg=10.0),
            Prim("cylinder", np.array([-0.3, 1.9, 0.0]), 0.2, "teal", height=1.3),
            Prim("sphere", np.array([-2.0, -0.2, 0.22]), 0.22, "violet_plastic")]


def clutter_prims() -> list[Prim]:
    """The clutter layout: sizes and yaws from CLUTTER_SEED, positions by rejection sampling in
    a disc of radius 1.6 (well inside the ground) with gaps of at least 0.06 between footprints."""
    rng = np.random.default_rng(CLUTTER_SEED)
    prims: list[Prim] = []
    for kind, material in CLUTTER_TABLE:
        if kind == "sphere":
            p = Prim(kind, np.zeros(3), float(rng.uniform(0.12, 0.32)), material)
            lift = p.size
        elif kind == "cube":
            p = Prim(kind, np.zeros(3), float(rng.uniform(0.10, 0.24)), material,
                     yaw_deg=float(rng.uniform(0.0, 90.0)))
            lift = p.size
        else:
            p = Prim(kind, np.zeros(3), float(rng.uniform(0.08, 0.20)), material,
                     height=float(rng.uniform(0.25, 0.85)))
            lift = 0.0
        for _ in range(10000):
            r = (1.6 - p.footprint) * math.sqrt(rng.random())
            a = rng.uniform(0.0, 2 * math.pi)
            xy = np.array([r * math.cos(a), r * math.sin(a)])
            if all(np.linalg.norm(xy - q.centre[:2]) >= p.footprint + q.footprint + 0.06
                   for q in prims):
                break
        else:
            raise RuntimeError(f"cannot place clutter primitive {len(prims)}")
        p.centre = np.array([xy[0], xy[1], lift])
        prims.append(p)
    return prims


class SceneBuilder:
    """Builds Mitsuba scenes (one per time for the moving variant) from the analytic objects."""

    def __init__(self, mi, variant: str):
        self.mi = mi
        self.variant = variant
        self.ground_tex = mi.Bitmap(ground_texture())
        self.box_tex = mi.Bitmap(box_texture())
        self._cache: dict[float, object] = {}
        if variant in CLUTTER_CONTENT + ("corridor",) + ROOM_VARIANTS:
            # the sky's glow follows the sun: world azimuth = pi/2 - envmap longitude
            self.sky = mi.Bitmap(sky_texture(glow_phi=math.pi / 2 - CLUTTER_SUN[0]))
            self.clutter_tex = {
                "marble": mi.Bitmap(marble_texture(TEXTURE_SEED + 3, [0.12, 0.22, 0.55],
                                                   [0.85, 0.85, 0.8])),
                "spots": mi.Bitmap(spots_texture(TEXTURE_SEED + 4, [0.8, 0.62, 0.12],
                                                 [0.25, 0.12, 0.06])),
            }
        else:
            self.sky = mi.Bitmap(sky_texture())
        if variant in ("forward", "corridor") + ROOM_VARIANTS:
            self.wall_tex = mi.Bitmap(wall_texture())

    def ground_mesh(self, bsdf):
        """A flat disc as a triangle fan with planar uv (the texture spans the diameter)."""
        mi = self.mi
        seg = 128
        ang = np.arange(seg) * 2 * math.pi / seg
        xy = np.concatenate([[[0.0, 0.0]], GROUND_RADIUS * np.stack([np.cos(ang), np.sin(ang)], 1)])
        pos = np.concatenate([xy, np.zeros((seg + 1, 1))], 1)
        uv = xy / (2 * GROUND_RADIUS) + 0.5
        faces = np.stack([np.zeros(seg), 1 + np.arange(seg), 1 + (np.arange(seg) + 1) % seg], 1)
        mesh = mi.Mesh("ground", seg + 1, seg, has_vertex_normals=False,
                       has_vertex_texcoords=True)
        params = mi.traverse(mesh)
        # buffer types differ between the JIT (llvm) and scalar variants: reuse the mesh's own
        for key, arr in (("vertex_positions", pos.astype(np.float32)),
                         ("vertex_texcoords", uv.astype(np.float32)),
                         ("faces", faces.astype(np.uint32))):
            params[key] = type(params[key])(arr.ravel())
        params.update()
        mesh.set_bsdf(mi.load_dict(bsdf))
        return mesh

    def materials(self) -> dict:
        ground = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": self.ground_tex}}
        if self.variant in REFLECTIVE_MATERIALS:
            return {
                "ground": ground,
                "ball": {"type": "conductor", "material": "Ag"},  # a mirror ball
                "metal": {"type": "roughconductor", "material": "Cu", "alpha": 0.06},
                "box": {"type": "roughconductor", "material": "Al", "alpha": 0.12},
                "cyl": {"type": "plastic", "diffuse_reflectance": {"type": "rgb",
                                                                   "value": [0.1, 0.2, 0.6]}},
            }
        mats = {
            "ground": ground,
            "ball": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.12, 0.1]}},
            "metal": {"type": "roughconductor", "material": "Au", "alpha": 0.2},
            "box": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": self.box_tex}},
            "cyl": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.12, 0.3, 0.65]}},
        }
        if self.variant == "object-dark":  # a near-black matte ball and a black glossy plastic cylinder
            black = {"type": "rgb", "value": [0.01, 0.01, 0.01]}
            mats["ball"] = {"type": "diffuse", "reflectance": black}
            mats["cyl"] = {"type": "plastic", "diffuse_reflectance": black}
        return mats

    def clutter_materials(self) -> dict:
        def diffuse(rgb):
            return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}

        def textured(name):
            return {"type": "diffuse",
                    "reflectance": {"type": "bitmap", "bitmap": self.clutter_tex[name]}}

        def plastic(rgb):
            return {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": rgb}}

        return {
            "ground": {"type": "diffuse",
                       "reflectance": {"type": "bitmap", "bitmap": self.ground_tex}},
            "red": diffuse([0.75, 0.22, 0.08]),
            "ivory": diffuse([0.78, 0.76, 0.68]),
            "teal": diffuse([0.08, 0.42, 0.45]),
            "marble": textured("marble"),
            "spots": textured("spots"),
            "green_plastic": plastic([0.10, 0.50, 0.15]),
            "violet_plastic": plastic([0.32, 0.14, 0.58]),
            "copper": {"type": "roughconductor", "material": "Cu", "alpha": 0.3},
            "aluminium": {"type": "roughconductor", "material": "Al", "alpha": 0.12},
            "chrome": {"type": "roughconductor", "material": "Cr", "alpha": 0.45},
            "glass": {"type": "dielectric", "int_ior": 1.5},
        }

    def tiled(self, bitmap, repeat_u: float, repeat_v: float) -> dict:
        """A diffuse BSDF of ``bitmap`` repeated repeat_u x repeat_v times over a shape's uv."""
        return {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": bitmap,
                                                   "to_uv": self.mi.ScalarTransform4f().scale([repeat_u, repeat_v, 1.0])}}

    def corridor_dict(self) -> dict:
        """The corridor: floor, side and end walls, sky, a sun from CORRIDOR_SUN, primitives."""
        T = self.mi.ScalarTransform4f
        mat = self.clutter_materials()
        az, el = CORRIDOR_SUN
        sun_dir = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        length = CORRIDOR_END - CORRIDOR_START

        tex = self.tiled
        skins = {"floor": tex(self.ground_tex, 1.0, length / 4.0),
                 "left": tex(self.wall_tex, length / 4.0, 1.0), "right": tex(self.wall_tex, length / 4.0, 1.0),
                 "end": mat["marble"]}
        out = {"type": "scene", "integrator": {"type": "path", "max_depth": 6},
               "sky": {"type": "envmap", "bitmap": self.sky, "scale": 1.0, "to_world": T().rotate([1, 0, 0], 90)},
               "sun": {"type": "directional", "direction": sun_dir.tolist(),
                       "irradiance": {"type": "rgb", "value": [2.3, 2.0, 1.7]}}}
        for name, M in corridor_rects().items():
            out[name] = {"type": "rectangle", "to_world": T(M.tolist()), "bsdf": skins[name]}
        out.update(self.prims_dict(corridor_prims(), mat))
        return out

    def room_dict(self) -> dict:
        """The room: floor, ceiling, walls, the ceiling lamp (the only light) and primitives."""
        T = self.mi.ScalarTransform4f
        mat = self.clutter_materials()
        span = 2 * ROOM_HALF

        brick = self.tiled(self.wall_tex, span / 4.0, ROOM_HEIGHT / 2.0)
        skins = {"floor": self.tiled(self.ground_tex, 1.0, 1.0), "ceiling": mat["ivory"], "west": brick,
                 "east": brick, "south": mat["spots"], "north": mat["marble"]}
        out = {"type": "scene", "integrator": {"type": "path", "max_depth": 6}}
        for name, M in room_rects().items():
            if name == "lamp":
                out[name] = {"type": "rectangle", "to_world": T(M.tolist()),
                             "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(ROOM_LAMP_RADIANCE)}}}
            else:
                out[name] = {"type": "rectangle", "to_world": T(M.tolist()), "bsdf": skins[name]}
        out.update(self.prims_dict(room_prims(), mat))
        return out

    def prims_dict(self, prims: list[Prim], mat: dict) -> dict:
        """Mitsuba shapes of ``prims`` (cylinders with a top cap), keyed p00, p01, ..."""
        T = self.mi.ScalarTransform4f
        out = {}
        for i, p in enumerate(prims):
            bsdf = mat[p.material]
            if p.kind == "sphere":
                out[f"p{i:02d}"] = {"type": "sphere", "center": p.centre.tolist(),
                                    "radius": p.size, "bsdf": bsdf}
            elif p.kind == "cube":
                out[f"p{i:02d}"] = {"type": "cube", "bsdf": bsdf, "to_world": T(
                    cube_to_world(p.centre, p.size, p.yaw_deg).tolist())}
            else:
                top = p.centre + np.array([0.0, 0.0, p.height])
                out[f"p{i:02d}"] = {"type": "cylinder", "p0": p.centre.tolist(),
                                    "p1": top.tolist(), "radius": p.size, "bsdf": bsdf}
                out[f"p{i:02d}_cap"] = {"type": "disk", "bsdf": bsdf,
                                        "to_world": T().translate(top.tolist()).scale(
                                            [p.size, p.size, 1.0])}
        return out

    def clutter_dict(self) -> dict:
        """The clutter scene: ground, sky, a sun from CLUTTER_SUN and the primitives."""
        T = self.mi.ScalarTransform4f
        mat = self.clutter_materials()
        az, el = CLUTTER_SUN
        sun_dir = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                             math.sin(el)])  # light travels this way
        out = {
            "type": "scene",
            # a smooth dielectric needs 2 bounces more to show what lies behind it
            "integrator": {"type": "path", "max_depth": 8},
            "sky": {"type": "envmap", "bitmap": self.sky, "scale": 1.0,
                    "to_world": T().rotate([1, 0, 0], 90)},
            "sun": {"type": "directional", "direction": sun_dir.tolist(),
                    "irradiance": {"type": "rgb", "value": [2.3, 2.0, 1.7]}},
            "ground": self.ground_mesh(mat["ground"]),
        }
        out.update(self.prims_dict(clutter_prims(), mat))
        return out

    def scene(self, t: float = 0.0):
        key = t if self.variant in MOVING_VARIANTS else 0.0
        if key not in self._cache:
            if self.variant in MOVING_VARIANTS:
                self._cache.clear()  # one time at a time: keep memory flat
            self._cache[key] = self.mi.load_dict(self.scene_dict(key))
        return self._cache[key]

    def scene_dict(self, t: float) -> dict:
        if self.variant in CLUTTER_CONTENT:
            return self.clutter_dict()
        if self.variant == "corridor":
            return self.corridor_dict()
        if self.variant in ROOM_VARIANTS:
            return self.room_dict()
        mi = self.mi
        T = mi.ScalarTransform4f
        obj = objects_at(self.variant, t)
        mat = self.materials()
        top = obj.cyl_base + np.array([0, 0, obj.cyl_height])
        sun_dir = np.array([-math.cos(0.9), -math.sin(0.9), -1.1])  # light travels this way
        sun_dir = sun_dir / np.linalg.norm(sun_dir)
        lights = {
            # Mitsuba's envmap has +y up; rotate it so its zenith is the world's +z
            "sky": {"type": "envmap", "bitmap": self.sky, "scale": 1.0,
                    "to_world": T().rotate([1, 0, 0], 90)},
            "sun": {"type": "directional", "direction": sun_dir.tolist(),
                    "irradiance": {"type": "rgb", "value": [2.2, 2.0, 1.75]}},
        }
        if self.variant in REFLECTIVE_MATERIALS:
            # No delta sun here: a path tracer cannot find sun -> near-mirror -> diffuse paths
            # except by luck, and those caustic fireflies would need far more samples.
            lights = {"sky": {**lights["sky"], "scale": 1.3}}
        out = {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 8 if self.variant in REFLECTIVE_MATERIALS else 6,
                           # an object on a transparent backdrop: the sky lights it, no ray shows it
                           "hide_emitters": self.variant in ALPHA_VARIANTS},
            **lights,
            "ground": self.ground_mesh(mat["ground"]),
            "ball": {"type": "sphere", "center": obj.ball_centre.tolist(),
                     "radius": obj.ball_radius, "bsdf": mat["ball"]},
            "metal": {"type": "sphere", "center": obj.metal_centre.tolist(),
                      "radius": obj.metal_radius, "bsdf": mat["metal"]},
            "box": {"type": "cube", "to_world": T(box_to_world(obj).tolist()), "bsdf": mat["box"]},
            "cyl": {"type": "cylinder", "p0": obj.cyl_base.tolist(), "p1": top.tolist(),
                    "radius": obj.cyl_radius, "bsdf": mat["cyl"]},
            "cyl_cap": {"type": "disk", "bsdf": mat["cyl"],
                        "to_world": T().translate(top.tolist()).scale(
                            [obj.cyl_radius, obj.cyl_radius, 1.0])},
        }
        if self.variant in ALPHA_VARIANTS:  # floating, seen from below too: no ground, the cylinder closed
            del out["ground"]
            out["cyl_base_cap"] = {"type": "disk", "bsdf": mat["cyl"], "flip_normals": True,
                                   "to_world": T().translate(obj.cyl_base.tolist()).scale(
                                       [obj.cyl_radius, obj.cyl_radius, 1.0])}
        if self.variant == "thin":
            colour = {"post": [0.06, 0.06, 0.07], "wire": [0.85, 0.85, 0.8]}  # dark posts, pale wires
            for k, (p0, p1, r, kind) in enumerate(fence_segments()):
                out[f"fence_{k}"] = {"type": "cylinder", "p0": p0.tolist(), "p1": p1.tolist(), "radius": r,
                                     "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": colour[kind]}}}
        if self.variant == "forward":
            out["wall"] = {"type": "rectangle", "to_world": T(wall_to_world().tolist()),
                           "bsdf": {"type": "diffuse", "reflectance": {
                               "type": "bitmap", "bitmap": self.wall_tex}}}
        return out


def sensor_dict(mi, view: View, spp: int, alpha: bool = False) -> dict:
    """Mitsuba perspective sensor that images exactly like (K, w2c) in OpenCV axes."""
    K = view.K
    if abs(K[0, 0] - K[1, 1]) > 1e-9 * K[0, 0]:
        raise ValueError(f"Mitsuba's perspective sensor needs fx == fy, got {K[0, 0]}, {K[1, 1]}")
    fov_x = math.degrees(2 * math.atan(0.5 * view.width / K[0, 0]))
    # Mitsuba's principal point offsets are fractions of the film size from its centre, with
    # the opposite sign to a pixel shift (measured: +0.1 moves the image point 0.1*W left)
    off_x = -(K[0, 2] - 0.5 * view.width) / view.width
    off_y = -(K[1, 2] - 0.5 * view.height) / view.height
    to_world = view.c2w @ np.diag([-1.0, -1.0, 1.0, 1.0])  # Mitsuba: x left, y up, z forward
    return {
        "type": "perspective", "fov": fov_x, "fov_axis": "x",
        "principal_point_offset_x": off_x, "principal_point_offset_y": off_y,
        "near_clip": 0.01, "far_clip": 100.0,
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "sampler": {"type": "independent", "sample_count": spp},
        # box filter: each pixel is the plain average of the radiance over its square
        "film": {"type": "hdrfilm", "width": view.width, "height": view.height,
                 "pixel_format": "rgba" if alpha else "rgb", "rfilter": {"type": "box"}},
    }


def render_view(mi, scene, view: View, spp: int, seed: int, pass_spp: int = 256, alpha: bool = False) -> np.ndarray:
    """Linear radiance [H, W, 3] float32, the mean of passes of at most ``pass_spp`` samples;
    alpha: [H, W, 4], the coverage in the last channel and the colour premultiplied by it
    (a box filter averages a missed ray's zero)."""
    sensor = mi.load_dict(sensor_dict(mi, view, min(spp, pass_spp), alpha=alpha))
    acc, done, p = 0.0, 0, 0
    while done < spp:
        n = min(pass_spp, spp - done)
        img = mi.render(scene, sensor=sensor, spp=n, seed=(seed * 1000 + p) % 2 ** 32)
        acc = acc + np.array(img, dtype=np.float64) * n
        done += n
        p += 1
    return (acc / spp).astype(np.float32)


def to_srgb8(mi, linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB exactly as ``Bitmap.convert(..., UInt8, srgb_gamma=True)`` makes it."""
    bmp = mi.Bitmap(np.ascontiguousarray(linear, dtype=np.float32))
    out = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    return np.array(out, copy=True)


def to_srgba8(mi, linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB with straight (not premultiplied) alpha, as Blender writes NeRF-synthetic's
    PNGs, from a premultiplied linear [H, W, 4]: the colour divided by the coverage, then
    encoded; a pixel no ray hit is (0, 0, 0, 0)."""
    cover = np.clip(linear[..., 3:], 0.0, 1.0)
    straight = np.where(cover > 0, linear[..., :3] / np.maximum(cover, 1e-12), 0.0)
    a8 = np.round(cover * 255.0).astype(np.uint8)
    return np.concatenate([to_srgb8(mi, straight.astype(np.float32)), a8], axis=-1)


def write_png(mi, path: str, rgb8: np.ndarray) -> None:
    fmt = mi.Bitmap.PixelFormat.RGBA if rgb8.shape[-1] == 4 else mi.Bitmap.PixelFormat.RGB
    bmp = mi.Bitmap(np.ascontiguousarray(rgb8), fmt)
    bmp.set_srgb_gamma(True)
    bmp.write(path, quality=9)  # quality = zlib level for PNG


# ----------------------------------------------------------------------------- points
def sample_sphere(n, centre, radius, rng):
    d = rng.normal(size=(n, 3))
    return centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def sample_box(n, to_world, rng):
    """Uniform on the cube's six faces (all equal area), then mapped to the world."""
    face = rng.integers(0, 6, n)
    p = rng.uniform(-1, 1, (n, 3))
    axis, sign = face // 2, np.where(face % 2 == 0, -1.0, 1.0)
    p[np.arange(n), axis] = sign
    return p @ to_world[:3, :3].T + to_world[:3, 3]


def sample_cylinder(n, base, radius, height, rng):
    """Side and top cap, area-weighted."""
    side = 2 * math.pi * radius * height
    cap = math.pi * radius ** 2
    on_cap = rng.random(n) < cap / (side + cap)
    a = rng.uniform(0, 2 * math.pi, n)
    r = np.where(on_cap, radius * np.sqrt(rng.random(n)), radius)
    z = np.where(on_cap, height, rng.uniform(0, height, n))
    return base + np.stack([r * np.cos(a), r * np.sin(a), z], 1)


def sample_ground(n, rng):
    # stay inside the 128-gon that approximates the disc
    r = GROUND_RADIUS * math.cos(math.pi / 128) * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * math.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], 1)


def sample_rectangle(n, to_world, rng):
    """Uniform on Mitsuba's rectangle [-1, 1]^2 x {0} mapped to the world."""
    p = np.concatenate([rng.uniform(-1, 1, (n, 2)), np.zeros((n, 1))], 1)
    return p @ to_world[:3, :3].T + to_world[:3, 3]


def sample_prims(prims: list[Prim], n: int, rng) -> list[np.ndarray]:
    """n points on ``prims``, shared by area."""
    areas = np.array([p.area for p in prims])
    counts = np.floor(n * areas / areas.sum()).astype(int)
    parts = []
    for p, k in zip(prims, counts):
        if p.kind == "sphere":
            parts.append(sample_sphere(k, p.centre, p.size, rng))
        elif p.kind == "cube":
            parts.append(sample_box(k, cube_to_world(p.centre, p.size, p.yaw_deg), rng))
        else:
            parts.append(sample_cylinder(k, p.centre, p.size, p.height, rng))
    return parts


def sample_clutter(n, rng):
    """35% on the ground, the rest on the clutter primitives by area."""
    n_ground = int(0.35 * n)
    return np.concatenate([sample_ground(n_ground, rng)] + sample_prims(clutter_prims(), n - n_ground, rng))


def sample_corridor(n, rng):
    """25% on the floor, 30% on the side walls, 10% on the end wall, the rest on the primitives."""
    rects = corridor_rects()
    shares = {"floor": 0.25, "left": 0.15, "right": 0.15, "end": 0.10}
    parts = [sample_rectangle(int(f * n), rects[k], rng) for k, f in shares.items()]
    return np.concatenate(parts + sample_prims(corridor_prims(), n - sum(len(p) for p in parts), rng))


def sample_room(n, rng):
    """20% on the floor, 10% on the ceiling, 10% on each wall, the rest on the primitives."""
    rects = room_rects()
    shares = {"floor": 0.2, "ceiling": 0.1, "west": 0.1, "east": 0.1, "south": 0.1, "north": 0.1}
    parts = [sample_rectangle(int(f * n), rects[k], rng) for k, f in shares.items()]
    return np.concatenate(parts + sample_prims(room_prims(), n - sum(len(p) for p in parts), rng))


def sample_surface(variant: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Candidate surface points [n, 3]: 35% on the ground, the rest on objects by area.

    The moving variant keeps only the static ground: a 3D point on a moving object has no
    single position to put in a (static) COLMAP model. The forward variant first puts 30% on
    its back wall (most of the ground lies outside its views anyway); clutter has its own
    objects.
    """
    if variant in MOVING_VARIANTS:
        return sample_ground(n, rng)
    if variant in CLUTTER_CONTENT:
        return sample_clutter(n, rng)
    if variant == "corridor":
        return sample_corridor(n, rng)
    if variant in ROOM_VARIANTS:
        return sample_room(n, rng)
    n_wall = int(0.3 * n) if variant == "forward" else 0
    n_ground_share = 0.0 if variant in ALPHA_VARIANTS else 0.35  # floating objects: no ground
    n_fence = int(0.08 * n) if variant == "thin" else 0
    n = n - n_wall - n_fence
    obj = objects_at(variant, 0.0)
    cyl_area = 2 * math.pi * obj.cyl_radius * obj.cyl_height + math.pi * obj.cyl_radius ** 2
    areas = np.array([4 * math.pi * obj.ball_radius ** 2, 4 * math.pi * obj.metal_radius ** 2,
                      24 * obj.box_half ** 2, cyl_area])
    n_ground = int(n_ground_share * n)
    counts = np.floor((n - n_ground) * areas / areas.sum()).astype(int)
    parts = [sample_ground(n_ground, rng),
             sample_sphere(counts[0], obj.ball_centre, obj.ball_radius, rng),
             sample_sphere(counts[1], obj.metal_centre, obj.metal_radius, rng),
             sample_box(counts[2], box_to_world(obj), rng),
             sample_cylinder(counts[3], obj.cyl_base, obj.cyl_radius, obj.cyl_height, rng)]
    if n_wall:
        parts.append(sample_rectangle(n_wall, wall_to_world(), rng))
    if n_fence:
        parts.append(sample_segments(n_fence, fence_segments(), rng))
    return np.concatenate(parts)


def project(view: View, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [N, 2] (centres at +0.5) and camera depth [N]."""
    cam = pts @ view.w2c[:3, :3].T + view.w2c[:3, 3]
    z = cam[:, 2]
    uv = (cam[:, :2] / np.maximum(z, 1e-9)[:, None]) @ view.K[:2, :2].T + view.K[:2, 2]
    return uv, z


def visible(mi, scene, view: View, pts: np.ndarray) -> np.ndarray:
    """[N] bool: in the image, in front, and the first surface hit on the ray from the centre."""
    uv, z = project(view, pts)
    inside = (z > 0.01) & (uv[:, 0] >= 0) & (uv[:, 0] < view.width) \
        & (uv[:, 1] >= 0) & (uv[:, 1] < view.height)
    centre = view.c2w[:3, 3]
    d = pts - centre
    dist = np.linalg.norm(d, axis=1)
    d = d / dist[:, None]
    t_hit = first_hit(mi, scene, centre, d)
    return inside & (np.abs(t_hit - dist) < 1e-3 * dist + 1e-4)


def first_hit(mi, scene, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance [N] to the first surface along unit rays ``dirs`` [N, 3] from ``origin`` [3]."""
    if mi.variant().startswith("scalar"):  # no vectorised rays: one call per ray
        return np.array([scene.ray_intersect(mi.Ray3f(origin.tolist(), d.tolist())).t
                         for d in dirs], dtype=np.float64)
    o = np.broadcast_to(origin, dirs.shape)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, i].astype(np.float32)) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(dirs[:, i].astype(np.float32)) for i in range(3)]))
    return np.array(scene.ray_intersect(ray).t, dtype=np.float64)


def make_points(mi, builder, views, images, n_points, rng, max_track=0):
    """Surface points seen by >= 2 train views; colour = median of their pixel colours.

    Returns points [N, 3], colours [N, 3] uint8, the track mask [V_train, N] (at most
    ``max_track`` views per point when > 0) and the train views.
    """
    pts = sample_surface(builder.variant, int(n_points * 1.6) + 100, rng)
    train = [v for v in views if v.split == "train"]
    vis = np.stack([visible(mi, builder.scene(v.time), v, pts) for v in train])  # [V, N]
    keep = np.flatnonzero(vis.sum(0) >= 2)
    if len(keep) > n_points:
        keep = np.sort(rng.choice(keep, n_points, replace=False))
    pts, vis = pts[keep], vis[:, keep]
    samples = np.full((len(train), len(pts), 3), np.nan)
    for i, v in enumerate(train):
        uv, _ = project(v, pts[vis[i]])
        px = np.clip(np.floor(uv).astype(int), 0, [v.width - 1, v.height - 1])
        samples[i, vis[i]] = images[v.name][px[:, 1], px[:, 0]]
    colours = np.round(np.nanmedian(samples, axis=0)).astype(np.uint8)
    if max_track > 0:  # keep the model small: a spread-out subset of the views that see it
        for p in np.flatnonzero(vis.sum(0) > max_track):
            rows = np.flatnonzero(vis[:, p])
            vis[:, p] = False
            vis[rows[np.round(np.linspace(0, len(rows) - 1, max_track)).astype(int)], p] = True
    return pts, colours, vis, train


# ----------------------------------------------------------------------------- writers
def opengl_c2w(view: View) -> np.ndarray:
    """NeRF/Blender convention: camera x right, y up, z backward."""
    return view.c2w @ np.diag([1.0, -1.0, -1.0, 1.0])


def write_transforms(out: str, views: list[View], variant: str) -> None:
    v0 = views[0]
    K = v0.K
    header = {
        "camera_angle_x": 2 * math.atan(0.5 * v0.width / K[0, 0]),
        "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
        "w": v0.width, "h": v0.height,
    }
    splits = {"train": "train", "test": "test"}
    if variant == "moving":
        splits["val"] = "test"  # D-NeRF layout ships a val split; ours equals test
    for name, split in splits.items():
        frames = []
        for v in views:
            if v.split != split:
                continue
            f = {"file_path": v.name, "transform_matrix": opengl_c2w(v).tolist()}
            if variant == "moving":
                f["time"] = v.time
            frames.append(f)
        with open(os.path.join(out, f"transforms_{name}.json"), "w") as fh:
            json.dump({**header, "frames": frames}, fh, indent=2)


def write_poses_bounds(out: str, views: list[View]) -> None:
    """LLFF's poses_bounds.npy, one row per camera (cam00, cam01, ...): the camera-to-world axes
    in LLFF's order (down, right, back), its centre, (height, width, focal), near and far."""
    rows = []
    for cam in sorted({v.camera for v in views}):
        v = next(v for v in views if v.camera == cam)
        c2w = v.c2w  # OpenCV: x right, y down, z forward
        m = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3],
                      np.array([v.height, v.width, v.K[0, 0]], dtype=float)], axis=1)
        rows.append(np.concatenate([m.reshape(-1), [0.5 * MULTICAM_DIST, 2.0 * MULTICAM_DIST]]))
    np.save(os.path.join(out, "poses_bounds.npy"), np.asarray(rows, dtype=np.float64))


def write_colmap(out: str, views: list[View], pts, colours, vis, train) -> None:
    import pycolmap

    v0 = views[0]
    K = v0.K
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=v0.width, height=v0.height,
                          params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    train_row = {v.name: i for i, v in enumerate(train)}
    point_index = {}  # (image_id, point) -> point2D_idx
    for image_id, v in enumerate(views, start=1):
        if v.split == "train":
            seen = np.flatnonzero(vis[train_row[v.name]])
            uv, _ = project(v, pts[seen])
            point_index.update({(image_id, int(p)): k for k, p in enumerate(seen)})
        else:
            uv = np.zeros((0, 2))
        image = pycolmap.Image(name=v.name + ".png", keypoints=uv.astype(np.float64),
                               camera_id=1, image_id=image_id)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(v.w2c[:3, :3]), v.w2c[:3, 3])
        rec.add_image_with_trivial_frame(image, pose)
    id_of = {v.name: i for i, v in enumerate(views, start=1)}
    for p in range(len(pts)):
        track = pycolmap.Track()
        for row, v in enumerate(train):
            if vis[row, p]:
                track.add_element(id_of[v.name], point_index[(id_of[v.name], p)])
        rec.add_point3D(pts[p].astype(np.float64), track, colours[p])
    sparse = os.path.join(out, "sparse", "0")
    os.makedirs(sparse, exist_ok=True)
    rec.write_binary(sparse)


def write_ply(path: str, pts: np.ndarray, colours: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    rows = np.empty(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                     ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        rows[k] = pts[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        rows[k] = colours[:, i]
    PlyData([PlyElement.describe(rows, "vertex")]).write(path)


# ----------------------------------------------------------------------------- checks
def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def check_noise(mi, builder, views, spp, seed, n_views=3) -> float:
    """Render a few train views with two seeds; PSNR between the 8-bit sRGB results."""
    chosen = [v for v in views if v.split == "train"][:: max(1, len(views) // (n_views * 2))]
    chosen = chosen[:n_views]
    errs = []
    for v in chosen:
        a = to_srgb8(mi, render_view(mi, builder.scene(v.time), v, spp, seed)) / 255.0
        b = to_srgb8(mi, render_view(mi, builder.scene(v.time), v, spp, seed + 7919)) / 255.0
        errs.append(np.mean((a - b) ** 2))
        print(f"  noise {v.name}: PSNR {psnr(a, b):.2f} dB")
    total = 10 * math.log10(1.0 / float(np.mean(errs)))
    print(f"noise check: {len(chosen)} views at {spp} spp, seeds {seed} vs {seed + 7919}: "
          f"PSNR {total:.2f} dB (8-bit sRGB)")
    return total


def views_from_json(folder: str) -> list[View]:
    """Cameras as the NeRF-synthetic files state them (OpenGL c2w -> OpenCV w2c)."""
    views = []
    for split in ("train", "test"):
        with open(os.path.join(folder, f"transforms_{split}.json")) as fh:
            meta = json.load(fh)
        K = np.array([[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1]])
        for i, f in enumerate(meta["frames"]):
            c2w_cv = np.array(f["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])
            views.append(View(split, i, np.linalg.inv(c2w_cv), K, int(meta["w"]),
                              int(meta["h"]), float(f.get("time", 0.0))))
    return views


def check_projection(mi, folder: str, n_views: int = 8) -> float:
    """Render three coloured emissive markers through the written cameras and compare each
    marker's pixel centroid with its projection by the json's K, c2w and by COLMAP's model."""
    import pycolmap

    rec = pycolmap.Reconstruction(os.path.join(folder, "sparse", "0"))
    by_name = {img.name: img for img in rec.images.values()}
    colours = np.eye(3) * 20.0
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1}, **{
        f"m{i}": {"type": "sphere", "center": MARKERS[i].tolist(), "radius": MARKER_RADIUS,
                  "emitter": {"type": "area", "radiance": {"type": "rgb",
                                                           "value": colours[i].tolist()}}}
        for i in range(3)}})
    views = views_from_json(folder)
    chosen = []
    for split in ("train", "test"):  # half from each split, spread over the rig
        in_split = [v for v in views if v.split == split]
        chosen += in_split[:: max(1, len(in_split) // (n_views // 2))][: n_views // 2]
    worst = 0.0
    for v in chosen:
        img = render_view(mi, scene, v, 64, seed=0)
        uv, _ = project(v, MARKERS)
        col = by_name[v.name + ".png"]
        for i in range(3):
            w = img[..., i] * (img[..., i] > 0.5 * img[..., [j for j in range(3) if j != i]]
                               .max(-1))
            if w.sum() <= 0:
                print(f"  {v.name}: marker {i} not visible (expected at {uv[i].round(2)})")
                continue
            if min(uv[i][0], uv[i][1], v.width - uv[i][0], v.height - uv[i][1]) < BORDER_PX:
                # the image edge cuts the marker's blob, which pulls its centroid inwards
                print(f"  {v.name}: marker {i} at the image border (expected at {uv[i].round(2)}): not measured")
                continue
            ys, xs = np.mgrid[0:v.height, 0:v.width]
            seen = np.array([(w * (xs + 0.5)).sum(), (w * (ys + 0.5)).sum()]) / w.sum()
            col_uv = np.asarray(col.project_point(MARKERS[i]))
            err = max(np.abs(seen - uv[i]).max(), np.abs(seen - col_uv).max())
            worst = max(worst, err)
            print(f"  {v.name} marker {i}: rendered ({seen[0]:.2f}, {seen[1]:.2f})  json "
                  f"({uv[i][0]:.2f}, {uv[i][1]:.2f})  colmap ({col_uv[0]:.2f}, {col_uv[1]:.2f})")
    print(f"projection check: {len(chosen)} views x 3 markers, worst error {worst:.3f} px "
          f"({'PASS' if worst < 1.0 else 'FAIL'}, tolerance 1 px)")
    return worst


# ----------------------------------------------------------------------------- main
def pick_variant(mi, wanted: str | None) -> str:
    if wanted:
        mi.set_variant(wanted)
        return wanted
    import drjit as dr

    for name in ("llvm_ad_rgb", "scalar_rgb"):
        if name.startswith("llvm") and not dr.has_backend(dr.JitBackend.LLVM):
            print("libLLVM not found: falling back to scalar_rgb (slow); "
                  "install it, e.g. apt-get install -y libllvm19", file=sys.stderr)
            continue
        if name in mi.variants():
            try:
                mi.set_variant(name)
                return name
            except Exception as exc:  # e.g. libLLVM missing for the llvm variants
                print(f"mitsuba variant {name} unavailable: {exc}", file=sys.stderr)
    raise RuntimeError(f"no usable Mitsuba variant among {mi.variants()}")


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--out", required=True, help="output scene folder (required)")
    ap.add_argument("--variant", choices=VARIANTS, default="default",
                    help="scene variant (see the module docstring)")
    ap.add_argument("--n-train", type=int, default=None,
                    help="train views; None means 48, or 10 for --variant sparse, 32 for "
                         "the forward-facing variants (forward, forward-clutter, corridor); multicam: the "
                         "training cameras (8)")
    ap.add_argument("--n-test", type=int, default=None,
                    help="test views, interleaved with train; None means 12, or 8 for "
                         "the forward-facing variants; multicam: the frames each camera films (12)")
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels (arc: the width of its 4:3 images; aerial: the height of its 3:4 ones)")
    ap.add_argument("--spp", type=int, default=1024, help="samples per pixel")
    ap.add_argument("--seed", type=int, default=0, help="Monte Carlo and point-sampling seed")
    ap.add_argument("--n-points", type=int, default=4000, help="sparse surface points (max)")
    ap.add_argument("--max-track", type=int, default=8,
                    help="observations kept per COLMAP track (0 = every train view that sees "
                         "the point); bounds the size of images.bin")
    ap.add_argument("--mitsuba-variant", default=None,
                    help="force a Mitsuba variant (default: llvm_ad_rgb, else scalar_rgb)")
    ap.add_argument("--no-render", action="store_true",
                    help="write nothing; only run the requested checks (on --out for "
                         "--check-projection)")
    ap.add_argument("--check-noise", action="store_true",
                    help="render a few views twice with different seeds and print the PSNR")
    ap.add_argument("--check-projection", action="store_true",
                    help="render markers through the written cameras; print pixel errors")
    args = ap.parse_args(argv)
    if args.n_train is None:
        args.n_train = 32 if args.variant in FORWARD_VARIANTS else {"sparse": 10, "multicam": 8}.get(args.variant, 48)
    if args.n_test is None:
        args.n_test = 8 if args.variant in FORWARD_VARIANTS else {"multicam": MULTICAM_FRAMES}.get(args.variant, 12)
    if args.max_track == 1 or args.max_track < 0:
        ap.error(f"--max-track must be 0 (unlimited) or >= 2, got {args.max_track}")
    if args.variant == "multicam" and args.n_test < 2:
        ap.error(f"--variant multicam films --n-test frames per camera: at least 2, got {args.n_test}")
    if args.n_train < 2 or args.n_test < 0 or args.size < 8 or args.spp < 1:
        ap.error(f"bad sizes: n_train={args.n_train} n_test={args.n_test} size={args.size} "
                 f"spp={args.spp}")
    return args


def generate(mi, args, builder, views) -> None:
    out = args.out
    for v in views:
        os.makedirs(os.path.dirname(os.path.join(out, v.name)), exist_ok=True)
    images = {}
    t0 = time.time()
    for k, v in enumerate(views):
        alpha = args.variant in ALPHA_VARIANTS
        lin = render_view(mi, builder.scene(v.time), v, args.spp, args.seed * 100003 + k, alpha=alpha)
        png = to_srgba8(mi, lin) if alpha else to_srgb8(mi, lin)
        write_png(mi, os.path.join(out, v.name + ".png"), png)
        images[v.name] = png[..., :3]  # the points' colours (with alpha: the object's own, straight)
        print(f"  [{k + 1}/{len(views)}] {v.name}  {time.time() - t0:.1f}s", flush=True)
    if args.variant == "multicam":  # DyNeRF's layout: poses_bounds.npy, frames per camera, no points
        write_poses_bounds(out, views)
        print(f"wrote {len(views)} frames of {len({v.camera for v in views})} cameras to {out} "
              f"(render {time.time() - t0:.1f}s)")
        return
    rng = np.random.default_rng(args.seed)
    pts, colours, vis, train = make_points(mi, builder, views, images, args.n_points, rng,
                                           args.max_track)
    write_transforms(out, views, args.variant)
    write_colmap(out, views, pts, colours, vis, train)
    write_ply(os.path.join(out, "points3d.ply"), pts, colours)
    print(f"wrote {len(views)} views and {len(pts)} points to {out} "
          f"(render {time.time() - t0:.1f}s)")


def main(argv=None) -> int:
    args = parse_args(argv)
    import mitsuba as mi

    variant = pick_variant(mi, args.mitsuba_variant)
    print(f"mitsuba {mi.__version__}, variant {variant}")
    builder = SceneBuilder(mi, args.variant)
    views = make_views(args.variant, args.n_train, args.n_test, args.size)
    start = time.time()
    if not args.no_render:
        generate(mi, args, builder, views)
    if args.check_noise:
        check_noise(mi, builder, views, args.spp, args.seed)
    if args.check_projection:
        worst = check_projection(mi, args.out)
        if worst >= 1.0:
            return 1
    print(f"total {time.time() - start:.1f}s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
