"""Which training views each step sees (multi-view regulated training).

Views are drawn without replacement from a shuffled epoch; a step never holds the same view
twice, and every view is seen once per epoch. When a step straddles an epoch boundary, the
views it already holds are moved to the end of the next epoch's order (so they are still seen
once in that epoch, just not in this step) — the released MVGS code could repeat a view there.
Seeded and reproducible; the state (generator and the rest of the epoch) is saved in
checkpoints.
"""

from __future__ import annotations

import warnings
from typing import Dict, List

import torch


class ViewSampler:
    """Draws M distinct view indices per step from range(n_views)."""

    def __init__(self, n_views: int, seed: int = 0):
        if isinstance(n_views, bool) or not isinstance(n_views, int) or n_views < 1:
            raise ValueError(f"n_views must be a positive int, got {n_views!r}")
        self.n_views = n_views
        self._gen = torch.Generator().manual_seed(seed)
        self._queue: List[int] = []
        self._warned = False

    def sample(self, m: int) -> List[int]:
        """M distinct indices. M larger than the number of views is capped to it (with a
        warning, once): a step then sees every view exactly once."""
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ValueError(f"views per step must be a positive int, got {m!r}")
        if m > self.n_views:
            if not self._warned:
                warnings.warn(f"{m} views per step requested but only {self.n_views} training views: using {self.n_views}")
                self._warned = True
            m = self.n_views
        picked: List[int] = []
        while len(picked) < m:
            if not self._queue:
                order = torch.randperm(self.n_views, generator=self._gen).tolist()
                taken = set(picked)
                self._queue = [i for i in order if i not in taken] + [i for i in order if i in taken]
            picked.append(self._queue.pop(0))
        return picked

    def state_dict(self) -> Dict:
        return {"n_views": self.n_views, "generator": self._gen.get_state(), "queue": list(self._queue)}

    def load_state_dict(self, state: Dict) -> None:
        if state["n_views"] != self.n_views:
            raise ValueError(f"sampler state is for {state['n_views']} views, this sampler has {self.n_views}")
        self._gen.set_state(state["generator"])
        self._queue = list(state["queue"])
