"""Tests of the Spark base emulator: the pure model (`SparkBaseSim`) and the pty process."""

from __future__ import annotations

import itertools
import json
import math
import os
import queue
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import serial

from drivers.spark.protocol import (
    BASE_TO_HOST,
    FEEDBACK_LEN_IMU,
    FEEDBACK_LEN_NO_IMU,
    VENDOR_QUERY,
    WELLFORMED_QUERY,
    Feedback,
    FrameParser,
    decode_feedback,
    encode_frame,
    signed_delta32,
    wheel_speed_frame,
)
from sim_stub.base_emulator import main as emulator_main
from sim_stub.base_sim import (
    BasePhysics,
    SparkBaseSim,
    abs_integral_linear,
    noise_bytes,
    wrap_deg,
)

REPO = Path(__file__).resolve().parents[1]
M_PER_TICK = BasePhysics().m_per_tick
DT = 0.02


def parse_one(frame: bytes) -> Feedback:
    """Decode one feedback frame through the same parser the host uses."""
    frames = FrameParser(BASE_TO_HOST).feed(frame)
    assert len(frames) == 1
    return decode_feedback(frames[0].payload)


def drive(sim: SparkBaseSim, left: int, right: int, seconds: float) -> list[dict[str, Any]]:
    """Resend a wheel-speed command every step (as the host driver does) for `seconds`."""
    events: list[dict[str, Any]] = []
    for _ in range(round(seconds / DT)):
        events += sim.receive(wheel_speed_frame(left, right), sim.t)
        events += sim.step(DT)
    return events


def encoder_deltas(before: Feedback, after: Feedback) -> tuple[int, int]:
    """Signed tick deltas of (offset 10, offset 14), wrap-safe."""
    return (
        signed_delta32(after.encoder_10, before.encoder_10),
        signed_delta32(after.encoder_14, before.encoder_14),
    )


# --- the pure model -----------------------------------------------------------------------------


def test_692_ticks_for_two_seconds_covers_0_4_m_less_the_ramp() -> None:
    sim = SparkBaseSim()
    start = parse_one(sim.feedback_frame())
    drive(sim, 692, 692, 2.0)
    v = 692 * M_PER_TICK
    expected = v * 2.0 - v * v / (2 * 1.0)  # the ramp at 1 m/s² loses v²/2a
    truth = sim.truth()
    assert truth["distance"] == pytest.approx(expected, abs=1e-9)
    assert truth["x"] == pytest.approx(expected, abs=1e-9)
    assert truth["y"] == pytest.approx(0.0, abs=1e-12)
    assert truth["v"] == pytest.approx(v)
    d10, d14 = encoder_deltas(start, parse_one(sim.feedback_frame()))
    assert d10 == d14 == pytest.approx(expected / M_PER_TICK, abs=1)


@pytest.mark.parametrize("left_offset", [14, 10])
def test_positive_omega_turns_left_and_the_right_encoder_rises_faster(left_offset: int) -> None:
    sim = SparkBaseSim(BasePhysics(left_encoder_offset=left_offset))
    start = parse_one(sim.feedback_frame())
    drive(sim, -460, 460, 1.0)
    truth = sim.truth()
    assert truth["omega"] > 0 and truth["theta"] > 0
    assert truth["right_m_s"] > truth["left_m_s"]
    fb = parse_one(sim.feedback_frame())
    assert fb.gyro_dps is not None and fb.rpy_deg is not None
    assert fb.gyro_dps[2] == pytest.approx(math.degrees(truth["omega"]))
    assert fb.rpy_deg[2] == pytest.approx(math.degrees(truth["theta"]))
    d10, d14 = encoder_deltas(start, fb)
    right, left = (d10, d14) if left_offset == 14 else (d14, d10)
    assert right > 0 > left


def test_constant_wheel_speeds_trace_an_exact_circle() -> None:
    sim = SparkBaseSim(BasePhysics(max_wheel_accel_m_s2=1e12), watchdog_s=0)
    sim.receive(wheel_speed_frame(300, 600), 0.0)
    v_left, v_right = 300 * M_PER_TICK, 600 * M_PER_TICK
    omega = (v_right - v_left) / 0.266
    period = math.tau / omega
    for _ in range(10):
        sim.step(period / 10)  # big steps: exact arcs, no integration drift
    truth = sim.truth()
    assert truth["x"] == pytest.approx(0.0, abs=1e-6)
    assert truth["y"] == pytest.approx(0.0, abs=1e-6)
    assert truth["theta_unwrapped"] == pytest.approx(math.tau, rel=1e-9)


