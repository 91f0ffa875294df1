"""Data-parallel MVGS over torch.distributed: the M views of a step are sharded over ranks.

Every rank holds the full model and builds the same step plan (same config, same seed, so the
sampler draws the same views on every rank). Rank r renders and backpropagates its share of the
step's views (``shard``); then, per step:

    status      all_gather  [W, 5] float64: failed?, local loss, step, primitive count, views hash
    gradients   all_reduce  SUM, one flat buffer per dtype: every group's .grad (+ 1 flag per
                group: did any rank produce a gradient for it)
    and on densification steps only:
    loss maps   all_gather  [ceil(M/W), H', W'] per rank (cross-ray densification needs all M)
    statistics  all_reduce  SUM (gradient norms, visit counts) and MAX (screen radii)

so the step equals the single-process summed step (up to float rounding in the order of the
sum), and every rank takes the same densification decision and stays identical. The MVAD rule
and the CRD boxes are computed by every rank from the global set of views.

Faults: a rank whose render / loss / backward raises still joins the status exchange with its
error; every rank then stops (the failing one with its own exception, the others with a
DistributedError naming the rank, the step and the message). A rank that dies or stalls
elsewhere is caught by the backend: its peers' next collective fails (connection closed) or
times out after ``timeout`` seconds (init_process_group(timeout=...)), and raises a
DistributedError saying which collective at which step. Run each rank's work inside
``abort_on_error()``: after an error it prints the traceback and ends the process with
os._exit(1), because the interpreter's normal shutdown can block in the backend's destructors
while a peer is stalled (and a launcher like torchrun then waits forever).

Launch with torchrun (``torchrun --nproc-per-node N examples/train_3dgs.py ...``): ``init_from_env``
reads the environment torchrun sets and returns None in a plain single-process run.
"""

from __future__ import annotations

import contextlib
import datetime
import math
import os
import sys
import traceback
from typing import Callable, Dict, Iterator, List, Optional, Sequence, TypeVar

import torch
import torch.distributed as dist
from torch import Tensor

from .checks import check_int

__all__ = ["Collective", "DistributedError", "shard", "backend_for", "init_from_env", "require_support",
           "abort_on_error", "DEFAULT_TIMEOUT"]

DEFAULT_TIMEOUT = 300.0  # seconds a collective waits for its peers before failing
_REQUIRED = ("gradient_parameters", "statistics", "load_statistics")
T = TypeVar("T")


class DistributedError(RuntimeError):
    """Another rank failed, died, stalled past the timeout, or the ranks' models diverged."""


def shard(m: int, rank: int, world_size: int) -> List[int]:
    """Positions (in the step's view list) rank `rank` renders: contiguous blocks, the first
    m % world_size ranks one view more. Rank 0 always holds position 0 (when m >= 1); with
    m < world_size the last ranks hold none (they still join every collective)."""
    for name, v, lo in (("m", m, 0), ("world_size", world_size, 1), ("rank", rank, 0)):
        check_int(name, v, lo)
    if rank >= world_size:
        raise ValueError(f"rank must be < world_size={world_size}, got {rank}")
    q, r = divmod(m, world_size)
    start = rank * q + min(rank, r)
    return list(range(start, start + q + (1 if rank < r else 0)))


def backend_for(device) -> str:
    """NCCL for CUDA tensors, gloo otherwise (CPU)."""
    return "nccl" if torch.device(device).type == "cuda" else "gloo"


def require_support(adapter) -> None:
    """Raise TypeError unless the adapter has the DistributedAdapter methods."""
    missing = [m for m in _REQUIRED if not callable(getattr(adapter, m, None))]
    if missing:
        raise TypeError(f"{type(adapter).__name__} cannot be trained over several processes: it lacks "
                        f"{missing} (see mvgs_plugin.protocol.DistributedAdapter)")


