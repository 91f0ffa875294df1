"""benchmarks/bench_step_parts.py: its counts against a render loop written here, its times
consistent, bad input said by name."""

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples" / "gsplat_loop"))

import bench_step_parts  # noqa: E402
import common  # noqa: E402
import simple_trainer_mvgs  # noqa: E402
from mvgs_plugin.io import load_checked  # noqa: E402
from mvgs_plugin.reference_renderer import rasterization  # noqa: E402


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    cfg = common.parse_config(["--data", str(FORWARD), "--steps", "60", "--threads", "1", "--save-steps", "60",
                               "--out", str(out)])
    common.run(simple_trainer_mvgs.Runner, cfg)
    return out / "ckpt_60.pt"


def test_the_rows_counts_are_those_of_a_plain_render_loop(checkpoint):
    text = bench_step_parts.main([str(checkpoint), "--data", str(FORWARD), "--repeats", "1"])
    row = [c.strip() for c in text.strip().splitlines()[-1].split("|")[1:-1]]
    splats = load_checked(str(checkpoint))["splats"]
    parser = common.Parser(FORWARD)
    views = common.Dataset(parser, "train")
    pairs = visible = 0
    degree = int(round((splats["shN"].shape[1] + 1) ** 0.5)) - 1
    with torch.no_grad():
        for i in range(len(views)):
            d = views[i]
            h, w = d["image"].shape[:2]
            bg = None if parser.background is None else torch.tensor([parser.background], dtype=torch.float32)
            _, _, info = rasterization(
                means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
                opacities=torch.sigmoid(splats["opacities"]), colors=torch.cat([splats["sh0"], splats["shN"]], 1),
                viewmats=torch.linalg.inv(d["camtoworld"][None]), Ks=d["K"][None], width=w, height=h,
                sh_degree=degree, backgrounds=bg)
            pairs += len(info["flatten_ids"])
            visible += int((info["radii"] > 0).all(-1).sum())
    assert int(row[1]) == len(splats["means"])
    assert int(row[2]) == round(visible / len(views))
    assert int(row[3]) == round(pairs / len(views))
    times = [float(x) for x in row[5:]]
    parts, whole = times[:-1], times[-1]
    assert all(t >= 0 for t in times) and whole > 0
    # the kernels and the loss and Adam are parts of the whole view's time
    assert sum(parts) <= whole * 1.05 + 0.5


def test_bad_input_is_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench_step_parts.main([str(tmp_path / "none.pt")])
    assert "no such checkpoint" in capsys.readouterr().err
    other = tmp_path / "other.pt"
    from mvgs_plugin.io import save_checked
    save_checked({"step": 3}, str(other))
    with pytest.raises(ValueError, match="other.pt: not a checkpoint of the gsplat loop"):
        bench_step_parts.main([str(other), "--data", str(FORWARD)])
