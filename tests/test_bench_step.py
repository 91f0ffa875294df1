"""benchmarks/bench_step.py --views-sweep: the cost of an M-view step in one-view steps."""

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_step  # noqa: E402


def test_views_sweep_divides_each_step_by_the_one_view_step_of_its_model(monkeypatch, capsys):
    # a made-up clock: a step of m views over n Gaussians takes n/1e4 (2 + 3 m) ms and twice that in CPU
    def fake(spec, threads, args, cache, src=None):
        n, big, factor, m = spec
        assert (big, factor) == (False, 1)
        t = n / 1e4 * (2 + 3 * m) * 1e-3
        return None if (n, m) == (30_000, 8) else {"seconds": t, "cpu": 2 * t}
    monkeypatch.setattr(bench_step, "measure", fake)
    bench_step.sweep_table(1, SimpleNamespace(), {})
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| 10000") or ln.startswith("| 30000")]
    cells = {(int(r[0]), int(r[1])): r[2:] for r in ([c.strip() for c in ln.split("|")[1:-1]] for ln in lines)}
    assert set(cells) == {(n, m) for n in bench_step.SWEEP_GAUSSIANS for m in bench_step.SWEEP_VIEWS}
    for (n, m), row in cells.items():
        if (n, m) == (30_000, 8):
            assert row[1] == "failed"  # a measurement that failed says so instead of a ratio
            continue
        assert float(row[0]) == pytest.approx(n / 1e4 * (2 + 3 * m), abs=0.05)
        assert float(row[2]) == pytest.approx((2 + 3 * m) / 5, abs=0.005)  # independent of n
        assert float(row[3]) == pytest.approx((2 + 3 * m) / 5, abs=0.005)


def test_views_sweep_refuses_the_options_it_does_not_print(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_step.py", "--views-sweep", "--json", "x.json"])
    with pytest.raises(SystemExit):
        bench_step.main()
    assert "--views-sweep prints its own table only" in capsys.readouterr().err
