"""The command line of every script a user runs, and the install's import names.

- `--help` states every option's default (switches excepted), read from the help text a user sees;
- bad values end in an argparse usage error (exit code 2) naming the flag, before any work;
- the installed package answers to `mvgs_plugin.adapters` / `mvgs_plugin.reference_renderer`
  only: no top-level `adapters` or `reference_renderer` that could collide with other packages.
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

from mvgs_plugin.adapters.ops import growth_cap, log_linear

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = [
    "examples/train_3dgs.py", "examples/train_4dgs.py", "examples/train_scaffold.py", "examples/ablation.py",
    "examples/graphdeco_loop/train_mvgs.py", "examples/gsplat_loop/simple_trainer.py",
    "examples/gsplat_loop/simple_trainer_mvgs.py", "examples/gsplat_loop/simple_trainer_chunked.py",
    "examples/three_line_wrap/mvgs.py",
    "examples/three_line_wrap/single_view.py", "tools/make_scene.py",
]


def _run(args, cwd=ROOT, timeout=120):
    return subprocess.run([sys.executable, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def _options(help_text: str):
    """(flags, takes a value, help) for each option block of argparse's --help output."""
    section = help_text.split("options:", 1)[1]
    blocks = re.split(r"\n(?=  -)", "\n" + section)
    out = []
    for block in blocks:
        block = block.strip("\n")
        if not block.startswith("  -"):
            continue
        head = block.strip().split("  ")[0]  # "--steps STEPS" / "--mvad, --no-mvad"
        flags = [t for t in re.split(r"[ ,]+", head) if t.startswith("-")]
        takes_value = any(not t.startswith("-") for t in re.split(r"[ ,]+", head) if t)
        out.append((flags, takes_value, " ".join(block.split())))
    return out


@pytest.mark.parametrize("script", SCRIPTS)
def test_help_states_every_default(script):
    r = _run([script, "--help"])
    assert r.returncode == 0, r.stderr
    options = _options(r.stdout)
    assert len(options) >= 3, r.stdout
    missing = [flags for flags, takes_value, text in options
               if takes_value and "--help" not in flags and "default" not in text.lower() and "required" not in text]
    assert not missing, f"{script}: options whose help gives no default: {missing}"


@pytest.mark.parametrize("script, argv, flag", [
    ("examples/train_3dgs.py", ["--data", "/nonexistent/scene"], "--data"),
    ("examples/train_3dgs.py", ["--steps", "0"], "--steps"),
    ("examples/train_3dgs.py", ["--budget", "nan"], "--budget"),
    ("examples/train_3dgs.py", ["--stages", "8:x:100"], "--stages"),
    ("examples/train_3dgs.py", ["--preset", "fast"], "--preset"),
    ("examples/train_3dgs.py", ["--background", "0.5,0.5"], "--background"),
    ("examples/train_scaffold.py", ["--background", "1.2,0,0"], "--background"),
    ("examples/train_4dgs.py", ["--data", str(ROOT / "README.md")], "--data"),
    ("examples/train_4dgs.py", ["--data", str(ROOT), "--coarse-fraction", "1.5"], "--coarse-fraction"),
    ("examples/train_4dgs.py", ["--data", str(ROOT), "--export-times", "2"], "--export-times"),
    ("examples/train_scaffold.py", ["--voxel-size", "-1"], "--voxel-size"),
    ("examples/ablation.py", ["--steps", "many"], "--steps"),
    ("examples/graphdeco_loop/train_mvgs.py", ["--data", "/nonexistent/scene"], "--data"),
    ("examples/graphdeco_loop/train_mvgs.py", ["--background", "grey"], "--background"),
    ("examples/three_line_wrap/mvgs.py", ["--steps", "-3"], "--steps"),
])
def test_bad_arguments_are_usage_errors(script, argv, flag, tmp_path):
    r = _run([script, *argv, "--out", str(tmp_path / "out")] if "train_" in script and "loop" not in script
             else [script, *argv])
    assert r.returncode == 2, (r.returncode, r.stderr[-500:])
    assert "usage:" in r.stderr and f"argument {flag}" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_missing_data_folder_says_it_does_not_exist():
    r = _run(["examples/train_3dgs.py", "--data", "/nonexistent/scene"])
    assert "'/nonexistent/scene' does not exist" in r.stderr


