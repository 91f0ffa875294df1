"""File writing shared by the controller and the adapters."""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import secrets
from typing import Any, Callable

import torch


def _partial_prefix(path) -> str:
    """Temporary files of `path` are named .<name>.partial-<pid>-<random>: the target and the
    writing process can be read back from the name (see remove_stale_partials)."""
    return f".{os.path.basename(path)}.partial-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def remove_stale_partials(path) -> list:
    """Delete the temporary files a killed writer of `path` left behind: those whose writing
    process (on this machine) no longer exists. A writer that is still running keeps its file.
    Returns the removed paths."""
    folder = os.path.dirname(os.path.abspath(path))
    prefix = _partial_prefix(path)
    removed = []
    for name in os.listdir(folder):
        if not name.startswith(prefix):
            continue
        pid = name[len(prefix):].split("-", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            try:
                os.unlink(os.path.join(folder, name))
                removed.append(os.path.join(folder, name))
            except FileNotFoundError:  # another writer cleaned it first
                pass
    return removed


def write_atomic(path, write: Callable[[Any], None], binary: bool, make_folder: bool = False) -> None:
    """Call `write(file)` on a temporary file in `path`'s folder (with the usual new-file mode),
    flush it to disk and rename it over `path`: a crash leaves any previous file intact and
    never half of one; the temporary file is removed on failure, and the ones a killed earlier
    writer of the same path left are removed first (remove_stale_partials)."""
    folder = os.path.dirname(os.path.abspath(path))
    if make_folder:
        os.makedirs(folder, exist_ok=True)
    remove_stale_partials(path)
    # Created with mode 0o666 under the process umask, as open() would make the file (mkstemp's
    # 0o600 would leave metrics, PLYs and checkpoints unreadable to others after the rename).
    while True:
        tmp = os.path.join(folder, f"{_partial_prefix(path)}{os.getpid()}-{secrets.token_hex(4)}")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _sync_folder(folder)  # the rename itself on disk: after a power loss the new file, not the old
    except Exception as err:
        # Ctrl-C inside a writer that turns it into its own error (torch.save's zip writer raises
        # RuntimeError "unexpected pos" with the KeyboardInterrupt as its context): an interrupt,
        # which callers handle as one (the CLI's "interrupted at step N" note), not a crash
        if _interrupted(err):
            raise KeyboardInterrupt from None
        raise
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _sync_folder(folder: str) -> None:
    """fsync a folder, so a rename in it survives a power loss (POSIX); a no-op where folders
    cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse to sync a folder: the file itself is synced
        pass
    finally:
        os.close(fd)


def _interrupted(err: BaseException) -> bool:
    """Whether a KeyboardInterrupt is among the exceptions `err` was raised during or from."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def atomic_write_text(path, text: str) -> None:
    """Write `text` to `path` atomically, with the usual new-file mode (see write_atomic)."""
    write_atomic(path, lambda f: f.write(text), binary=False)


def save_atomic(obj: Any, path: str) -> None:
    """torch.save `obj` to `path` atomically: written to a temporary file in the same folder,
    flushed to disk, then renamed over `path`, so a crash mid-write leaves any previous file
    intact and never a half-written one. The folder is created if needed."""
    write_atomic(path, lambda f: torch.save(obj, f), binary=True, make_folder=True)


CHECKED_FORMAT = "mvgs-checked-1"


def save_checked(obj: Any, path: str) -> None:
    """save_atomic with a SHA-256 of the payload: the file is a torch.save of {"format",
    "sha256", "payload": the bytes of torch.save(obj)}, so load_checked can tell a damaged file
    (a flipped bit would otherwise load silently) and the file still opens with torch.load."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    payload = buf.getvalue()
    # the payload as a uint8 tensor: torch stores it as raw bytes beside the pickle (a bytes object
    # is pickled by torch's protocol 2 as a latin-1 string: 1.5x the size, and refused above 4 GiB)
    save_atomic({"format": CHECKED_FORMAT, "sha256": hashlib.sha256(payload).hexdigest(),
                 "payload": torch.frombuffer(bytearray(payload), dtype=torch.uint8)}, path)


def load_checked(path: str, map_location: Any = "cpu") -> Any:
    """Load a save_checked() file with torch.load(weights_only=True) (no code runs on load) and
    verify its checksum; a file without the wrapper (older checkpoints) loads as it is. Raises
    ValueError naming the file when the checksum does not match. Tensors load on map_location
    (torch.load's meaning): the CPU by default, so a checkpoint written on a GPU opens on a
    machine without one; whoever restores it moves each tensor to its own device."""
    try:
        outer = torch.load(path, weights_only=True, map_location=map_location)
    except pickle.UnpicklingError:  # not a torch.save file (a text file), or one with objects that run code
        raise ValueError(f"{path}: not a file torch.save wrote with tensors and plain values only (a text file, another "
                         "format, or objects that would run code when loaded, which is never done here)") from None
    except (RuntimeError, KeyError, EOFError) as err:  # torch's zip reader on a truncated or foreign file
        said = str(err).splitlines()[0] if str(err) else ""
        raise ValueError(f"{path}: not a whole torch.save file (truncated, or another format): "
                         f"{type(err).__name__}: {said}") from None
    if not (isinstance(outer, dict) and outer.get("format") == CHECKED_FORMAT):
        return outer
    payload = outer.get("payload")
    if isinstance(payload, torch.Tensor) and payload.dtype == torch.uint8 and payload.ndim == 1:
        payload = payload.numpy().tobytes()  # save_checked's layout (files written before hold a bytes object)
    if not isinstance(payload, bytes) or hashlib.sha256(payload).hexdigest() != outer.get("sha256"):
        raise ValueError(f"{path}: checksum mismatch, the file is damaged (sha256 recorded {outer.get('sha256')!r})")
    return torch.load(io.BytesIO(payload), weights_only=True, map_location=map_location)
