"""A plan's wall-clock deadline, one value from the node's parameter to the solver.

`Deadline` is a `time.perf_counter()` instant: the node makes one per replan from
`solve_deadline_s` (less what recording needs), the pipeline passes it to the learned proposal
and to every SCVx* run (a share of what is left for a first run that may be retried), and each
stage asks it how much time is left. Nothing else is converted on the way.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class Deadline:
    """A wall-clock deadline.

    Attributes:
        at_s: the instant, on the `time.perf_counter()` clock [s].
    """

    at_s: float

    def __post_init__(self) -> None:
        if math.isnan(self.at_s):
            raise ValueError("a deadline is a number, got NaN")

    @classmethod
    def after(cls, seconds: float) -> "Deadline":
        """The deadline `seconds` [s] from now."""
        return cls(time.perf_counter() + float(seconds))

    def left_s(self) -> float:
        """What is left of it [s] (0 once passed)."""
        return max(self.at_s - time.perf_counter(), 0.0)

    def passed(self) -> bool:
        """Whether it has passed."""
        return time.perf_counter() >= self.at_s

    def share(self, fraction: float) -> "Deadline":
        """An earlier deadline that leaves the rest for later: `fraction` of what is left."""
        return Deadline.after(fraction * self.left_s())
