"""Each training example through every phase a user's run reaches (stage hand-offs,
densification, opacity resets), interrupted and resumed from its checkpoint: the resumed run ends
with the same model and metrics as the uninterrupted one, to the last digit.

The interruption is a crash raised inside the step after the last periodic checkpoint
(--checkpoint-every), as a killed run would leave it; the second process is the same command with
--resume. 3DGS and Scaffold-GS train on the bundled scene at 1/8 resolution (16 px), 4DGS on a
generated D-NeRF scene.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from mvgs_plugin import controller
from mvgs_plugin.config import DEFAULT_SHARES
from mvgs_plugin.testing import synthetic_scene

ROOT = Path(__file__).resolve().parents[1]
STEPS, EVERY = 400, 150  # 4DGS: 240, 90 (its phases fit in 240 steps, which cost more than 3DGS's)


def _example(script: str):
    spec = importlib.util.spec_from_file_location(script[:-3] + "_resume", ROOT / "examples" / script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _dnerf(root: Path) -> Path:
    """A generated D-NeRF scene with its 300 points in points3d.ply (without them the example
    triangulates, finds nothing at 16 px and starts from 10,000 random points)."""
    import numpy as np
    from plyfile import PlyData, PlyElement
    from test_adapter_gs4d import _write_dnerf  # the D-NeRF writer the 4DGS example test uses

    scene = synthetic_scene(n_train=12, n_test=2, size=16, time=True)
    _write_dnerf(root, scene)
    xyz, rgb = scene.points.xyz.numpy(), (scene.points.rgb.numpy() * 255).round().astype(np.uint8)
    vertex = np.empty(len(xyz), dtype=[(k, "f4") for k in "xyz"] + [(k, "u1") for k in ("red", "green", "blue")])
    for i, k in enumerate("xyz"):
        vertex[k] = xyz[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        vertex[k] = rgb[:, i]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(root / "points3d.ply"))
    return root


class Crash(RuntimeError):
    pass


def record_steps(monkeypatch) -> list:
    """A list that gets the StepInfo of every MVGS.step() the test runs (clear it between runs)."""
    infos = []
    step = controller.MVGS.step

    def recording(self):
        info = step(self)
        infos.append(info)
        return info

    monkeypatch.setattr(controller.MVGS, "step", recording)
    return infos


@pytest.mark.slow
@pytest.mark.parametrize("script, extra, views, steps, every", [
    # 3DGS's unscaled threshold: at 16 px the default's (meant for 800 px) grows nothing
    ("train_3dgs.py", ["--resolution-scale", "8", "--threshold-width", "0"], 2, STEPS, EVERY),
    # with the faintest splats cut at every densification (their blend statistics are checkpointed)
    ("train_3dgs.py", ["--resolution-scale", "8", "--threshold-width", "0", "--prune-faint", "0.02"], 2, STEPS, EVERY),
    ("train_scaffold.py", ["--resolution-scale", "8", "--voxel-size", "0.1", "--threshold-width", "0"], 2, STEPS, EVERY),
    # 4DGS's own default: one view per pyramid step, then 2-view steps at the end (--late-views);
    # its M-view steps at every level run through the same adapter in test_adapter_gs4d.py
    # (a threshold meant for 48 px: it grows 1.4k Gaussians to 4.5k, where 3DGS's grows 11k)
    # (resets 10 densifications apart: with 3DGS's 30 a 240-step run has none)
    ("train_4dgs.py", ["--init-random", "60", "--export-times", "0.5", "--threshold-width", "48",
                       "--min-densify-per-reset", "10"], None, 240, 90),
])
def test_interrupted_run_resumes_to_the_same_result(tmp_path, monkeypatch, script, extra, views, steps, every):
    if script == "train_4dgs.py":
        extra = extra + ["--data", str(_dnerf(tmp_path / "scene"))]
    example = _example(script)
    base = ["--preset", "default", "--steps", str(steps), "--threads", "1", "--no-progress", *extra]
    base += ["--views", str(views)] if views else []

    step = controller.MVGS.step  # the real one, for the crash and the resume below
    infos = record_steps(monkeypatch)
    whole = example.main(base + ["--out", str(tmp_path / "whole")])
    # the run went through every phase
    levels = len(DEFAULT_SHARES)  # the default's pyramid levels; 4DGS adds its late 2-view stage
    assert len(infos) == steps and len({i.stage for i in infos}) == (levels if views else levels + 1)
    if not views:  # the late 2-view stage, in the part the resumed run makes
        late = [i for i in infos if i.stage == levels]
        assert late and all(len(i.views) == 2 for i in late) and late[0].step > every
        assert all(len(i.views) == 1 for i in infos if i.stage < levels)
    densified = [i.step for i in infos if i.densify is not None]
    resets = [i.step for i in infos if i.opacity_reset]
    assert densified and resets, (densified, resets)
    grown = [i.step for i in infos if i.densify is not None and i.densify.after > i.densify.before]
    assert any(d > every for d in grown), ("the resumed part must grow the model too", grown)
    if "--prune-faint" in extra:  # the cut removes Gaussians, in the resumed part too
        cut = [i.step for i in infos if i.densify is not None and i.densify.extra["faint"] > 0]
        assert any(d > every for d in cut), cut
        assert whole["densification"]["faint"] == sum(i.densify.extra["faint"] for i in infos if i.densify)

    def crashing(self):
        if self.step_count == 2 * every - 20:  # after the checkpoint at `every`, before the next
            raise Crash("simulated kill")
        return step(self)

    monkeypatch.setattr(controller.MVGS, "step", crashing)
    with pytest.raises(Crash):
        example.main(base + ["--out", str(tmp_path / "cut"), "--checkpoint-every", str(every)])
    checkpoint = tmp_path / "cut" / "checkpoint.pt"
    assert checkpoint.exists() and not (tmp_path / "cut" / "metrics.json").exists()

    monkeypatch.setattr(controller.MVGS, "step", step)
    infos = record_steps(monkeypatch)  # the resumed run's steps, from the real step
    resumed = example.main(base + ["--out", str(tmp_path / "resumed"), "--resume", str(checkpoint)])
    assert [i.step for i in infos] == list(range(every + 1, steps + 1))  # only the steps after the checkpoint
    for key in ("psnr", "ssim", "steps", "work", "num_gaussians"):
        assert resumed[key] == whole[key], (key, resumed[key], whole[key])
    # the densification record is the whole run's, not the resumed part's (the checkpoint carries it)
    assert resumed["densification"] == whole["densification"], (resumed["densification"], whole["densification"])
    assert [v["psnr"] for v in resumed["per_view"]] == [v["psnr"] for v in whole["per_view"]]
    assert (tmp_path / "resumed" / "point_cloud.ply").read_bytes() == (tmp_path / "whole" / "point_cloud.ply").read_bytes()
    saved = json.loads((tmp_path / "resumed" / "metrics.json").read_text())
    assert saved["psnr"] == whole["psnr"]


def test_resume_needs_an_existing_file(tmp_path):
    example = _example("train_3dgs.py")
    with pytest.raises(SystemExit):
        example.parse_args(["--resume", str(tmp_path / "missing.pt")])


def test_ctrl_c_says_where_the_run_stopped_and_how_to_resume(tmp_path, monkeypatch, capsys):
    """A KeyboardInterrupt inside a step ends the example with exit code 130 and one line naming
    the step and the checkpoint to resume from (or that nothing was saved), not a traceback; the
    checkpoint resumed with another model flag (--world-size-rule) is refused naming it."""
    example = _example("train_3dgs.py")
    step = controller.MVGS.step

    def interrupted(self):
        if self.step_count == 7:
            raise KeyboardInterrupt
        return step(self)

    monkeypatch.setattr(controller.MVGS, "step", interrupted)
    base = ["--steps", "20", "--threads", "1", "--no-progress", "--resolution-scale", "8"]
    with pytest.raises(SystemExit) as err:
        example.main(base + ["--out", str(tmp_path / "a"), "--checkpoint-every", "5"])
    checkpoint = tmp_path / "a" / "checkpoint.pt"
    assert err.value.code == 130 and checkpoint.exists()
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said.endswith(f"interrupted at step 7 of 20; the checkpoint {checkpoint} (written at step 5) resumes "
                         f"it: the same command with --resume {checkpoint}")
    monkeypatch.setattr(controller.MVGS, "step", step)
    with pytest.raises(SystemExit) as err:  # a model flag the checkpoint was not made with: refused, named
        example.main(base + ["--out", str(tmp_path / "r"), "--resume", str(checkpoint), "--world-size-rule", "extent"])
    assert err.value.code == 2
    assert "other model settings (world_size_rule: checkpoint 'distance', this command 'extent')" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit) as err:  # another run config: named, with a command line's advice
        example.main(base + ["--out", str(tmp_path / "r"), "--resume", str(checkpoint), "--max-gaussians", "900"])
    said = capsys.readouterr().err
    assert err.value.code == 2 and "made with other settings (max_gaussians: checkpoint None, this run 900); resume " \
        "with the flags it was written with" in said and "strict=False" not in said
    with pytest.raises(SystemExit) as err:  # another script's model: named as such, before its config
        _example("train_scaffold.py").main(base + ["--out", str(tmp_path / "s"), "--resume", str(checkpoint)])
    said = capsys.readouterr().err
    assert err.value.code == 2 and "the checkpoint holds a 'mvgs-gs3d/1' model and this run trains a " \
        "'mvgs-scaffold/1' model (ScaffoldAdapter): it was written by another script or adapter" in said
    assert "stages" not in said and not (tmp_path / "s" / "metrics.json").exists()
    monkeypatch.setattr(controller.MVGS, "step", interrupted)
    for out in ("b", "a"):  # no checkpoint; a checkpoint.pt of an earlier run in --out is not this run's
        with pytest.raises(SystemExit) as err:
            example.main(base + ["--out", str(tmp_path / out)])
        assert err.value.code == 130
        assert "interrupted at step 7 of 20; no checkpoint of this run was written (--checkpoint-every N" in \
            capsys.readouterr().err
