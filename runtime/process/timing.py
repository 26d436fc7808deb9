"""Cycle timing: a rate keeper on absolute monotonic deadlines and preallocated stage timings.

The loop is the only user of clocks; stages never read time. Timing buffers are allocated once,
so recording a sample in the hot path allocates nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np


class RateKeeper:
    """Wake at t0 + k·period. After a miss, restart the schedule from now instead of bursting.

    `wait(seconds)` sleeps and returns True when interrupted; on the robot it is a
    threading.Event's wait, so a signal handler that sets the event ends the sleep at once
    (SIGTERM must reach the base as a stop frame within a fraction of a period); a test passes
    one that advances a simulated clock.
    """

    def __init__(
        self,
        period_s: float,
        clock: Callable[[], float],
        wait: Callable[[float], bool],
    ) -> None:
        self.period = period_s
        self._clock = clock
        self._wait = wait
        self.deadline = clock() + period_s
        self.misses = 0

    def sleep(self) -> bool:
        """Sleep until the next deadline; False when interrupted. Counts a miss if already late."""
        now = self._clock()
        if now > self.deadline:
            self.misses += 1
            self.deadline = now + self.period
            return True
        if self._wait(self.deadline - now):
            return False
        self.deadline += self.period
        return True


class RingStats:
    """Fixed-capacity ring of float samples per named channel, summarised on demand."""

    def __init__(self, names: Sequence[str], capacity: int = 4096) -> None:
        self.names = tuple(names)
        self._index = {name: i for i, name in enumerate(self.names)}
        self._data = np.zeros((len(self.names), capacity))
        self._count = np.zeros(len(self.names), dtype=np.int64)
        self._capacity = capacity

    def channel(self, name: str) -> int:
        return self._index[name]

    def record(self, channel: int, value: float) -> None:
        n = self._count[channel]
        self._data[channel, n % self._capacity] = value
        self._count[channel] = n + 1

    def samples(self, name: str) -> np.ndarray:
        i = self._index[name]
        n = int(min(self._count[i], self._capacity))
        return self._data[i, :n]

    def summary(self, name: str, scale: float = 1000.0) -> dict[str, float]:
        """p50/p99/max of the recent samples, scaled (default: seconds → milliseconds)."""
        s = self.samples(name)
        if s.size == 0:
            return {"p50": 0.0, "p99": 0.0, "max": 0.0}
        p50, p99 = np.percentile(s, [50, 99])
        return {
            "p50": round(float(p50) * scale, 4),
            "p99": round(float(p99) * scale, 4),
            "max": round(float(s.max()) * scale, 4),
        }
