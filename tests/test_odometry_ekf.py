"""Odometry EKF: a 60 s scripted drive on the Spark base model with encoder noise, glitch frames,
wheel slip and a 0.02 rad/s gyro bias; bias convergence at rest; gating; wrapping; covariance."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.spark.feedback import FeedbackConverter
from drivers.spark.protocol import (
    BASE_TO_HOST,
    FrameParser,
    decode_feedback,
    twist_to_wheel_ticks,
    wheel_speed_frame,
)
from runtime.config.schema import build, render_documented
from runtime.config.settings import OdometryCalibration
from runtime.errors import ConfigError
from runtime.odometry.dead_reckoning import advance
from runtime.odometry.ekf import OdometryEKF, OdometryFilterConfig
from runtime.types import BaseStatus, CliffSensor, Odometry, Proximity, WheelIncrement
from sim_stub.base_sim import BasePhysics, SparkBaseSim

DT = 0.02
BIAS = 0.02
NOISE_TICKS = 2.0
CAL = OdometryCalibration()
AXLE = CAL.axle_length_m
# The emulator's count jitter is 2 ticks σ on each reading, so one increment's travel error is
# about 2·√2 ticks (plus quantisation): tell the filter so.
SIM_FILTER = OdometryFilterConfig(wheel_travel_sigma_m=2.9 * CAL.m_per_tick)

# (seconds, v m/s, ω rad/s): straights, arcs, in-place turns and stops; 60 s, ~9 m.
SCRIPT = (
    (3.0, 0.0, 0.0),
    (6.0, 0.3, 0.0),
    (8.0, 0.2, 0.4),
    (2.0, 0.0, 0.0),
    (4.0, 0.0, 0.8),
    (5.0, 0.25, 0.0),
    (6.0, 0.2, -0.5),
    (2.0, 0.0, 0.0),
    (3.0, 0.0, -1.0),
    (8.0, 0.3, 0.0),
    (8.0, 0.15, 0.3),
    (5.0, 0.0, 0.0),
)
SLIP_TIMES = (12.0, 30.0, 47.0)  # s: one frame in which the right wheel spins 10 mm on the spot


@dataclass
class DriveResult:
    truth: dict[str, float]
    ekf: OdometryEKF
    ekf_odom: Odometry
    dead_reckoning: Odometry
    gyro_heading: float  # plain integral of the (biased) gyro
    converter_rejected: dict[str, int]
    increments: int
    slips: int

    def heading_error(self, theta: float) -> float:
        err = math.remainder(theta - self.truth["theta_unwrapped"], math.tau)
        return abs(err)

    def position_error(self, odom: Odometry) -> float:
        return math.hypot(odom.x - self.truth["x"], odom.y - self.truth["y"])


def _increment(t: float, dt: float, d_left: float, d_right: float, gyro: float | None):
    return WheelIncrement(
        t=t,
        dt=dt,
        d_left=d_left,
        d_right=d_right,
        gyro_z=gyro,
        yaw=None,
        cliffs=CliffSensor(0),
        proximity=Proximity(0),
        status=BaseStatus(0),
    )


def scripted_drive(seed: int = 1, glitch_every_s: float = 2.5) -> DriveResult:
    sim = SparkBaseSim(
        BasePhysics(gyro_bias_rad_s=BIAS, encoder_noise_ticks=NOISE_TICKS, seed=seed)
    )
    parser = FrameParser(BASE_TO_HOST)
    converter = FeedbackConverter(CAL)
    ekf = OdometryEKF(AXLE, SIM_FILTER)
    dr = Odometry()
    gyro_heading = 0.0
    odom = Odometry()
    t = 0.0
    n = 0
    slips = 0
    steps_per_glitch = round(glitch_every_s / DT)
    pending_slips = list(SLIP_TIMES)
    for duration, v, omega in SCRIPT:
        frame = wheel_speed_frame(*twist_to_wheel_ticks(v, omega))
        for _ in range(round(duration / DT)):
            sim.receive(frame, t)
            sim.step(DT)
            t += DT
            n += 1
            if n % steps_per_glitch == 0:
                # Alternate a big spike (the converter drops it) and a small one that is within
                # what the wheels can travel in a frame and must be stopped by the filter's gate.
                sim.glitch_next_frame(5000 if (n // steps_per_glitch) % 2 else 40)
            for fr in parser.feed(sim.feedback_frame()):
                inc = converter.convert(decode_feedback(fr.payload), t)
                if inc is None:
                    continue
                if pending_slips and t >= pending_slips[0] and abs(v) > 0.1:
                    pending_slips.pop(0)
                    inc = replace(inc, d_right=inc.d_right + 0.010)
                    slips += 1
                odom = ekf.step(inc)
                dr = advance(dr, inc, AXLE)
                gyro_heading += inc.gyro_z * inc.dt
    return DriveResult(
        truth=sim.truth(),
        ekf=ekf,
        ekf_odom=odom,
        dead_reckoning=dr,
        gyro_heading=gyro_heading,
        converter_rejected=dict(converter.rejected),
        increments=n,
        slips=slips,
    )


@pytest.fixture(scope="module")
def drive() -> DriveResult:
    return scripted_drive()


def test_scripted_drive_meets_accuracy(drive: DriveResult) -> None:
    distance = drive.truth["distance"]
    heading_err_deg = math.degrees(drive.heading_error(drive.ekf_odom.theta))
    pos_err = drive.position_error(drive.ekf_odom)
    dr_heading_deg = math.degrees(drive.heading_error(drive.dead_reckoning.theta))
    dr_pos = drive.position_error(drive.dead_reckoning)
    gyro_deg = math.degrees(drive.heading_error(drive.gyro_heading))
    print(
        f"\ndistance {distance:.2f} m; EKF heading {heading_err_deg:.3f}°, position"
        f" {100 * pos_err / distance:.3f} % ({pos_err * 1000:.1f} mm); bias {drive.ekf.bias:.5f}"
        f" ± {drive.ekf.bias_sigma:.5f} rad/s (true {BIAS}); dead reckoning heading"
        f" {dr_heading_deg:.3f}°, position {100 * dr_pos / distance:.3f} %; gyro-only heading"
        f" {gyro_deg:.2f}°; EKF rejected {dict(drive.ekf.rejected)}; converter"
        f" rejected {drive.converter_rejected}"
    )
    assert distance > 5.0
    assert drive.slips == len(SLIP_TIMES)
    assert heading_err_deg <= 2.0
    assert pos_err <= 0.01 * distance
    assert drive.ekf.bias == pytest.approx(BIAS, abs=0.003)
    # What the filter buys: the biased gyro alone is off by ~1.2 rad, and the slips cost dead
    # reckoning their full heading jump (3 × 10 mm / 0.266 m ≈ 6.5°).
    assert gyro_deg > 30.0
    assert dr_heading_deg > 3.0
    assert heading_err_deg < dr_heading_deg / 2


def test_scripted_drive_gates_glitches_and_slips(drive: DriveResult) -> None:
    assert drive.converter_rejected["encoder_jump"] >= 5  # the 5000-tick spikes
    # Each small spike gives two bad increments (spike up, then back down); each slip one.
    assert drive.ekf.rejected["wheel_gate"] >= drive.slips + 2 * 5
    assert drive.ekf.rejected["wheel_reacquire"] == 0
    assert drive.ekf.rejected["gyro_reacquire"] == 0
    # Good frames are hardly ever rejected (99.9 % gate): most increments were fused.
    assert drive.ekf.accepted["wheel"] >= 0.97 * drive.increments
    assert drive.ekf.accepted["gyro"] >= 0.97 * drive.increments


def test_bias_converges_standing_still() -> None:
    sim = SparkBaseSim(BasePhysics(gyro_bias_rad_s=BIAS, encoder_noise_ticks=NOISE_TICKS, seed=3))
    parser = FrameParser(BASE_TO_HOST)
    converter = FeedbackConverter(CAL)
    ekf = OdometryEKF(AXLE, SIM_FILTER)
    t = 0.0
    bias_at: dict[int, float] = {}
    for n in range(1, 501):  # 10 s
        sim.step(DT)
        t += DT
        for fr in parser.feed(sim.feedback_frame()):
            inc = converter.convert(decode_feedback(fr.payload), t)
            if inc is not None:
                odom = ekf.step(inc)
        bias_at[n] = ekf.bias
    assert abs(bias_at[500] - BIAS) < 0.001
    assert abs(bias_at[100] - BIAS) < 0.004  # after 2 s
    # The gyro's 0.2 rad of bias drift is not heading; what is left is the encoder readings' own
    # error (2 ticks σ on each count ≈ 0.2° of wheel heading), the baseline reading's included.
    assert abs(odom.theta) < math.radians(0.5)
    assert math.hypot(odom.x, odom.y) < 0.002


def _run_straight(ekf: OdometryEKF, n: int, t0: float = 0.0, v: float = 0.2) -> float:
    t = t0
    for _ in range(n):
        t += DT
        ekf.step(_increment(t, DT, v * DT, v * DT, 0.0))
    return t


@pytest.mark.parametrize("mode", ["cumulative", "rate"])
def test_single_slip_is_gated_and_ignored(mode: str) -> None:
    config = OdometryFilterConfig(wheel_heading=mode)
    ekf, twin = OdometryEKF(AXLE, config), OdometryEKF(AXLE, config)
    t = _run_straight(ekf, 200)
    _run_straight(twin, 200)
    before = ekf.x
    good = _increment(t + DT, DT, 0.2 * DT, 0.2 * DT, 0.0)
    slip = replace(good, d_right=good.d_right + 0.012)  # right wheel spins 12 mm, gyro sees none
    ekf.step(slip)
    twin.step(good)
    assert ekf.rejected["wheel_gate"] == 1
    assert twin.rejected.total() == 0
    # Heading, speed and turn rate: only the prediction and the gyro moved them, as in the twin
    # that got the good frame.
    np.testing.assert_allclose(ekf.x[2:5], twin.x[2:5], atol=2e-4)
    assert abs(ekf.x[2] - before[2]) < 1e-4
    # The position follows every increment's travel (a wrong count is undone by the next one),
    # so half the spinning wheel's 12 mm stays in it, as in any wheel odometry.
    assert ekf.x[0] - twin.x[0] == pytest.approx(0.006, abs=2e-4)
    assert abs(ekf.x[1] - twin.x[1]) < 2e-4


def test_normal_driving_is_not_rejected() -> None:
    """Accelerating and turning at the base's limits passes the gate (no false slips)."""
    ekf = OdometryEKF(AXLE)
    rng = np.random.default_rng(5)
    t = 0.0
    v_l = v_r = 0.0
    for k in range(3000):
        target = (0.5, -0.5) if (k // 150) % 2 else (-0.3, 0.5)
        v_l += float(np.clip(target[0] - v_l, -DT, DT))  # 1 m/s² ramps
        v_r += float(np.clip(target[1] - v_r, -DT, DT))
        t += DT
        d_l = v_l * DT + rng.normal(0.0, 0.0004)
        d_r = v_r * DT + rng.normal(0.0, 0.0004)
        gyro = (v_r - v_l) / AXLE + 0.03 + rng.normal(0.0, 0.005)
        ekf.step(_increment(t, DT, d_l, d_r, gyro))
    assert ekf.rejected["wheel_gate"] <= 10
    assert ekf.rejected["gyro_gate"] <= 10
    assert ekf.rejected["wheel_reacquire"] == ekf.rejected["gyro_reacquire"] == 0
    assert ekf.bias == pytest.approx(0.03, abs=0.005)


@pytest.mark.parametrize("mode", ["cumulative", "rate"])
def test_angles_wrap(mode: str) -> None:
    ekf = OdometryEKF(AXLE, OdometryFilterConfig(wheel_heading=mode))
    omega = 1.0
    t = 0.0
    theta_true = 0.0
    for _ in range(1000):  # 20 s at 1 rad/s: more than three turns
        t += DT
        d = 0.5 * omega * AXLE * DT
        odom = ekf.step(_increment(t, DT, -d, d, omega))
        theta_true += omega * DT
        assert -math.pi <= odom.theta < math.pi
    assert math.remainder(odom.theta - theta_true, math.tau) == pytest.approx(0.0, abs=0.01)
    assert ekf.x[2] == odom.theta


def test_bad_increments_are_counted_not_fused() -> None:
    ekf = OdometryEKF(AXLE)
    ekf.step(_increment(0.02, 0.0, 0.01, 0.01, 0.0))
    ekf.step(_increment(0.04, 0.02, math.nan, 0.01, math.inf))
    assert ekf.rejected["bad_dt"] == 1
    assert ekf.rejected["wheel_nonfinite"] == 1
    assert ekf.rejected["gyro_nonfinite"] == 1
    assert np.all(np.isfinite(ekf.x))
    # Without a gyro the wheels alone drive the estimate.
    t = 0.04
    for _ in range(50):
        t += DT
        odom = ekf.step(_increment(t, DT, 0.004, 0.004, None))
    assert odom.v == pytest.approx(0.2, abs=0.01)
    assert odom.t == t


def test_persistent_disagreement_reacquires() -> None:
    """A gate must not lock the wheels out for good: after max_consecutive_rejects the filter
    takes them again (here a speed step far faster than the process noise allows)."""
    ekf = OdometryEKF(AXLE, OdometryFilterConfig(max_consecutive_rejects=2))
    t = 0.0
    for k in range(150):
        t += DT
        v = 0.0 if k < 100 else 1.0
        odom = ekf.step(_increment(t, DT, v * DT, v * DT, 0.0))
    assert ekf.rejected["wheel_gate"] == 1
    assert ekf.rejected["wheel_reacquire"] == 1
    assert odom.v == pytest.approx(1.0, abs=1e-3)
    assert abs(odom.theta) < 1e-3


def test_gyro_bias_step_does_not_turn_the_robot() -> None:
    """A sudden large gyro bias change while still: the wheels hold the heading and the bias
    estimate follows (slowly: the bias random walk is small by design)."""
    ekf = OdometryEKF(AXLE)
    t = 0.0
    for k in range(1500):
        t += DT
        odom = ekf.step(_increment(t, DT, 0.0, 0.0, 0.01 if k < 500 else 0.3))
    assert abs(odom.theta) < 0.01
    assert ekf.bias > 0.15


def _assert_spd(P: np.ndarray) -> None:
    assert np.allclose(P, P.T, atol=1e-12)
    assert np.all(np.isfinite(P))
    assert np.linalg.eigvalsh(P).min() > 0.0


step_st = st.tuples(
    st.floats(0.005, 0.2),  # dt
    st.floats(-0.02, 0.02),  # d_left
    st.floats(-0.02, 0.02),  # d_right
    st.one_of(st.none(), st.floats(-5.0, 5.0)),  # gyro
)


@settings(max_examples=40, deadline=None)
@given(st.lists(step_st, min_size=1, max_size=80))
def test_covariance_stays_spd_on_arbitrary_input(steps) -> None:
    ekf = OdometryEKF(AXLE)
    t = 0.0
    for dt, d_l, d_r, gyro in steps:
        t += dt
        odom = ekf.step(_increment(t, dt, d_l, d_r, gyro))
        _assert_spd(ekf.covariance)
        assert -math.pi <= odom.theta < math.pi


def test_covariance_stays_spd_over_the_drive(drive: DriveResult) -> None:
    _assert_spd(drive.ekf.covariance)
    sd = np.sqrt(np.diag(drive.ekf.covariance))
    assert sd[5] < 0.01  # the bias is well determined after the drive


def test_config_is_a_documented_schema() -> None:
    text = render_documented(OdometryFilterConfig(), "odometry")
    for key in ("accel_sigma_m_s2", "wheel_gate_chi2", "gyro_gate_chi2", "wheel_heading"):
        assert key in text
    config = build(OdometryFilterConfig, {"gyro_sigma_rad_s": 0.02}, "test.yaml")
    assert config.gyro_sigma_rad_s == 0.02
    with pytest.raises(ConfigError, match="wheel_heading"):
        build(OdometryFilterConfig, {"wheel_heading": "both"}, "test.yaml")
    with pytest.raises(ValueError, match="axle_m"):
        OdometryEKF(0.0)


def test_closed_form_gate_distance_matches_a_general_solve() -> None:
    from runtime.odometry.ekf import _mahalanobis2

    rng = np.random.default_rng(4)
    for n in (1, 2):
        for _ in range(200):
            a = rng.normal(size=(n, n))
            S = a @ a.T + 0.1 * np.eye(n)
            y = rng.normal(size=(n, 1))
            assert _mahalanobis2(y, S) == pytest.approx((y.T @ np.linalg.solve(S, y)).item(), rel=1e-9)
    assert _mahalanobis2(np.ones((2, 1)), np.zeros((2, 2))) == math.inf


def test_position_follows_the_wheels_travel_when_frames_are_missing() -> None:
    """Braking from 0.3 m/s at 1 m/s² with four frames of five missing: each increment spans
    100 ms in which the speed fell by 0.1 m/s. Predicting at the speed from before an increment
    put the position 5 mm further per increment; the travel puts it where the wheels went."""
    ekf = OdometryEKF(AXLE)
    t = _run_straight(ekf, 100, v=0.3)
    x0, travelled, v = ekf.x[0], 0.0, 0.3
    for _ in range(3):
        ds = v * 0.1 - 0.5 * 1.0 * 0.1**2
        v -= 0.1
        t += 0.1
        travelled += ds
        ekf.step(_increment(t, 0.1, ds, ds, 0.0))
    assert ekf.x[0] - x0 == pytest.approx(travelled, abs=1e-6)
    assert ekf.rejected.total() == 0


def test_an_increment_over_a_gap_moves_the_pose_by_its_travel_and_turn() -> None:
    """3 s without a usable frame, in which the robot braked and turned 0.2 rad: predicted at
    its speed from before the gap it would have gone 0.6 m on; it went 0.06 m."""
    ekf = OdometryEKF(AXLE)
    t = _run_straight(ekf, 100, v=0.2)
    x0, y0 = ekf.x[0], ekf.x[1]
    turn = 0.2
    d_left, d_right = 0.06 - turn * AXLE / 2, 0.06 + turn * AXLE / 2
    ekf.step(_increment(t + 3.0, 3.0, d_left, d_right, 0.0))
    assert ekf.accepted["wheel_gap"] == 1
    assert ekf.x[2] == pytest.approx(turn, abs=1e-3)
    assert ekf.x[0] - x0 == pytest.approx(0.06 * math.cos(turn / 2), abs=1e-4)
    assert ekf.x[1] - y0 == pytest.approx(0.06 * math.sin(turn / 2), abs=1e-4)
    # standing still afterwards: the speed settles to 0 at once, the pose stays
    t = _run_straight(ekf, 10, t0=t + 3.0, v=0.0)
    assert abs(ekf.x[3]) < 0.01 and ekf.x[0] - x0 == pytest.approx(0.06 * math.cos(0.1), abs=1e-4)


def test_a_wrong_count_and_the_increment_that_undoes_it_cost_no_position() -> None:
    """A corrupted count within what the wheels can do (+30 mm on the left wheel) gets past the
    driver; the next increment takes it back. Whatever the gate makes of the pair, the position
    and heading end where the wheels went."""
    ekf, twin = OdometryEKF(AXLE), OdometryEKF(AXLE)
    t = _run_straight(ekf, 100)
    _run_straight(twin, 100)
    step = 0.2 * DT
    ekf.step(_increment(t + DT, DT, step + 0.03, step, 0.0))
    ekf.step(_increment(t + 2 * DT, DT, step - 0.03, step, 0.0))
    _run_straight(twin, 2, t0=t)
    np.testing.assert_allclose(ekf.x[:3], twin.x[:3], atol=1e-4)
