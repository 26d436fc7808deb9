"""FeedbackConverter: feedback frames → wheel increments, and what it refuses to believe.

Hand-built frames at the base's 50 Hz (frame k is stamped 200·k base ticks and arrives 3 ms
later on the host clock), then whole corrupted byte streams from the base model through the
seeded corrupter of `sim_stub.serial_proxy`: no processes, no sleeps.
"""

from __future__ import annotations

import math

import pytest

from drivers.spark.feedback import FeedbackConverter
from drivers.spark.protocol import BASE_TO_HOST, Feedback, FrameParser, decode_feedback
from drivers.spark.protocol import wheel_speed_frame as wheels
from runtime.config.settings import BaseConfig, OdometryCalibration
from runtime.types import BaseStatus, CliffSensor, Proximity, WheelIncrement
from sim_stub.base_sim import BasePhysics, SparkBaseSim
from sim_stub.serial_proxy import ByteCorrupter

M_PER_TICK = OdometryCalibration().m_per_tick
NO_CLIFF = 0x3F
HOST0 = 100.0  # host clock at base time 0
LATENCY = 0.003


def fb(e10: int = 0, e14: int = 0, t: int = 0, *, cliff: int = NO_CLIFF, bumper: int = 0,
       status: int = 0, gyro_z_dps: float | None = None, yaw_deg: float | None = None,
       accel_x_g: float = 0.0) -> Feedback:
    imu = {}
    if gyro_z_dps is not None or yaw_deg is not None:
        imu = {"accel_g": (accel_x_g, 0.0, 1.0), "gyro_dps": (0.0, 0.0, gyro_z_dps or 0.0),
               "mag": (0.0, 0.0, 0.0), "rpy_deg": (0.0, 0.0, yaw_deg or 0.0)}
    return Feedback(cliff, bumper, status, 0, 0, e10 & 0xFFFFFFFF, e14 & 0xFFFFFFFF,
                    t & 0xFFFFFFFF, **imu)


def conv(offset: int = 14, **cfg) -> FeedbackConverter:
    return FeedbackConverter(OdometryCalibration(left_encoder_offset=offset), BaseConfig(**cfg))


def at(c: FeedbackConverter, k: int, e10: int = 0, e14: int = 0, **kw) -> WheelIncrement | None:
    """Frame k of the stream (stamped 200·k ticks, i.e. 20 ms apart), arriving on time."""
    return c.convert(fb(e10, e14, 200 * k, **kw), HOST0 + 0.02 * k + LATENCY)


def started(offset: int = 14, e10: int = 0, e14: int = 0, **cfg) -> FeedbackConverter:
    """A converter whose baseline (frames 0 and 1, standing still) is taken."""
    c = conv(offset, **cfg)
    assert at(c, 0, e10, e14) is None and at(c, 1, e10, e14) is None
    assert c.counts["baseline"] == 1 and c.usable
    return c


def ticks(w: WheelIncrement | None) -> tuple[int, int]:
    assert w is not None
    return round(w.d_left / M_PER_TICK), round(w.d_right / M_PER_TICK)


# --- baseline ------------------------------------------------------------------------------------


def test_a_baseline_needs_two_frames_that_agree() -> None:
    c = conv()
    assert at(c, 0, 100, 200) is None
    assert not c.usable and c.counts["baseline"] == 0  # one frame alone proves nothing
    assert at(c, 1, 110, 215) is None
    assert c.usable and c.counts["baseline"] == 1
    assert ticks(at(c, 2, 120, 230)) == (15, 10)  # from the second frame on


def test_a_corrupted_count_never_becomes_the_baseline() -> None:
    c = conv()
    at(c, 0, 100, 100)
    assert at(c, 1, 100, 100 + 4096) is None and not c.usable  # disagrees with frame 0
    assert at(c, 2, 100, 100) is None and not c.usable  # disagrees with frame 1
    assert at(c, 3, 100, 100) is None and c.counts["baseline"] == 1  # 2 and 3 agree
    assert ticks(at(c, 4, 100, 130)) == (30, 0)
    assert c.rejected["unconfirmed"] == 2


def test_two_frames_far_apart_are_no_baseline() -> None:
    c = conv()
    at(c, 0)
    assert at(c, 10) is None and not c.usable  # 200 ms apart: too loose to vouch for each other
    assert at(c, 11) is None and c.usable


# --- conversion ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("offset", "left", "right"), [(14, 30, 10), (10, 10, 30)])
def test_left_right_mapping_follows_the_calibration(offset: int, left: int, right: int) -> None:
    c = started(offset, e10=1000, e14=5000)
    w = at(c, 2, 1010, 5030)
    assert w is not None and w.t == pytest.approx(HOST0 + 0.04 + LATENCY)
    assert w.dt == pytest.approx(0.02)  # dt from the base clock (0.1 ms ticks)
    assert ticks(w) == (left, right)


