"""Which training views each step sees (multi-view regulated training).

Views are drawn without replacement from a shuffled epoch; a step never holds the same view
twice, and every view is seen once per epoch. When a step straddles an epoch boundary, the
views it already holds are moved to the end of the next epoch's order (so they are still seen
once in that epoch, just not in this step) — the released MVGS code could repeat a view there.
Seeded and reproducible; the state (generator and the rest of the epoch) is saved in
checkpoints.

Dynamic scenes (cameras with a time): ``time_spread`` chooses how a step's M views spread over
time. "random" is the rule above (times fall where the shuffle puts them). "stratified" sorts the
training views by time (ties by index), cuts them into M contiguous bins of nearly equal count
(sizes differ by at most one; equal counts rather than equal widths, so no bin is empty however
the times are distributed) and draws one view from each bin: a step always spans the whole time
range, and never holds two views of one bin. Each bin keeps its own shuffled queue, so within a
bin every view is seen once before any repeats. The bins depend on M (the pyramid stages change
M); each M keeps its own queues.

"instant", for a synchronized rig (several cameras filming together, a multi-camera video): a
step's M views are M cameras' views of one instant (one time), so a deformable model is deformed
once for all of them. The instants are visited in a shuffled queue in which an instant of C
views appears ceil(C / M) times; each visit draws M of its views from that instant's own
shuffled queue (so its cameras are all seen before any repeats, and every view about once per
epoch). M above an instant's view count is capped to it, with a warning (once).
"""

from __future__ import annotations

import math
import warnings
from typing import Dict, List, Optional, Sequence

import torch

from .checks import check_int

TIME_SPREADS = ("random", "stratified", "instant")


