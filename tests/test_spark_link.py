"""The pyserial link on a real pseudo-terminal, with the test playing the base on the master side."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable

import pytest

from drivers.spark import link as spark_link
from drivers.spark.link import SparkBaseLink
from drivers.spark.protocol import (
    CMD_WHEEL_SPEED,
    HOST_TO_BASE,
    STOP_FRAME,
    Feedback,
    FrameParser,
    decode_wheel_speed,
    encode_feedback,
)
from runtime.config.calibration import OdometryCalibration
from runtime.config.devices import BaseConfig
from runtime.types import Twist


def wheel_commands(data: bytes, parser: FrameParser | None = None) -> list[tuple[int, int]]:
    parser = FrameParser(HOST_TO_BASE) if parser is None else parser
    return [decode_wheel_speed(f.payload) for f in parser.feed(data) if f.command == CMD_WHEEL_SPEED]


def read_commands(master: int, parser: FrameParser) -> list[tuple[int, int]]:
    try:
        data = os.read(master, 65536)
    except BlockingIOError:
        return []
    return wheel_commands(data, parser)


def read_until(master: int, done: Callable[[bytes], bool], timeout: float = 2.0) -> bytes:
    """What the link wrote, read until `done` holds (or the timeout): a pty hands the slave's
    bytes to the master asynchronously, so a write that returned may not be readable yet."""
    data, deadline = b"", time.monotonic() + timeout
    while not done(data) and time.monotonic() < deadline:
        try:
            data += os.read(master, 65536)
        except BlockingIOError:
            time.sleep(0.005)
    return data


def collect(master: int, seconds: float, feed=None) -> list[tuple[float, tuple[int, int]]]:
    parser, out = FrameParser(HOST_TO_BASE), []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if feed is not None:
            feed()
        out += [(time.monotonic(), c) for c in read_commands(master, parser)]
        time.sleep(0.005)
    return out


def make_link(port: str, **cfg) -> SparkBaseLink:
    link = SparkBaseLink(BaseConfig(port=port, **cfg), OdometryCalibration())
    link.open()
    return link


def test_current_command_is_resent_at_the_fixed_rate(pty_pair):
    master, port = pty_pair
    link = make_link(port, resend_hz=20.0)
    try:
        frames = collect(master, 1.2, feed=lambda: link.set_command(Twist(0.2, 0.0), time.monotonic()))
    finally:
        link.close()
    moving = [t for t, c in frames if c == (692, 692)]
    assert 19 <= len(moving) <= 25  # 20 Hz over ~1.1 s of motion
    gaps = [b - a for a, b in itertools.pairwise(moving)]
    assert max(gaps) < 0.1


def test_stop_is_sent_when_the_loop_stops_feeding_commands(pty_pair):
    master, port = pty_pair
    link = make_link(port, command_timeout_s=0.25)
    try:
        link.set_command(Twist(0.2, 0.0), time.monotonic())
        fed = time.monotonic()
        frames = collect(master, 0.8)
    finally:
        link.close()
    first_stop = next(t for t, c in frames if c == (0, 0) and t > fed + 0.05)
    assert 0.2 <= first_stop - fed <= 0.4
    assert all(c == (0, 0) for t, c in frames if t > first_stop)
    assert link.stats().command_timeouts == 1


def test_close_sends_stop_last(pty_pair):
    master, port = pty_pair
    link = make_link(port)
    link.set_command(Twist(0.2, 0.0), time.monotonic())
    time.sleep(0.2)
    link.close()
    sent = wheel_commands(read_until(master, lambda d: wheel_commands(d)[-2:] == [(0, 0), (0, 0)]
                                     and (692, 692) in wheel_commands(d)))
    assert (692, 692) in sent and sent[-1] == (0, 0)
    assert link.stats().stops_sent >= 2


def test_fresh_connection_starts_with_stop_then_vendor_query(pty_pair):
    master, port = pty_pair
    link = make_link(port)
    time.sleep(0.05)
    link.close()
    data = read_until(master, lambda d: len(d) >= len(STOP_FRAME) + 8)
    assert data.startswith(STOP_FRAME + bytes.fromhex("534B020016000D0A"))


def feedback(left: int, right: int, time_ticks: int) -> bytes:
    return encode_feedback(Feedback(0x3F, 0, 0, 0, 0, right & 0xFFFFFFFF, left & 0xFFFFFFFF,
                                    time_ticks, (0, 0, 1), (0, 0, 57.29577951308232),
                                    (0, 0, 0), (0, 0, 90.0)))


def poll_until(link: SparkBaseLink, count: int, timeout: float = 2.0) -> list:
    deadline = time.monotonic() + timeout
    incs: list = []
    while len(incs) < count and time.monotonic() < deadline:
        incs += link.poll()
        time.sleep(0.01)
    return incs


def test_feedback_becomes_si_increments_across_the_u32_wrap(pty_pair):
    master, port = pty_pair
    link = make_link(port)
    m_per_tick = OdometryCalibration().m_per_tick
    try:
        # two frames that agree make the baseline; the third crosses the u32 wrap
        os.write(master, feedback(-30, -20, 1000) + b"\x00garbage" + feedback(-10, -5, 1200))
        time.sleep(0.05)
        os.write(master, feedback(10, 20, 1400))
        incs = poll_until(link, 1)
    finally:
        link.close()
    assert len(incs) == 1
    inc = incs[0]
    assert inc.d_left == pytest.approx(20 * m_per_tick)
    assert inc.d_right == pytest.approx(25 * m_per_tick)
    assert inc.dt == pytest.approx(0.02)
    assert inc.gyro_z == pytest.approx(1.0)
    assert inc.yaw == pytest.approx(1.5707963, abs=1e-6)
    assert inc.hazard is None
    assert link.stats().skipped_bytes > 0


def test_implausible_frames_are_counted_by_reason_logged_once_and_cost_no_distance(
        pty_pair, monkeypatch, caplog):
    for interval in ("FIRST_REJECT_LOG_S", "REJECT_LOG_INTERVAL_S"):  # a summary every read
        monkeypatch.setattr(spark_link, interval, 0.0)
    master, port = pty_pair
    link = make_link(port)
    m_per_tick = OdometryCalibration().m_per_tick
    bad_checksum = bytearray(feedback(0, 0, 1400))
    bad_checksum[-3] ^= 1
    try:
        os.write(master, feedback(0, 0, 1000) + feedback(10, 10, 1200))
        time.sleep(0.05)
        # passes the checksum but the left wheel jumped 4096 ticks (0.06 m/s at most in 20 ms)
        os.write(master, bytes(bad_checksum) + feedback(4096 + 20, 20, 1400))
        time.sleep(0.05)
        os.write(master, feedback(30, 30, 1600))
        incs = poll_until(link, 1)
    finally:
        link.close()
    assert [round(i.d_left / m_per_tick) for i in incs] == [20]  # spans the rejected frame
    assert incs[0].dt == pytest.approx(0.04)
    rejected = link.stats().rejected
    assert rejected["checksum"] >= 1 and rejected["encoder_jump"] == 1
    summaries = [r.getMessage() for r in caplog.records if "frames dropped" in r.getMessage()]
    assert any("1 encoder_jump" in m for m in summaries)