def test_encoder_and_clock_u32_wrap() -> None:
    c = conv()
    t0 = 0xFFFFFF00  # the base clock wraps between frames 1 and 2
    for k, (e10, e14) in enumerate([(0xFFFFFFE0, 0xFFFFFFF0), (0xFFFFFFF0, 0xFFFFFFFF)]):
        c.convert(fb(e10, e14, t0 + 200 * k), HOST0 + 0.02 * k)
    w = c.convert(fb(0x10, 0x00, t0 + 400), HOST0 + 0.04)
    assert w is not None and w.dt == pytest.approx(0.02)
    assert ticks(w) == (1, 0x20)  # 0xFFFFFFFF -> 0: one tick; 0xFFFFFFF0 -> 0x10: 32
    back = c.convert(fb(0xFFFFFFF0, 0xFFFFFFFF, t0 + 600), HOST0 + 0.06)
    assert ticks(back) == (-1, -0x20)


def test_si_conversions() -> None:
    c = conv()
    c.convert(fb(t=0, gyro_z_dps=0.0, yaw_deg=0.0), HOST0)
    c.convert(fb(t=200, gyro_z_dps=0.0, yaw_deg=0.0), HOST0 + 0.02)
    w = c.convert(fb(e14=40, e10=-40, t=400, gyro_z_dps=90.0, yaw_deg=-180.0), HOST0 + 0.04)
    assert w is not None and ticks(w) == (40, -40)
    assert w.d_left == pytest.approx(40 * 0.00028885)
    assert w.dt == pytest.approx(0.02)
    assert w.gyro_z == pytest.approx(math.pi / 2)
    assert w.yaw == pytest.approx(-math.pi)
    no_imu = c.convert(fb(e14=40, e10=-40, t=600), HOST0 + 0.06)
    assert no_imu is not None and no_imu.gyro_z is None and no_imu.yaw is None


# --- plausibility --------------------------------------------------------------------------------


def test_the_encoder_bound_scales_with_the_base_clock_time() -> None:
    def bound(dt: float) -> int:  # 1.5 × the 0.5 m/s clamp, plus glitch_ticks (20)
        return math.floor(1.5 * 0.5 * dt / M_PER_TICK + 20)

    c = started()
    assert bound(0.02) == 71
    assert ticks(at(c, 2, 0, 71)) == (71, 0)
    assert at(c, 3, 0, 71 + 72) is None and c.rejected["encoder_jump"] == 1
    # nine frames lost after that one: 0.22 s of wheel travel
    assert ticks(at(c, 13, 0, 71 + bound(0.22))) == (bound(0.22), 0)


def test_a_corrupted_jump_costs_no_distance() -> None:
    c = started()
    a = at(c, 2, 14, 14)
    assert at(c, 3, 28, 28 + 4096) is None  # bit 12 flipped in one count
    assert c.rejected["encoder_jump"] == 1 and not c.usable
    b = at(c, 4, 42, 42)
    assert ticks(b) == (28, 28)  # from the last accepted counts: the lost frame is in it
    assert b is not None and b.dt == pytest.approx(0.04)
    assert ticks(a)[0] + ticks(b)[0] == 42


def test_a_plausible_corrupted_count_is_undone_by_the_next_increment() -> None:
    c = started()
    assert ticks(at(c, 2, 14, 14 + 32)) == (46, 14)  # bit 5: inside what a wheel can do
    assert ticks(at(c, 3, 28, 28)) == (-18, 14)
    assert ticks(at(c, 4, 42, 42)) == (14, 14)  # the sum is the true 42 ticks again


def test_a_corrupted_last_reading_is_corrected_by_the_reading_before_it() -> None:
    c = started()  # both wheels turn 14 ticks a frame from frame 1 on: frame k reads 14·(k − 1)
    at(c, 2, 14, 14)
    # 9 frames lost, then one whose left count is 350 ticks off: within 0.2 s of wheel travel
    assert ticks(at(c, 12, 154, 154 + 350)) == (490, 140)
    assert at(c, 13, 168, 168) is None  # 20 ms after that reading: 336 ticks back is impossible
    w = at(c, 14, 182, 182)  # agrees with frame 13, and both with frame 2
    assert c.counts["corrected"] == 1 and c.counts["rebaseline"] == 0
    assert ticks(w) == (-322, 28)  # undoes the bad reading: the sum is the true 182 again


