"""Spark feedback frames → SI wheel increments: plausibility, odometry recovery, flag debounce.

This is the driver edge where ticks, 0.1 ms and degrees become metres, seconds and radians.
Pure (no I/O), so it is tested directly and reused by the lock-stepped simulator.

Why a frame that passed the parser can still be wrong: the 8-bit sum misses two corrupted bytes
whose changes cancel (one bit up and the same bit down in another byte, or bit 7 flipped
twice). With 1 % of bytes corrupted, about one frame in a hundred that reaches us carries wrong
content. So a frame is used only if it is what the base could physically have sent:

- its IMU values are finite and within physical range (accelerometer full scale, the turn rate
  the wheels allow, angles within one turn: the sheet does not say ±180° or 0–360°);
- its base timestamp is later than the last accepted frame's and agrees with the host's arrival
  time: no earlier than the fastest delivery seen (`CLOCK_SLACK_S`) and no more than
  `MAX_LATENCY_S` later; the two clocks may drift apart by `CLOCK_DRIFT`;
- each wheel's encoder delta fits what the wheel can travel in the base-clock time elapsed:
  `SPEED_MARGIN` × the firmware's wheel-speed clamp, plus `glitch_ticks` of slack. The bound
  is the clamp, not the commanded speed: a command corrupted on its way to the base passes the
  same 8-bit sum and can drive a wheel at up to the clamp, and a pushed robot moves without
  any command; a bound from the command would throw that real motion away.

Odometry is not lost to rejected frames: the counts on the wire are cumulative, so every
increment is measured from the last *accepted* counts and spans whatever was rejected in
between; a reading that was wrong but plausible is undone by the next increment. Across a gap
longer than `MAX_UNCONFIRMED_DT_S` the bound is too loose to vouch for one frame, so such an
increment is released only when two frames in a row agree, one of them following the last
accepted reading. Two frames that agree with each other but not with the last accepted reading
are judged by the accepted reading before it: if that one agrees, the last one was corrupted
and the next increment corrects it (`corrected`); if not, the counters restarted (base reboot)
and a new baseline is taken (`rebaseline`: the distance since the last good frame is lost). A
baseline always needs two agreeing frames at most `BASELINE_PAIR_MAX_DT_S` apart, never one
frame alone: an error in it would stay in the odometry for good.

Cliff and wheel-drop flags change only when `flag_debounce_frames` accepted frames in a row
agree, so one corrupted flag cannot stop the robot and one corrupted clear flag cannot release
it. The cost is latency: (N − 1) frame periods, 20 ms per extra frame at the base's 50 Hz.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass
from functools import reduce
from operator import and_, or_

from drivers.spark.protocol import Feedback, signed_delta32
from runtime.config.calibration import OdometryCalibration
from runtime.config.devices import BaseConfig
from runtime.types import (
    MAX_UNCONFIRMED_DT_S,
    BaseStatus,
    CliffSensor,
    Proximity,
    WheelIncrement,
)

BASE_TICK_S = 1e-4  # base timestamp resolution: 0.1 ms
CLIFF_MASK = 0x3F
WHEEL_DROP = int(BaseStatus.WHEEL_DROP_LEFT | BaseStatus.WHEEL_DROP_RIGHT)
SPEED_MARGIN = 1.5  # over the firmware clamp: overshoot, coasting, a robot pushed by hand
CLOCK_SLACK_S = 0.01  # a stamp may lead the fastest delivery by this (where the base stamps
# in its loop, and the USB bridge's batching, are unverified: a few ms of jitter either way)
CLOCK_DRIFT = 1e-3  # base crystal vs host clock, s/s (ten times a poor crystal's 100 ppm)
MAX_LATENCY_S = 0.5  # a frame delivered this much slower than the fastest one is not trusted
BASELINE_PAIR_MAX_DT_S = 0.1  # a baseline's two frames: a few apart at 50 Hz; a base that
# streams slower than its unverified "about 50 Hz", down to 10 Hz, can still start
MAX_ACCEL_G = 16.0  # accelerometer full scale: beyond it the float is corrupted, not measured
FEEDBACK_REJECT_REASONS = ("imu", "clock_backwards", "clock_jump", "encoder_jump", "unconfirmed")


@dataclass(frozen=True, slots=True)
class _Pending:
    """The latest frame not used as it arrived, and why (against the last accepted reading)."""

    fb: Feedback
    t_host: float
    problem: str


@dataclass(frozen=True, slots=True)
class _Reading:
    """An accepted frame with its arrival time and its base time unwrapped along the chain (s)."""

    fb: Feedback
    t_host: float
    base_s: float


class FeedbackConverter:
    """Stateful conversion of successive feedback frames into increments (see the module doc).

    `rejected` counts frames not used as they arrived, by reason; `counts` the baseline events
    (`baseline`, `rebaseline`), `recovered` (an increment over a gap, released once the next
    frame agreed) and `corrected` (the last accepted reading turned out to be the bad one).
    """

    def __init__(self, calibration: OdometryCalibration, cfg: BaseConfig | None = None) -> None:
        cfg = cfg or BaseConfig()
        self._m_per_tick = calibration.m_per_tick
        self._left_is_14 = calibration.left_encoder_offset == 14
        self._max_tick_rate = SPEED_MARGIN * cfg.max_wheel_speed_m_s / calibration.m_per_tick
        self._slack_ticks = cfg.glitch_ticks
        # Both wheels at the clamp in opposite directions, with the same margin.
        self._max_turn_dps = math.degrees(
            SPEED_MARGIN * 2.0 * cfg.max_wheel_speed_m_s / calibration.axle_length_m
        )
        self._flags: deque[int] = deque(maxlen=cfg.flag_debounce_frames)
        self._flag_state = 0
        self._last: _Reading | None = None
        self._prev: _Reading | None = None  # the accepted reading before `_last`
        self._pending: _Pending | None = None
        self._min_lag = math.inf  # host arrival − base time of the fastest delivery (s)
        self.usable = False
        self.rejected: Counter[str] = Counter({reason: 0 for reason in FEEDBACK_REJECT_REASONS})
        self.counts: Counter[str] = Counter()

    def convert(self, fb: Feedback, t_host: float) -> WheelIncrement | None:
        """The increment since the last accepted frame, or None (rejected, held or baseline).

        `usable` says afterwards whether a frame was taken (as an increment or as a new
        baseline): only usable frames count as fresh feedback, so a link that delivers nothing
        plausible makes the loop DEGRADED, not blind.
        """
        self.usable = False
        if not self._imu_plausible(fb):
            self.rejected["imu"] += 1
            return None
        last, pending = self._last, self._pending
        problem = "unconfirmed" if last is None else self._problem(last, fb, t_host)
        if problem is None:
            assert last is not None
            return self._accept(fb, t_host, last)
        self._pending = _Pending(fb, t_host, problem)
        if pending is None:  # nothing to confirm it yet
            if last is not None:  # (the very first frame is not counted: it only waits)
                self.rejected[problem] += 1
            return None
        agree = self._agree(pending.fb, fb, MAX_UNCONFIRMED_DT_S)
        if agree and last is not None and "unconfirmed" in (problem, pending.problem):
            # Two frames agree and one of them follows the last accepted reading across the
            # gap: release the increment to the later one that does.
            self.counts["recovered"] += 1
            if problem == "unconfirmed":
                return self._accept(fb, t_host, last)
            self.rejected[problem] += 1  # `fb` disagrees with the reading its partner follows
            return self._accept(pending.fb, pending.t_host, last)
        prev = self._prev
        if agree and prev is not None and self._problem(prev, fb, t_host, math.inf) is None:
            # Two frames agree with the reading before the last accepted one, not with that
            # one: it was the corrupted one, and this increment undoes its error.
            self.counts["corrected"] += 1
            return self._accept(fb, t_host, prev)
        if agree and self._agree(pending.fb, fb, BASELINE_PAIR_MAX_DT_S):
            # No accepted reading vouches for them: a (re)baseline needs the two close.
            self._take_baseline(pending, fb, t_host)
            return None
        self.rejected[problem] += 1
        return None

    # --- checks ------------------------------------------------------------------------------

    def _imu_plausible(self, fb: Feedback) -> bool:
        if fb.gyro_dps is None or fb.rpy_deg is None or fb.accel_g is None or fb.mag is None:
            return True  # a 25-byte frame has no IMU
        values = (*fb.accel_g, *fb.gyro_dps, *fb.mag, *fb.rpy_deg)
        return (
            all(math.isfinite(v) for v in values)
            and all(abs(a) <= MAX_ACCEL_G for a in fb.accel_g)
            and abs(fb.gyro_dps[2]) <= self._max_turn_dps
            and all(abs(a) <= 360.0 for a in fb.rpy_deg)
        )

    def _problem(self, ref: _Reading, fb: Feedback, t_host: float,
                 max_dt: float = MAX_UNCONFIRMED_DT_S) -> str | None:
        """Why `fb` cannot follow the accepted reading `ref`, or None."""
        dt = self._dt(ref.fb, fb)
        if dt <= 0.0:
            return "clock_backwards"
        lag = t_host - (ref.base_s + dt)
        drift = CLOCK_DRIFT * dt
        if not -CLOCK_SLACK_S - drift <= lag - self._min_lag <= MAX_LATENCY_S + drift:
            return "clock_jump"
        if self._too_far(ref.fb, fb, dt):
            return "encoder_jump"
        return "unconfirmed" if dt > max_dt else None

    def _agree(self, first: Feedback, second: Feedback, max_dt: float) -> bool:
        """Whether two frames in a row, at most `max_dt` apart, can both be true readings."""
        dt = self._dt(first, second)
        return 0.0 < dt <= max_dt and not self._too_far(first, second, dt)

    def _too_far(self, a: Feedback, b: Feedback, dt: float) -> bool:
        limit = self._max_tick_rate * dt + self._slack_ticks
        return (abs(signed_delta32(b.encoder_10, a.encoder_10)) > limit
                or abs(signed_delta32(b.encoder_14, a.encoder_14)) > limit)

    @staticmethod
    def _dt(a: Feedback, b: Feedback) -> float:
        return signed_delta32(b.base_time, a.base_time) * BASE_TICK_S

    # --- state changes -----------------------------------------------------------------------

    def _accept(self, fb: Feedback, t_host: float, anchor: _Reading) -> WheelIncrement:
        """Increment from the last accepted counts to `fb`, so it spans every rejected frame (and
        corrects the last reading when it was the bad one). `anchor` is the accepted reading
        `fb` was checked against: it carries the base clock on."""
        last = self._last
        assert last is not None
        dt_anchor = self._dt(anchor.fb, fb)
        base_s = anchor.base_s + dt_anchor
        # The lag's floor may rise only at the drift rate: a stamp corrupted late cannot lift it.
        self._min_lag = min(t_host - base_s, self._min_lag + CLOCK_DRIFT * dt_anchor)
        self._prev, self._last, self._pending = anchor, _Reading(fb, t_host, base_s), None
        self.usable = True
        left_now, right_now = self._wheels(fb)
        left_last, right_last = self._wheels(last.fb)
        flags = self._debounce(fb)
        return WheelIncrement(
            t=t_host,
            dt=self._dt(last.fb, fb),
            d_left=signed_delta32(left_now, left_last) * self._m_per_tick,
            d_right=signed_delta32(right_now, right_last) * self._m_per_tick,
            gyro_z=math.radians(fb.gyro_dps[2]) if fb.gyro_dps is not None else None,
            yaw=math.radians(fb.rpy_deg[2]) if fb.rpy_deg is not None else None,
            cliffs=CliffSensor(flags & CLIFF_MASK),
            proximity=Proximity(fb.bumper_bits & 0x7F),
            status=BaseStatus((fb.status_bits & ~WHEEL_DROP & 0xFF) | (flags >> 8)),
        )

    def _take_baseline(self, pending: _Pending, fb: Feedback, t_host: float) -> None:
        """Start the chain afresh at `fb`, confirmed by the frame before it; base time 0 at `fb`."""
        self.counts["baseline" if self._last is None else "rebaseline"] += 1
        self._min_lag = min(t_host, pending.t_host + self._dt(pending.fb, fb))
        self._last, self._prev, self._pending = _Reading(fb, t_host, 0.0), None, None
        self.usable = True
        self._debounce(fb)

    def _debounce(self, fb: Feedback) -> int:
        """Cliff bits (low byte, already inverted from active-low) and wheel-drop bits (<< 8):
        a bit turns on when set in each of the last N accepted frames, off when clear in each."""
        self._flags.append((~fb.cliff_bits & CLIFF_MASK) | ((fb.status_bits & WHEEL_DROP) << 8))
        if len(self._flags) == self._flags.maxlen:
            every, some = reduce(and_, self._flags), reduce(or_, self._flags)
            self._flag_state = (self._flag_state | every) & some
        return self._flag_state

    def _wheels(self, fb: Feedback) -> tuple[int, int]:
        return (fb.encoder_14, fb.encoder_10) if self._left_is_14 else (fb.encoder_10, fb.encoder_14)
