"""Unit-test doubles shared by the loop tests (real links are tested in the HIL tests)."""

from __future__ import annotations

import time

from runtime.types import Twist


class FreshFeedbackLink:
    """Base link whose feedback is always fresh; records the commands it is given."""

    def __init__(self) -> None:
        self.commands: list[Twist] = []

    @property
    def last_feedback_time(self) -> float:
        return time.monotonic()

    def poll(self) -> list:
        return []

    def set_command(self, twist: Twist, now: float) -> None:
        self.commands.append(twist)
