"""examples/train_3dgs.py end to end on the bundled scene (a few steps): its outputs exist and
say what they should."""

import importlib.util
import json
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
import torch
from plyfile import PlyData

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "train_3dgs.py"


def load_example():
    spec = importlib.util.spec_from_file_location("train_3dgs", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("preset,layout", [("baseline", "nerf"), ("default", "colmap")])
def test_train_3dgs_writes_metrics_renders_and_ply(tmp_path, preset, layout):
    example = load_example()
    data = example.BUNDLED
    if layout == "colmap":  # the same scene through the COLMAP loader
        data = tmp_path / "colmap_scene"
        data.mkdir()
        (data / "sparse").symlink_to(example.BUNDLED / "sparse")
        for split in ("train", "test"):
            (data / split).symlink_to(example.BUNDLED / split)
    out = tmp_path / "out"
    metrics = example.main(["--data", str(data), "--preset", preset, "--steps", "4", "--views", "2",
                            "--resolution-scale", "4", "--out", str(out), "--no-progress"])
    saved = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "lpips", "train_seconds", "steps", "num_gaussians", "peak_memory_mb", "preset", "config"):
        assert key in saved, key
    assert saved["steps"] == 4 and saved["preset"] == preset and saved == json.loads(json.dumps(metrics))
    assert 0 < saved["psnr"] < 60 and 0 < saved["ssim"] <= 1
    # the bundled images have no alpha and a border of many colours: white, the NeRF loader's default;
    # COLMAP drops alpha and has no background: black
    assert saved["background"]["colour"] == ([1.0, 1.0, 1.0] if layout == "nerf" else [0.0, 0.0, 0.0])
    renders = sorted((out / "test").glob("*.png"))
    assert len(renders) == len(saved["per_view"]) > 0
    ply = PlyData.read(str(out / "point_cloud.ply"))
    assert ply["vertex"].count == saved["num_gaussians"]
    names = [p.name for p in ply["vertex"].properties]
    assert names[:6] == ["x", "y", "z", "nx", "ny", "nz"] and names[-4:] == ["rot_0", "rot_1", "rot_2", "rot_3"]


def test_a_nerfstudio_folder_composited_on_black_trains_in_front_of_black(tmp_path, capsys):
    """One transforms.json (nerfstudio's keys, with a lens distortion k1), RGB images of an object
    on black: the run holds out every 8th view, trains on the undistorted images, finds the black
    backdrop in their borders, says so and trains in front of it; --background overrides it."""
    import warnings

    from test_data_transforms import _frames, _object_on, _write

    frames, _ = _frames(9, tmp_path / "scene", paint=_object_on((0, 0, 0)))
    _write(tmp_path / "scene", frames, k1=-0.05)
    example = load_example()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the random init's
        saved = example.main(["--data", str(tmp_path / "scene"), "--preset", "baseline", "--steps", "3",
                              "--init", "random", "--out", str(tmp_path / "auto"), "--no-progress"])
        assert "note: background: the training images have no transparent pixel and their borders are one colour, " \
               "(0.000, 0.000, 0.000)" in capsys.readouterr().err
        assert saved["background"]["colour"] == [0.0, 0.0, 0.0] and len(saved["per_view"]) == 2
        example.main(["--data", str(tmp_path / "scene"), "--preset", "baseline", "--steps", "3",
                             "--init", "random", "--background", "0.2,0.4,0.6", "--out", str(tmp_path / "told"),
                             "--no-progress"])
    told = json.loads((tmp_path / "told" / "metrics.json").read_text())
    from PIL import Image
    with Image.open(tmp_path / "told" / "test" / "frame_00000.png") as render:  # the undistorted camera's size
        assert render.size != (48, 36) and abs(render.size[0] - 48) <= 4
    assert told["background"] == {"colour": [0.2, 0.4, 0.6], "origin": "--background"}
    assert told["config"]["background"] == [0.2, 0.4, 0.6]


def _spy_backgrounds(monkeypatch):
    """Every ViewSchedule._backgrounds call recorded as (config.background, the colours drawn)."""
    from mvgs_plugin.schedule import ViewSchedule

    seen, draw = [], ViewSchedule._backgrounds

    def spy(self, n):
        out = draw(self, n)
        seen.append((self.config.background, out.clone()))
        return out

    monkeypatch.setattr(ViewSchedule, "_backgrounds", spy)
    return seen