def test_counters_that_restart_with_the_base_clock_take_a_new_baseline() -> None:
    c = started(e10=3_000_000, e14=3_000_000)
    at(c, 2, 3_000_010, 3_000_010)
    # the base rebooted: its clock and counters start from zero again
    assert c.convert(fb(10, 10, 100), HOST0 + 2.0) is None
    assert c.rejected["clock_backwards"] == 1 and not c.usable
    assert c.convert(fb(20, 20, 300), HOST0 + 2.02) is None
    assert c.counts["rebaseline"] == 1 and c.usable
    w = c.convert(fb(30, 25, 500), HOST0 + 2.04)
    assert ticks(w) == (5, 10) and w is not None and w.dt == pytest.approx(0.02)


@pytest.mark.parametrize("stamp", [400, 399], ids=["same", "backwards"])
def test_a_base_clock_that_does_not_advance_is_rejected(stamp: int) -> None:
    c = started()
    assert at(c, 2, 0, 10) is not None
    assert c.convert(fb(0, 20, stamp), HOST0 + 0.06) is None
    assert c.rejected["clock_backwards"] == 1 and not c.usable
    assert ticks(at(c, 4, 0, 30)) == (20, 0)


@pytest.mark.parametrize(("lead_s", "ok"), [(0.008, True), (0.0128, False), (0.6, False)],
                         ids=["jitter", "bit-7-ahead", "far-ahead"])
def test_a_stamp_ahead_of_its_arrival_is_rejected(lead_s: float, ok: bool) -> None:
    c = started()
    at(c, 2)
    # frame 3 arrives on time but its stamp says it was sent later than that
    w = c.convert(fb(0, 14, 600 + round(lead_s * 10_000)), HOST0 + 0.06 + LATENCY)
    assert (w is not None) == ok
    assert c.rejected["clock_jump"] == (0 if ok else 1)


def test_a_frame_delivered_half_a_second_late_is_not_trusted() -> None:
    c = started()
    at(c, 2)
    assert c.convert(fb(0, 14, 600), HOST0 + 0.06 + LATENCY + 0.55) is None
    assert c.rejected["clock_jump"] == 1
    assert c.convert(fb(0, 14, 600 + 2750), HOST0 + 0.06 + LATENCY + 0.55) is not None


@pytest.mark.parametrize(
    "imu",
    [{"gyro_z_dps": math.nan}, {"gyro_z_dps": 400.0}, {"gyro_z_dps": 0.0, "yaw_deg": 400.0},
     {"gyro_z_dps": 0.0, "accel_x_g": 3e20}],
    ids=["nan-gyro", "turn-rate", "yaw", "accel"],
)
def test_imu_values_outside_physics_reject_the_frame(imu: dict) -> None:
    c = started()
    assert at(c, 2, 0, 14, **imu) is None
    assert c.rejected["imu"] == 1
    assert ticks(at(c, 3, 0, 28, gyro_z_dps=300.0)) == (28, 0)  # 300°/s: inside what wheels do


def test_after_an_outage_the_increment_waits_for_a_second_frame_and_spans_it() -> None:
    c = started()
    at(c, 2)
    assert at(c, 102, 3462, 3462) is None  # 2 s later, 1 m on: plausible, but not yet proven
    assert c.rejected["unconfirmed"] == 1 and not c.usable
    w = at(c, 103, 3476, 3476)
    assert c.counts["recovered"] == 1 and c.usable
    assert ticks(w) == (3476, 3476) and w is not None and w.dt == pytest.approx(2.02)


def test_after_an_outage_a_corrupted_frame_is_not_released() -> None:
    c = started()
    at(c, 2)
    assert at(c, 102, 3462 + 1024, 3462) is None  # within 2 s of wheel travel, but corrupted
    assert at(c, 103, 3476, 3476) is None  # disagrees with frame 102
    w = at(c, 104, 3490, 3490)  # agrees with frame 103
    assert ticks(w) == (3490, 3490) and c.counts["recovered"] == 1


def test_after_an_outage_a_frame_with_a_corrupted_stamp_lets_its_partner_through() -> None:
    c = started()
    at(c, 2)
    assert at(c, 102, 3462, 3462) is None
    # the next frame's counts agree, but its stamp is 80 ms ahead of its arrival
    assert c.convert(fb(3476, 3476, 200 * 103 + 800), HOST0 + 2.06 + LATENCY) is not None
    assert c.counts["recovered"] == 1 and c.rejected["clock_jump"] == 1
    assert ticks(at(c, 104, 3490, 3490)) == (28, 28)  # from frame 102, which was released


# --- flags ---------------------------------------------------------------------------------------


