"""benchmarks/probe_blend_weight.py: its rows against quantities computed here (the test PSNR of
the whole model, the weight the removed Gaussians carry), bad input said by name."""

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import common  # noqa: E402
import probe_blend_weight  # noqa: E402
import simple_trainer_mvgs  # noqa: E402
from mvgs_plugin.io import load_checked  # noqa: E402
from test_bench_step_parts import checkpoint, plain_render  # noqa: E402,F401  (the 60-step gsplat-loop checkpoint fixture)


def _rows(text):
    return [[c.strip() for c in line.split("|")[1:-1]] for line in text.strip().splitlines()[-3:]]


def test_rows_against_a_psnr_and_weights_computed_here(checkpoint):
    text = probe_blend_weight.main([str(checkpoint), "--data", str(FORWARD), "--shares", "0.01", "0.05",
                                    "--repeats", "1"])
    rows = _rows(text)
    assert [r[1].split(" / ")[0] for r in rows] == ["0.00%", "1.00%", "5.00%"]
    splats = load_checked(str(checkpoint))["splats"]
    n = len(splats["means"])
    # the whole model's test PSNR, rendered here through the renderer's own entry point
    parser = common.Parser(FORWARD)
    views = common.Dataset(parser, "test")
    degree = int(round((splats["shN"].shape[1] + 1) ** 0.5)) - 1
    psnrs = []
    with torch.no_grad():
        for i in range(len(views)):
            d = views[i]
            img, _, _ = plain_render(splats, parser, d, degree)
            psnrs.append(float(-10 * torch.log10(((img[0].clamp(0, 1) - d["image"] / 255.0) ** 2).mean())))
    assert float(rows[0][6]) == pytest.approx(sum(psnrs) / len(psnrs), abs=2e-3)
    assert rows[0][2] == "0" and int(rows[0][3]) == n and rows[0][4] == "0.0%"
    removed = [int(r[2]) for r in rows]
    assert removed[0] < removed[1] <= removed[2] and all(int(r[2]) + int(r[3]) == n for r in rows)
    for r in rows[1:]:
        asked, got = (float(x.rstrip("%")) for x in r[1].split(" / "))
        assert got <= asked + 1e-6  # the removed Gaussians carry at most the share asked
        assert float(r[4].rstrip("%")) > got  # and take a larger share of the pixels: least weight per pixel first
    # fewer Gaussians blended per pixel once they are gone
    assert float(rows[2][5]) < float(rows[0][5])


def test_bad_input_is_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        probe_blend_weight.main([str(tmp_path / "none.pt")])
    assert "no such checkpoint" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        probe_blend_weight.main([str(tmp_path / "none.pt"), "--shares", "1.5"])
    assert "--shares 1.5: each share must be in (0, 1)" in capsys.readouterr().err


def test_a_pruned_checkpoint_keeps_the_rows_it_keeps_and_resumes(tmp_path):
    # an 80-step run saved at step 60, pruned there, then resumed to 80
    first = tmp_path / "first"
    args = ["--data", str(FORWARD), "--steps", "80", "--threads", "1"]
    common.run(simple_trainer_mvgs.Runner, common.parse_config(args + ["--save-steps", "60", "--out", str(first)]))
    checkpoint = first / "ckpt_60.pt"
    out = tmp_path / "pruned"
    out.mkdir()
    probe_blend_weight.main([str(checkpoint), "--data", str(FORWARD), "--shares", "0.05", "--repeats", "1",
                             "--write-pruned", str(out)])
    saved = load_checked(str(checkpoint))
    pruned = load_checked(str(out / "ckpt_60_pruned_0.05.pt"))
    n, m = len(saved["splats"]["means"]), len(pruned["splats"]["means"])
    assert 0 < m < n and pruned["data"]["mvgs"]["count"] == m
    # the kept rows are the original's, in order, in the parameters, Adam's moments and the statistics
    means, kept = saved["splats"]["means"], pruned["splats"]["means"]
    rows = [int(torch.nonzero((means == kept[j]).all(-1))[0, 0]) for j in range(m)]
    assert rows == sorted(rows)
    idx = torch.tensor(rows)
    for name in saved["splats"]:
        assert torch.equal(pruned["splats"][name], saved["splats"][name][idx])
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(pruned["optimizers"][name]["state"][0][key], saved["optimizers"][name]["state"][0][key][idx])
    for key in ("grad2d", "count"):
        assert torch.equal(pruned["strategy_state"][key], saved["strategy_state"][key][idx])
    # and the loop resumes from it: 20 more steps on the smaller model
    run = tmp_path / "resumed"
    cfg = common.parse_config(args + ["--save-steps", "80", "--resume", str(out / "ckpt_60_pruned_0.05.pt"),
                                      "--out", str(run)])
    common.run(simple_trainer_mvgs.Runner, cfg)
    final = load_checked(str(run / "ckpt_80.pt"))
    assert final["step"] == 80 and len(final["splats"]["means"]) == m


def test_write_pruned_needs_a_directory(checkpoint, tmp_path, capsys):
    with pytest.raises(SystemExit):
        probe_blend_weight.main([str(checkpoint), "--write-pruned", str(tmp_path / "nowhere")])
    assert "--write-pruned" in capsys.readouterr().err
