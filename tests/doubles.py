"""Unit-test doubles shared by the loop tests (real links are tested in the HIL tests)."""

from __future__ import annotations

import time
from collections.abc import Callable

from runtime.types import Twist


class SimClock:
    """Simulated monotonic time for stepping the control loop without sleeping: pass it as the
    loop's clock and its `wait` as the loop's wait."""

    def __init__(self, t0: float = 100.0) -> None:
        self.now = t0

    def __call__(self) -> float:
        return self.now

    def wait(self, seconds: float) -> bool:
        """Sleep on simulated time; never interrupted."""
        self.now += max(0.0, seconds)
        return False


class FreshFeedbackLink:
    """Base link whose feedback is always fresh; records the commands it is given."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.commands: list[Twist] = []
        self._clock = clock

    @property
    def last_feedback_time(self) -> float:
        return self._clock()

    def poll(self) -> list:
        return []

    def set_command(self, twist: Twist, now: float) -> None:
        self.commands.append(twist)