def test_random_background_draws_a_colour_per_training_view_and_evaluates_on_the_scenes(tmp_path, capsys,
                                                                                         monkeypatch):
    """--background random (3DGS's --random_background): the training views of a step are drawn
    in front of colours drawn for them, every one different; the images are composited as auto
    composites them (black, found in the borders) and the metrics and test renders use that colour."""
    import warnings

    from test_data_transforms import _frames, _object_on, _write

    frames, _ = _frames(9, tmp_path / "scene", paint=_object_on((0, 0, 0)))
    _write(tmp_path / "scene", frames)
    seen = _spy_backgrounds(monkeypatch)
    example = load_example()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the random init's
        saved = example.main(["--data", str(tmp_path / "scene"), "--preset", "baseline", "--steps", "6", "--views", "2",
                              "--init", "random", "--background", "random", "--out", str(tmp_path / "o"),
                              "--no-progress"])
    assert "borders are one colour, (0.000, 0.000, 0.000)" in capsys.readouterr().err  # auto's rule found black
    colours = torch.cat([c for bg, c in seen])
    assert {bg for bg, _ in seen} == {"random"} and len(colours) == 6 * 2
    assert len({tuple(c.tolist()) for c in colours}) == len(colours)  # a new colour for every view of every step
    assert ((colours >= 0) & (colours <= 1)).all() and colours.std(0).min() > 0.1
    assert saved["background"]["colour"] == [0.0, 0.0, 0.0] and "borders" in saved["background"]["origin"]
    assert saved["background"]["training"].startswith("random") and saved["config"]["background"] == "random"


@pytest.mark.filterwarnings("ignore:this run densifies at no step")  # 3 steps: it is the background's test
def test_graphdeco_loop_passes_random_background_to_its_schedule(monkeypatch, capsys):
    """The graphdeco-shaped loop's --background random reaches its ViewSchedule (colours drawn per
    view), while its scene is loaded with auto's colour (the forward scene's: black)."""
    import runpy

    from mvgs_plugin.data import load_scene

    loaded = []
    monkeypatch.setattr("mvgs_plugin.data.load_scene", lambda *a, **k: loaded.append(k) or load_scene(*a, **k))
    seen = _spy_backgrounds(monkeypatch)
    script = Path(__file__).resolve().parents[1] / "examples" / "graphdeco_loop" / "train_mvgs.py"
    data = Path(__file__).resolve().parent / "data" / "forward64"
    monkeypatch.setattr(sys, "argv", [str(script), "--data", str(data), "--steps", "3", "--background", "random"])
    monkeypatch.syspath_prepend(str(script.parent))
    runpy.run_path(str(script), run_name="__main__")
    assert "PSNR" in capsys.readouterr().out
    assert [k["background"] for k in loaded] == ["auto"]
    colours = torch.cat([c for bg, c in seen])
    assert {bg for bg, _ in seen} == {"random"} and len({tuple(c.tolist()) for c in colours}) == len(colours) >= 3


def test_bad_data_folder_is_named(tmp_path):
    example = load_example()
    with pytest.raises(ValueError, match="neither a COLMAP scene"):  # --debug: the exception, not one line
        example.main(["--data", str(tmp_path), "--steps", "2", "--out", str(tmp_path / "o"), "--no-progress", "--debug"])


def test_ablation_refuses_an_unknown_variant_naming_them_all(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("ablation_only", EXAMPLE.parent / "ablation.py")
    ablation = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ablation)
    with pytest.raises(SystemExit) as err:
        ablation.main(["--steps", "6", "--only", "+CIG", "baseline", "--out", str(tmp_path / "a")])
    assert err.value.code == 2 and not (tmp_path / "a").exists()
    said = capsys.readouterr().err
    assert "--only +CIG: no such variant; the variants are 'baseline', '+MVRL'" in said and "'+CIG (= default)'" in said


