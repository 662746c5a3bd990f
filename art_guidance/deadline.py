"""A plan's wall-clock deadline, one value from the node's parameter to the solver.

`Deadline` is a `time.perf_counter()` instant: the node makes one per replan from
`solve_deadline_s` (less what recording needs), the pipeline passes it to the learned proposal
and to every SCVx* run (a share of what is left for a first run that may be retried), and each
stage asks it how much time is left. Nothing else is converted on the way.

A deadline remembers whether a stage found it passed (`hit`, shared with its shares): such a
plan's result depends on the clock (a stage was cut, skipped or timed out), so a replay, which
is not time-boxed, cannot reproduce it; the record says so (`PlanResult.deadline_hit`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Deadline:
    """A wall-clock deadline.

    Attributes:
        at_s: the instant, on the `time.perf_counter()` clock [s].
        hits: where a stage found it (or a share of it) passed: one entry per such finding,
            shared by the deadline and its shares (`hit`).
    """

    at_s: float
    hits: list = field(default_factory=list, compare=False, repr=False)

    def __post_init__(self) -> None:
        if math.isnan(self.at_s):
            raise ValueError("a deadline is a number, got NaN")

    @classmethod
    def after(cls, seconds: float) -> "Deadline":
        """The deadline `seconds` [s] from now."""
        return cls(time.perf_counter() + float(seconds))

    @property
    def hit(self) -> bool:
        """Whether a stage found this deadline, or one of its shares, passed."""
        return bool(self.hits)

    def mark_hit(self) -> None:
        """A stage elsewhere (the proposal worker, on its copy of this deadline) found it
        passed."""
        self.hits.append(self.at_s)

    def left_s(self) -> float:
        """What is left of it [s] (0 once passed: a hit)."""
        left = self.at_s - time.perf_counter()
        if left <= 0.0:
            self.hits.append(self.at_s)
        return max(left, 0.0)

    def passed(self) -> bool:
        """Whether it has passed (a hit when it has)."""
        if time.perf_counter() >= self.at_s:
            self.hits.append(self.at_s)
            return True
        return False

    def share(self, fraction: float) -> "Deadline":
        """An earlier deadline that leaves the rest for later: `fraction` of what is left
        (its hits are this deadline's)."""
        return Deadline(time.perf_counter() + fraction * self.left_s(), self.hits)