def _check_timeout(timeout) -> float:
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not (0 < timeout < math.inf):
        raise ValueError(f"timeout must be a finite number of seconds > 0, got {timeout!r}")
    return float(timeout)


@contextlib.contextmanager
def abort_on_error(exit_code: int = 1) -> Iterator[None]:
    """End the process at once when the block raises: print the traceback (with the rank) to
    stderr and call os._exit(exit_code), skipping the interpreter's shutdown, which can block in
    the process group's destructors while a peer is stalled. Use it around a rank's work in a
    distributed run only (it never returns control after an error); a SystemExit with code 0 or
    None passes through."""
    try:
        yield
    except SystemExit as exc:
        if exc.code in (0, None):
            raise
        _abort(exit_code if not isinstance(exc.code, int) else exc.code)
    except BaseException:
        _abort(exit_code)


def _abort(code: int) -> None:
    rank = os.environ.get("RANK", str(dist.get_rank()) if dist.is_available() and dist.is_initialized() else "?")
    sys.stderr.write(f"[rank {rank}] stopping after an error:\n{traceback.format_exc()}")
    sys.stderr.flush()
    sys.stdout.flush()
    os._exit(code)


def init_from_env(device=None, timeout: float = DEFAULT_TIMEOUT, backend: Optional[str] = None
                  ) -> Optional["Collective"]:
    """Join the process group torchrun describes (WORLD_SIZE, RANK, LOCAL_RANK, MASTER_ADDR,
    MASTER_PORT) and return its Collective; None when not launched with more than one process.

    device: where the model lives ("cpu", "cuda"; default: cuda when available). The backend
    follows it (backend_for) unless given; with CUDA each rank uses cuda:LOCAL_RANK.
    timeout: seconds any collective waits for the other ranks before failing.
    """
    timeout = _check_timeout(timeout)
    world = os.environ.get("WORLD_SIZE")
    if world is None:
        return None
    if not world.strip().isdigit():
        raise ValueError(f"the WORLD_SIZE environment variable must be a positive int, got {world!r}")
    if int(world) <= 1:
        return None
    if not dist.is_available():
        raise RuntimeError("WORLD_SIZE > 1 but this torch build has no torch.distributed")
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(device)
    backend = backend or backend_for(device)
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout))
    return Collective(timeout=timeout, device=device)