@pytest.mark.slow
def test_ablation_smoke(tmp_path, monkeypatch):
    """examples/ablation.py runs every variant and writes its table and plots (a few steps)."""
    spec = importlib.util.spec_from_file_location("ablation", EXAMPLE.parent / "ablation.py")
    ablation = importlib.util.module_from_spec(spec)
    # Registered under its import name, its folder on the path the spawned processes inherit:
    # each variant runs in one, which imports ablation.run by name.
    monkeypatch.setitem(sys.modules, "ablation", ablation)
    monkeypatch.syspath_prepend(str(EXAMPLE.parent))
    spec.loader.exec_module(ablation)
    rows = ablation.main(["--steps", "6", "--views", "2", "--curve-points", "2", "--out", str(tmp_path)])
    names = ["baseline", "+MVRL", "+CRD", "+MVAD", "+CIG (= default)", "paper"]
    assert list(rows)[:6] == names and len(rows) == 7 and list(rows)[6].startswith("baseline, equal time (")
    equal = rows[list(rows)[6]]
    # The equal-time baseline runs as many steps as the full run's time allows at its step time.
    expected = rows["+CIG (= default)"]["seconds"] / (rows["baseline"]["seconds"] / 6)
    assert equal["steps"] == max(6, round(expected))
    table = (tmp_path / "ablation.md").read_text()
    assert all(f"| {name} |" in table for name in rows)
    assert "at equal steps" in table and "At equal wall time" in table
    assert (tmp_path / "ablation.png").stat().st_size > 0 and (tmp_path / "psnr_vs_time.png").stat().st_size > 0
    assert all(0 <= r["overhead"] <= r["outside"] <= 1 for r in rows.values())
    assert all(r["steps"] == 6 for n, r in rows.items() if n in names)
    assert len(rows["baseline"]["curve"]) >= 2 and rows["+MVRL"]["curve"] == []
    # Counters: the baseline never lowers its threshold nor gets boxes; +MVRL has no MVAD/CRD.
    assert rows["baseline"]["mvad_fired"] == 0 and rows["+MVRL"]["crd_boxes"] == 0
    # One threshold policy for every variant but paper (the released code never scales it).
    for width in (800.0, None):
        configs = ablation.variants(300, 4, 0, width)
        assert all(c.grad_threshold_width == width for n, c in configs.items() if n != "paper")
        assert configs["paper"].grad_threshold_width is None
    assert "--threshold-width 800" in table


def _run_example(argv):
    return load_example().main(argv)


@pytest.mark.slow
def test_train_3dgs_on_a_budget(tmp_path):
    """--budget: baseline and MVGS do the same work (full-resolution view renders) through
    densification and opacity resets; metrics.json says what was spent, in work and CPU time."""
    example = load_example()
    argv = {preset: ["--preset", preset, "--budget", "600", *views, "--resolution-scale", "4", "--threads", "1",
                     "--out", str(tmp_path / preset), "--no-progress"]
            for preset, views in (("baseline", []), ("default", []), ("multiview", ["--views", "2"]))}
    # the default with its warm-up held to 60 views' work (warmup_work_cap binds: 30 % would be 180)
    argv["capped"] = [*argv["default"][:-3], "--warmup-work-cap", "60", "--out", str(tmp_path / "capped"),
                      "--no-progress"]
    # three independent runs, two at a time in their own processes (one thread each)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        runs = {preset: pool.submit(_run_example, args) for preset, args in argv.items()}
        runs = {preset: run.result() for preset, run in runs.items()}
    for preset in runs:
        saved = json.loads((tmp_path / preset / "metrics.json").read_text())
        assert saved["budget"] == 600 and saved["cpu_seconds"] > 0 and saved["train_seconds"] > 0
        # Each stage's step count is rounded to whole steps: within half a step's work per stage.
        assert saved["work"] == pytest.approx(600, abs=4)
        assert saved["num_gaussians"] != 4000  # densified / pruned from the 4000 scene points
    base, default, multiview, capped = runs["baseline"], runs["default"], runs["multiview"], runs["capped"]
    assert base["steps"] == 600 and multiview["steps"] < 600  # multi-view steps cost more views each
    # The default's coarse-to-fine warm-up (30 % of the work at 1/2 resolution) makes cheap
    # steps: a step at 1/2 costs 0.1 + 0.9 / 2 = 0.55 of a full one, so 180 / 0.55 + 420.
    assert default["steps"] == pytest.approx(180 / 0.55 + 420, abs=2)
    # Held to 60 views' work, the warm-up gives the rest to full resolution: 60 / 0.55 + 540 steps.
    assert capped["steps"] == pytest.approx(60 / 0.55 + 540, abs=2)
    plan = json.loads((tmp_path / "capped" / "metrics.json").read_text())["config"]["stages"]
    assert [(s["factor"], s["steps"]) for s in plan] == [(8, round(60 / 0.55)), (4, 540)]
    with pytest.raises(SystemExit) as err:  # argparse's usage error, before any work
        example.main(["--budget", "-3", "--out", str(tmp_path / "bad"), "--no-progress"])
    assert err.value.code == 2 and not (tmp_path / "bad").exists()


