"""Unit and property tests of the pure stages: limits, odometry, jobs (feedback conversion: see
test_spark_feedback.py).

No processes, no sleeps, no devices: hand-built Feedback / Odometry / WheelIncrement values.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.config.settings import LimitsConfig
from runtime.geometry import from_frame, into_frame, wrap_angle
from runtime.jobs.drive import STILL_FOR_S, DriveJob, HoldJob, Segment
from runtime.odometry.dead_reckoning import advance
from runtime.safety.limits import apply_limits
from runtime.types import (
    STOP,
    BaseStatus,
    CliffSensor,
    Odometry,
    Proximity,
    Twist,
    WheelIncrement,
)

LIMITS = LimitsConfig()  # v [-0.1, 0.3], |omega| <= 1, accel 0.5, decel 1.0, alpha 2.0
AXLE = 0.266

# --- apply_limits --------------------------------------------------------------------------------


def test_velocity_box_clamp() -> None:
    # dt large enough that the rate limits do not bind
    assert apply_limits(Twist(1.0, 5.0), STOP, 10.0, LIMITS) == Twist(0.3, 1.0)
    assert apply_limits(Twist(-1.0, -5.0), STOP, 10.0, LIMITS) == Twist(-0.1, -1.0)
    assert apply_limits(Twist(0.2, 0.5), STOP, 10.0, LIMITS) == Twist(0.2, 0.5)


def test_acceleration_limit_when_speeding_up() -> None:
    out = apply_limits(Twist(0.3, 0.0), Twist(0.1, 0.0), 0.05, LIMITS)
    assert out.v == pytest.approx(0.1 + 0.5 * 0.05)
    out = apply_limits(Twist(-0.1, 0.0), STOP, 0.05, LIMITS)  # from rest, backwards
    assert out.v == pytest.approx(-0.5 * 0.05)


@pytest.mark.parametrize("target", [0.0, 0.1], ids=["to-stop", "to-slower"])
def test_decel_limit_when_slowing_down_is_the_larger_one(target: float) -> None:
    out = apply_limits(Twist(target, 0.0), Twist(0.3, 0.0), 0.05, LIMITS)
    assert out.v == pytest.approx(0.3 - 1.0 * 0.05)  # decel_max, not the smaller accel_max
    back = apply_limits(Twist(0.0, 0.0), Twist(-0.1, 0.0), 0.05, LIMITS)
    assert back.v == pytest.approx(-0.1 + 1.0 * 0.05)


def test_a_brake_is_never_softened_by_the_comfort_limit() -> None:
    soft = dataclasses.replace(LIMITS, accel_max=0.1, decel_max=2.0)
    v, steps = 0.3, 0
    while v != 0.0:
        new = apply_limits(STOP, Twist(v, 0.0), 0.05, soft).v
        assert v - new == pytest.approx(min(v, 2.0 * 0.05))
        v, steps = new, steps + 1
    assert steps == 3


def test_reversing_passes_through_zero_with_decel_then_accelerates_with_accel() -> None:
    v, seq = 0.2, []
    for _ in range(10):
        v = apply_limits(Twist(-0.1, 0.0), Twist(v, 0.0), 0.05, LIMITS).v
        seq.append(v)
    assert seq[:4] == pytest.approx([0.15, 0.10, 0.05, 0.0])
    assert seq[3] == 0.0  # exactly stopped, not a rounding residue
    assert seq[4:8] == pytest.approx([-0.025, -0.05, -0.075, -0.1])
    assert seq[8:] == pytest.approx([-0.1, -0.1])


def test_speeding_up_after_crossing_zero_uses_accel() -> None:
    out = apply_limits(Twist(-0.1, 0.0), Twist(1e-6, 0.0), 0.05, LIMITS)
    assert out.v >= -LIMITS.accel_max * 0.05 - 1e-9


def test_omega_limited_by_alpha_both_ways() -> None:
    assert apply_limits(Twist(0.0, 1.0), STOP, 0.05, LIMITS).omega == pytest.approx(0.1)
    assert apply_limits(Twist(0.0, -1.0), Twist(0.0, 1.0), 0.05, LIMITS).omega == pytest.approx(0.9)
    assert apply_limits(STOP, Twist(0.0, 0.05), 0.05, LIMITS).omega == 0.0


def test_output_never_exceeds_the_box_even_by_rounding() -> None:
    out = apply_limits(Twist(0.3, 0.0), Twist(-0.1, 0.0), 1.0, LIMITS)
    assert LIMITS.v_min <= out.v <= LIMITS.v_max


finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@st.composite
def limits_and_previous(draw, min_rate: float = 1e-3):
    limits = LimitsConfig(
        v_max=draw(st.floats(0.0, 0.5)),
        v_min=draw(st.floats(-0.5, 0.0)),
        omega_max=draw(st.floats(0.0, 4.0)),
        accel_max=draw(st.floats(min_rate, 5.0)),
        decel_max=draw(st.floats(min_rate, 5.0)),
        alpha_max=draw(st.floats(min_rate, 20.0)),
    )
    previous = Twist(
        draw(st.floats(limits.v_min, limits.v_max)),
        draw(st.floats(-limits.omega_max, limits.omega_max)),
    )
    return limits, previous


RATE_SLACK = 1e-9


@settings(max_examples=300, deadline=None)
@given(limits_and_previous(), st.tuples(finite, finite), st.floats(1e-4, 1.0))
def test_limits_property(lp, target, dt) -> None:
    limits, previous = lp
    out = apply_limits(Twist(*target), previous, dt, limits)
    assert math.isfinite(out.v) and math.isfinite(out.omega)
    assert limits.v_min <= out.v <= limits.v_max
    assert abs(out.omega) <= limits.omega_max
    dv = out.v - previous.v
    assert abs(dv) <= max(limits.accel_max, limits.decel_max) * dt + RATE_SLACK
    assert abs(out.omega - previous.omega) <= limits.alpha_max * dt + RATE_SLACK
    same_direction = previous.v == 0.0 or (out.v > 0) == (previous.v > 0)
    if same_direction and abs(out.v) > abs(previous.v):  # speeding up without crossing zero
        assert abs(dv) <= limits.accel_max * dt + RATE_SLACK


@settings(max_examples=100, deadline=None)
@given(limits_and_previous(min_rate=0.1), st.tuples(finite, finite))
def test_limits_converge_to_the_clamped_target(lp, target) -> None:
    limits, previous = lp
    want_v = min(limits.v_max, max(limits.v_min, target[0]))
    want_w = min(limits.omega_max, max(-limits.omega_max, target[1]))
    cmd = previous
    for _ in range(2000):  # 0.05 s steps at >= 0.1 m/s^2, rad/s^2: enough to cross any box
        new = apply_limits(Twist(*target), cmd, 0.05, limits)
        if new == cmd:
            break
        cmd = new
    assert cmd.v == pytest.approx(want_v, abs=1e-9)
    assert cmd.omega == pytest.approx(want_w, abs=1e-9)


# --- odometry ------------------------------------------------------------------------------------


def inc(d_left: float, d_right: float, dt: float = 0.05, t: float = 1.0) -> WheelIncrement:
    return WheelIncrement(t, dt, d_left, d_right, None, None, CliffSensor(0), Proximity(0),
                          BaseStatus(0))


def test_straight_line() -> None:
    o = advance(Odometry(), inc(0.1, 0.1, dt=0.5, t=3.0), AXLE)
    assert (o.t, o.x, o.y, o.theta) == (3.0, pytest.approx(0.1), 0.0, 0.0)
    assert o.v == pytest.approx(0.2) and o.omega == 0.0 and o.distance == pytest.approx(0.1)
    up = advance(Odometry(theta=math.pi / 2), inc(0.1, 0.1), AXLE)
    assert up.x == pytest.approx(0.0, abs=1e-12) and up.y == pytest.approx(0.1)


def test_pure_rotation_positive_when_the_right_wheel_travels_more() -> None:
    d = 0.05 * AXLE / 2  # each wheel, so that dtheta = (dR - dL) / axle = 0.05
    o = advance(Odometry(x=1.0, y=2.0), inc(-d, d, dt=0.1), AXLE)
    assert o.theta == pytest.approx(0.05)
    assert (o.x, o.y, o.v) == (1.0, 2.0, 0.0)
    assert o.omega == pytest.approx(0.5)
    assert o.distance == 0.0
    cw = advance(Odometry(), inc(d, -d), AXLE)
    assert cw.theta == pytest.approx(-0.05)


@pytest.mark.parametrize("direction", [1.0, -1.0], ids=["forward-ccw", "backward-cw"])
def test_full_circle_of_small_increments_closes(direction: float) -> None:
    radius, n = 0.5, 2000
    dth = direction * 2 * math.pi / n
    ds = radius * abs(dth) * direction
    d_left, d_right = ds - dth * AXLE / 2, ds + dth * AXLE / 2
    o = Odometry()
    max_dist_from_start = 0.0
    for k in range(n):
        o = advance(o, inc(d_left, d_right, t=k * 0.05), AXLE)
        assert -math.pi <= o.theta < math.pi
        max_dist_from_start = max(max_dist_from_start, math.hypot(o.x, o.y))
    assert math.hypot(o.x, o.y) < 1e-3
    assert abs(wrap_angle(o.theta)) < 1e-9
    assert max_dist_from_start == pytest.approx(2 * radius, rel=1e-4)  # it did go round
    assert o.distance == pytest.approx(2 * math.pi * radius)


def test_theta_wraps_past_pi() -> None:
    o = advance(Odometry(theta=3.1), inc(-0.01, 0.01), AXLE)  # +0.075 rad
    assert o.theta == pytest.approx(3.1 + 0.02 / AXLE - 2 * math.pi)


def test_speeds_come_from_dt_and_distance_accumulates_magnitude() -> None:
    o = advance(Odometry(), inc(0.02, 0.02, dt=0.1), AXLE)
    o = advance(o, inc(-0.03, -0.03, dt=0.2), AXLE)
    assert o.v == pytest.approx(-0.15)
    assert o.x == pytest.approx(-0.01)
    assert o.distance == pytest.approx(0.05)
    same = advance(o, inc(0.0, 0.0, dt=0.0), AXLE)  # dt 0: speeds are kept, not divided by 0
    assert (same.v, same.omega) == (o.v, o.omega)


@given(st.floats(-1e6, 1e6, allow_nan=False))
def test_wrap_angle_property(a: float) -> None:
    w = wrap_angle(a)
    assert -math.pi <= w < math.pi
    assert math.cos(w) == pytest.approx(math.cos(a), abs=1e-6)
    assert math.sin(w) == pytest.approx(math.sin(a), abs=1e-6)


def test_wrap_angle_just_below_minus_pi() -> None:
    assert wrap_angle(math.nextafter(-math.pi, -4.0)) < math.pi


def test_from_frame_places_base_link_points_in_odom_and_undoes_into_frame() -> None:
    # the robot at (1, 2) facing +y: 1 m ahead is (1, 3), 1 m to its left is (0, 2)
    assert from_frame(1.0, 2.0, math.pi / 2, 1.0, 0.0) == pytest.approx((1.0, 3.0))
    assert from_frame(1.0, 2.0, math.pi / 2, 0.0, 1.0) == pytest.approx((0.0, 2.0))
    x, y = from_frame(-3.0, 0.5, 2.4, 0.7, -1.3)
    assert into_frame(x + 3.0, y - 0.5, 2.4) == pytest.approx((0.7, -1.3))


# --- DriveJob ------------------------------------------------------------------------------------

MOVING = Odometry(v=0.2)
STILL = Odometry()
A, B, C = Twist(0.2, 0.0), Twist(0.0, 0.8), Twist(-0.05, 0.1)


def run_cycles(job, period: float, n: int, t0: float = 0.0, odom: Odometry = MOVING,
               start: int = 0) -> list[Twist]:
    return [job.step(t0 + (start + k) * period, odom) for k in range(n)]


@pytest.mark.parametrize(
    ("duration", "period", "cycles"),
    [(2.0, 0.05, 40), (2.5, 0.05, 50), (1.9635, 0.05, 39), (0.5, 0.1, 5), (3.0, 1 / 30, 90),
     (1.0, 0.0625, 16), (0.12, 0.05, 2)],
)
def test_a_segment_gets_round_duration_over_period_cycles(duration, period, cycles) -> None:
    job = DriveJob([Segment(A, duration)], period)
    out = run_cycles(job, period, cycles + 5, t0=1000.0)
    assert out == [A] * cycles + [STOP] * 5


def test_segments_play_back_to_back() -> None:
    job = DriveJob([Segment(A, 1.0), Segment(B, 0.5), Segment(C, 0.25)], 0.05)
    out = run_cycles(job, 0.05, 40)
    assert out == [A] * 20 + [B] * 10 + [C] * 5 + [STOP] * 5
    assert job.summary()["segments"] == 3 and job.summary()["script_s"] == pytest.approx(1.75)


def test_unaligned_segments_round_on_the_cumulative_end() -> None:
    # 0.12 s each at 0.05 s: round(0.12/0.05) = 2 per segment, but the cycles follow the
    # cumulative ends (0.12 -> 2, 0.24 -> 5): the script as a whole keeps its length.
    job = DriveJob([Segment(A, 0.12), Segment(B, 0.12)], 0.05)
    out = run_cycles(job, 0.05, 7)
    assert out == [A] * 2 + [B] * 3 + [STOP] * 2


def test_time_out_of_running_does_not_count() -> None:
    job = DriveJob([Segment(A, 2.0)], 0.05)
    before = run_cycles(job, 0.05, 10)
    elapsed = job.summary()["elapsed_s"]
    job.pause()
    assert job.step(500.0, MOVING) == A  # a long outage did not end the segment
    # only the period of the last RUNNING cycle before the pause counts, not the outage
    assert job.summary()["elapsed_s"] == pytest.approx(elapsed + 0.05)
    after = run_cycles(job, 0.05, 60, t0=500.0, start=1)
    assert before == [A] * 10
    assert 10 + 1 + after.index(STOP) == 40


def test_a_pause_does_not_add_a_running_cycle() -> None:
    job = DriveJob([Segment(A, 2.0)], 0.05)
    running = run_cycles(job, 0.05, 10)
    job.pause()
    running += run_cycles(job, 0.05, 60, t0=500.0)
    assert running.count(A) == 40


def test_after_the_script_it_stops_and_finishes_once_still_for_0_3_s() -> None:
    p = 0.0625  # exact in binary, so the 0.3 s comparison is not a rounding question
    job = DriveJob([Segment(A, 0.5)], p)
    assert run_cycles(job, p, 8) == [A] * 8
    # braking: STOP while odometry still shows motion, not finished
    braking = run_cycles(job, p, 4, start=8, odom=MOVING)
    assert braking == [STOP] * 4 and not job.finished
    # still from cycle 12; one moving blip at 14 restarts the still timer
    assert job.step(12 * p, STILL) == STOP
    assert job.step(13 * p, Odometry(omega=0.02)) == STOP
    for k in range(14, 14 + 5):  # 0 .. 0.25 s still
        job.step(k * p, Odometry(v=0.004, omega=-0.009))  # below the still thresholds
        assert not job.finished
    job.step(19 * p, STILL)  # 0.3125 s still
    assert job.finished and job.settled
    assert 5 * p >= STILL_FOR_S > 4 * p
    s = job.summary()
    assert s["settled"] is True and s["elapsed_s"] == pytest.approx(19 * p)


def test_settle_times_out_unsettled() -> None:
    p = 0.0625
    job = DriveJob([Segment(A, 0.5)], p)
    run_cycles(job, p, 8)
    start = 8 * p
    k = 0
    while not job.finished:
        assert job.step(start + k * p, MOVING) == STOP
        k += 1
        assert k < 100
    assert (k - 1) * p == pytest.approx(3.0625)  # finished on the first cycle past 3 s
    assert job.finished and not job.settled
    assert job.summary()["settled"] is False


def test_hold_job_always_stops_and_never_finishes() -> None:
    job = HoldJob()
    for k in range(200):
        assert job.decide(job.prepare(k * 0.05, MOVING if k % 2 else STILL)) == STOP
        if k % 50 == 0:
            job.pause()
        assert not job.finished
    assert job.summary() == {}

