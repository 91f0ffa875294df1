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
    rows = bench.measure("train_3dgs.py", ["--resolution-scale", "4", "--threads", "1", "--background-points", "0"],
                         rounds=1, warmup=0)
    assert [(r["factor"], r["views"]) for r in rows] == list(bench.PAIRS)
    for r in rows:
        assert math.isclose(r["model"], r["views"] * (0.1 + 0.9 / r["factor"]), rel_tol=1e-12)
        assert r["px"] == f"{128 // (4 * r['factor'])}x{128 // (4 * r['factor'])}"
        assert r["ms"] > 0 and math.isfinite(r["measured"]) and r["measured"] > 0
    assert rows[0]["measured"] == 1.0 and len({r["gaussians"] for r in rows}) == 1  # no densification ran
    text = bench.table(rows)
    assert text.count("\n") == len(rows) + 1 and "| 4 | 4 | 8x8 |" in text


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
    with pytest.raises(ValueError, match="one-view row at a factor > 1"):
        bench.fitted_view_cost([dict(factor=1, views=1, measured=1.0)])
