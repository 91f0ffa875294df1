"""The command line the training examples share (examples/train_3dgs.py, train_4dgs.py,
train_scaffold.py; the gsplat, graphdeco and three-line loops use parts of it).

``common_args`` adds the flags every train_*.py script takes (preset, views, steps or budget,
stages, the MVGS options, output, seed, threads, device, rasterizer); ``config_from_args`` turns
them into an :class:`~mvgs_plugin.MVGSConfig`; ``launch`` runs a script in one process or on
every torchrun rank; ``train_and_evaluate`` and ``metrics_record`` train, evaluate and build the
``metrics.json`` record. Bad arguments end in an argparse usage error (exit code 2) naming the
flag and the value, before any scene is read or folder written; bad input found later (a scene
folder that holds no scene, an --out that cannot be a folder, a checkpoint that does not fit,
a --resolution-scale that leaves images too small) ends the same way, one line on stderr and
exit code 2, with the traceback only under --debug (:class:`UsageError`, :func:`launch`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Callable, Optional

import torch

from mvgs_plugin.adapters.gs3d import GS3DConfig
from mvgs_plugin.config import MAX_PRIMITIVES, MAX_SEED, PRESETS, MVGSConfig, Stage
from mvgs_plugin.controller import MVGS, ConfigMismatch, StageMismatch
from mvgs_plugin.data import load_scene
from mvgs_plugin.data.init import SHELL_RADIUS
from mvgs_plugin.data.triangulate import INIT_METHODS
from mvgs_plugin.distributed import DEFAULT_TIMEOUT, abort_on_error, init_from_env
from mvgs_plugin.io import atomic_write_text, load_checked
from mvgs_plugin.schedule import NoDensificationWarning, densifies_at_some_step, no_densification_message

__all__ = [
    "UsageError", "MIN_IMAGE_SIDE", "check_resolution", "repo_path", "without_machine_paths", "ROOT",
    "BUNDLED", "HelpFormatter", "common_args", "config_from_args", "launch", "train_and_evaluate",
    "metrics_record", "model_config", "write_json", "int_at_least", "float_above", "scene_folder",
    "parse_stages", "checkpoint_file", "out_folder", "check_device", "check_out", "rasterize_function",
    "save_test_renders", "load_scene", "scene_from_args", "MAX_STEPS", "MAX_INIT_POINTS",
    "background_colour", "scene_background",
]

# The bundled scene ships with the repository (examples/scenes/tabletop), not inside the package:
# beside the package in a checkout or editable install, else relative to the working directory
# (a wheel install running the examples from the repository's root).
_BESIDE_PACKAGE = Path(__file__).resolve().parents[1] / "examples" / "scenes" / "tabletop"
BUNDLED = _BESIDE_PACKAGE if _BESIDE_PACKAGE.is_dir() else Path("examples") / "scenes" / "tabletop"


ROOT = Path(__file__).resolve().parents[1]  # the repository, for a checkout or an editable install
# --resolution-scale may not leave an image's short side under this many pixels: below it a test
# view is a few pixels of average colour and its PSNR says nothing
MIN_IMAGE_SIDE = 16
# --background-points' default (mvgs_plugin.data.init.background_shell; docs/data.md#the-far-background):
# fixed before it was measured, never varied; 0 keeps 3DGS's init
BACKGROUND_POINTS = 2000
# Upper bounds of the run's length and of a generated init: a run of more steps, or a shell of
# more points, than any trainer runs or any scene holds is a typo (1e12 steps never ends; 1e11
# points fail an allocation deep in the init)
MAX_STEPS = 10**8
MAX_INIT_POINTS = 10**7


class UsageError(ValueError):
    """Bad input a user can fix (a flag's value, a scene folder, a checkpoint): launch() prints
    it as one line, "prog: error: message", and exits with code 2 (argparse's way), unless
    --debug asks for the traceback."""


def repo_path(path) -> str:
    """A path as benchmark records keep it: relative to the repository when inside it, else
    '.../' and its last two parts (never the machine's absolute path)."""
    p = Path(path)
    if not p.is_absolute():
        return p.as_posix()
    try:
        return p.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return ".../" + "/".join(p.parts[-2:] if len(p.parts) > 3 else p.parts[-1:])


def without_machine_paths(text: str) -> str:
    """``text`` with every absolute path inside this repository (wherever it was cloned) or under
    /work, /tmp, /home or /root replaced by :func:`repo_path` (benchmark records that name other
    checkouts or scene folders)."""
    import re

    roots = f"{re.escape(ROOT.as_posix())}|/(?:work|tmp|home|root)"
    return re.sub(rf"(?<![\w.])(?:{roots})(?:/[\w./-]*[\w-])?(?![\w/])", lambda m: repo_path(m.group(0)), text)


def check_resolution(scene, scale: int) -> None:
    """Refuse a --resolution-scale that leaves any image's short side under MIN_IMAGE_SIDE."""
    from mvgs_plugin.camera import scaled_size

    for cam in scene.cameras:
        w, h = scaled_size(cam.width, cam.height, scale)
        if min(w, h) < MIN_IMAGE_SIDE:
            most = max(1, min(cam.width, cam.height) // MIN_IMAGE_SIDE)
            raise UsageError(f"--resolution-scale {scale} makes the {cam.width}x{cam.height} images {w}x{h}; the "
                             f"short side must stay >= {MIN_IMAGE_SIDE} px (use at most {most})")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps a script's docstring as written and ends every option's help with its default
    (unless the help already states it, or the option is an on/off switch)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (action.default is argparse.SUPPRESS or "default" in text or not action.option_strings
                or action.required or isinstance(action.default, bool)):
            return text
        return f"{text} (default: %(default)s)"


def scene_folder(text: str) -> Path:
    """An argparse type for --data: an existing folder (what is in it the loaders check)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text!r} does not exist (expected a scene folder)")
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a file, expected a scene folder")
    return path


def scene_from_args(args, dynamic_model: bool = False):
    """The scene of --data, with initial points by --init (cached in --init-cache, else OUT/init)
    when it has no point file; the init's threads follow --threads. A scene whose frames carry
    times given to a static model (dynamic_model False) is trained, with a note that says so."""
    cache = args.init_cache if args.init_cache is not None else Path(args.out) / "init"
    try:
        scene = load_scene(args.data, init=args.init, init_seed=args.seed, init_cache=cache, threads=args.threads,
                           background_points=args.background_points, background=scene_background(args),
                           background_radius=getattr(args, "background_radius", None),
                           backdrop_drawn=getattr(args, "background", "auto") != "random",
                           images=getattr(args, "images", None))
    except (ValueError, OSError) as err:  # the folder's content: a usage error, not a bug
        if args.init_cache is not None and str(args.init_cache) in str(err):
            raise UsageError(f"--init-cache {args.init_cache}: {err}") from err
        if getattr(args, "images", None) is not None and f"images={args.images!r}" in str(err):
            raise UsageError(f"--images {args.images}: {err}") from err
        raise UsageError(f"--data: {err}" if str(args.data) in str(err) else f"--data {args.data}: {err}") from err
    check_resolution(scene, args.resolution_scale)
    check_renders_spare_images(Path(args.out), scene)
    if scene.background_origin.startswith("the training images have no transparent pixel"):  # found, not told: say so
        print(f"{Path(sys.argv[0]).name}: note: background: {scene.background_origin}: the Gaussians are trained "
              "in front of it (--background to choose another)", file=sys.stderr)
    timed = sum(c.time is not None for c in scene.train_cameras)
    if timed and not dynamic_model:
        print(f"{Path(sys.argv[0]).name}: note: {timed} of the {len(scene.train_cameras)} training frames of --data "
              f"{args.data} carry a time (a dynamic scene); this script trains one static model for all of them: "
              "examples/train_4dgs.py trains a deformation over time", file=sys.stderr)
    return scene


def check_renders_spare_images(out: Path, scene) -> None:
    """Refuse an --out whose test renders (OUT/test/<view>.png, render_file_names) would
    replace one of the scene's images, before any work: --out set to a NeRF-layout scene's own
    folder puts every render on its ground-truth test image, and the next run would score its
    own renders."""
    cams = list(scene.test_cameras)
    if not cams:
        return
    images = {}
    for cam in list(scene.train_cameras) + cams:
        src = scene.image_file(cam)
        if src is not None:
            images[src.resolve()] = src
    folder = (out / "test").resolve()
    for name in render_file_names([c.name for c in cams]):
        hit = images.get(folder / name)
        if hit is not None:
            raise UsageError(f"--out {out}: the test render {out / 'test' / name} would replace the scene's image "
                             f"{hit} (--out is the scene's own folder?); choose an output folder outside the scene's")


def model_config(config: MVGSConfig, seed: int, max_gaussians=None, rasterize=None,
                 world_size_rule=None, means_lr_rule=None, opacity_reset_scope=None,
                 budget_growth_order=None, beside_cull=None) -> GS3DConfig:
    """The 3DGS model's own schedules (means learning-rate decay over 30k steps, SH degree +1
    every 1000) compressed with the run, as the controller's densification clock is; rasterize:
    the rasterizer (None: GS3DConfig's, the reference one); max_gaussians: the model's own
    growth cap (the CLI's --max-gaussians is MVGSConfig.max_gaussians, the run's budget, instead);
    world_size_rule, means_lr_rule, opacity_reset_scope, budget_growth_order, beside_cull:
    GS3DConfig's (None: its default)."""
    extra = {} if rasterize is None else {"rasterize": rasterize}
    for name, value in (("world_size_rule", world_size_rule), ("means_lr_rule", means_lr_rule),
                        ("opacity_reset_scope", opacity_reset_scope), ("budget_growth_order", budget_growth_order),
                        ("beside_cull", beside_cull)):
        if value is not None:
            extra[name] = value
    return GS3DConfig.for_run(config, max_gaussians=max_gaussians, seed=seed, **extra)


class DensifyTally:
    """What densification did over a run's steps, from each StepInfo (metrics.json
    "densification"; benchmarks/bench_equal_compute.py): calls, cloned, split, pruned, faint (the
    prune_faint cut's rows), budget_cut (the rows a Gaussian budget cut before a step rendered: a
    loaded model above it, at the first step) and the largest count a step ended with (`count`,
    the model before the first step, only until a step has run: a budget's first cut comes at the
    first step, so the points loaded above the budget are not a count the run held)."""

    def __init__(self, count: int):
        self.totals = {"calls": 0, "cloned": 0, "split": 0, "pruned": 0, "faint": 0, "budget_cut": 0,
                       "peak_primitives": count}
        self._stepped = False

    def resume(self, record: dict) -> None:
        """Continue the totals a checkpoint recorded (MVGS.record) over the steps before it; a
        checkpoint written before they were recorded leaves them counting from the resume."""
        for key, value in record.items():
            if key in self.totals:
                self.totals[key] = value
                self._stepped = True

    def add(self, info) -> None:
        t = self.totals
        t["peak_primitives"] = max(t["peak_primitives"], info.num_primitives) if self._stepped else info.num_primitives
        self._stepped = True
        t["budget_cut"] += int(getattr(info, "budget_cut", 0))
        if info.densify is not None:
            t["calls"] += 1
            for key in ("cloned", "split", "pruned"):
                t[key] += getattr(info.densify, key)
            t["faint"] += int(info.densify.extra.get("faint", 0))


MODEL_FLAGS = ("world_size_rule", "means_lr_rule", "opacity_reset_scope", "budget_growth_order", "beside_cull")


def model_config_from_args(config: MVGSConfig, args, rasterize=None) -> GS3DConfig:
    """model_config with the model flags of world_size_arg's parser (MODEL_FLAGS) as given on the
    command line (the 3DGS and 4DGS examples, benchmarks/bench_equal_compute.py)."""
    return model_config(config, args.seed, rasterize=rasterize,
                        **{name: getattr(args, name, None) for name in MODEL_FLAGS})


def write_json(path: Path, data: dict) -> None:
    """Atomic JSON write: a crash never leaves a half-written metrics file."""
    atomic_write_text(path, json.dumps(data, indent=2))


def int_at_least(low: int, high: Optional[int] = None) -> Callable[[str], int]:
    """An argparse type: an int >= low (and <= high when given; argparse turns the error into a
    usage message)."""
    want = f"an int >= {low}" if high is None else f"an int in {low}..{high}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected {want}, got {value}")
        return value
    return parse


def float_above(low: float, inclusive: bool = False, high: float = math.inf) -> Callable[[str], float]:
    """An argparse type: a finite float > low (>= low when inclusive) and <= high."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value >= low if inclusive else value > low) and value <= high):
            bound = "" if high == math.inf else f" and <= {high:g}"
            raise argparse.ArgumentTypeError(f"expected a finite number {'>=' if inclusive else '>'} {low:g}{bound}, "
                                             f"got {text!r}")
        return value
    return parse


def background_colour(text: str):
    """An argparse type for --background: "auto", "black", "white", "random" or "R,G,B" (floats in [0, 1])."""
    named = {"auto": "auto", "random": "random", "black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
    if text.strip().lower() in named:
        return named[text.strip().lower()]
    parts = text.split(",")
    try:
        rgb = tuple(float(p) for p in parts)
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in rgb):
        raise argparse.ArgumentTypeError(f"expected auto, black, white, random or R,G,B with each in [0, 1] "
                                         f"(e.g. 0.5,0.5,0.5), got {text!r}")
    return rgb


def scene_background(args):
    """The colour --background asks the scene's RGBA images to be composited on: "random" trains
    in front of a new colour every view and step (MVGSConfig.background) and composites on the
    scene's own, as "auto" does."""
    bg = getattr(args, "background", "auto")
    return "auto" if bg == "random" else bg


def check_device(args) -> None:
    """Refuse --device / --rasterizer choices the machine it runs on cannot run, before any work."""
    if args.device == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device cuda: torch {torch.__version__} sees no CUDA device here "
                         "(torch.cuda.is_available() is False); use --device cpu")
    if args.rasterizer == "gsplat":
        if args.device != "cuda":
            raise ValueError("--rasterizer gsplat needs --device cuda (gsplat's rasterization runs on CUDA); on the "
                             "CPU use --rasterizer reference, which has the same call shape")
        import importlib.util

        if importlib.util.find_spec("gsplat") is None:
            raise ValueError("--rasterizer gsplat: gsplat is not installed; pip install gsplat")


def rasterize_function(args):
    """The rasterizer --rasterizer asks for (GS3DConfig.rasterize)."""
    if args.rasterizer == "gsplat":
        from gsplat import rasterization as gsplat_rasterization

        return gsplat_rasterization
    from mvgs_plugin.reference_renderer import rasterization

    return rasterization


OUTPUT_FILES = ("metrics.json", "checkpoint.pt", "point_cloud.ply", "deformation.pt", "anchors.pt")  # the examples' files in OUT


def check_out(out: Path) -> None:
    """Refuse an output folder that cannot be one, before any work: an existing file, a path
    under a file, or a folder (or its nearest existing parent) this process cannot write."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is an existing file, expected a folder (new or existing)")
    probe = out
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise ValueError(f"--out {out}: {probe} is a file, so the folder cannot be created under it")
    if probe.exists() and not os.access(probe, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out}: {probe} is not writable by this user")
    if probe.is_dir():  # permissions are not the whole answer (root under /sys, a read-only mount): try it
        try:
            os.rmdir(tempfile.mkdtemp(prefix=".mvgs-out-check-", dir=probe))
        except OSError as err:
            raise ValueError(f"--out {out}: a folder cannot be made in {probe} ({err.strerror or err})") from None
    if out.is_dir():  # a reused folder: what a run writes there must be able to take its place
        if (out / "test").exists() and not (out / "test").is_dir():
            raise ValueError(f"--out {out}: {out / 'test'} is a file, where the test renders' folder goes")
        for name in OUTPUT_FILES:
            if (out / name).is_dir():
                raise ValueError(f"--out {out}: {out / name} is a folder, where the run writes its {name}")


def world_size_arg(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """--world-size-rule, --means-lr-rule, --opacity-reset-scope and --budget-growth-order, for the examples whose model is 3DGS's
    (train_3dgs, train_4dgs; Scaffold-GS prunes anchors by opacity only and places its neural
    Gaussians by offsets from fixed anchors)."""
    ap.add_argument("--world-size-rule", choices=("extent", "distance"), default=None,
                    help="size pruning (after the first opacity reset): distance prunes Gaussians larger than 0.1 x "
                         "the scene extent within the extent of the rig's centre and 0.1 x their distance from it "
                         "beyond, so the far background keeps its large Gaussians; extent is 3DGS's rule, 0.1 x the "
                         "extent everywhere (default: GS3DConfig's, distance)")
    ap.add_argument("--means-lr-rule", choices=("auto", "extent", "distance", "disparity"), default=None,
                    help="position steps: distance scales each Gaussian's step by f = max(extent, d) / extent, d its "
                         "distance from the rig's centre, so far content moves by the same angle as near; disparity "
                         "scales the part along the line of sight by f^2 (uniform in 1/d); extent is 3DGS's rule, "
                         "the same step everywhere; auto is disparity on a forward-facing rig, extent elsewhere "
                         "(default: GS3DConfig's, auto)")
    ap.add_argument("--opacity-reset-scope", choices=("all", "inside"), default=None,
                    help="which opacities a reset caps: inside leaves the far background (3/4 of the initial model's "
                         "farthest distance from the rig's centre or more: beyond 1.5 rig radii with the background "
                         "shell) as it is, since most of it is seen by one training view and does not recover before "
                         "the next reset; all is 3DGS's rule (default: GS3DConfig's, inside)")
    ap.add_argument("--budget-growth-order", choices=("auto", "inside-first", "score"), default=None,
                    help="under a Gaussian budget (--max-gaussians, --pixels-per-gaussian), which candidates grow "
                         "first: inside-first grows every one inside the line --opacity-reset-scope uses before any "
                         "of the far background beyond it, each group by score; score ranks them all by score "
                         "(--densify-rank); auto is inside-first on a rig that surrounds the scene, score on a "
                         "forward-facing one (default: GS3DConfig's, auto)")
    ap.add_argument("--beside-cull", type=float_above(0, inclusive=True), default=None, metavar="K",
                    help="0: off; K > 0: a Gaussian whose centre is beside a view's camera (outside the image widened "
                         "by 0.3 tan(fov/2) per side) and nearer than K x its largest scale is not drawn in that view, "
                         "where its splat would smear over the frame (GS3DConfig.beside_cull) (default: 0)")
    return ap


def late_views_arg(ap: argparse.ArgumentParser, default_views: int) -> argparse.ArgumentParser:
    """--late-views M (MVGSConfig.with_late_views): the work the pyramid saves per step spent as
    M-view steps at the end of the run. `default_views` is the example's M for the pyramid
    presets (default, compact) when none of --stages, --views, --budget is given (help text);
    resolve_late_views(args, default_views) applies it after parsing."""
    ap.add_argument("--late-views", type=int_at_least(1), default=None,
                    help="the work the pyramid's coarse steps save, spent as M-view full-resolution steps at the end, "
                         f"so a run of N steps does the work of N baseline steps; 1 turns it off (default: {default_views} "
                         "with --preset default or compact and none of --stages, --views, --budget, else 1)")
    return ap


def resolve_late_views(args, default_views: int) -> argparse.Namespace:
    """args with --late-views resolved: its value, else `default_views` for the pyramid presets
    when the user gave none of --stages, --views, --budget (at equal work the pyramid's saving
    already buys steps), else 1."""
    args.late_views_given = args.late_views is not None  # config_from_args says when a given value adds nothing
    if args.late_views is None:
        plain = args.preset in ("default", "compact") and not args.stages and args.views is None and args.budget is None
        args.late_views = default_views if plain else 1
    return args


def budget_scope_args(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """--budget-rigs and --budget-views, what a budget from the data (--pixels-per-gaussian)
    counts: the example scripts' and gsplat's loop's (examples/gsplat_loop/common.py) flags."""
    ap.add_argument("--budget-rigs", choices=["all", "round"], default=None,
                    help="with --pixels-per-gaussian: the rigs it budgets: all, or round (only a rig round the scene, "
                         "not a forward-facing one nor one that looks outward) (MVGSConfig.budget_rigs; compact: "
                         "round; default: all)")
    ap.add_argument("--budget-views", type=int_at_least(0, MAX_PRIMITIVES), default=None, metavar="V",
                    help="with --pixels-per-gaussian: count the pixels of V views of the training views' mean size, "
                         "however many the rig has; 0: every view (MVGSConfig.budget_views; compact: 48, its "
                         "runs saved before 2026-11-28 resume with 0; default: every view)")
    return ap


def common_args(ap: argparse.ArgumentParser, out: str) -> argparse.ArgumentParser:
    """The CLI contract every train_*.py example shares (each adds --data and its own options)."""
    ap.add_argument("--preset", choices=PRESETS, default="default",
                    help="the recipe (default: default). default: cost-aware (coarse-to-fine, one view per step); multiview: M views at every "
                         "pyramid level with MVAD and CRD (wins at equal steps); compact: default with a budget of "
                         "48 mean training views' pixels / 213 primitives (3692 at 128 px, whatever the number of "
                         "views; Gaussians; anchors for Scaffold-GS; none on a forward-facing rig nor on one that looks "
                         "outward); paper: the released code; "
                         "baseline: the plain model (3DGS, Scaffold-GS or 4DGS: one view per step at full "
                         "resolution, no MVGS rule)")
    ap.add_argument("--views", type=int_at_least(1), default=None, help="views per step M at full resolution (coarser stages scale; default: as the preset)")
    ap.add_argument("--steps", type=int_at_least(1, MAX_STEPS), default=3000, help="total steps (the preset's schedule is rescaled to it)")
    ap.add_argument("--budget", type=float_above(0, high=MAX_STEPS), default=None,
                    help="train on a budget of work instead of --steps: full-resolution view renders (a baseline "
                         "step is 1; a view at pyramid factor f counts A + (1 - A) / f, --view-cost); every schedule runs "
                         "on it (default: not set, --steps counts)")
    ap.add_argument("--view-cost", type=float_above(0, inclusive=True, high=1.0), default=None, metavar="A",
                    help="the cost model of the budget clock and of the default's stage shares: a view at pyramid "
                         "factor f costs A + (1 - A) / f of a full-resolution one (MVGSConfig.view_cost = (A, 1 - A)); "
                         "measure your model's with benchmarks/bench_view_cost.py (default: 0.1, the reference renderer's per-view "
                         "cost)")
    ap.add_argument("--resolution-scale", type=int_at_least(1), default=1, help="train and evaluate at 1/s resolution")
    ap.add_argument("--init", choices=list(INIT_METHODS), default="triangulate",
                    help="initial points of a scene without a point file: triangulate (pycolmap from the training "
                         "views at their poses, the rest filled with photo-consistent points; falls back to random "
                         "with the reason when too few tracks are found), random (the 3DGS cube when the cameras "
                         "surround the scene, inside the views' silhouettes when the images show an object on a "
                         "backdrop, the training frusta when they face one way), frusta or cube")
    ap.add_argument("--background-points", type=int_at_least(0, MAX_INIT_POINTS), default=BACKGROUND_POINTS, metavar="N",
                    help="N more initial points on a sphere twice the rig's radius for the far background (sky, "
                         "horizon) when the cameras surround the scene, coloured by the views that see them; 0: none "
                         "(3DGS's init). A forward-facing rig gets none, nor does an object on a backdrop (every "
                         "training image's border the background colour)")
    ap.add_argument("--background-radius", type=float_above(1.0), default=None, metavar="R",
                    help="the radius of --background-points' sphere, in rig radii (the largest distance of a "
                         f"training camera from the rig's centre) (default: {SHELL_RADIUS:g})")
    ap.add_argument("--background", type=background_colour, default="auto", metavar="auto|black|white|random|R,G,B",
                    help="the colour behind the Gaussians, and the one RGBA images are composited on. auto: a "
                         "NeRF-style scene's RGBA images on white; images without alpha on the colour their borders "
                         "show when it is one colour (they were composited on it), else white; a COLMAP scene black "
                         "(alpha dropped). random (3DGS's --random_background): the renders of a training step in "
                         "front of a new colour every view and step, so what the model leaves transparent is penalised "
                         "instead of showing a fixed colour that matches; the images and the test renders keep "
                         "auto's. Default: auto")
    ap.add_argument("--images", type=str, default=None, metavar="DIR",
                    help="a COLMAP scene's image folder, relative to --data: a copy downscaled by one factor, such "
                         "as Mip-NeRF 360's images_4, scales the cameras to it (default: --data/images when there is "
                         "one, else --data); for a nerfstudio transforms.json, the downscaled copy of its images/ "
                         "(images_2, images_4, ...) read in its place; for LLFF still images, the copy of images/ "
                         "(images_4); for a HyperNeRF capture, rgb/1x, rgb/4x, ... (default rgb/2x, as 4DGS)")
    ap.add_argument("--init-cache", type=Path, default=None, metavar="DIR",
                    help="folder the triangulation (features and points) is kept in and read back from by the next "
                         "run (default: OUT/init; the scene folder is never written unless DIR is in it)")
    ap.add_argument("--stages", type=parse_stages, default=None, metavar="F:M:STEPS,...",
                    help="replace the preset's stage plan: pyramid factor, views per step and recipe steps per "
                         "stage, e.g. 8:16:1000,4:8:1000,2:4:1000,1:1:30000 (then rescaled by --steps or --budget; default: "
                         "the preset's plan)")
    ap.add_argument("--warmup-work-cap", type=float_above(0, inclusive=True), default=None, metavar="W",
                    help="the most work (full-resolution view renders) the coarser pyramid levels get in a run; "
                         "beyond it their share goes to full resolution (MVGSConfig.warmup_work_cap; 0: no cap; "
                         "default: as the preset, 1000 for default, none for the others and with --stages)")
    ap.add_argument("--mvad", action=argparse.BooleanOptionalAction, default=None,
                    help="multi-view augmented densification on/off (default: as the preset)")
    ap.add_argument("--crd", action=argparse.BooleanOptionalAction, default=None,
                    help="cross-ray densification on/off (default: as the preset)")
    ap.add_argument("--threshold-width", type=float_above(0, inclusive=True), default=None,
                    help="image width in pixels the gradient threshold is meant for; it is scaled to the "
                         "rendered width (0: never scaled, as 3DGS; default: as the preset, 800 for default)")
    ap.add_argument("--forward-rig", choices=["pyramid", "finest"], default=None,
                    help="on a forward-facing rig (nearly parallel optical axes): keep the stage plan (pyramid) "
                         "or train at full resolution only (finest) (default: as the preset, finest for default)")
    ap.add_argument("--views-scaling", choices=["none", "sqrt"], default=None,
                    help="optimizer for M-view steps: none (the summed loss, single-view rates) or sqrt (Grendel-GS: "
                         "learning rates x sqrt(M), Adam betas ** M, eps / sqrt(M)) (default: as the preset, none)")
    ap.add_argument("--max-views-fraction", type=float_above(0, high=1.0), default=None,
                    help="sparse-view guard: cap every step's views at this fraction of the training views "
                         "(at least 1; default: no cap)")
    ap.add_argument("--stage-growth", type=float_above(1), default=None,
                    help="cap densification within a stage at this multiple of the count the stage began with "
                         "(default: no cap)")
    ap.add_argument("--max-gaussians", type=int_at_least(1, MAX_PRIMITIVES), default=None,
                    help="budget of primitives (Gaussians; anchors for Scaffold-GS): the run never holds more; "
                         "a larger initial model is cut to it by keep score, growth follows a schedule that "
                         "reaches it when densification ends (MVGSConfig.max_gaussians; default: no budget)")
    ap.add_argument("--pixels-per-gaussian", type=float_above(0), default=None, metavar="P",
                    help="budget from the data: --max-gaussians = the training views' pixels / P (3DGS ends near "
                         "70-210 on its benchmarks; MVGSConfig.pixels_per_gaussian; ignored with --max-gaussians)")
    budget_scope_args(ap)
    ap.add_argument("--densify-rank", choices=["consistency", "gradient"], default=None,
                    help="score that picks growth candidates when a budget binds: consistency (the gradient times "
                         "how evenly the views share it) or gradient (3DGS) (default: consistency)")
    ap.add_argument("--budget-swap", type=float_above(0, inclusive=True, high=0.999999), default=None, metavar="S",
                    help="share of the budget a densification call may swap while it binds: the lowest keep scores "
                         "make way for the best growth candidates (MVGSConfig.budget_swap) (default: 0, off)")
    ap.add_argument("--prune-faint", type=float_above(0, inclusive=True, high=0.99), default=None, metavar="S",
                    help="0: off; S in (0, 1): once densification has ended, remove in one cut the Gaussians with the "
                         "least blend weight (alpha x transmittance) per pixel they are blended at, as many as carry S "
                         "of all the weight the training views blend (MVGSConfig.prune_faint) (default: the preset's: 0.01 with "
                         "default, 0 with the others and in train_4dgs.py)")
    ap.add_argument("--budget-initial-share", type=float_above(0, high=1.0), default=None, metavar="S",
                    help="with a budget, cut a larger initial model to this share of it before the first step, so "
                         "the rest is grown where the views ask (MVGSConfig.budget_initial_share) (default: 1)")
    ap.add_argument("--budget-size-pruning", action="store_true", default=None,
                    help="with a budget, still prune Gaussians by size after the first opacity reset, as 3DGS "
                         "(MVGSConfig.budget_size_pruning; default: off with a budget, on without)")
    ap.add_argument("--coarse-opacity-reset", action=argparse.BooleanOptionalAction, default=None,
                    help="periodic opacity resets also at the coarser pyramid levels, or at the finest only "
                         "(MVGSConfig.coarse_opacity_reset; default: as the preset, finest only for default)")
    ap.add_argument("--lambda-dssim", type=float_above(0, inclusive=True, high=1.0), default=None, metavar="W",
                    help="weight of the SSIM term in the loss (1 - W) L1 + W (1 - SSIM) (MVGSConfig.lambda_dssim; "
                         "default: 0.2 as 3DGS and Scaffold-GS; train_4dgs.py: 0, 4DGS's L1 alone)")
    ap.add_argument("--min-densify-per-reset", type=int_at_least(1), default=None, metavar="K",
                    help="a compressed schedule resets opacities no sooner than K densification calls apart "
                         "(MVGSConfig.min_densify_per_reset; default: as the preset)")
    ap.add_argument("--out", type=out_folder, default=Path(out),
                    help="output folder (created; metrics.json, test/*.png and the model are written there)")
    ap.add_argument("--seed", type=int_at_least(0, MAX_SEED), default=0,
                    help="seed of the view order, the model's random draws and torch")
    ap.add_argument("--threads", type=int_at_least(1), default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="where the model trains (cuda: the model, renders and optimizer on the GPU)")
    ap.add_argument("--rasterizer", choices=["reference", "gsplat"], default="reference",
                    help="reference: this package's renderer (CPU or CUDA tensors); gsplat: gsplat's CUDA "
                         "rasterization (needs --device cuda and gsplat installed)")
    ap.add_argument("--dist-timeout", type=float_above(0), default=DEFAULT_TIMEOUT,
                    help="under torchrun: seconds a rank waits for the others before stopping with an error")
    ap.add_argument("--checkpoint", action="store_true", help="also write OUT/checkpoint.pt after training")
    ap.add_argument("--checkpoint-every", type=int_at_least(1), default=None, metavar="K",
                    help="write OUT/checkpoint.pt every K steps as well (replaced atomically; --resume continues "
                         "from it; default: only with --checkpoint, at the end)")
    ap.add_argument("--debug", action="store_true",
                    help="show the full traceback of an input error (bad data, --out, checkpoint) instead of one line")
    ap.add_argument("--resume", type=checkpoint_file, default=None, metavar="CHECKPOINT",
                    help="continue the run a checkpoint was written by (same data and flags; it is refused "
                         "otherwise, naming the settings that differ; default: start fresh)")
    return ap


def out_folder(text: str) -> Path:
    """An argparse type for --out: a non-empty path (what is there check_out checks)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a folder path, got {text!r} (to write into the current folder, "
                                         "say so: --out .)")
    return Path(text)


def checkpoint_file(text: str) -> Path:
    """An argparse type for --resume: an existing file (its content MVGS.load_checkpoint checks)."""
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text!r} is not an existing file (expected a checkpoint.pt)")
    return path


def parse_stages(text: str) -> tuple:
    """"F:M:STEPS,..." -> (Stage, ...) for --stages (argparse reports a ValueError as a usage error)."""
    try:
        stages = tuple(Stage(*(int(v) for v in part.split(":"))) for part in text.split(","))
    except (TypeError, ValueError) as exc:
        raise argparse.ArgumentTypeError(f"--stages must be F:M:STEPS[,F:M:STEPS...] with positive ints, got "
                                         f"{text!r} ({exc})") from None
    return stages


def config_from_args(args, scene=None, **preset_overrides) -> MVGSConfig:
    """The MVGSConfig the common CLI asks for: preset, --views, resolved for the scene's rig
    (MVGSConfig.for_scene with --forward-rig, when a scene is given), rescaled to --steps (or run on --budget),
    --mvad/--crd, --threshold-width, and every pyramid factor times --resolution-scale."""
    if getattr(args, "stages", None):  # the user's plan, run as given unless a cap is asked for too
        preset_overrides = {**preset_overrides, "stages": args.stages, "warmup_work_cap": None}
    if getattr(args, "warmup_work_cap", None) is not None:
        preset_overrides = {**preset_overrides, "warmup_work_cap": args.warmup_work_cap or None}
    if getattr(args, "budget_views", None) is not None:  # 0: every training view
        preset_overrides = {**preset_overrides, "budget_views": args.budget_views or None}
    for name in ("forward_rig", "views_scaling", "max_views_fraction", "stage_growth", "max_gaussians",
                 "pixels_per_gaussian", "budget_rigs", "densify_rank", "budget_swap", "budget_size_pruning",
                 "prune_faint", "budget_initial_share", "coarse_opacity_reset", "min_densify_per_reset", "lambda_dssim"):
        if getattr(args, name, None) is not None:
            preset_overrides = {**preset_overrides, name: getattr(args, name)}
    if getattr(args, "background", "auto") != "auto":  # the colour the scene's images were composited on
        preset_overrides = {**preset_overrides, "background": args.background}
    if getattr(args, "view_cost", None) is not None:
        preset_overrides = {**preset_overrides, "view_cost": (args.view_cost, 1.0 - args.view_cost)}
    config = MVGSConfig.from_preset(args.preset, seed=args.seed, **preset_overrides)
    if args.views is not None:
        config = config.with_views(args.views)
    if args.resolution_scale != 1:
        s = args.resolution_scale
        config = dataclasses.replace(config, stages=tuple(Stage(st.factor * s, st.views, st.steps) for st in config.stages))
    if scene is not None:
        try:
            config = config.for_scene(scene)  # on the recipe, so --steps N stays N steps
        except ValueError as err:  # e.g. a --pixels-per-gaussian that leaves no Gaussian
            ppg = getattr(args, "pixels_per_gaussian", None)
            raise UsageError(f"--pixels-per-gaussian {ppg:g}: {err}" if ppg is not None and "pixels_per_gaussian" in str(err)
                             else str(err)) from err
    late = getattr(args, "late_views", None) not in (None, 1)  # train_4dgs.py's --late-views, after for_scene:
    recipe_stages = len(config.stages)
    if late:
        before = config.stages
        try:  # a forward-facing rig has no coarse stage left, so no saving to spend
            config = config.with_late_views(args.late_views)
        except ValueError as err:  # a preset whose plan has no room for it: the user's to fix
            raise UsageError(f"--late-views {args.late_views}: {err}") from err
        if config.stages == before and getattr(args, "late_views_given", False):
            why = ("the plan has no coarser stage" if len(before) == 1 else
                   "its coarser stages save less than one step's work")
            print(f"{Path(sys.argv[0]).name}: note: --late-views {args.late_views} changes nothing here: {why}, so there "
                  f"is no saving to spend as {args.late_views}-view steps (stages {list(before)})", file=sys.stderr)
        if scene is not None:
            config = config.for_scene(scene)  # its view cap (--max-views-fraction) on the new stage
    if args.budget is not None:
        if config.restart_per_stage:
            raise UsageError(f"--budget {args.budget:g}: the {args.preset} preset restarts its schedules at every stage, "
                             "and a budget needs one continuous clock (use --steps)")
        config = config.with_budget(args.budget)  # stage shares depend on M: after with_views
        planned = config.total_work
        if planned > 1.5 * args.budget:  # every stage needs a step: a budget below that is overspent
            raise UsageError(f"--budget {args.budget:g}: the stage plan's {len(config.stages)} stages need at least one "
                             f"step each, so this budget would run {planned:.3g} full-resolution view renders; give a "
                             f"budget of at least {planned:.3g}")
    else:
        if args.steps < len(config.stages):  # every stage needs a step
            added = (f" (--late-views {args.late_views} added a stage; --late-views 1 does not)"
                     if len(config.stages) > recipe_stages else "")
            raise UsageError(f"--steps {args.steps}: the stage plan has {len(config.stages)} stages, so the run needs at "
                             f"least {len(config.stages)} steps{added}")
        config = config.with_total_steps(args.steps)
    for rule in ("mvad", "crd"):  # --mvad/--no-mvad, --crd/--no-crd switch the preset's rule, keeping its settings
        if getattr(args, rule) is not None:
            config = dataclasses.replace(config, **{rule: dataclasses.replace(getattr(config, rule),
                                                                              enabled=getattr(args, rule))})
    if args.threshold_width is not None:
        config = dataclasses.replace(config, grad_threshold_width=args.threshold_width or None)
    if not densifies_at_some_step(config):
        length = f"--budget {args.budget:g}" if args.budget is not None else f"--steps {args.steps}"
        print(f"{Path(sys.argv[0]).name}: note: {length}: {no_densification_message(config)}", file=sys.stderr)
    return config


def late_views_hint(args, scene, config: MVGSConfig) -> str:
    """For a --resume of train_4dgs.py refused for its stage plan alone (StageMismatch: the same
    model, views and images), whose checkpoint has another stage plan than this run's `config`:
    when that plan is the one another --late-views value (1 to 8, the values one would run) gives
    this command line, a hint naming it; else "" (also when the plans agree and the refusal is
    about something else). The plan depends only on the flags config_from_args
    reads, so it is rebuilt from them."""
    late = getattr(args, "late_views", None)
    if late is None:
        return ""
    try:
        saved = MVGSConfig.from_dict(load_checked(str(args.resume))["config"]).stages
    except Exception:  # the error being reported already says what is wrong with the file
        return ""
    if saved == config.stages:
        return ""
    for m in range(1, 9):
        if m == late:
            continue
        try:
            stages = config_from_args(argparse.Namespace(**{**vars(args), "late_views": m, "late_views_given": False}),
                                      scene).stages
        except ValueError:
            continue
        if stages == saved:
            return f" (the checkpoint's stage plan is this command's with --late-views {m}: add it to resume)"
    return ""


RENDERS_MANIFEST = "renders.json"  # OUT/test's list of the renders a run wrote (save_test_renders)


def render_file_names(names) -> list:
    """The file name of each view's test render: its image's stem ("r_000.png"), or, when two
    views share a stem (cameras in sub-folders), its path without the extension and with "/" as
    "_" ("camA_view.png"), so no render replaces another."""
    stems = [Path(n).stem for n in names]
    if len(set(stems)) == len(stems):
        return [stem + ".png" for stem in stems]
    return [str(Path(n).with_suffix("")).replace("/", "_").replace("\\", "_") + ".png" for n in names]


def save_test_renders(out: Path, result) -> None:
    """OUT/test/<view>.png for every evaluated view (atomic writes; names: render_file_names).
    OUT/test/renders.json lists them; a render an earlier run listed there (in a reused --out)
    and this run does not write is removed, so the folder holds this run's renders. Nothing
    else is removed: a PNG no run of ours listed (a dataset's, when --out is its folder) stays."""
    folder = out / "test"
    folder.mkdir(parents=True, exist_ok=True)
    from mvgs_plugin.reference_renderer.demo import save_png

    written = render_file_names([row["name"] for row in result.per_view])
    for row, name in zip(result.per_view, written):
        save_png(str(folder / name), row["image"].numpy())
    manifest = folder / RENDERS_MANIFEST
    remove_stale_outputs(folder, listed_in(manifest, "renders"), written, suffix=".png")
    write_json(manifest, {"renders": written})


def listed_in(record: Path, key: str) -> list:
    """The file names an earlier run listed under `key` of its JSON record (OUT/test/renders.json,
    OUT/metrics.json), or [] when there is none or it is not ours."""
    try:
        names = json.loads(Path(record).read_text()).get(key, [])
    except (OSError, ValueError, AttributeError):
        return []
    return [n for n in names if isinstance(n, str)] if isinstance(names, list) else []


def remove_stale_outputs(folder: Path, earlier, written, prefix: str = "", suffix: str = "") -> None:
    """In a reused output folder, remove the files an earlier run listed (`earlier`, see
    listed_in) that this run did not write (`written`): plain names with `prefix` and `suffix`
    only, so a file no run of ours listed (a dataset's, when --out is its folder) stays."""
    for name in sorted(set(earlier) - set(written)):
        if Path(name).name == name and name.startswith(prefix) and name.endswith(suffix) and (folder / name).is_file():
            (folder / name).unlink()


def model_settings(adapter) -> dict:
    """The model config values an adapter's checkpoint carries ({"field": value}, nested configs
    as "canonical.field", 4DGS's own as "4dgs.field"), from its config attributes (config,
    gs4d_config) with saved_values()."""
    out = {}

    def add(prefix: str, cfg) -> None:
        for name, value in cfg.saved_values().items():
            if hasattr(value, "saved_values"):
                add(f"{prefix}{name}.", value)
            else:
                out[prefix + name] = value

    for attr, prefix in (("config", ""), ("gs4d_config", "4dgs.")):
        cfg = getattr(adapter, attr, None)
        if hasattr(cfg, "saved_values"):
            add(prefix, cfg)
    return out


def _other_settings(args, what: str, differences, this: str) -> UsageError:
    """The refusal of a --resume whose checkpoint was made with other `what`: each (name,
    checkpoint value, this run's value) named, and the command-line advice."""
    said = "; ".join(f"{name}: checkpoint {a!r}, {this} {b!r}" for name, a, b in differences)
    return UsageError(f"--resume {args.resume}: the checkpoint was made with other {what} ({said}); resume with the "
                      "flags it was written with")


def train_and_evaluate(adapter, scene, config: MVGSConfig, args, dist):
    """Trains on every rank (each on its share of a step's views under torchrun; progress bar
    unless --no-progress), from args.resume when given; writes OUT/checkpoint.pt every
    args.checkpoint_every steps and at the end, or only at the end with args.checkpoint (every
    rank takes part, rank 0 writes), then evaluates on rank 0 and writes OUT/test/<view>.png.
    The seconds cover the steps this process ran (after a resume, the rest of the run). Returns
    (trainer, training wall seconds, test result), the result None on the other ranks: the
    model is the same on every rank."""
    with warnings.catch_warnings():  # config_from_args said so in its own note
        warnings.simplefilter("ignore", NoDensificationWarning)
        trainer = MVGS(adapter, scene, config, distributed=dist)
    if getattr(args, "resume", None) is not None:
        asked = model_settings(adapter)
        try:
            trainer.load_checkpoint(str(args.resume))  # then fit() runs the remaining steps
        except ConfigMismatch as err:  # the Python advice (strict=False, from_dict) is not a command line's
            raise _other_settings(args, "settings", err.differences, "this run") from err
        except ValueError as err:  # another run's checkpoint, a damaged file: the user's to fix
            hint = late_views_hint(args, scene, config) if isinstance(err, StageMismatch) else ""
            raise UsageError(f"--resume {args.resume}: {err}{hint}") from err
        saved = model_settings(adapter)  # an adapter's load_state_dict takes the checkpoint's model config
        rig_rule = getattr(args, "means_lr_rule", None) is None  # "auto" chose for the rig: the checkpoint's rule stays
        differ = [(k, saved[k], asked[k]) for k in asked if k in saved and saved[k] != asked[k]
                  and not (rig_rule and k.endswith("means_lr_rule"))]
        if differ:
            raise _other_settings(args, "model settings", differ, "this command")
    path, every = str(args.out / "checkpoint.pt"), getattr(args, "checkpoint_every", None)

    written = []  # steps this process checkpointed at (a checkpoint.pt left by an earlier run is not this run's)

    tally = DensifyTally(trainer.adapter.num_primitives())  # over the run's steps (a resume's too: below)
    if trainer.step_count:  # resumed: the checkpoint's record of the steps before it
        tally.resume(trainer.record)
    trainer.densify_totals = trainer.record = tally.totals  # the record saves with each checkpoint

    def periodic(info) -> None:  # on every rank (save_checkpoint is collective), at the same steps
        tally.add(info)
        if every and trainer.step_count % every == 0 and trainer.step_count < trainer.total_steps:
            trainer.save_checkpoint(path)
            written.append(trainer.step_count)

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        trainer.fit(callback=periodic, progress=not args.no_progress)
    except KeyboardInterrupt:
        if dist is not None:
            raise
        resumed_from = getattr(args, "resume", None) is not None and os.path.abspath(args.resume) == os.path.abspath(path)
        how = f"written at step {written[-1]}" if written else "the one this run resumed from"
        saved = (f"the checkpoint {path} ({how}) resumes it: the same command with --resume {path}"
                 if written or resumed_from else
                 "no checkpoint of this run was written (--checkpoint-every N writes one every N steps)")
        print(f"{Path(sys.argv[0]).name}: interrupted at step {trainer.step_count} of {trainer.total_steps}; {saved}",
              file=sys.stderr)
        raise SystemExit(130) from None
    seconds = time.perf_counter() - t0
    trainer.cpu_seconds = time.process_time() - c0  # user + sys of this process, all its threads
    if getattr(args, "checkpoint", False) or every:
        trainer.save_checkpoint(path)
    if not trainer.is_main:
        return trainer, seconds, None
    result = trainer.evaluate(factor=args.resolution_scale)
    save_test_renders(args.out, result)
    return trainer, seconds, result


def _masks_said(scene) -> Optional[str]:
    """How many views have a mask (Scene.mask), for metrics.json; None for a scene without."""
    if not getattr(scene, "has_masks", False):
        return None
    train, test = len(scene.masked(scene.train_cameras)), len(scene.masked(scene.test_cameras))
    return (f"{train} of {len(scene.train_cameras)} training and {test} of {len(scene.test_cameras)} test views have a "
            "mask: the loss and the test metrics count the pixels it keeps")


def metrics_record(args, config: MVGSConfig, trainer: MVGS, result, train_seconds: float, **extra) -> dict:
    """The metrics.json every train_*.py script writes: test PSNR/SSIM/LPIPS, training seconds,
    steps, primitives, peak memory, the run's settings and per-view results; `extra` adds the
    model family's own entries (model size, anchors, ...)."""
    return {
        "psnr": result.psnr,
        "ssim": result.ssim,
        "ssim_3dgs": result.ssim_3dgs,
        "lpips": result.lpips,
        "train_seconds": train_seconds,
        "cpu_seconds": getattr(trainer, "cpu_seconds", None),
        "steps": trainer.step_count,
        "budget": config.budget,
        "work": trainer.schedule.work_done,
        "num_gaussians": trainer.adapter.num_primitives(),
        "densification": getattr(trainer, "densify_totals", None),
        "init": getattr(trainer.scene, "points_origin", None),
        "masks": _masks_said(trainer.scene),
        "background": {"colour": list(trainer.schedule.background_value()),
                       "origin": ("--background" if scene_background(args) != "auto"
                                  else getattr(trainer.scene, "background_origin", None)),
                       **({"training": "random: a new colour every view and step (--background random)"}
                          if getattr(args, "background", "auto") == "random" else {})},
        **extra,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "preset": args.preset,
        "data": repo_path(args.data) if Path(args.data).resolve().is_relative_to(ROOT) else str(args.data),
        "threads": torch.get_num_threads(),
        "device": getattr(args, "device", "cpu"),
        "rasterizer": getattr(args, "rasterizer", "reference"),
        "world_size": 1 if trainer.distributed is None else trainer.distributed.world_size,
        "config": trainer.config.to_dict(),  # as run (prune_faint 0 where the model reports no blend weights)
        "model": json.loads(json.dumps(model_settings(trainer.adapter), default=str)),  # as resolved (means_lr_rule)
        "per_view": [{k: v for k, v in r.items() if k != "image"} for r in result.per_view],
    }


def launch(args, run: Callable) -> dict:
    """run(args, dist) in one process (dist None; returns its metrics), or on every rank when
    torchrun started more than one (dist a Collective; the training script itself is
    unchanged), after which the process exits with code 0. Every train_*.py example starts
    this way. A UsageError (or a ValueError from the --out and --device checks) ends the
    process with one line on stderr and exit code 2, as argparse does, unless args.debug."""
    try:
        return _launch(args, run)
    except UsageError as err:
        if getattr(args, "debug", False):
            raise
        message = " ".join(str(err).split())  # one line, whatever the message held
        print(f"{Path(sys.argv[0]).name}: error: {message}", file=sys.stderr)
        sys.stderr.flush()
        raise SystemExit(2) from None


def _launch(args, run: Callable) -> dict:
    try:
        check_out(args.out)
        check_device(args)
    except ValueError as err:
        raise UsageError(str(err)) from err
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    dist = init_from_env(device=args.device, timeout=args.dist_timeout)  # None unless torchrun started > 1 process
    if dist is None:
        return run(args, None)
    with abort_on_error():  # an error ends this rank at once; the others' next collective then fails
        run(args, dist)
        dist.close()  # every rank waits for rank 0's evaluation and writes, then all leave together
    # The process ends here: even after the ranks left the group together, gloo's threads now
    # and then abort the interpreter's teardown ("terminate called without an active exception",
    # SIGABRT, about 1 in 15 two-rank runs); every output is written and closed by now.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
