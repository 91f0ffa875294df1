"""File writing shared by the controller and the adapters."""

from __future__ import annotations

import os
import tempfile
from typing import Any, Callable

import torch


def new_file_mode() -> int:
    """The mode open() gives a new file under the process umask (0o644 under the usual 022).
    mkstemp creates its temporary files 0o600; every atomic writer here sets this mode on the
    temporary file before the rename, so a replaced file is as readable as a plainly written one."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _write_atomic(path, write: Callable[[Any], None], binary: bool, make_folder: bool = False) -> None:
    """Call `write(file)` on a temporary file in `path`'s folder, flush it to disk, give it the
    usual new-file mode and rename it over `path`: a crash leaves any previous file intact and
    never half of one; the temporary file is removed on failure."""
    folder = os.path.dirname(os.path.abspath(path))
    if make_folder:
        os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".partial-", dir=folder)
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path, text: str) -> None:
    """Write `text` to `path` atomically, with the usual new-file mode (see _write_atomic)."""
    _write_atomic(path, lambda f: f.write(text), binary=False)


def save_atomic(obj: Any, path: str) -> None:
    """torch.save `obj` to `path` atomically: written to a temporary file in the same folder,
    flushed to disk, then renamed over `path`, so a crash mid-write leaves any previous file
    intact and never a half-written one. The folder is created if needed."""
    _write_atomic(path, lambda f: torch.save(obj, f), binary=True, make_folder=True)
