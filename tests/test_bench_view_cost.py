"""bench_view_cost builds each (factor, views) trainer from the example's own flags and prints the
budget clock's cost model beside the measured CPU; the model column is checked here against the
formula written out (a view at factor f costs 0.1 + 0.9 / f), and every pair against the stage it
asked for. Times themselves are the benchmark's to report, not asserted."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_view_cost as bench  # noqa: E402


def test_the_table_has_every_pair_with_the_cost_model_written_out():
    """--resolution-scale 3 on the 128 px tabletop: the image column is the size of the image the
    scene hands the renderer at each factor (42.7 px rounds to 43, 10.7 to 11), read from the
    image itself."""
    from mvgs_plugin.data import load_scene

    rows = bench.measure("train_3dgs.py", ["--resolution-scale", "3", "--threads", "1", "--background-points", "0"],
                         rounds=1, warmup=0)
    assert [(r["factor"], r["views"]) for r in rows] == list(bench.PAIRS)
    scene = load_scene(ROOT / "examples" / "scenes" / "tabletop")
    for r in rows:
        assert math.isclose(r["model"], r["views"] * (0.1 + 0.9 / r["factor"]), rel_tol=1e-12)
        img = scene.image(scene.train_cameras[0], 3 * r["factor"])
        assert r["px"] == f"{img.shape[1]}x{img.shape[0]}"  # [H, W, 3]
        assert r["ms"] > 0 and math.isfinite(r["measured"]) and r["measured"] > 0
    assert len({r["gaussians"] for r in rows}) == 1  # no densification ran: the count never moved
    assert rows[2]["px"] == "11x11"
    text = bench.table(rows)
    assert text.count("\n") == len(rows) + 1 and "| 4 | 4 | 11x11 |" in text


def test_an_example_without_a_model_of_its_own_is_refused():
    with pytest.raises(SystemExit, match="train_3dgs.py, train_4dgs.py, train_scaffold.py, got 'ablation.py'"):
        bench.load_example("ablation.py")


def test_the_fitted_view_cost_recovers_a_model_it_was_made_from():
    """Rows made exactly from A + (1 - A) / f give A back; noisy ones the least-squares value
    worked out by hand; multi-view rows are not used."""
    for a in (0.0, 0.1, 0.64, 1.0):
        rows = [dict(factor=f, views=1, measured=a + (1 - a) / f) for f in (1, 2, 4)]
        rows.append(dict(factor=4, views=4, measured=9.0))
        assert math.isclose(bench.fitted_view_cost(rows), a, abs_tol=1e-12)
    # f = 2: 0.81, f = 4: 0.76 -> u = (0.5, 0.75), c = (0.31, 0.51): A = (0.155 + 0.3825) / 0.8125
    rows = [dict(factor=1, views=1, measured=1.0), dict(factor=2, views=1, measured=0.81),
            dict(factor=4, views=1, measured=0.76)]
    assert math.isclose(bench.fitted_view_cost(rows), 0.5375 / 0.8125, rel_tol=1e-12)
    # 3DGS's whole steps (0.36 at 1/2, 0.19 at 1/4) fit a negative A: clipped to 0, as a slope above 1 to 1
    rows = [dict(factor=2, views=1, measured=0.36), dict(factor=4, views=1, measured=0.19)]
    assert (0.5 * (0.36 - 0.5) + 0.75 * (0.19 - 0.25)) < 0 and bench.fitted_view_cost(rows) == 0.0
    assert bench.fitted_view_cost([dict(factor=2, views=1, measured=1.3)]) == 1.0
    with pytest.raises(ValueError, match="one-view row at a factor > 1"):
        bench.fitted_view_cost([dict(factor=1, views=1, measured=1.0)])
