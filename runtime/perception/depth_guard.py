"""Admission of depth frames: a frame whose stamp or shape cannot be trusted never reaches the
world model.

A depth stamp is the clock of everything downstream: the stale-depth check, obstacle memory's
decay and the tracker's velocities. A NaN stamp made `now − t > max_age` never true (the loop
drove on through a camera stall), and a stamp an hour off crashed the tracker. So every frame
is checked against the host clock and the last admitted frame before it is used: a rejected
frame is counted by reason and logged (the first of a streak), and the loop then sees no new
depth, so the stale-depth check brakes the robot if good frames stop coming. Pure: the caller
passes the time.
"""

from __future__ import annotations

import logging
import math
from collections import Counter

import numpy as np

from runtime.types import DepthFrame

log = logging.getLogger("safemove.depth")


class DepthGuard:
    """Checks each frame's stamp (finite, not ahead of the host clock by more than `max_future_s`,
    not before the last admitted frame) and its image (uint16, shape matching finite positive
    intrinsics)."""

    def __init__(self, max_future_s: float) -> None:
        self._max_future_s = max_future_s
        self.last_t: float | None = None
        self.rejected: Counter[str] = Counter()
        self._streak: str | None = None

    def admit(self, frame: DepthFrame, now: float) -> bool:
        """True if the frame may be used; otherwise it is counted and (first of a streak) logged."""
        why = self._problem(frame, now)
        if why is None:
            if self._streak is not None:
                log.warning("depth frames admitted again from frame %d (%s)", frame.frame_number,
                            self._summary())
            self._streak = None
            self.last_t = frame.t
            return True
        kind, detail = why
        self.rejected[kind] += 1
        if self._streak != kind:
            log.warning("depth frame %d dropped: %s", frame.frame_number, detail)
        self._streak = kind
        return False

    def _problem(self, frame: DepthFrame, now: float) -> tuple[str, str] | None:
        t = frame.t
        if not math.isfinite(t):
            return "bad_stamp", f"stamp {t!r} is not a time"
        if t > now + self._max_future_s:
            return "clock_jump", (f"stamped {t - now:+.3f} s ahead of the host clock (a sensor"
                                  " clock jump?)")
        if self.last_t is not None and t < self.last_t:
            return "clock_jump", (f"stamped {t - self.last_t:+.3f} s before the previous frame"
                                  " (a sensor clock jump?)")
        k = frame.intrinsics
        params = (k.fx, k.fy, k.cx, k.cy, k.depth_unit_m)
        if not all(math.isfinite(p) for p in params) or min(k.fx, k.fy, k.depth_unit_m) <= 0:
            return "bad_intrinsics", f"intrinsics {k} are not finite and positive"
        depth = frame.depth
        want = frame.image_shape if frame.decimation >= 1 else None
        if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.shape != want:
            return "bad_image", (f"image {getattr(depth, 'dtype', type(depth))}"
                                 f" {getattr(depth, 'shape', '')} is not uint16"
                                 f" {k.height}x{k.width}"
                                 + (f" decimated by {frame.decimation}"
                                    if frame.decimation != 1 else ""))
        return None

    def _summary(self) -> str:
        return ", ".join(f"{n} {kind}" for kind, n in sorted(self.rejected.items())) + " so far"
