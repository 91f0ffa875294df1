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


def test_an_example_other_than_3dgs_or_4dgs_is_refused():
    with pytest.raises(SystemExit, match="train_3dgs.py or train_4dgs.py, got 'train_scaffold.py'"):
        bench.load_example("train_scaffold.py")
