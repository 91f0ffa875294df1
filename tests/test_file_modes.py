"""Atomic writers give their files the mode a plain open() would (mkstemp's temporary files are
0o600: a metrics.json or PLY renamed from one would be unreadable to anyone else on the machine)."""

import json
import os

import torch

from mvgs_plugin.adapters.ply import write_gaussian_ply
from mvgs_plugin.io import atomic_write_text, save_atomic

from mvgs_plugin import cli  # noqa: E402


def _mode(path) -> int:
    return os.stat(path).st_mode & 0o777


def test_atomic_writers_use_the_plain_new_file_mode(tmp_path):
    old = os.umask(0o027)  # an unusual umask, so a hard-coded 0o644 would fail too
    try:
        plain = tmp_path / "plain.txt"
        with open(plain, "w") as f:
            f.write("x")
        expected = _mode(plain)
        assert expected == 0o640
        atomic_write_text(tmp_path / "a.md", "hello")
        save_atomic({"w": torch.ones(2)}, str(tmp_path / "b.pt"))
        n = 3
        write_gaussian_ply(tmp_path / "c.ply", torch.zeros(n, 3), torch.zeros(n, 1, 3), torch.zeros(n, 0, 3),
                           torch.zeros(n), torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1))
        cli.write_json(tmp_path / "d.json", {"psnr": 1.0})
    finally:
        os.umask(old)
    for name in ("a.md", "b.pt", "c.ply", "d.json"):
        assert _mode(tmp_path / name) == expected, name
    assert (tmp_path / "a.md").read_text() == "hello"
    assert json.loads((tmp_path / "d.json").read_text()) == {"psnr": 1.0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.md", "b.pt", "c.ply", "d.json", "plain.txt"]