def test_installed_names_are_namespaced(tmp_path):
    """From outside the repository (so the checkout's folders are not on sys.path) the
    package's parts import under mvgs_plugin and the bare names are not installed."""
    code = ("import importlib.util as u, mvgs_plugin.adapters.gs3d, mvgs_plugin.adapters.scaffold, "
            "mvgs_plugin.adapters.gs4d, mvgs_plugin.reference_renderer as r;"
            "print(u.find_spec('adapters') is None, u.find_spec('reference_renderer') is None, "
            "hasattr(r, 'rasterization'))")
    r = _run(["-c", code], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True", "True", "True"]


def test_no_adapter_imports_another_adapters_private_names():
    pattern = re.compile(r"from \.(\w+) import ([^\n(]+|\([^)]*\))")
    for path in (ROOT / "adapters").glob("*.py"):
        for module, names in pattern.findall(path.read_text()):
            private = [n.strip() for n in names.strip("()").replace("\n", " ").split(",") if n.strip().startswith("_")]
            assert not private, f"{path.name} imports {private} from .{module}"


def test_log_linear_is_geometric_interpolation():
    for step, want in ((0, 1.0), (10, 1.0), (15, math.sqrt(1e-2)), (20, 1e-2), (99, 1e-2)):
        assert math.isclose(log_linear(step, 10, 10, 1.0, 1e-2), want, rel_tol=1e-12)


def test_growth_cap_takes_the_lower_set_cap():
    assert growth_cap(None, None) is None
    assert growth_cap(7, None) == 7 and growth_cap(None, 3) == 3 and growth_cap(7, 3) == 3
    with pytest.raises(ValueError, match="max_primitives"):
        growth_cap(True, 3)


def test_test_renders_of_views_that_share_a_stem_keep_their_folders_apart():
    """OUT/test/<name>.png: the image's stem when the stems are unique (the bundled layout), else the
    path with "/" as "_" (cameras in sub-folders), so no render replaces another."""
    from mvgs_plugin.cli import render_file_names

    assert render_file_names(["test/r_000.png", "test/r_001.png"]) == ["r_000.png", "r_001.png"]
    names = render_file_names(["camA/view.png", "camB/view.png", "camA/view2.jpg", "camB/view2.jpg"])
    assert names == ["camA_view.png", "camB_view.png", "camA_view2.png", "camB_view2.png"]
    assert len(set(names)) == 4


def test_a_reused_out_keeps_only_this_runs_test_renders(tmp_path):
    """An earlier run's renders in OUT/test (another scene's view names, listed in its
    renders.json) go once this run's are written; this run's are the images it evaluated; a PNG
    no run listed (a dataset's, when --out is its folder) and other files in OUT are left alone."""
    import types

    import numpy as np
    import torch

    from mvgs_plugin.cli import save_test_renders
    from PIL import Image

    def result(names, value):
        return types.SimpleNamespace(per_view=[{"name": n, "image": torch.full((4, 5, 3), value)} for n in names])

    (tmp_path / "test").mkdir()
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(tmp_path / "test" / "r_0_depth.png")  # not ours: a dataset's
    save_test_renders(tmp_path, result(["a/r_000.png", "a/r_001.png", "a/r_002.png"], 0.25))
    (tmp_path / "notes.txt").write_text("mine")
    save_test_renders(tmp_path, result(["b/v_0.png", "b/r_001.png"], 0.75))
    assert sorted(p.name for p in (tmp_path / "test").iterdir()) == ["r_001.png", "r_0_depth.png", "renders.json",
                                                                      "v_0.png"]
    assert np.allclose(np.asarray(Image.open(tmp_path / "test" / "r_001.png"), dtype=float) / 255, 0.75, atol=1 / 255)
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_a_budget_below_one_step_per_stage_is_refused_not_overspent(tmp_path):
    """multiview at --budget 1: each of its 4 stages needs a step, which is 32.6 views of work on
    the bundled scene; the run is refused naming that, where it used to run 33x its budget."""
    import argparse

    from mvgs_plugin import cli

    scene = cli.load_scene(cli.BUNDLED)
    ap = cli.common_args(argparse.ArgumentParser(), "out")
    with pytest.raises(cli.UsageError, match=r"--budget 1: the stage plan's 4 stages need at least one step each, so "
                                             r"this budget would run 32.6 full-resolution view renders"):
        cli.config_from_args(ap.parse_args(["--preset", "multiview", "--budget", "1"]), scene)
    config = cli.config_from_args(ap.parse_args(["--preset", "multiview", "--budget", "40"]), scene)
    assert config.total_work <= 1.5 * 40


def test_images_names_a_downscaled_colmap_folder(tmp_path):
    """--images images_2 on a COLMAP scene: cameras at the copies' size; on a NeRF-style scene, or
    a folder that is not there, a usage error naming --images."""
    import argparse

    import numpy as np
    from PIL import Image
    from skimage.transform import resize

    from mvgs_plugin import cli
    from test_data_colmap import H, W, write_model

    write_model(tmp_path / "s")
    for f in (tmp_path / "s" / "images").rglob("*.png"):
        out = tmp_path / "s" / "images_2" / f.parent.name / f.name
        out.parent.mkdir(parents=True, exist_ok=True)
        # by 1.5 (27 x 20): the scene's 40 x 30 halved would fall below the examples' 16 px
        Image.fromarray((resize(np.asarray(Image.open(f)), (20, 27)) * 255).astype(np.uint8)).save(out)
    ap = cli.common_args(argparse.ArgumentParser(), "out")
    ap.add_argument("--data", type=cli.scene_folder)

    def scene(*argv):
        return cli.scene_from_args(ap.parse_args(["--data", str(tmp_path / "s"), "--init", "random",
                                                  "--out", str(tmp_path / "o"), *argv]))
    cams = scene("--images", "images_2").cameras
    assert {(c.width, c.height) for c in cams} == {(27, 20)} and (W, H) == (40, 30)
    assert {round(c.fx, 9) for c in cams} == {round(27 / 40 * 50.0, 9), round(27 / 40 * 45.0, 9)}  # the two cameras
    with pytest.raises(cli.UsageError, match=r"--images images_9: images folder .*images_9 does not exist"):
        scene("--images", "images_9")
    ap2 = cli.common_args(argparse.ArgumentParser(), "out")
    ap2.add_argument("--data", type=cli.scene_folder)
    with pytest.raises(cli.UsageError, match=r"--images images_2: images='images_2': a NeRF-style scene takes a downscaled copy of nerfstudio's images/"):
        cli.scene_from_args(ap2.parse_args(["--data", str(cli.BUNDLED), "--images", "images_2",
                                            "--out", str(tmp_path / "o2")]))
