"""benchmarks/bench_step_parts.py: its counts against a render loop written here, its times
consistent, bad input said by name."""

import math
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


def plain_render(splats, parser, d, degree: int):
    """One view d of the loop's model rendered through the renderer's own entry point, with none of
    the loop's code: (image, alphas, info)."""
    h, w = d["image"].shape[:2]
    bg = None if parser.background is None else torch.tensor([parser.background], dtype=torch.float32)
    return rasterization(
        means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
        opacities=torch.sigmoid(splats["opacities"]), colors=torch.cat([splats["sh0"], splats["shN"]], 1),
        viewmats=torch.linalg.inv(d["camtoworld"][None]), Ks=d["K"][None], width=w, height=h,
        sh_degree=degree, backgrounds=bg)


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
            _, _, info = plain_render(splats, parser, views[i], degree)
            pairs += len(info["flatten_ids"])
            visible += int((info["radii"] > 0).all(-1).sum())
    assert int(row[1]) == len(splats["means"])
    assert int(row[2]) == round(visible / len(views))
    assert int(row[3]) == round(pairs / len(views))
    assert float(row[5]) > 0  # blended / pixel
    times = [float(x) for x in row[6:]]
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


def _info(means2d, conics, opacities, depths):
    n = len(means2d)
    return {"means2d": torch.tensor([means2d], dtype=torch.float32), "conics": torch.tensor([conics], dtype=torch.float32),
            "opacities": torch.tensor([opacities], dtype=torch.float32), "depths": torch.tensor([depths], dtype=torch.float32),
            "radii": torch.full((1, n, 2), 3, dtype=torch.int32), "tile_size": 16}


def test_blended_count_of_a_stack_is_where_the_transmittance_stops():
    # 20 Gaussians of opacity 0.5 centred on pixel (4, 4): there the transmittance halves with
    # each one, and the 14th would take it to 0.5**14 = 6.1e-5 < 1e-4, so 13 are blended.
    # At pixel (6, 4), two pixels off, sigma = 0.5 * 4 * 0.5 = 1 (conic a = 0.5): alpha =
    # 0.5 e^-1 each, so k are blended while (1 - 0.5 e^-1)**k >= 1e-4.
    n = 20
    counts, trans, pairs, weight = bench_step_parts.contributors_per_pixel(
        _info([[4.5, 4.5]] * n, [[0.5, 0.0, 0.5]] * n, [0.5] * n, list(range(1, n + 1))), 9, 9)
    assert counts[4, 4] == 13
    assert float(trans[4, 4]) == pytest.approx(0.5 ** 13, rel=1e-9)
    a = 0.5 * math.exp(-1.0)
    k = int(math.floor(math.log(1e-4) / math.log(1.0 - a)))
    expected = min(n, k)
    assert counts[4, 6] == expected
    assert float(trans[4, 6]) == pytest.approx((1.0 - a) ** expected, rel=1e-6)
    # a pixel corner far from the centre: sigma = 0.5 * 0.5 * (16 + 16) = 8, alpha = 0.5 e^-8 < 1/255
    assert counts[0, 0] == 0 and float(trans[0, 0]) == 1.0
    # per Gaussian: the front one is blended wherever any is, and carries alpha there (T = 1 in
    # front of it); the 14th is blended nowhere near the centre
    front = torch.tensor([0.5 * math.exp(-0.5 * 0.5 * ((x + 0.5 - 4.5) ** 2 + (y + 0.5 - 4.5) ** 2))
                          for y in range(9) for x in range(9)], dtype=torch.float64)
    front = front[front >= 1.0 / 255.0]
    assert int(pairs[0]) == len(front)
    assert float(weight[0]) == pytest.approx(float(front.sum()), rel=1e-6)
    assert pairs[13] < pairs[0]


def test_blended_count_agrees_with_the_renderers_transmittance(checkpoint):
    splats = load_checked(str(checkpoint))["splats"]
    parser = common.Parser(FORWARD)
    d = common.Dataset(parser, "train")[0]
    h, w = d["image"].shape[:2]
    degree = int(round((splats["shN"].shape[1] + 1) ** 0.5)) - 1
    with torch.no_grad():
        _, alpha, info = rasterization(
            means=splats["means"], quats=splats["quats"], scales=torch.exp(splats["scales"]),
            opacities=torch.sigmoid(splats["opacities"]), colors=torch.cat([splats["sh0"], splats["shN"]], 1),
            viewmats=torch.linalg.inv(d["camtoworld"][None]), Ks=d["K"][None], width=w, height=h, sh_degree=degree)
    counts, trans, pairs, weight = bench_step_parts.contributors_per_pixel(info, w, h)
    rendered = 1.0 - alpha[0, ..., 0].double()
    # every blended Gaussian takes at least 1/255 of what is left: a count off by one would move
    # the transmittance by 0.4 % of itself (a count that ignores the tile lists is off by one in
    # a few pixels of this view, where a Gaussian reaches past its 3-sigma tiles)
    assert torch.allclose(trans, rendered, rtol=1e-3, atol=1e-6)
    assert counts.min() >= 0 and counts.max() <= int((info["radii"] > 0).all(-1).sum())
    assert counts.mean() > 1.0
    # the per-Gaussian sums add up to the per-pixel ones: pairs to the counts, weights to the
    # opacity each pixel reached (1 - T: what is not transmitted was blended)
    assert float(pairs.sum()) == float(counts.sum())
    assert float(weight.sum()) == pytest.approx(float((1.0 - trans).sum()), rel=1e-9)
    assert bool((pairs[~(info["radii"][0] > 0).all(-1)] == 0).all())
