"""The stage plan of cross-intrinsic guidance: which stage a global step is in, and which step
the learning-rate and densification clocks see (restarted per stage, or continuous)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from .config import Stage


@dataclass(frozen=True)
class StagePosition:
    """Where a global step (1-based) falls: the stage, its index, the step within the stage
    (1-based), and the clock the schedules see."""

    index: int
    stage: Stage
    local_step: int
    clock: int
    first_in_stage: bool


class StagePlan:
    """A list of stages run back to back; the model carries over from one to the next."""

    def __init__(self, stages: Sequence[Stage], restart_per_stage: bool = False):
        self.stages = tuple(stages)
        self.restart_per_stage = restart_per_stage
        self.total_steps = sum(s.steps for s in self.stages)

    def locate(self, step: int) -> StagePosition:
        if not 1 <= step <= self.total_steps:
            raise ValueError(f"step must be in [1, {self.total_steps}], got {step}")
        start = 0
        for i, stage in enumerate(self.stages):
            if step <= start + stage.steps:
                local = step - start
                clock = local if self.restart_per_stage else step
                return StagePosition(i, stage, local, clock, local == 1)
            start += stage.steps
        raise AssertionError("unreachable")