def test_acceleration_limit_holds_on_every_wheel_and_reversal_counts_path_length() -> None:
    sim = SparkBaseSim(BasePhysics(max_wheel_accel_m_s2=1.0))
    drive(sim, 692, 692, 0.5)
    previous = sim.truth()
    for _ in range(40):
        sim.receive(wheel_speed_frame(-692, -692), sim.t)
        sim.step(DT)
        now = sim.truth()
        for wheel in ("left_m_s", "right_m_s"):
            assert abs(now[wheel] - previous[wheel]) <= 1.0 * DT + 1e-12
        previous = now
    v = 692 * M_PER_TICK
    assert sim.truth()["v"] == pytest.approx(-v)
    # forward ramp + cruise + stopping, then the reverse ramp: |v| counted both ways
    assert sim.truth()["distance"] > abs(sim.truth()["x"]) + v * v / 2


def test_imu_reports_longitudinal_acceleration_in_g() -> None:
    sim = SparkBaseSim()
    drive(sim, 692, 692, 0.1)
    fb = parse_one(sim.feedback_frame())
    assert fb.accel_g is not None
    assert fb.accel_g[0] == pytest.approx(1.0 / 9.80665)
    assert fb.accel_g[2] == 1.0


def test_wheel_speeds_clamp_at_the_physical_limit() -> None:
    sim = SparkBaseSim(BasePhysics(max_wheel_accel_m_s2=1e12))
    sim.receive(wheel_speed_frame(30000, -30000), 0.0)
    sim.step(0.1)
    assert sim.truth()["right_m_s"] == pytest.approx(-0.5)
    assert sim.truth()["left_m_s"] == pytest.approx(0.5)


def test_gyro_bias_makes_imu_yaw_drift_while_standing() -> None:
    sim = SparkBaseSim(BasePhysics(gyro_bias_rad_s=0.01))
    sim.step(10.0)
    fb = parse_one(sim.feedback_frame())
    assert fb.gyro_dps is not None and fb.rpy_deg is not None
    assert fb.gyro_dps[2] == pytest.approx(math.degrees(0.01))
    assert fb.rpy_deg[2] == pytest.approx(math.degrees(0.1))
    assert sim.truth()["theta"] == 0.0


def test_command_events_only_on_change_and_stop_is_reported() -> None:
    sim = SparkBaseSim()
    events = drive(sim, 100, 100, 0.2) + drive(sim, 0, 0, 0.2)
    assert [(e["left"], e["right"]) for e in events if e["event"] == "command"] == [
        (100, 100),
        (0, 0),
    ]


def test_watchdog_stops_once_after_silence_and_a_new_command_is_reported() -> None:
    sim = SparkBaseSim(watchdog_s=0.5)
    sim.receive(wheel_speed_frame(692, 692), 0.0)
    assert sim.step(0.45) == []
    events = sim.step(0.1)
    assert events == [{"event": "watchdog_stop", "t": pytest.approx(0.5)}]
    sim.step(1.0)
    assert sim.step(1.0) == []
    assert sim.truth()["v"] == 0.0
    assert [e["event"] for e in sim.receive(wheel_speed_frame(692, 692), sim.t)] == ["command"]


def test_watchdog_zero_disables_it() -> None:
    sim = SparkBaseSim(watchdog_s=0)
    sim.receive(wheel_speed_frame(692, 692), 0.0)
    assert sim.step(5.0) == []
    assert sim.truth()["v"] == pytest.approx(692 * M_PER_TICK)


@pytest.mark.parametrize(
    ("mode", "after_vendor", "after_wellformed"),
    [("stream", True, True), ("any_query", True, True), ("wellformed_query", False, True)],
)
def test_start_modes(mode: str, after_vendor: bool, after_wellformed: bool) -> None:
    sim = SparkBaseSim(start_mode=mode)
    assert sim.streaming is (mode == "stream")
    (event,) = sim.receive(VENDOR_QUERY, 0.0)
    assert event == {"event": "query", "t": 0.0, "vendor": True, "streaming": after_vendor}
    (event,) = sim.receive(WELLFORMED_QUERY, 0.1)
    assert event["vendor"] is False and sim.streaming is after_wellformed


