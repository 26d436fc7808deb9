"""Guided odometry runs through the real base link, and the procedure that chains them.

The runner drives the base with ordinary wheel commands through `SparkBaseLink` (pyserial) at
a fixed rate, closes the loop on the encoders (or the IMU yaw for the in-place turns), and
records raw tick totals per wire offset, so the estimators (`calibration.odometry_fit`) see
the encoders as they are, whatever the current calibration says. Speeds follow a ramp up and a
braking profile so the base stops close to its target; what it overshoots is measured anyway.

A run is cut short, with a one-line reason, when feedback goes stale (link lost, base silent),
when the operator interrupts (SIGINT), or when no answer comes; nothing is written then.

The operator (a person at the console, or a test reading the emulator's ground truth) places
the robot and reports what a tape measure says: `Operator`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from calibration.odometry_fit import (
    EstimateError,
    MappingResult,
    RunTotals,
    SquareRun,
    UMBmarkResult,
    axle_from_turns,
    encoder_mapping,
    m_per_tick,
    umbmark,
)
from runtime.config.calibration import OdometryCalibration
from runtime.errors import UserError
from runtime.types import STOP, Twist, WheelIncrement

OTHER_OFFSET = {10: 14, 14: 10}


class RunCutShort(UserError):
    """A guided run could not finish; the calibration file is left as it was."""


class Link(Protocol):
    """What the runner needs from `drivers.spark.link.SparkBaseLink`."""

    @property
    def last_feedback_time(self) -> float | None: ...

    def poll(self) -> list[WheelIncrement]: ...

    def set_command(self, twist: Twist, now: float) -> None: ...


class Operator(Protocol):
    """The person with the tape measure (or, in tests, the emulator's ground truth)."""

    def prepare(self, instruction: str) -> None:
        """Show what to set up and wait until it is done (the next run starts on return)."""

    def measured_length(self, odometry_m: float) -> float:
        """Straight-line distance from the start mark to the end mark, m."""

    def measured_end(self, square: str) -> tuple[float, float]:
        """End position from the start mark in the start frame: forward, left (m)."""

    def measured_turn_deg(self, commanded_deg: float) -> float:
        """The angle the robot actually turned (deg, counter-clockwise positive)."""


@dataclass(frozen=True)
class RunConfig:
    """Speeds and limits of the guided runs (modest: a person stands next to the robot)."""

    rate_hz: float = 20.0
    v_max: float = 0.25  # m/s
    v_min: float = 0.03  # crawl speed for the last centimetres
    accel: float = 0.5  # m/s², up and down
    omega_max: float = 1.5  # rad/s
    omega_min: float = 0.15
    alpha: float = 3.0  # rad/s²
    feedback_max_age_s: float = 0.5  # older feedback: the run is cut short
    still_for_s: float = 0.3  # no encoder change this long after a stop: standing still
    settle_timeout_s: float = 3.0
    segment_timeout_s: float = 60.0


@dataclass
class Estimates:
    """What the runner's odometry uses while driving; refined run by run."""

    m_per_tick: float
    axle_m: float
    left_offset: int


@dataclass
class _Track:
    """Running totals of one run (or one square over its segments)."""

    ticks: dict[int, int] = field(default_factory=lambda: {10: 0, 14: 0})
    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0
    distance: float = 0.0  # signed path length of the wheel centre
    imu: float | None = 0.0
    t0: float = 0.0


class BaseRunner:
    """Drives the base and integrates its feedback. One instance per session."""

    def __init__(self, link: Link, link_calibration: OdometryCalibration, config: RunConfig,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 abort: threading.Event | None = None) -> None:
        self.link = link
        self.cfg = config
        self._link_mpt = link_calibration.m_per_tick
        self._link_left = link_calibration.left_encoder_offset
        self._clock = clock
        self._sleep = sleep
        self.abort = abort if abort is not None else threading.Event()
        self._yaw: float | None = None  # last IMU yaw seen (wrapped), to unwrap across polls
        self._tracks: list[_Track] = []
        self._moved_at = 0.0
        self.imu_present = False

    # --- feedback ----------------------------------------------------------------------------

    def _take(self, incs: list[WheelIncrement], est: Estimates, now: float) -> None:
        for inc in incs:
            ticks = {self._link_left: round(inc.d_left / self._link_mpt),
                     OTHER_OFFSET[self._link_left]: round(inc.d_right / self._link_mpt)}
            if ticks[10] or ticks[14]:
                self._moved_at = now
            d_yaw = None
            if inc.yaw is not None:
                self.imu_present = True
                if self._yaw is not None:
                    d_yaw = math.remainder(inc.yaw - self._yaw, math.tau)
                self._yaw = inc.yaw
            dl = ticks[est.left_offset] * est.m_per_tick
            dr = ticks[OTHER_OFFSET[est.left_offset]] * est.m_per_tick
            ds, dth = (dl + dr) / 2.0, (dr - dl) / est.axle_m
            for tr in self._tracks:
                tr.ticks[10] += ticks[10]
                tr.ticks[14] += ticks[14]
                heading = tr.theta + dth / 2.0
                tr.x += ds * math.cos(heading)
                tr.y += ds * math.sin(heading)
                tr.theta += dth
                tr.distance += ds
                tr.imu = None if d_yaw is None or tr.imu is None else tr.imu + d_yaw

    def _cycle(self, est: Estimates) -> float:
        """Drain feedback, check health; returns now."""
        now = self._clock()
        self._take(self.link.poll(), est, now)
        if self.abort.is_set():
            raise RunCutShort("calibration interrupted: the file is left as it was")
        last = self.link.last_feedback_time
        if last is None or now - last > self.cfg.feedback_max_age_s:
            age = "none yet" if last is None else f"{now - last:.2f} s old"
            raise RunCutShort(f"base feedback is stale ({age}): run cut short, the calibration"
                              " file is left as it was")
        return now

    def _wait(self, until: float) -> None:
        delay = until - self._clock()
        if delay > 0:
            self._sleep(delay)

    # --- driving -----------------------------------------------------------------------------

    def start(self, est: Estimates, wait_s: float = 2.0) -> None:
        """Wait for fresh feedback before the first run (the link may still be starting)."""
        deadline = self._clock() + wait_s
        while self.link.last_feedback_time is None and self._clock() < deadline:
            self.link.set_command(STOP, self._clock())
            self._take(self.link.poll(), est, self._clock())
            self._sleep(1.0 / self.cfg.rate_hz)
        self.hold(0.2, est)

    def hold(self, seconds: float, est: Estimates) -> _Track:
        """Stand still for `seconds` (gyro bias, baseline) and return what moved meanwhile."""
        track = self._open()
        period = 1.0 / self.cfg.rate_hz
        end = self._clock() + seconds
        try:
            while True:
                now = self._cycle(est)
                self.link.set_command(STOP, now)
                if now >= end:
                    return track
                self._wait(min(end, now + period))
        finally:
            self._close(track)

    def _open(self) -> _Track:
        track = _Track(imu=0.0 if self._yaw is not None else None, t0=self._clock())
        self._tracks.append(track)
        return track

    def _close(self, track: _Track) -> None:
        self._tracks.remove(track)

    def drive(self, est: Estimates, target: Callable[[_Track, Twist, float], Twist | None],
              track: _Track | None = None) -> _Track:
        """Command `target(track, last_command, dt)` every period until it returns None, then
        stop and wait until the wheels are still. Returns the run's totals (including the
        stop)."""
        own = track is None
        track = track if track is not None else self._open()
        period = 1.0 / self.cfg.rate_hz
        command = STOP
        started = self._clock()
        try:
            while True:
                now = self._cycle(est)
                nxt = target(track, command, period)
                if nxt is None:
                    break
                if now - started > self.cfg.segment_timeout_s:
                    raise RunCutShort(f"a run did not reach its target within"
                                      f" {self.cfg.segment_timeout_s:g} s: is the robot blocked?")
                command = nxt
                self.link.set_command(command, now)
                self._wait(now + period)
            self._settle(est)
        except BaseException:
            self.link.set_command(STOP, self._clock())
            if own:
                self._close(track)
            raise
        if own:
            self._close(track)
        return track

    def _settle(self, est: Estimates) -> None:
        period = 1.0 / self.cfg.rate_hz
        start = self._clock()
        self._moved_at = start
        while True:
            now = self._cycle(est)
            self.link.set_command(STOP, now)
            if now - self._moved_at >= self.cfg.still_for_s:
                return
            if now - start > self.cfg.settle_timeout_s:
                raise RunCutShort("the robot did not come to a stop after a run")
            self._wait(now + period)

    # --- targets -----------------------------------------------------------------------------

    def _ramp(self, current: float, target: float, rate: float, dt: float) -> float:
        step = rate * dt
        return current + max(-step, min(step, target - current))

    def straight(self, distance: float) -> Callable[[_Track, Twist, float], Twist | None]:
        """Forward by `distance` of wheel-centre travel (by the encoders)."""
        c = self.cfg

        def target(tr: _Track, last: Twist, dt: float) -> Twist | None:
            remaining = distance - tr.distance
            if remaining <= 0.0:
                return None
            v = min(c.v_max, max(c.v_min, math.sqrt(2.0 * c.accel * remaining)))
            return Twist(self._ramp(last.v, v, c.accel, dt), 0.0)

        return target

    def turn(self, angle: float, by_imu: bool, base: float = 0.0
             ) -> Callable[[_Track, Twist, float], Twist | None]:
        """Turn in place until the heading (IMU or encoders, since the track opened) reaches
        `base + angle` (rad, signed)."""
        c = self.cfg
        sign = 1.0 if angle > 0 else -1.0
        goal = base + angle

        def target(tr: _Track, last: Twist, dt: float) -> Twist | None:
            heading = tr.imu if by_imu else tr.theta
            remaining = sign * (goal - heading)
            if remaining <= 0.0:
                return None
            w = min(c.omega_max, max(c.omega_min, math.sqrt(2.0 * c.alpha * remaining)))
            return Twist(0.0, self._ramp(last.omega, sign * w, c.alpha, dt))

        return target

    def timed(self, twist: Twist, seconds: float) -> Callable[[_Track, Twist, float],
                                                              Twist | None]:
        """Hold a twist (ramped) for `seconds`: for the mapping check, before any estimate."""
        c = self.cfg
        end = [None]

        def target(tr: _Track, last: Twist, dt: float) -> Twist | None:
            now = self._clock()
            if end[0] is None:
                end[0] = now + seconds
            if now >= end[0]:
                return None
            return Twist(self._ramp(last.v, twist.v, c.accel, dt),
                         self._ramp(last.omega, twist.omega, c.alpha, dt))

        return target

    def square(self, side: float, clockwise: bool, est: Estimates) -> _Track:
        """One UMBmark square by the encoders: four sides, four 90° turns in place, each
        turn aimed at the absolute heading so a small overshoot does not add up."""
        track = self._open()
        sign = -1.0 if clockwise else 1.0
        try:
            for k in range(4):
                self.drive(est, self._segment_straight(side), track)
                self.drive(est, self.turn(sign * math.pi / 2, False, base=sign * k * math.pi / 2),
                           track)
        finally:
            self._close(track)
        return track

    def _segment_straight(self, side: float) -> Callable[[_Track, Twist, float], Twist | None]:
        start: list[float | None] = [None]
        inner = self.straight(side)

        def target(tr: _Track, last: Twist, dt: float) -> Twist | None:
            if start[0] is None:
                start[0] = tr.distance
            shifted = _Track(distance=tr.distance - start[0])
            return inner(shifted, last, dt)

        return target


    def totals(self, track: _Track) -> RunTotals:
        return RunTotals(track.ticks[10], track.ticks[14], track.imu, self._clock() - track.t0)


# --- the procedure -----------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryPlan:
    """What the guided session drives."""

    length_m: float = 2.0  # the straight run
    turns: int = 2  # full in-place turns each way
    squares: int = 5  # UMBmark squares per direction (0 skips UMBmark)
    side_m: float = 1.0  # UMBmark square side
    still_s: float = 2.0  # standing still first: gyro bias


@dataclass(frozen=True)
class OdometryResult:
    calibration: OdometryCalibration
    previous: OdometryCalibration
    mapping: MappingResult
    axle_turns_m: float  # from the in-place turns, before UMBmark
    turns_by: str  # "imu" or "measured"
    gyro_bias_rad_s: float | None
    umbmark: UMBmarkResult | None

    def summary(self) -> dict:
        out: dict = {
            "m_per_tick": self.calibration.m_per_tick,
            "m_per_tick_change_pct": round(100.0 * (self.calibration.m_per_tick
                                                    / self.previous.m_per_tick - 1.0), 3),
            "axle_length_m": round(self.calibration.axle_length_m, 5),
            "axle_turns_m": round(self.axle_turns_m, 5),
            "turns_by": self.turns_by,
            "left_encoder_offset": self.calibration.left_encoder_offset,
            "encoders_swapped": self.calibration.left_encoder_offset
            != self.previous.left_encoder_offset,
            "imu_agrees": self.mapping.imu_agrees,
            "gyro_bias_rad_s": None if self.gyro_bias_rad_s is None
            else round(self.gyro_bias_rad_s, 6),
        }
        if self.umbmark is not None:
            u = self.umbmark
            out.update(umbmark_runs=u.runs, umbmark_ed=round(u.ed, 5), umbmark_eb=round(u.eb, 5))
        return out


def calibrate_odometry(runner: BaseRunner, operator: Operator, previous: OdometryCalibration,
                       plan: OdometryPlan) -> OdometryResult:
    """Mapping turn → straight run → turns both ways → UMBmark squares; each step drives with
    what the steps before it found. Raises RunCutShort or UserError; writes nothing."""
    est = Estimates(previous.m_per_tick, previous.axle_length_m, previous.left_encoder_offset)
    runner.start(est)
    operator.prepare(
        f"Put the robot on open, level floor with {plan.length_m + 0.5:.1f} m free ahead and"
        f" {plan.side_m + 0.5:.1f} m free to each side. It will first stand still for"
        f" {plan.still_s:g} s, then turn left a little.")
    still = runner.totals(runner.hold(plan.still_s, est))
    bias = None if still.imu_yaw_rad is None else still.imu_yaw_rad / still.duration_s
    mapping = _estimate(lambda: encoder_mapping(
        runner.totals(runner.drive(est, runner.timed(Twist(0.0, 0.8), 1.0)))))
    est.left_offset = mapping.left_encoder_offset

    operator.prepare(f"Mark the robot's position on the floor: it will drive about"
                     f" {plan.length_m:g} m straight ahead.")
    straight = runner.drive(est, runner.straight(plan.length_m))
    measured = operator.measured_length(straight.distance)
    est.m_per_tick = _estimate(lambda: m_per_tick(runner.totals(straight), est.left_offset,
                                                  measured))

    by_imu = runner.imu_present and bias is not None
    angle = math.tau * plan.turns
    turns = []
    for sign in (1.0, -1.0):
        if not by_imu:
            operator.prepare("Mark the robot's heading on the floor: it will turn in place"
                             f" {math.degrees(sign * angle):+.0f} deg.")
        track = runner.drive(est, runner.turn(sign * angle, by_imu))
        run = runner.totals(track)
        if by_imu:
            turned = run.imu_yaw_rad - bias * run.duration_s
        else:
            turned = math.radians(operator.measured_turn_deg(math.degrees(track.theta)))
        turns.append((run, turned))
    (ccw, a_ccw), (cw, a_cw) = turns
    est.axle_m = _estimate(lambda: axle_from_turns(ccw, cw, est.left_offset, est.m_per_tick,
                                                   a_ccw, a_cw))
    axle_turns = est.axle_m

    squares = []
    for clockwise in (True, False):
        way = "clockwise" if clockwise else "counter-clockwise"
        for i in range(plan.squares):
            label = f"{way} square {i + 1} of {plan.squares}"
            operator.prepare(f"Put the robot on the start mark facing the start direction:"
                             f" {label}, {plan.side_m:g} m sides.")
            track = runner.square(plan.side_m, clockwise, est)
            squares.append(SquareRun(plan.side_m, clockwise, (track.x, track.y),
                                     operator.measured_end(label)))
    umb = _estimate(lambda: umbmark(squares, est.axle_m)) if squares else None
    axle = est.axle_m * umb.eb if umb is not None else est.axle_m
    result = OdometryCalibration(est.m_per_tick, axle, est.left_offset)
    return OdometryResult(result, previous, mapping, axle_turns, "imu" if by_imu else "measured",
                          bias, umb)


def _estimate(compute: Callable[[], object]) -> object:
    """An estimator's EstimateError as a one-line user error."""
    try:
        return compute()
    except EstimateError as exc:
        raise UserError(f"odometry calibration: {exc}; the calibration file is left as it"
                        " was") from None