class ViewSampler:
    """Draws M distinct view indices per step from range(n_views).

    times: per view its time in [0, 1] (needed by time_spread "stratified" and "instant", else
        unused).
    time_spread: "random", "stratified" or "instant" (see the module docstring).
    """

    def __init__(self, n_views: int, seed: int = 0, times: Optional[Sequence[Optional[float]]] = None,
                 time_spread: str = "random"):
        check_int("n_views", n_views, 1)
        if time_spread not in TIME_SPREADS:
            raise ValueError(f"time_spread must be one of {TIME_SPREADS}, got {time_spread!r}")
        self.n_views = n_views
        self.time_spread = time_spread
        self._order: List[int] = []
        self._instants: List[List[int]] = []  # "instant": the views of each time, earliest first
        if time_spread != "random":
            self._order = self._time_order(times, n_views, time_spread)
        if time_spread == "instant":
            for i in self._order:
                if self._instants and times[self._instants[-1][0]] == times[i]:
                    self._instants[-1].append(i)
                else:
                    self._instants.append([i])
            if max(len(v) for v in self._instants) < 2:
                raise ValueError(f'time_spread="instant" needs views that share a time (a synchronized rig, several '
                                 f"cameras filming together); the {n_views} views have {len(self._instants)} distinct "
                                 "times, one view each")
        self._visits: Dict[int, List[int]] = {}  # "instant": M -> the queue of instants to visit
        self._at: List[List[int]] = [[] for _ in self._instants]  # "instant": each instant's queue of views
        self._gen = torch.Generator().manual_seed(seed)
        self._queue: List[int] = []
        self._bins: Dict[int, List[List[int]]] = {}  # M -> one queue per time bin
        self._warned = False

    @staticmethod
    def _time_order(times, n_views: int, spread: str = "stratified") -> List[int]:
        """View indices sorted by time (ties by index); every time must be a number in [0, 1]."""
        if times is None or len(times) != n_views:
            got = None if times is None else len(times)
            raise ValueError(f'time_spread="{spread}" needs one time per view ({n_views}), got {got}')
        for i, t in enumerate(times):
            if t is None or isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 <= t <= 1.0:
                raise ValueError(f'time_spread="{spread}" needs every view\'s time in [0, 1]; '
                                 f"view {i} has {t!r}")
        return sorted(range(n_views), key=lambda i: (float(times[i]), i))

    def sample(self, m: int) -> List[int]:
        """M distinct indices. M larger than the number of views is capped to it (with a
        warning, once): a step then sees every view exactly once."""
        check_int("views per step", m, 1)
        if m > self.n_views:
            if not self._warned:
                warnings.warn(f"{m} views per step requested but only {self.n_views} training views: using {self.n_views}")
                self._warned = True
            m = self.n_views
        if self.time_spread == "stratified":
            return self._sample_stratified(m)
        if self.time_spread == "instant":
            return self._sample_instant(m)
        picked: List[int] = []
        while len(picked) < m:
            if not self._queue:
                order = torch.randperm(self.n_views, generator=self._gen).tolist()
                taken = set(picked)
                self._queue = [i for i in order if i not in taken] + [i for i in order if i in taken]
            picked.append(self._queue.pop(0))
        return picked

    def time_bins(self, m: int) -> List[List[int]]:
        """The M bins of the stratified rule: contiguous runs of the time order, sizes
        floor(n/M) or ceil(n/M), earliest times first."""
        n = self.n_views
        edges = [math.floor(k * n / m) for k in range(m + 1)]
        return [self._order[edges[k]:edges[k + 1]] for k in range(m)]

    def _sample_stratified(self, m: int) -> List[int]:
        queues = self._bins.setdefault(m, [[] for _ in range(m)])
        picked = []
        for k, members in enumerate(self.time_bins(m)):
            if not queues[k]:
                queues[k] = [members[i] for i in torch.randperm(len(members), generator=self._gen).tolist()]
            picked.append(queues[k].pop(0))
        return picked

    def _sample_instant(self, m: int) -> List[int]:
        visits = self._visits.setdefault(m, [])
        if not visits:
            entries = [k for k, views in enumerate(self._instants) for _ in range(-(-len(views) // m))]
            visits.extend(entries[i] for i in torch.randperm(len(entries), generator=self._gen).tolist())
        k = visits.pop(0)
        views = self._instants[k]
        if m > len(views) and not self._warned:
            warnings.warn(f"{m} views per step requested but an instant holds {len(views)} views: a step takes every "
                          "view of its instant")
            self._warned = True
        queue, picked = self._at[k], []
        while len(picked) < min(m, len(views)):
            if not queue:
                order = [views[i] for i in torch.randperm(len(views), generator=self._gen).tolist()]
                queue.extend([i for i in order if i not in picked] + [i for i in order if i in picked])
            picked.append(queue.pop(0))
        return picked

    def state_dict(self) -> Dict:
        bins = {m: [list(q) for q in qs] for m, qs in self._bins.items()}
        return {"n_views": self.n_views, "generator": self._gen.get_state(), "queue": list(self._queue),
                "time_spread": self.time_spread, "bins": bins,
                "visits": {m: list(q) for m, q in self._visits.items()}, "at": [list(q) for q in self._at]}

    def load_state_dict(self, state: Dict) -> None:
        if state["n_views"] != self.n_views:
            raise ValueError(f"sampler state is for {state['n_views']} views, this sampler has {self.n_views}")
        spread = state.get("time_spread", "random")  # states saved before the option existed
        if spread != self.time_spread:
            raise ValueError(f"sampler state is for time_spread={spread!r}, this sampler has {self.time_spread!r}")
        self._gen.set_state(state["generator"])
        self._queue = list(state["queue"])
        self._bins = {int(m): [list(q) for q in qs] for m, qs in state.get("bins", {}).items()}
        self._visits = {int(m): list(q) for m, q in state.get("visits", {}).items()}
        at = state.get("at", [])
        if self.time_spread == "instant" and len(at) != len(self._instants):
            raise ValueError(f"sampler state is for {len(at)} instants, this sampler has {len(self._instants)}")
        self._at = [list(q) for q in at] if at else [[] for _ in self._instants]