class Collective:
    """The collectives of a data-parallel MVGS step on an initialised process group.

    Args:
        group: the process group (default: the world).
        timeout: the group's collective timeout in seconds (for messages only: the timeout itself
            is set when the group is created).
        device: where small control tensors live (cuda for NCCL, cpu for gloo); default: the
            current CUDA device for NCCL, else cpu.
    """

    def __init__(self, group=None, timeout: float = DEFAULT_TIMEOUT, device=None):
        if not (dist.is_available() and dist.is_initialized()):
            raise RuntimeError("torch.distributed is not initialised: call init_from_env() (under torchrun) "
                               "or torch.distributed.init_process_group() first")
        self.group = group
        self.timeout = _check_timeout(timeout)
        self.rank = dist.get_rank(group)
        self.world_size = dist.get_world_size(group)
        self.backend = str(dist.get_backend(group))
        if device is None:
            device = torch.device("cuda", torch.cuda.current_device()) if self.backend == "nccl" else torch.device("cpu")
        self.device = torch.device(device)

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that writes checkpoints, metrics and renders."""
        return self.rank == 0

    def positions(self, m: int) -> List[int]:
        """This rank's share of a step of m views (see shard)."""
        return shard(m, self.rank, self.world_size)

    def __repr__(self) -> str:
        return f"Collective(rank={self.rank}, world_size={self.world_size}, backend={self.backend!r})"

    # ---- plumbing ---------------------------------------------------------------------------
    def _call(self, what: str, step: Optional[int], fn: Callable[[], T]) -> T:
        """Run a collective; a backend failure (peer gone, timeout) becomes a DistributedError that
        says which collective, at which step, on which rank."""
        try:
            return fn()
        except DistributedError:
            raise
        except Exception as exc:  # gloo / NCCL report peer loss and timeouts as RuntimeError subclasses
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            at = "" if step is None else f" of step {step}"
            raise DistributedError(
                f"rank {self.rank}/{self.world_size}: the {what} collective{at} failed: another "
                f"rank exited or did not answer within {self.timeout:g} s ({type(exc).__name__}: {detail})"
            ) from exc

    def barrier(self, what: str, step: Optional[int] = 0) -> None:
        """Wait for every rank (with the group's timeout)."""
        # A tiny all_reduce rather than dist.barrier(): it obeys the timeout on every backend.
        flag = torch.ones(1, device=self.device)
        self._call(what, step, lambda: dist.all_reduce(flag, group=self.group))

    def close(self) -> None:
        """Leave the process group together: wait until every rank got here (rank 0 may still be
        evaluating and writing; the wait obeys the group's timeout), then destroy the group.
        A rank that tears its group down and exits while a peer still works can abort in gloo's
        worker threads ("terminate called without an active exception"); ending together avoids it."""
        self.barrier("finish", None)
        if self.group is None:
            dist.destroy_process_group()

    # ---- per step ---------------------------------------------------------------------------
    def exchange_status(self, step: int, error: Optional[BaseException], loss: float, num_primitives: int,
                        views: Sequence[int]) -> float:
        """Every rank reports whether its share of the step failed, its loss, and a fingerprint of
        its model and plan. Returns the global loss (the sum over ranks, in rank order). Raises on
        every rank when any rank failed (this rank's own error, or a DistributedError naming the
        failed ranks and their messages), or when the ranks disagree on the step, the views or
        the primitive count (they diverged)."""
        views_hash = float(sum((i + 1) * (v + 1) for i, v in enumerate(views)) % (1 << 50))
        mine = torch.tensor([float(error is not None), 0.0 if error is not None else float(loss), float(step),
                             float(num_primitives), views_hash], dtype=torch.float64, device=self.device)
        rows = [torch.empty_like(mine) for _ in range(self.world_size)]
        self._call("status", step, lambda: dist.all_gather(rows, mine, group=self.group))
        table = torch.stack(rows).cpu()
        failed = [r for r in range(self.world_size) if table[r, 0] > 0]
        if failed:
            message = "" if error is None else f"{type(error).__name__}: {error}"
            messages: List[Optional[str]] = [None] * self.world_size
            self._call("error report", step, lambda: dist.all_gather_object(messages, message, group=self.group))
            if error is not None:
                raise error
            said = "; ".join(f"rank {r}: {messages[r]}" for r in failed)
            raise DistributedError(f"rank {self.rank}/{self.world_size} stops at step {step} because "
                                   f"{'rank' if len(failed) == 1 else 'ranks'} {failed} failed ({said})")
        for col, what in ((2, "step"), (3, "primitive count"), (4, "views (hash)")):
            if not bool((table[:, col] == table[0, col]).all()):
                values = {r: int(table[r, col]) for r in range(self.world_size)}
                raise DistributedError(f"ranks diverged at step {step}: {what} per rank {values}; every rank "
                                       f"must run the same config, seed and checkpoint")
        return float(table[:, 1].sum())

    def all_reduce_gradients(self, adapter, step: int = 0) -> int:
        """Sum every group's .grad over ranks, in place (a rank without a gradient for a group
        contributes zeros and receives the sum; a group no rank has a gradient for stays None).
        Returns the bytes this rank put into the all-reduce."""
        params = adapter.gradient_parameters()
        names = list(params)
        present = [params[n].grad is not None for n in names]
        sent = 0
        by_dtype: Dict[torch.dtype, List[str]] = {}
        for n in names:
            by_dtype.setdefault(params[n].dtype, []).append(n)
        flags_reduced: Optional[Tensor] = None
        for k, (dtype, group_names) in enumerate(by_dtype.items()):
            ref = params[group_names[0]]
            parts = [(params[n].grad if params[n].grad is not None else torch.zeros_like(params[n])).reshape(-1)
                     for n in group_names]
            if k == 0:  # one presence flag per group rides with the first buffer
                parts.append(torch.tensor(present, dtype=dtype, device=ref.device))
            flat = torch.cat(parts).to(ref.device)
            self._call("gradient", step, lambda: dist.all_reduce(flat, op=dist.ReduceOp.SUM, group=self.group))
            sent += flat.numel() * flat.element_size()
            if k == 0:
                flags_reduced = flat[-len(names):]
            offset = 0
            for n in group_names:
                p = params[n]
                block = flat[offset:offset + p.numel()].view_as(p)
                offset += p.numel()
                any_rank = bool(flags_reduced[names.index(n)] > 0)
                if not any_rank:
                    continue
                if p.grad is None:
                    p.grad = block.clone()
                else:
                    p.grad.copy_(block)
        return sent

    def reduce_statistics(self, adapter, step: int = 0) -> Dict[str, Tensor]:
        """The adapter's densification statistics combined over ranks (SUM or MAX as its
        statistics() declares). Collective; the adapter is not changed."""
        stats = adapter.statistics()
        bad = {n: how for n, (_, how) in stats.items() if how not in ("sum", "max")}
        if bad:  # the same on every rank, so every rank raises before any collective
            raise ValueError(f"statistics() must combine by 'sum' or 'max', got {bad}")
        out: Dict[str, Tensor] = {}
        for op_name, op in (("sum", dist.ReduceOp.SUM), ("max", dist.ReduceOp.MAX)):
            names = [n for n, (_, how) in stats.items() if how == op_name]
            if not names:
                continue
            flat = torch.cat([stats[n][0].reshape(-1) for n in names])
            self._call(f"statistics ({op_name})", step, lambda: dist.all_reduce(flat, op=op, group=self.group))
            offset = 0
            for n in names:
                t = stats[n][0]
                out[n] = flat[offset:offset + t.numel()].view_as(t).clone()
                offset += t.numel()
        return out

    def all_reduce_statistics(self, adapter, step: int = 0) -> None:
        """Replace the adapter's statistics by their combination over ranks (before densify)."""
        adapter.load_statistics(self.reduce_statistics(adapter, step))

    def gather_loss_maps(self, local: Sequence[Tensor], m: int, height: int, width: int, dtype: torch.dtype,
                         device, step: int = 0, sizes: Optional[Sequence[tuple]] = None) -> List[Tensor]:
        """All M per-view loss maps [H', W'] of the step, in the step's view order, on every rank;
        `local` are this rank's (in the order of its positions). Views of mixed sizes: pass the
        largest height and width and `sizes`, each view's (H', W') in step order; the maps travel
        zero-padded and come back cropped."""
        mine = self.positions(m)
        if len(local) != len(mine):
            raise ValueError(f"rank {self.rank} holds {len(mine)} views of the step but gave {len(local)} loss maps")
        rows = len(shard(m, 0, self.world_size))  # rank 0 holds the most
        buf = torch.zeros(rows, height, width, dtype=dtype, device=device)
        for j, t in enumerate(local):
            buf[j, :t.shape[0], :t.shape[1]] = t
        parts = [torch.empty_like(buf) for _ in range(self.world_size)]
        self._call("loss maps", step, lambda: dist.all_gather(parts, buf, group=self.group))
        maps: List[Optional[Tensor]] = [None] * m
        for r in range(self.world_size):
            for j, pos in enumerate(shard(m, r, self.world_size)):
                h, w = (height, width) if sizes is None else sizes[pos]
                maps[pos] = parts[r][j, :h, :w]
        return maps  # type: ignore[return-value]
