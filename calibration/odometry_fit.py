"""Odometry constants from guided runs: pure estimators (run totals in, constants out).

- Encoder mapping: while the base turns in place counter-clockwise (ω > 0 commanded), the right
  wheel's count rises and the left wheel's falls; the IMU yaw must rise too.
- Metres per tick: a straight run's measured length over the mean tick count of both wheels.
- Axle length: wheel travel difference over the turned angle, from in-place turns both ways.
  With the IMU yaw as the angle a constant gyro bias adds the same drift to both directions;
  taking the difference of the two directions cancels it.
- UMBmark (Borenstein & Feng 1996): L×L squares driven by odometry clockwise and
  counter-clockwise; from the mean return position errors (actual − odometry) along x follow
  the wheel-diameter ratio Ed and the wheelbase factor Eb. It does not fix overall scale: that
  is the straight run's job (field notes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

STRAIGHT_MISMATCH_MAX = 0.05  # wheels of a straight run disagree by more: not a straight run
TURN_BALANCE_MIN = 0.5  # in an in-place turn the smaller wheel count is at least this share


class EstimateError(ValueError):
    """The run's data cannot give the estimate; the message says what the run did instead."""


@dataclass(frozen=True)
class RunTotals:
    """Signed tick totals per wire offset over a run, and the IMU yaw change (None: no IMU)."""

    ticks_10: int
    ticks_14: int
    imu_yaw_rad: float | None
    duration_s: float

    def wheels(self, left_offset: int) -> tuple[int, int]:
        """(left, right) ticks under a mapping."""
        return (self.ticks_14, self.ticks_10) if left_offset == 14 else (self.ticks_10,
                                                                          self.ticks_14)


@dataclass(frozen=True)
class MappingResult:
    left_encoder_offset: int
    imu_agrees: bool | None  # None without IMU


def encoder_mapping(turn_left: RunTotals) -> MappingResult:
    """Which wire offset is the left wheel, from an in-place turn commanded with ω > 0."""
    a, b = turn_left.ticks_10, turn_left.ticks_14
    if a * b >= 0 or min(abs(a), abs(b)) < TURN_BALANCE_MIN * max(abs(a), abs(b)):
        raise EstimateError(
            f"a left turn in place should move one encoder forward and the other back by about"
            f" the same; offset 10 moved {a:+d} and offset 14 {b:+d} ticks")
    imu = None if turn_left.imu_yaw_rad is None else turn_left.imu_yaw_rad > 0
    if imu is False:
        raise EstimateError(
            f"the IMU yaw fell by {math.degrees(-turn_left.imu_yaw_rad):.1f} deg during a"
            " commanded left turn: the base turned right (motor wiring) or the IMU is reversed")
    return MappingResult(10 if a < 0 else 14, imu)


def m_per_tick(straight: RunTotals, left_offset: int, measured_m: float) -> float:
    """Metres per tick from a straight run whose length the user measured."""
    left, right = straight.wheels(left_offset)
    mean = (left + right) / 2.0
    if left <= 0 or right <= 0:
        raise EstimateError(f"a straight run forward should move both wheels forward; left"
                            f" {left:+d}, right {right:+d} ticks")
    if abs(left - right) > STRAIGHT_MISMATCH_MAX * mean:
        raise EstimateError(f"the wheels of the straight run differ by {abs(left - right)} of"
                            f" {mean:.0f} ticks: the robot did not drive straight")
    if not (math.isfinite(measured_m) and measured_m > 0):
        raise EstimateError(f"the measured length must be a positive number, got {measured_m}")
    return measured_m / mean


def axle_from_turns(ccw: RunTotals, cw: RunTotals, left_offset: int, m_tick: float,
                    ccw_rad: float, cw_rad: float) -> float:
    """Axle length from a counter-clockwise and a clockwise in-place turn whose angles
    (signed, rad; from the IMU or measured) are given."""
    diff_ccw = (ccw.wheels(left_offset)[1] - ccw.wheels(left_offset)[0]) * m_tick
    diff_cw = (cw.wheels(left_offset)[1] - cw.wheels(left_offset)[0]) * m_tick
    turned = ccw_rad - cw_rad
    if not (ccw_rad > 0 > cw_rad) or diff_ccw <= 0 or diff_cw >= 0:
        raise EstimateError(
            f"the in-place turns went the wrong way: {math.degrees(ccw_rad):+.0f} and"
            f" {math.degrees(cw_rad):+.0f} deg, wheel differences {diff_ccw:+.3f} and"
            f" {diff_cw:+.3f} m")
    return (diff_ccw - diff_cw) / turned


@dataclass(frozen=True)
class SquareRun:
    """One UMBmark square: side, direction, odometry's end position and the measured one, both
    in the start frame (x forward, y left)."""

    side_m: float
    clockwise: bool
    odometry_xy: tuple[float, float]
    actual_xy: tuple[float, float]


@dataclass(frozen=True)
class UMBmarkResult:
    ed: float  # wheel diameter ratio right / left
    eb: float  # actual wheelbase / the wheelbase odometry used
    alpha_rad: float  # the turn error that scales with the wheelbase
    beta_rad: float  # the curvature error from unequal wheels
    runs: int


def umbmark(runs: list[SquareRun], wheelbase_m: float) -> UMBmarkResult:
    """Borenstein's x-based UMBmark: α = (x_cw + x_ccw)/(−4L), β = (x_cw − x_ccw)/(−4L),
    R = (L/2)/sin(β/2), Ed = (R + b/2)/(R − b/2), Eb = (π/2)/(π/2 − α), with x the mean
    return error (actual − odometry) of each direction."""
    cw = [r for r in runs if r.clockwise]
    ccw = [r for r in runs if not r.clockwise]
    if not cw or not ccw:
        raise EstimateError("UMBmark needs squares in both directions")
    sides = {r.side_m for r in runs}
    if len(sides) != 1:
        raise EstimateError("UMBmark squares must all have the same side")
    side = sides.pop()

    def mean_x_error(rs: list[SquareRun]) -> float:
        return sum(r.actual_xy[0] - r.odometry_xy[0] for r in rs) / len(rs)

    x_cw, x_ccw = mean_x_error(cw), mean_x_error(ccw)
    alpha = (x_cw + x_ccw) / (-4.0 * side)
    beta = (x_cw - x_ccw) / (-4.0 * side)
    if abs(alpha) > math.pi / 8 or abs(beta) > math.pi / 8:
        raise EstimateError(
            f"the squares end {x_cw:+.3f} m (clockwise) and {x_ccw:+.3f} m off: too far for"
            " systematic odometry errors; check the measurements (forward offset first)")
    ed = 1.0
    if abs(beta) > 1e-12:
        radius = (side / 2.0) / math.sin(beta / 2.0)
        ed = (radius + wheelbase_m / 2.0) / (radius - wheelbase_m / 2.0)
    eb = (math.pi / 2.0) / (math.pi / 2.0 - alpha)
    return UMBmarkResult(ed, eb, alpha, beta, len(runs))