def test_encoders_wrap_u32_within_the_first_metre_from_the_default_start() -> None:
    sim = SparkBaseSim()
    frames = [parse_one(sim.feedback_frame())]
    for _ in range(4):
        drive(sim, 1500, 1500, 0.5)
        frames.append(parse_one(sim.feedback_frame()))
    assert sim.truth()["distance"] < 1.0
    raw = [fb.encoder_14 for fb in frames]
    assert any(b < a for a, b in itertools.pairwise(raw)), "raw counts never wrapped"
    total = sum(signed_delta32(b, a) for a, b in itertools.pairwise(raw))
    assert total == pytest.approx(sim.truth()["distance"] / M_PER_TICK, abs=1)


def test_no_imu_gives_25_byte_frames() -> None:
    sim = SparkBaseSim(BasePhysics(imu=False))
    frame = sim.feedback_frame()
    assert len(frame) == FEEDBACK_LEN_NO_IMU
    assert parse_one(frame).accel_g is None
    assert len(SparkBaseSim().feedback_frame()) == FEEDBACK_LEN_IMU


def test_glitch_spikes_one_frame_only() -> None:
    sim = SparkBaseSim()
    before = parse_one(sim.feedback_frame())
    sim.glitch_next_frame(5000)
    spike = parse_one(sim.feedback_frame())
    after = parse_one(sim.feedback_frame())
    assert encoder_deltas(before, spike) == (5000, 5000)
    assert encoder_deltas(before, after) == (0, 0)


def test_encoder_noise_is_integer_jitter_around_the_truth_and_seeded() -> None:
    def counts(seed: int) -> list[int]:
        sim = SparkBaseSim(BasePhysics(encoder_noise_ticks=2.0, seed=seed))
        return [parse_one(sim.feedback_frame()).encoder_14 for _ in range(50)]

    start = BasePhysics().encoder_start
    jitter = [signed_delta32(c, start) for c in counts(1)]
    assert len(set(jitter)) > 3 and max(map(abs, jitter)) < 20
    assert counts(1) == counts(1) != counts(2)


def test_every_frame_parses_through_adversarial_noise_and_base_time_counts_0_1_ms() -> None:
    sim = SparkBaseSim()
    rng = random.Random(7)
    stream = bytearray()
    sent = 0
    for _ in range(100):
        sim.receive(wheel_speed_frame(-460, 692), sim.t)
        sim.step(DT)
        stream += noise_bytes(rng, rng.randint(0, 40)) + sim.feedback_frame()
        sent += 1
    parser = FrameParser(BASE_TO_HOST)
    frames = [decode_feedback(f.payload) for f in parser.feed(bytes(stream))]
    assert len(frames) == sent
    assert sum(parser.rejected.values()) > 0, "the noise never looked like a frame"
    assert frames[-1].base_time == round(sim.t * 10_000)
    assert all(fb.cliff_bits == 0x3F and fb.bumper_bits == fb.status_bits == 0 for fb in frames)


def test_noise_ends_in_a_header_that_claims_the_next_frame() -> None:
    noise = noise_bytes(random.Random(0), 30)
    assert len(noise) == 30 and noise.endswith(b"SK" + bytes([FEEDBACK_LEN_IMU, 0x00, 0x59]))


def test_other_commands_are_reported_as_ignored() -> None:
    (event,) = SparkBaseSim().receive(encode_frame(0x0010), 1.0)
    assert event == {"event": "ignored", "t": 1.0, "command": 0x0010}


def test_helpers_wrap_and_integrate() -> None:
    assert wrap_deg(180.0) == 180.0 and wrap_deg(-180.0) == 180.0 and wrap_deg(190.0) == -170.0
    assert abs_integral_linear(1.0, -2.0, 1.0) == pytest.approx(0.5)
    assert abs_integral_linear(-1.0, 0.0, 2.0) == pytest.approx(2.0)


