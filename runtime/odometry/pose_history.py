"""The robot's recent poses, so a sensor reading is placed where the robot was when it was
taken, not where it is when the loop gets to it.

A depth frame reaches the world model 30–100 ms after its stamp (exposure, transfer, the wait
for the next cycle). Placed with the current pose, everything in it is shifted by the motion
since: at 0.3 m/s and 1 rad/s over 80 ms, 2.4 cm forward and 4.6° of bearing, which is half the
shield's margin, and always toward the robot in the direction it is driving. Robotics
middleware does the same with a transform lookup at the message's stamp.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque

from runtime.geometry import wrap_angle
from runtime.types import Odometry


class PoseHistory:
    """Odometry by host time, the last `span_s` seconds; `at(t)` interpolates between the two
    poses around t (the oldest or newest one outside the span)."""

    def __init__(self, span_s: float = 2.0) -> None:
        self._span_s = span_s
        self._items: deque[Odometry] = deque()
        self._times: deque[float] = deque()

    def add(self, odom: Odometry) -> None:
        if self._times and odom.t < self._times[-1]:
            return  # odometry's clock never runs back; a late duplicate adds nothing
        self._items.append(odom)
        self._times.append(odom.t)
        while self._times[-1] - self._times[0] > self._span_s and len(self._times) > 2:
            self._items.popleft()
            self._times.popleft()

    def at(self, t: float, latest: Odometry) -> Odometry:
        """The pose at host time t (`latest` when there is no history yet)."""
        if not self._items or not math.isfinite(t):
            return latest
        k = bisect.bisect_left(self._times, t)
        if k == 0:
            return self._items[0]
        if k == len(self._items):
            return self._items[-1]
        a, b = self._items[k - 1], self._items[k]
        f = (t - a.t) / (b.t - a.t) if b.t > a.t else 1.0
        return dataclasses.replace(
            b, t=t, x=a.x + f * (b.x - a.x), y=a.y + f * (b.y - a.y),
            theta=wrap_angle(a.theta + f * wrap_angle(b.theta - a.theta)))
