"""Anytime work under a deadline, shared by the DWA's refinement and the shield's search.

A step may start only if the slowest step so far would still end by the deadline, so the last
step never runs past it by more than its own jitter. Without a clock every step may start: the
simulator's budgets are counts (refinement rounds, candidates), so episodes are deterministic.
"""

from __future__ import annotations

from collections.abc import Callable


class TimeBudget:
    """Deadline bookkeeping for one anytime call; `cut` tells whether it stopped a step,
    `allowed` how many steps it let start (with `cut`, what a replay needs to repeat it)."""

    def __init__(self, deadline: float, now: Callable[[], float] | None) -> None:
        self.deadline, self.now = deadline, now
        self.last = now() if now is not None else 0.0
        self.cut = False
        self.allowed = 0

    def allows(self, estimate: float) -> bool:
        """Whether a step taking `estimate` seconds may start now (False for good once cut)."""
        if self.now is not None and not self.cut and self.now() + estimate > self.deadline:
            self.cut = True
        self.allowed += not self.cut
        return not self.cut

    def lap(self) -> float:
        """Seconds since the previous lap or the start (0 without a clock)."""
        if self.now is None:
            return 0.0
        t = self.now()
        dt, self.last = t - self.last, t
        return dt


class ReplayedBudget(TimeBudget):
    """A recorded budget again: it allows the steps it allowed then, and cuts where it cut."""

    def __init__(self, allowed: int, cut: bool) -> None:
        super().__init__(float("inf"), None)
        self._limit, self._cuts = allowed, cut

    def allows(self, estimate: float) -> bool:
        if self._cuts and self.allowed >= self._limit:
            self.cut = True
            return False
        self.allowed += 1
        return True