def test_one_corrupted_cliff_frame_is_no_hazard_two_in_a_row_are() -> None:
    c = started()
    assert at(c, 2, cliff=NO_CLIFF & ~0x04).hazard is None  # front-left cliff bit cleared once
    assert at(c, 3).hazard is None
    assert at(c, 4, cliff=0x3B).hazard is None
    w = at(c, 5, cliff=0x3B)
    assert w is not None and w.cliffs == CliffSensor.FRONT_LEFT and "cliff" in (w.hazard or "")
    assert at(c, 6).cliffs == CliffSensor.FRONT_LEFT  # one clear frame does not release it
    assert at(c, 7).hazard is None


def test_debounce_counts_accepted_frames_only() -> None:
    c = started()
    at(c, 2, cliff=0x3E)
    at(c, 3, 0, 5000, cliff=0x3E)  # rejected: its cliff bit counts for nothing
    assert at(c, 4).hazard is None


def test_wheel_drop_is_debounced_and_other_status_bits_pass_as_they_are() -> None:
    c = started()
    drop = int(BaseStatus.WHEEL_DROP_LEFT | BaseStatus.CHARGER_PLUGGED)
    w = at(c, 2, status=drop)
    assert w is not None and w.status == BaseStatus.CHARGER_PLUGGED and w.hazard is None
    w = at(c, 3, status=drop)
    assert w is not None and w.status == BaseStatus(drop) and "wheel drop" in (w.hazard or "")


def test_without_debounce_a_flag_counts_at_once() -> None:
    c = started(flag_debounce_frames=1)
    assert "cliff" in (at(c, 2, cliff=0x3E).hazard or "")


@pytest.mark.parametrize(
    ("cliff_bits", "expected"),
    [
        (0x3F, CliffSensor(0)),
        (0xFF, CliffSensor(0)),  # bits above the six sensors are ignored
        (0x3E, CliffSensor.RIGHT),
        (0x1F, CliffSensor.BACK_LEFT),
        (0x00, CliffSensor(0x3F)),
    ],
)
def test_cliff_bits_are_active_low(cliff_bits: int, expected: CliffSensor) -> None:
    c = started(flag_debounce_frames=1)
    assert at(c, 2, cliff=cliff_bits).cliffs == expected


def test_proximity_ignores_the_error_flag_bit() -> None:
    c = started()
    assert at(c, 2, bumper=0x80 | 0x04).proximity == Proximity.FRONT


# --- whole corrupted streams ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("rate", "burst"), [(0.01, False), (0.03, False), (0.10, True)], ids=["1%", "3%", "10%-bursts"]
)
def test_a_corrupted_stream_gives_exact_odometry_and_no_hazard(rate: float, burst: bool) -> None:
    """Five minutes of the base model driving about (forward, turning, reversing), every byte of
    its feedback corrupted with probability `rate` (bit flips, seeded): at 1 % about one frame
    in a hundred that passes the checksum is wrong, at 10 % most of them are, and nearly
    nothing passes (so 10 % comes in 18 s bursts with 2 s of clean line between). No increment
    may report a hazard, and the increments must add up, wheel by wheel, to the true counts at
    the last frame taken, to the tick."""
    sim = SparkBaseSim(BasePhysics(seed=3), watchdog_s=0.0)
    corrupt = ByteCorrupter(rate, seed=11)
    parser, c = FrameParser(BASE_TO_HOST), conv()
    truth: dict[float, tuple[int, int]] = {}  # host time of each frame → its true (left, right)
    baseline: tuple[int, int] | None = None
    total = [0, 0]
    hazards = increments = 0
    plan = [(692, 692), (0, 0), (-400, 400), (600, 300), (-692, -692)]
    for k in range(5 * 60 * 50):
        if k % 250 == 0:
            sim.receive(wheels(*plan[k // 250 % len(plan)]), sim.t)
        if burst:
            corrupt.rate = rate if k % 1000 < 900 else 0.0
        sim.step(0.02)
        frame = sim.feedback_frame()
        true_fb = decode_feedback(frame[5:-3])
        t = HOST0 + sim.t + LATENCY
        truth[t] = (true_fb.encoder_14, true_fb.encoder_10)
        for f in parser.feed(corrupt(frame)):
            baselines = c.counts["baseline"]
            w = c.convert(decode_feedback(f.payload), t)
            if c.counts["baseline"] > baselines:
                baseline = last = truth[t]
            if w is not None:
                left, right = ticks(w)
                total[0] += left
                total[1] += right
                hazards += w.hazard is not None
                increments += 1
                last = truth[w.t]
    assert baseline is not None
    assert hazards == 0
    assert c.counts["rebaseline"] == 0
    assert total == [(last[i] - baseline[i] + 2**31) % 2**32 - 2**31 for i in (0, 1)]
    assert sum(c.rejected.values()) > 0 and increments > 0
