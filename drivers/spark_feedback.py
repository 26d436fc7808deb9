"""Spark feedback frames → SI wheel increments: encoder wrap, left/right mapping, glitch rejection.

This is the driver edge where ticks, 0.1 ms and degrees become metres, seconds and radians.
Pure (no I/O), so it is tested directly and reused by calibration tools.
"""

from __future__ import annotations

import math
from collections import Counter

from drivers.spark_protocol import Feedback, signed_delta32
from runtime.config import OdometryCalibration
from runtime.types import BaseStatus, CliffSensor, Proximity, WheelIncrement

BASE_TICK_S = 1e-4  # base timestamp resolution: 0.1 ms
CLIFF_MASK = 0x3F
MAX_FRAME_GAP_S = 1.0  # consecutive frames on a live link are ~20 ms apart on the base clock
MAX_CLOCK_DISAGREEMENT_S = 0.5  # host vs base clock over an outage (arrival jitter + latency)


class FeedbackConverter:
    """Stateful conversion of successive feedback frames into increments.

    The first frame (and the first after `rebaseline`) only sets the baseline. A jump of
    `glitch_ticks` or more in one frame, or a base clock that runs backwards or leaps, is
    dropped while the baseline is kept, so a one-frame spike costs nothing; after
    `max_consecutive_glitches` the counters are assumed to have been reset (base reboot) and the
    baseline is taken afresh. After a reconnect the first delta may span the outage: it is
    accepted only if the base clock advanced about as far as the host's and the speed it
    implies is plausible; otherwise the baseline is retaken at once.
    """

    def __init__(
        self,
        calibration: OdometryCalibration,
        glitch_ticks: int = 1000,
        max_plausible_wheel_m_s: float = 1.5,
        max_consecutive_glitches: int = 3,
    ) -> None:
        self._m_per_tick = calibration.m_per_tick
        self._left_is_14 = calibration.left_encoder_offset == 14
        self._glitch_ticks = glitch_ticks
        self._max_plausible = max_plausible_wheel_m_s
        self._max_glitches = max_consecutive_glitches
        self._last: Feedback | None = None
        self._after_gap = False
        self._glitch_run = 0
        self._last_t_host = 0.0
        self.usable = False
        self.counts: Counter[str] = Counter()

    def mark_gap(self) -> None:
        """The link was lost and regained: the next delta may span the outage."""
        self._after_gap = True

    def rebaseline(self) -> None:
        """Forget the previous counts entirely (next frame only sets the baseline)."""
        self._last = None

    def _wheels(self, fb: Feedback) -> tuple[int, int]:
        return (fb.encoder_14, fb.encoder_10) if self._left_is_14 else (fb.encoder_10, fb.encoder_14)

    def convert(self, fb: Feedback, t_host: float) -> WheelIncrement | None:
        """The increment since the previous accepted frame, or None (baseline or rejected).

        `usable` says afterwards whether the frame was taken (as an increment or as a new
        baseline): only usable frames count as fresh feedback, so a converter that rejects
        everything (a base whose counters restarted) makes the loop DEGRADED, not blind.
        """
        last = self._last
        if last is None:
            self._take_baseline(fb, t_host, "baseline")
            return None
        left_now, right_now = self._wheels(fb)
        left_last, right_last = self._wheels(last)
        d_left = signed_delta32(left_now, left_last)
        d_right = signed_delta32(right_now, right_last)
        dt = signed_delta32(fb.base_time, last.base_time) * BASE_TICK_S
        problem = self._problem(d_left, d_right, dt, t_host - self._last_t_host)
        if problem is not None:
            self.counts[problem] += 1
            self._glitch_run += 1
            # After an outage there is no pre-glitch baseline worth keeping: the base may have
            # rebooted. Otherwise allow a few one-frame spikes before assuming a counter reset.
            if self._after_gap or self._glitch_run >= self._max_glitches:
                self._take_baseline(fb, t_host, "rebaseline")
            else:
                self.usable = False
            return None
        self._glitch_run = 0
        self._after_gap = False
        self._last = fb
        self._last_t_host = t_host
        self.usable = True
        return WheelIncrement(
            t=t_host,
            dt=dt,
            d_left=d_left * self._m_per_tick,
            d_right=d_right * self._m_per_tick,
            gyro_z=math.radians(fb.gyro_dps[2]) if fb.gyro_dps is not None else None,
            yaw=math.radians(fb.rpy_deg[2]) if fb.rpy_deg is not None else None,
            cliffs=CliffSensor(~fb.cliff_bits & CLIFF_MASK),
            proximity=Proximity(fb.bumper_bits & 0x7F),
            status=BaseStatus(fb.status_bits),
        )

    def _take_baseline(self, fb: Feedback, t_host: float, why: str) -> None:
        self.counts[why] += 1
        self._last = fb
        self._last_t_host = t_host
        self._after_gap = False
        self._glitch_run = 0
        self.usable = True

    def _problem(self, d_left: int, d_right: int, dt: float, host_dt: float) -> str | None:
        """Why this frame's delta cannot be trusted, or None."""
        if dt <= 0.0:
            return "clock_backwards"
        biggest = max(abs(d_left), abs(d_right))
        if self._after_gap:
            # Across an outage the base clock must have advanced about as much as ours did;
            # otherwise the base rebooted (or its clock wrapped) and the counts are unrelated.
            if abs(dt - host_dt) > MAX_CLOCK_DISAGREEMENT_S + 0.2 * host_dt:
                return "clock_jump"
            return "glitch" if biggest * self._m_per_tick / dt > self._max_plausible else None
        if dt > MAX_FRAME_GAP_S:
            return "clock_jump"
        return "glitch" if biggest >= self._glitch_ticks else None