def test_stages_option_replaces_the_preset_plan():
    example = load_example()
    args = example.parse_args(["--stages", "8:16:1000,1:1:30000", "--budget", "500"])
    config = example.config_from_args(args)
    assert [(s.factor, s.views) for s in config.stages] == [(8, 16), (1, 1)]
    # 1000 recipe steps of 16 views at 1/8 (0.2125 each) against 30000 full-resolution ones.
    coarse = 1000 * 16 * (0.1 + 0.9 / 8)
    assert config.stages[0].steps == round(500 * coarse / (coarse + 30000) / (16 * (0.1 + 0.9 / 8)))
    for bad in ("8:x:10", "8:16", "0:1:10"):
        with pytest.raises(SystemExit):
            example.parse_args(["--stages", bad])


@pytest.mark.parametrize("flags,message", [
    (["--device", "cuda"], "--device cuda: torch .* sees no CUDA device here"),
    (["--rasterizer", "gsplat"], "--rasterizer gsplat needs --device cuda"),
])
def test_device_flags_this_machine_cannot_run_stop_before_any_work(tmp_path, monkeypatch, flags, message):
    """This CPU machine (torch.cuda.is_available() is False here, asserted) refuses --device cuda
    and a gsplat rasterizer on the CPU at once: no scene is loaded, no folder written."""
    import torch

    assert not torch.cuda.is_available()
    example = load_example()
    monkeypatch.setattr(example, "scene_from_args", lambda args: pytest.fail("loaded a scene before checking the device"))
    with pytest.raises(ValueError, match=message):
        example.main(flags + ["--steps", "3", "--no-progress", "--out", str(tmp_path / "out"), "--debug"])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("script", ["train_scaffold.py", "train_4dgs.py"])
def test_every_example_refuses_cuda_flags_this_machine_cannot_run(tmp_path, script):
    """The Scaffold-GS and 4DGS examples take --device / --rasterizer too, and stop the same way
    here (no CUDA): a clear error before any scene is read or folder written."""
    import torch

    assert not torch.cuda.is_available()
    spec = importlib.util.spec_from_file_location(script[:-3], EXAMPLE.parent / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    (tmp_path / "empty").mkdir()  # an existing folder that holds no scene: the device check comes first
    for flags, message in ((["--device", "cuda"], "sees no CUDA device here"),
                           (["--rasterizer", "gsplat"], "needs --device cuda")):
        with pytest.raises(ValueError, match=message):
            module.main(flags + ["--data", str(tmp_path / "empty"), "--steps", "3", "--no-progress",
                                 "--out", str(tmp_path / "out"), "--debug"])
    assert not (tmp_path / "out").exists()


def test_4dgs_says_when_test_views_lie_outside_the_training_times(tmp_path, capsys):
    """One transforms.json whose frames carry times k/8: the held-out frames 0 and 8 are at times
    0 and 1, outside the training views' [1/8, 7/8]; the run says so before training."""
    import warnings

    from test_data_transforms import _frames, _object_on, _write

    frames, _ = _frames(9, tmp_path / "scene", paint=_object_on((0, 0, 0)))
    for k, f in enumerate(frames):
        f["time"] = k / 8
    _write(tmp_path / "scene", frames)
    spec = importlib.util.spec_from_file_location("train_4dgs", EXAMPLE.parent / "train_4dgs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module.main(["--data", str(tmp_path / "scene"), "--preset", "baseline", "--steps", "20", "--init", "random",
                     "--out", str(tmp_path / "out"), "--no-progress"])
    assert ("note: 2 of the 2 test views lie outside the training views' times [0.125, 0.875] "
            "(e.g. 'images/frame_00000.png' at 0)") in capsys.readouterr().err
