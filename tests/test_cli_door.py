"""The door as a new user meets it (issue 25, part 2): an input error is one line on stderr and
exit code 2 (a traceback only with --debug), a --resolution-scale that leaves images too small
is refused, the main job prints one line when stderr is not a terminal, every output gets the
mode a plain open() gives, and benchmark records carry no machine path."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
TINY = ["--steps", "3", "--resolution-scale", "4", "--no-progress"]


def run(script: str, *argv: str, cwd=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, str(EXAMPLES / script), *argv], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=300)


def one_error_line(proc: subprocess.CompletedProcess, script: str, *needles: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith(f"{script}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture()
def folders(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    for name in ("r_000.png", "r_001.png"):
        (pngs / name).write_bytes((ROOT / "examples" / "scenes" / "tabletop" / "train" / name).read_bytes())
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    return empty, pngs, afile


@pytest.mark.parametrize("script", ["train_3dgs.py", "train_scaffold.py", "train_4dgs.py"])
def test_a_folder_without_a_scene_is_one_line_and_exit_2(script, folders, tmp_path):
    empty, pngs, _ = folders
    one_error_line(run(script, "--data", str(empty), "--out", str(tmp_path / "o1"), *TINY), script,
                   str(empty), "neither a COLMAP scene")
    if script == "train_3dgs.py":
        one_error_line(run(script, "--data", str(pngs), "--out", str(tmp_path / "o2"), *TINY), script, str(pngs))
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()  # nothing written


def test_4dgs_refuses_a_static_scene_and_an_empty_init_box_in_one_line(tmp_path):
    """A static NeRF-layout scene (the bundled tabletop) is refused before it is read; an --init-box
    whose minimum is not below its maximum, and --export-times that would write one file twice,
    before anything runs."""
    bundled = str(Path(__file__).resolve().parents[1] / "examples" / "scenes" / "tabletop")
    one_error_line(run("train_4dgs.py", "--data", bundled, "--out", str(tmp_path / "o"), *TINY), "train_4dgs.py",
                   bundled, "4DGS needs a dynamic scene")
    one_error_line(run("train_4dgs.py", "--data", bundled, "--init-box", "1", "1", "1", "0", "0", "0",
                       "--out", str(tmp_path / "o"), *TINY), "train_4dgs.py", "--init-box 1 1 1 0 0 0",
                   "each minimum below its maximum")
    one_error_line(run("train_4dgs.py", "--data", bundled, "--init-box", "0", "0", "0", "1", "1", "1",
                       "--out", str(tmp_path / "o"), *TINY), "train_4dgs.py", "--init-box 0 0 0 1 1 1",
                   "--init-random is 0", "give --init-random N too")
    one_error_line(run("train_4dgs.py", "--data", bundled, "--export-times", "0.0001", "0.0004", "0.5",
                       "--out", str(tmp_path / "o"), *TINY), "train_4dgs.py", "point_cloud_t0.000.ply",
                   "give each time once")
    assert not (tmp_path / "o").exists()


def test_an_out_that_is_a_file_is_one_line_and_the_file_is_kept(folders):
    _, _, afile = folders
    one_error_line(run("train_3dgs.py", "--out", str(afile), *TINY), "train_3dgs.py", str(afile), "existing file")
    assert afile.read_text() == "keep me"


def test_debug_shows_the_traceback(folders, tmp_path):
    empty, _, _ = folders
    proc = run("train_3dgs.py", "--data", str(empty), "--out", str(tmp_path / "o"), "--debug", *TINY)
    assert proc.returncode != 0 and "Traceback" in proc.stderr and "UsageError" in proc.stderr
    help_text = run("train_3dgs.py", "--help").stdout
    assert "--debug" in help_text and "--init {triangulate,random,frusta,cube}" in " ".join(help_text.split())


def test_a_resolution_scale_that_leaves_images_under_16_px_is_refused(tmp_path):
    line = one_error_line(run("train_3dgs.py", "--resolution-scale", "1000", "--steps", "3", "--out", str(tmp_path / "o")),
                          "train_3dgs.py", "--resolution-scale 1000", "128x128")
    # the sizes it names are the camera's own arithmetic, and the largest scale it offers works
    from mvgs_plugin.camera import scaled_size

    assert f"images {'x'.join(map(str, scaled_size(128, 128, 1000)))}" in line and "at most 8" in line
    assert not (tmp_path / "o").exists()
    from mvgs_plugin.cli import MIN_IMAGE_SIDE

    assert min(scaled_size(128, 128, 8)) >= MIN_IMAGE_SIDE > min(scaled_size(128, 128, 9))


def test_the_main_job_prints_one_line_when_stderr_is_not_a_terminal(tmp_path):
    proc = run("train_3dgs.py", "--steps", "3", "--resolution-scale", "4", "--out", str(tmp_path / "o"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    # a 3-step run is told that it densifies at no step (a note, before training), then the result
    assert len(lines) == 2 and lines[0].startswith("train_3dgs.py: note: --steps 3: this run densifies at no step")
    assert lines[1].startswith("default: test PSNR "), proc.stderr
    assert proc.stdout == ""


def test_a_run_too_short_to_densify_is_told_so_and_one_long_enough_is_not(capsys):
    """The note's rule against the schedule itself: a run gets the note exactly when none of its
    steps densifies (the controller's own plan, stepped through), for 3DGS's and 4DGS's flags."""
    import importlib.util

    from mvgs_plugin.schedule import ViewSchedule
    from mvgs_plugin.testing import synthetic_scene

    scene = synthetic_scene(n_train=6, n_test=2, size=16, n_points=80)
    for script, extra in (("train_3dgs.py", []), ("train_4dgs.py", ["--data", str(ROOT / "tests" / "data" / "forward64")])):
        spec = importlib.util.spec_from_file_location(script[:-3] + "_note", EXAMPLES / script)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        for steps in (60, 150, 160, 200, 400):
            capsys.readouterr()
            config = module.config_from_args(module.parse_args(["--steps", str(steps), *extra]))
            told = "densifies at no step" in capsys.readouterr().err
            densified = any(plan.densify for plan in ViewSchedule(scene, config, load_images=False))
            assert told == (not densified), (script, steps, told)


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_output_of_the_main_job_gets_the_plain_new_file_mode(tmp_path):
    old = os.umask(0o027)  # an unusual umask, so a hard-coded 0o644 would fail too
    try:
        plain = tmp_path / "plain.txt"
        plain.write_text("x")
        expected = os.stat(plain).st_mode & 0o777
        out = tmp_path / "o"
        _load("train_3dgs").main(["--out", str(out), "--checkpoint", *TINY])
    finally:
        os.umask(old)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert {p.suffix for p in files} >= {".png", ".json", ".ply", ".pt"}, files
    wrong = {str(p.relative_to(out)): oct(os.stat(p).st_mode & 0o777) for p in files
             if os.stat(p).st_mode & 0o777 != expected}
    assert not wrong and expected == 0o640, wrong


def test_benchmark_records_keep_paths_relative_to_the_repository(tmp_path):
    from mvgs_plugin.cli import repo_path, without_machine_paths

    assert repo_path(ROOT / "examples" / "scenes" / "tabletop") == "examples/scenes/tabletop"
    assert repo_path("scenes/forward") == "scenes/forward"
    outside = tmp_path / "scenes" / "forward"
    assert repo_path(outside) == ".../scenes/forward" and str(tmp_path) not in repo_path(outside)
    text = json.dumps({"data": str(outside), "cmd": f"python x.py --data {ROOT / 'examples'} --out {tmp_path}/o."})
    cleaned = json.loads(without_machine_paths(text))
    assert cleaned == {"data": ".../scenes/forward", "cmd": f"python x.py --data examples --out .../{tmp_path.name}/o."}


def test_records_written_from_a_clone_anywhere_lose_its_path(monkeypatch):
    # CI clones the repository outside /work, /tmp, /home and /root: its own paths still go
    import mvgs_plugin.cli as cli

    monkeypatch.setattr(cli, "ROOT", Path("/check/work/main"))
    text = "python b.py --data /check/work/main/examples/scenes/tabletop --out /check/work/main and /check/work/mainly/x"
    assert cli.without_machine_paths(text) == "python b.py --data examples/scenes/tabletop --out . and /check/work/mainly/x"


@pytest.mark.parametrize("script", ["train_3dgs.py", "train_scaffold.py"])
def test_an_out_folder_whose_renders_would_replace_the_scenes_images_is_refused(script, tmp_path):
    # --out set to a NeRF-layout scene's own folder: OUT/test/r_000.png is the scene's test image.
    # The refusal comes before any work, and every image of the scene keeps its bytes.
    scene = tmp_path / "scene"
    import shutil

    shutil.copytree(ROOT / "tests" / "data" / "forward64", scene)
    before = {p: p.read_bytes() for p in scene.rglob("*.png")}
    test_pngs = sorted((scene / "test").glob("*.png"))
    assert test_pngs
    for out in (scene, scene / "." / "test" / ".."):
        one_error_line(run(script, "--data", str(scene), "--out", str(out), *TINY), script,
                       f"--out {out}", "would replace the scene's image", test_pngs[0].name)
    assert {p: p.read_bytes() for p in scene.rglob("*.png")} == before
    assert not (scene / "metrics.json").exists() and not (scene / "checkpoint.pt").exists()
    # a folder beside the scene is fine
    proc = run(script, "--data", str(scene), "--out", str(tmp_path / "out"), *TINY)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert {p: p.read_bytes() for p in scene.rglob("*.png")} == before


def timed_scene(tmp_path) -> Path:
    """A copy of tests/data/forward64 whose frames carry times (a D-NeRF scene)."""
    import shutil

    scene = tmp_path / "timed"
    shutil.copytree(ROOT / "tests" / "data" / "forward64", scene)
    for split in ("train", "test"):
        path = scene / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        n = len(meta["frames"])
        for i, frame in enumerate(meta["frames"]):
            frame["time"] = i / max(1, n - 1)
        path.write_text(json.dumps(meta))
    return scene


def test_a_dynamic_scene_given_to_a_static_model_is_trained_with_a_note(tmp_path):
    # Frames with a time (D-NeRF) given to train_3dgs.py: one static model is trained, and the
    # user is told so and pointed at train_4dgs.py; a static scene gets no such line.
    scene = timed_scene(tmp_path)
    proc = run("train_3dgs.py", "--data", str(scene), "--out", str(tmp_path / "o"), *TINY)
    assert proc.returncode == 0, proc.stderr[-2000:]
    notes = [line for line in proc.stderr.splitlines()  # (a tiny run is also told it densifies at no step)
             if line.startswith("train_3dgs.py: note: ") and "densifies at no step" not in line]
    n_train = len(json.loads((scene / "transforms_train.json").read_text())["frames"])
    assert len(notes) == 1 and f"{n_train} of the {n_train} training frames" in notes[0] and "train_4dgs.py" in notes[0]
    plain = run("train_3dgs.py", "--data", str(ROOT / "tests" / "data" / "forward64"), "--out", str(tmp_path / "p"), *TINY)
    assert plain.returncode == 0 and "carry a time" not in plain.stderr, plain.stderr[-2000:]


@pytest.mark.parametrize("blocker, kind", [("test", "file"), ("point_cloud.ply", "folder"), ("metrics.json", "folder")])
def test_a_reused_out_whose_outputs_cannot_be_written_is_refused_before_training(tmp_path, blocker, kind):
    out = tmp_path / "o"
    out.mkdir()
    path = out / blocker
    if kind == "file":
        path.write_text("keep me")
    else:
        path.mkdir()
    one_error_line(run("train_3dgs.py", "--out", str(out), *TINY), "train_3dgs.py", f"--out {out}", str(path),
                   f"is a {kind}")
    assert sorted(p.name for p in out.iterdir()) == [blocker]  # nothing trained, nothing written
    assert kind != "file" or path.read_text() == "keep me"


def test_a_reused_4dgs_out_keeps_only_this_runs_baked_times(tmp_path):
    scene, out = timed_scene(tmp_path), tmp_path / "o"
    out.mkdir()
    (out / "point_cloud_t0.900.ply").write_text("not ours")  # no run of ours listed it: it stays
    common = ["--data", str(scene), "--out", str(out), "--preset", "baseline", "--steps", "6", "--no-progress"]
    assert run("train_4dgs.py", *common).returncode == 0
    first = {"point_cloud_t0.000.ply", "point_cloud_t0.500.ply", "point_cloud_t1.000.ply"}
    assert first <= {p.name for p in out.iterdir()}
    proc = run("train_4dgs.py", *common, "--export-times", "0.25")
    assert proc.returncode == 0, proc.stderr[-2000:]
    baked = sorted(p.name for p in out.glob("point_cloud_t*.ply"))
    assert baked == ["point_cloud_t0.250.ply", "point_cloud_t0.900.ply"], baked
    assert json.loads((out / "metrics.json").read_text())["baked"] == ["point_cloud_t0.250.ply"]
    (out / "point_cloud_t0.750.ply").mkdir()  # a folder where a bake goes: refused before training
    proc = run("train_4dgs.py", *common, "--export-times", "0.75", "--steps", "100000")
    one_error_line(proc, "train_4dgs.py", f"--out {out}: {out / 'point_cloud_t0.750.ply'} is a folder, where the "
                                          "run writes the baked point_cloud_t0.750.ply")
