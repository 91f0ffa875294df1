"""The GPU path: one flag on the gsplat loop, a benchmark ready for a GPU machine.

Without CUDA the GPU training test is skipped with its reason (shown in pytest's summary), and
bench_gpu.py says there is nothing to run and writes nothing; its table logic runs here on the
CPU with --device cpu, checked against the metrics files the runs wrote.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
FORWARD = ROOT / "tests" / "data" / "forward64"
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_gpu  # noqa: E402

NO_CUDA = "no CUDA device: the --device cuda --rasterizer gsplat path needs one"


@pytest.mark.skipif(not torch.cuda.is_available(), reason=NO_CUDA)
def test_the_gsplat_loop_trains_on_the_gpu_with_one_flag(tmp_path):
    out = tmp_path / "gpu"
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "gsplat_loop" / "simple_trainer_mvgs.py"),
                           "--data", str(FORWARD), "--steps", "120", "--out", str(out), "--preset", "multiview",
                           "--device", "cuda", "--rasterizer", "gsplat"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["device"] == "cuda" and metrics["gpu_peak_memory_mb"] > 0 and metrics["psnr"] > 15


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: bench_gpu.py would run")
def test_bench_gpu_without_cuda_says_so_and_writes_nothing(tmp_path, capsys):
    table = tmp_path / "t.md"
    assert bench_gpu.main(["--out", str(tmp_path / "o"), "--table", str(table)]) == 0
    assert "no CUDA device" in capsys.readouterr().out
    assert not table.exists() and not (tmp_path / "o").exists()


def test_bench_gpu_table_on_the_cpu(tmp_path, capsys):
    out = tmp_path / "o"
    assert bench_gpu.main(["--device", "cpu", "--steps", "12", "--presets", "default", "--data", str(FORWARD),
                           "--out", str(out), "--table", str(tmp_path / "t.md")]) == 0
    text = (tmp_path / "t.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| run")]
    assert len(rows) == 5
    runs = out / "forward64"
    single, preset = (json.loads((runs / n / "metrics.json").read_text()) for n in ("single", "default"))
    # the equal-time runs got the steps that cost the other run's time
    ratio = preset["cpu_seconds"] / single["cpu_seconds"]
    at = json.loads((runs / "single_at_default" / "metrics.json").read_text())
    assert at["steps"] == max(2, round(12 * ratio))
    assert f"| MVGS default, equal steps | 12 | {preset['psnr']:.2f} |" in text