@pytest.mark.parametrize(
    "bad",
    [{"left_encoder_offset": 12}, {"m_per_tick": 0.0}, {"encoder_start": -1},
     {"encoder_noise_ticks": -1.0}],
)
def test_physics_rejects_bad_parameters(bad: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        BasePhysics(**bad)


# --- the process on a pty -----------------------------------------------------------------------


class EventReader:
    """Reads the emulator's JSON lines on a thread so the test can wait with a deadline."""

    def __init__(self, stream: Any) -> None:
        self._queue: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self.seen: list[dict[str, Any]] = []
        threading.Thread(target=self._pump, args=(stream,), daemon=True).start()

    def _pump(self, stream: Any) -> None:
        for line in stream:
            self._queue.put(json.loads(line))
        self._queue.put(None)

    def wait_for(
        self,
        name: str,
        timeout: float = 5.0,
        match: Callable[[dict[str, Any]], bool] = lambda _e: True,
    ) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            try:
                event = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no {name!r} event in {timeout} s; saw {self.seen}") from None
            if event is None:
                raise AssertionError(f"emulator exited before {name!r}; saw {self.seen}")
            self.seen.append(event)
            if event["event"] == name and match(event):
                return event


@dataclass
class Emulator:
    proc: subprocess.Popen[str]
    events: EventReader
    link: Path

    def send(self, **op: Any) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(op) + "\n")
        self.proc.stdin.flush()


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[Emulator]:
    link = tmp_path / "sparkBase"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim_stub.base_emulator", "--link", str(link)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        bufsize=1,
    )
    try:
        yield Emulator(proc, EventReader(proc.stdout), link)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=5)


def read_feedback(port: serial.Serial, count: int, timeout: float = 3.0) -> list[Feedback]:
    parser = FrameParser(BASE_TO_HOST)
    frames: list[Feedback] = []
    deadline = time.monotonic() + timeout
    while len(frames) < count and time.monotonic() < deadline:
        frames += [decode_feedback(f.payload) for f in parser.feed(port.read(512))]
    assert len(frames) >= count, f"only {len(frames)} feedback frames in {timeout} s"
    return frames


def read_until_error(port: serial.Serial, timeout: float = 2.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        port.read(512)


@pytest.mark.hil
def test_process_streams_takes_commands_and_survives_a_replug(emulator: Emulator) -> None:
    ready = emulator.events.wait_for("ready")
    assert ready["link"] == str(emulator.link) and ready["pid"] == emulator.proc.pid
    assert os.readlink(emulator.link) == ready["pty"]

    old = serial.Serial(str(emulator.link), 115200, timeout=0.05)
    old.reset_input_buffer()
    sent_at = time.monotonic()
    old.write(WELLFORMED_QUERY + wheel_speed_frame(692, 692))
    assert emulator.events.wait_for("query")["vendor"] is False
    command = emulator.events.wait_for("command")
    assert (command["left"], command["right"]) == (692, 692)
    assert sent_at <= command["t"] < sent_at + 2.0  # one system-wide monotonic clock
    frames = read_feedback(old, 5)
    assert signed_delta32(frames[-1].encoder_14, frames[0].encoder_14) > 0

    emulator.send(op="reopen", down_s=0.6)  # longer than the 0.5 s watchdog
    emulator.events.wait_for("closed")
    with pytest.raises(serial.SerialException):
        read_until_error(old)
    reopened = emulator.events.wait_for("reopened")
    assert reopened["pty"] != ready["pty"]  # the old pts is still held open by `old`
    assert os.readlink(emulator.link) == reopened["pty"]
    assert any(e["event"] == "watchdog_stop" for e in emulator.events.seen), "robot not stopped"
    old.close()

    with serial.Serial(str(emulator.link), 115200, timeout=0.05) as new:
        emulator.send(op="noise", bytes=100)
        emulator.events.wait_for("ack", match=lambda e: e["op"] == "noise")
        assert len(read_feedback(new, 5)) >= 5
    emulator.send(op="stats")
    stats = emulator.events.wait_for("stats")
    assert stats["commands_received"] == 1 and stats["frames_sent"] >= 10
    emulator.send(op="no-such-op")
    assert "unknown op" in emulator.events.wait_for("error")["message"]

    emulator.send(op="quit")
    assert emulator.proc.wait(timeout=5) == 0
    assert not emulator.link.is_symlink()


@pytest.mark.hil
def test_process_outlives_stdin_eof_and_exits_cleanly_on_sigterm(emulator: Emulator) -> None:
    emulator.events.wait_for("ready")
    assert emulator.proc.stdin is not None
    emulator.proc.stdin.close()
    time.sleep(0.2)
    assert emulator.proc.poll() is None
    emulator.proc.send_signal(signal.SIGTERM)
    assert emulator.proc.wait(timeout=5) == 0
    assert not emulator.link.is_symlink()


@pytest.mark.parametrize(
    "argv", [["--rate-hz", "0"], ["--start-mode", "never"], ["--encoder-start", "0x1FFFFFFFF"]]
)
def test_bad_options_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        emulator_main(argv)
    assert exit_info.value.code == 2
    assert "usage:" in capsys.readouterr().err
