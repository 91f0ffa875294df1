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


def test_ctrl_c_inside_torch_save_is_an_interrupt_and_the_previous_file_survives(tmp_path, monkeypatch):
    """torch.save turns a KeyboardInterrupt raised inside its writes into RuntimeError "unexpected
    pos" (the interrupt as its context): the CLI's interrupt handler missed it and printed two
    tracebacks. save_atomic raises the KeyboardInterrupt; the earlier file and no partial remain."""
    import pytest

    from mvgs_plugin import io as mio

    path = tmp_path / "checkpoint.pt"
    save_atomic({"step": 1}, str(path))
    real_fdopen = os.fdopen

    class Interrupting:
        def __init__(self, f):
            self.f, self.calls = f, 0

        def write(self, b):
            self.calls += 1
            if self.calls == 3:
                raise KeyboardInterrupt
            return self.f.write(b)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(mio.os, "fdopen", lambda fd, mode: Interrupting(real_fdopen(fd, mode)))
    with pytest.raises(KeyboardInterrupt):
        save_atomic({"step": 2, "w": torch.zeros(1000)}, str(path))
    monkeypatch.setattr(mio.os, "fdopen", real_fdopen)
    assert torch.load(path, weights_only=True) == {"step": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]
    with pytest.raises(RuntimeError, match="boom"):  # other errors pass through as they were
        mio.write_atomic(tmp_path / "x.txt", lambda f: (_ for _ in ()).throw(RuntimeError("boom")), binary=False)


def test_a_file_that_is_not_a_checkpoint_is_named_not_unpickled(tmp_path):
    import pytest

    from mvgs_plugin.io import load_checked

    (tmp_path / "notes.txt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match=r"notes.txt: not a file torch.save wrote with tensors and plain values only"):
        load_checked(str(tmp_path / "notes.txt"))
    # a checkpoint cut short (a copy interrupted), and a file of five bytes: named, as ValueError
    from mvgs_plugin.io import save_checked
    import torch

    save_checked({"x": torch.zeros(1000)}, str(tmp_path / "whole.pt"))
    data = (tmp_path / "whole.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "five.txt").write_text("hello")
    for name in ("cut.pt", "five.txt"):
        with pytest.raises(ValueError, match=name + r": not a whole torch.save file \(truncated, or another format\)"):
            load_checked(str(tmp_path / name))


def test_a_checked_file_holds_its_payload_raw_and_files_written_before_still_load(tmp_path):
    """The payload (the bytes of torch.save(obj)) is kept as raw bytes: the file is the payload
    plus a few kB of zip and pickle (a bytes object pickled by torch's protocol 2 took 1.5x, and
    could not pass 4 GiB); a file of the earlier layout (the payload a bytes object) loads."""
    import hashlib
    import io
    import os

    import pytest
    import torch

    from mvgs_plugin.io import CHECKED_FORMAT, load_checked, save_atomic, save_checked

    obj = {"x": torch.rand(100_000, generator=torch.Generator().manual_seed(0)), "n": 3}
    buf = io.BytesIO()
    torch.save(obj, buf)
    payload = buf.getvalue()
    save_checked(obj, str(tmp_path / "new.pt"))
    assert len(payload) < os.path.getsize(tmp_path / "new.pt") < len(payload) + 4096
    got = load_checked(str(tmp_path / "new.pt"))
    assert torch.equal(got["x"], obj["x"]) and got["n"] == 3
    save_atomic({"format": CHECKED_FORMAT, "sha256": hashlib.sha256(payload).hexdigest(), "payload": payload},
                str(tmp_path / "old.pt"))
    assert os.path.getsize(tmp_path / "old.pt") > 1.3 * len(payload)
    assert torch.equal(load_checked(str(tmp_path / "old.pt"))["x"], obj["x"])
    save_atomic({"format": CHECKED_FORMAT, "sha256": "0" * 64, "payload": torch.frombuffer(bytearray(payload), dtype=torch.uint8)},
                str(tmp_path / "bad.pt"))
    with pytest.raises(ValueError, match=r"bad.pt: checksum mismatch"):
        load_checked(str(tmp_path / "bad.pt"))


def test_the_folder_is_synced_after_the_rename(tmp_path, monkeypatch):
    """The rename reaches the disk too: the folder is fsynced once the new file is in place."""
    import os

    from mvgs_plugin import io as mio

    seen = []
    real = os.fsync

    def spy(fd):
        target = os.readlink(f"/proc/self/fd/{fd}") if os.path.exists(f"/proc/self/fd/{fd}") else None
        seen.append((target, (tmp_path / "x.txt").exists() and (tmp_path / "x.txt").read_text() == "new"))
        return real(fd)

    (tmp_path / "x.txt").write_text("old")
    monkeypatch.setattr(os, "fsync", spy)
    mio.write_atomic(tmp_path / "x.txt", lambda f: f.write("new"), binary=False)
    assert seen[-1] == (str(tmp_path), True)  # the folder, after the file was replaced
    assert seen[0][1] is False  # the temporary file first, before the rename
