"""Pure model of the NXROBO Spark base: firmware behaviour, wheel physics, encoders and IMU.

No I/O and no clocks: the caller passes time in (`receive(data, t)`, `step(dt)`), so unit tests run
the model faster than real time and the pty emulator (`sim_stub.base_emulator`) runs it on the
host's monotonic clock. All wire handling goes through `drivers.spark.protocol`.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

from drivers.spark.protocol import (
    CMD_FEEDBACK,
    CMD_QUERY,
    CMD_WHEEL_SPEED,
    FEEDBACK_LEN_IMU,
    HEADER,
    HOST_TO_BASE,
    Feedback,
    Frame,
    FrameParser,
    decode_wheel_speed,
    encode_feedback,
)

G_M_S2 = 9.80665
U32 = 0xFFFFFFFF
BASE_TIME_TICKS_PER_S = 10_000  # the base timestamp counts 0.1 ms
NO_CLIFF_BITS = 0x3F  # six cliff sensors, active-low: all 1 means floor under every sensor
START_MODES = ("stream", "any_query", "wellformed_query")

Event = dict[str, Any]


@dataclass(frozen=True)
class BasePhysics:
    """The robot's true physical parameters. They may differ from the host's calibration on
    purpose, so calibration and odometry code can be tested against a known truth."""

    m_per_tick: float = 0.00028885
    axle_m: float = 0.266
    left_encoder_offset: int = 14  # wire offset (10 or 14) that carries the physical left wheel
    max_wheel_speed_m_s: float = 0.5
    max_wheel_accel_m_s2: float = 1.0
    gyro_bias_rad_s: float = 0.0
    encoder_noise_ticks: float = 0.0  # std-dev of integer noise on each reported count
    encoder_start: int = 0xFFFFF800  # 2048 ticks (0.59 m) below the u32 wrap: hit in the first metre
    imu: bool = True  # 73-byte feedback frames; False gives 25-byte frames
    seed: int = 0

    def __post_init__(self) -> None:
        if self.left_encoder_offset not in (10, 14):
            raise ValueError(f"left_encoder_offset must be 10 or 14, got {self.left_encoder_offset}")
        for name in ("m_per_tick", "axle_m", "max_wheel_speed_m_s", "max_wheel_accel_m_s2"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        if not (math.isfinite(self.gyro_bias_rad_s) and self.encoder_noise_ticks >= 0):
            raise ValueError("gyro_bias_rad_s must be finite and encoder_noise_ticks >= 0")
        if not 0 <= self.encoder_start <= U32:
            raise ValueError(f"encoder_start must be a u32, got {self.encoder_start}")


@dataclass
class _Wheel:
    """One wheel: commanded target, actual speed, and travel counted in (float) encoder ticks."""

    target_m_s: float
    speed_m_s: float
    ticks: float

    def time_to_target(self, accel: float) -> float:
        return abs(self.target_m_s - self.speed_m_s) / accel

    def accel_toward_target(self, accel: float) -> float:
        gap = self.target_m_s - self.speed_m_s
        return math.copysign(accel, gap) if gap else 0.0


def wrap_deg(angle: float) -> float:
    """Degrees wrapped to (−180, 180], the range the IMU reports yaw in."""
    wrapped = math.remainder(angle, 360.0)
    return 180.0 if wrapped == -180.0 else wrapped


def wrap_rad(angle: float) -> float:
    """Radians wrapped to (−π, π]."""
    wrapped = math.remainder(angle, math.tau)
    return math.pi if wrapped == -math.pi else wrapped


def abs_integral_linear(v0: float, accel: float, h: float) -> float:
    """∫₀ʰ |v0 + accel·τ| dτ, exact even when the speed changes sign inside the interval."""
    v1 = v0 + accel * h
    if v0 * v1 >= 0:
        return abs(v0 + v1) / 2.0 * h
    t_zero = -v0 / accel
    return (abs(v0) * t_zero + abs(v1) * (h - t_zero)) / 2.0


def noise_bytes(rng: random.Random, n: int) -> bytes:
    """n bytes of line noise that try to fool a parser: random bytes with embedded header
    fragments, ending in a plausible feedback header so the next real frame starts inside a
    claimed frame (a parser that drops the claimed length, like the vendor's, loses it)."""
    fake_header = HEADER + bytes([FEEDBACK_LEN_IMU]) + CMD_FEEDBACK.to_bytes(2, "big")
    out = bytearray()
    body = max(0, n - len(fake_header))
    while len(out) < body:
        if rng.random() < 0.1:
            out += fake_header[: rng.randint(2, len(fake_header))] + rng.randbytes(rng.randint(0, 8))
        else:
            out += rng.randbytes(1)
    del out[body:]
    out += fake_header[: n - len(out)]
    return bytes(out)


class SparkBaseSim:
    """The base as the host sees it: takes host bytes, moves the wheels, reports feedback.

    Time is host time in seconds: `t0` is power-on, `receive` is told when bytes arrived and
    `step` advances the model. Commanded speeds are in encoder ticks/s on the wire and become
    true wheel speeds through the true `m_per_tick`, so a host calibration error shows up as it
    would on the robot.
    """

    def __init__(
        self,
        physics: BasePhysics | None = None,
        start_mode: str = "stream",
        watchdog_s: float = 0.5,
        t0: float = 0.0,
    ) -> None:
        if start_mode not in START_MODES:
            raise ValueError(f"start_mode must be one of {START_MODES}, got {start_mode!r}")
        if not watchdog_s >= 0:
            raise ValueError(f"watchdog_s must be >= 0 (0 disables), got {watchdog_s}")
        self.physics = physics or BasePhysics()
        self.start_mode = start_mode
        self.watchdog_s = watchdog_s
        self.t0 = t0
        self.t = t0
        self.streaming = start_mode == "stream"
        self.commands_received = 0
        self.queries_received = 0
        self._parser = FrameParser(HOST_TO_BASE)
        self._rng = random.Random(self.physics.seed)
        start = float(self.physics.encoder_start)
        self._left = _Wheel(0.0, 0.0, start)
        self._right = _Wheel(0.0, 0.0, start)
        self._command = (0, 0)  # last commanded (left, right) ticks/s in force
        self._last_command_t: float | None = None  # arms the watchdog while a motion is commanded
        self._x = self._y = self._theta = self._distance = 0.0
        self._imu_yaw_rad = 0.0
        self._accel_x_m_s2 = 0.0
        self._glitch_ticks = 0

    # --- host bytes in ---------------------------------------------------------------------

    def receive(self, data: bytes, t: float) -> list[Event]:
        """Parse host bytes that arrived at time t and act on each frame; return events to log."""
        events: list[Event] = []
        for frame in self._parser.feed(data):
            event = self._handle(frame, t)
            if event is not None:
                events.append(event)
        return events

    def reset_input(self) -> None:
        """Forget a partial frame: after a reconnect the old bytes belong to another stream."""
        self._parser.reset()

    def rx_stats(self) -> dict[str, Any]:
        """Counts of what the host sent, including the parser's rejects by reason."""
        return {
            "commands_received": self.commands_received,
            "queries_received": self.queries_received,
            "rejected": dict(self._parser.rejected),
            "skipped_bytes": self._parser.skipped_bytes,
        }

    def _handle(self, frame: Frame, t: float) -> Event | None:
        if frame.command == CMD_WHEEL_SPEED:
            return self._on_wheel_speed(decode_wheel_speed(frame.payload), t)
        if frame.command == CMD_QUERY:
            return self._on_query(frame.vendor_query, t)
        return {"event": "ignored", "t": t, "command": frame.command}

    def _on_wheel_speed(self, ticks_s: tuple[int, int], t: float) -> Event | None:
        self.commands_received += 1
        self._last_command_t = t if ticks_s != (0, 0) else None
        limit = self.physics.max_wheel_speed_m_s
        self._left.target_m_s = _clamp(ticks_s[0] * self.physics.m_per_tick, limit)
        self._right.target_m_s = _clamp(ticks_s[1] * self.physics.m_per_tick, limit)
        if ticks_s == self._command:
            return None
        self._command = ticks_s
        return {
            "event": "command",
            "t": t,
            "left": ticks_s[0],
            "right": ticks_s[1],
            "left_m_s": self._left.target_m_s,
            "right_m_s": self._right.target_m_s,
        }

    def _on_query(self, vendor: bool, t: float) -> Event:
        self.queries_received += 1
        if self.start_mode == "any_query" or (self.start_mode == "wellformed_query" and not vendor):
            self.streaming = True
        return {"event": "query", "t": t, "vendor": vendor, "streaming": self.streaming}

    # --- physics ---------------------------------------------------------------------------

    def step(self, dt: float) -> list[Event]:
        """Advance the model by dt seconds; return events (a watchdog stop) that happened."""
        if not dt >= 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        end = self.t + dt
        v_start = self._speed()
        events: list[Event] = []
        deadline = self._watchdog_deadline()
        if deadline is not None and deadline < end:
            self._advance_to(max(deadline, self.t))
            events.append(self._watchdog_stop())
        self._advance_to(end)
        if dt > 0:
            self._accel_x_m_s2 = (self._speed() - v_start) / dt
        return events

    def _watchdog_deadline(self) -> float | None:
        if self.watchdog_s == 0 or self._last_command_t is None:
            return None
        return self._last_command_t + self.watchdog_s

    def _watchdog_stop(self) -> Event:
        self._left.target_m_s = self._right.target_m_s = 0.0
        self._command = (0, 0)
        self._last_command_t = None
        return {"event": "watchdog_stop", "t": self.t}

    def _advance_to(self, end: float) -> None:
        """Integrate in segments inside which each wheel's acceleration is constant."""
        accel = self.physics.max_wheel_accel_m_s2
        while self.t < end:
            for wheel in (self._left, self._right):
                if wheel.time_to_target(accel) == 0.0:
                    wheel.speed_m_s = wheel.target_m_s
            ramps = [w.time_to_target(accel) for w in (self._left, self._right)]
            h = min([end - self.t] + [r for r in ramps if r > 0])
            self._integrate(h, accel)
            for wheel, ramp in zip((self._left, self._right), ramps):
                if 0 < ramp <= h:
                    wheel.speed_m_s = wheel.target_m_s  # land exactly, no float residue
            self.t = end if h == end - self.t else self.t + h

    def _integrate(self, h: float, accel: float) -> None:
        """One constant-acceleration segment: wheel travel is exact; the pose follows the chord
        of the arc with the segment's mean curvature."""
        a_left = self._left.accel_toward_target(accel)
        a_right = self._right.accel_toward_target(accel)
        d_left = self._left.speed_m_s * h + 0.5 * a_left * h * h
        d_right = self._right.speed_m_s * h + 0.5 * a_right * h * h
        self._distance += abs_integral_linear(self._speed(), (a_left + a_right) / 2.0, h)
        self._left.speed_m_s += a_left * h
        self._right.speed_m_s += a_right * h
        self._left.ticks += d_left / self.physics.m_per_tick
        self._right.ticks += d_right / self.physics.m_per_tick
        ds = (d_left + d_right) / 2.0
        d_theta = (d_right - d_left) / self.physics.axle_m
        chord = ds * _sinc(d_theta / 2.0)
        self._x += chord * math.cos(self._theta + d_theta / 2.0)
        self._y += chord * math.sin(self._theta + d_theta / 2.0)
        self._theta += d_theta
        self._imu_yaw_rad += d_theta + self.physics.gyro_bias_rad_s * h

    def _speed(self) -> float:
        return (self._left.speed_m_s + self._right.speed_m_s) / 2.0

    def _omega(self) -> float:
        return (self._right.speed_m_s - self._left.speed_m_s) / self.physics.axle_m

    # --- feedback out ----------------------------------------------------------------------

    def glitch_next_frame(self, ticks: int = 5000) -> None:
        """Make the next feedback frame carry a one-frame spike of `ticks` on both encoders."""
        self._glitch_ticks = ticks

    def feedback_frame(self) -> bytes:
        """The 0x0059 frame the base would send now (73 bytes with IMU, 25 without)."""
        left, right = self._reported_count(self._left), self._reported_count(self._right)
        self._glitch_ticks = 0
        enc_10, enc_14 = (right, left) if self.physics.left_encoder_offset == 14 else (left, right)
        base_time = math.floor((self.t - self.t0) * BASE_TIME_TICKS_PER_S)
        imu = self._imu_fields() if self.physics.imu else {}
        return encode_feedback(Feedback(NO_CLIFF_BITS, 0, 0, 0, 0, enc_10, enc_14, base_time, **imu))

    def _reported_count(self, wheel: _Wheel) -> int:
        noise = self.physics.encoder_noise_ticks
        jitter = round(self._rng.gauss(0.0, noise)) if noise > 0 else 0
        return (math.floor(wheel.ticks) + jitter + self._glitch_ticks) & U32

    def _imu_fields(self) -> dict[str, tuple[float, float, float]]:
        v, omega = self._speed(), self._omega()
        gyro_z = math.degrees(omega + self.physics.gyro_bias_rad_s)
        return {
            "accel_g": (self._accel_x_m_s2 / G_M_S2, v * omega / G_M_S2, 1.0),
            "gyro_dps": (0.0, 0.0, gyro_z),
            "mag": (0.0, 0.0, 0.0),
            "rpy_deg": (0.0, 0.0, wrap_deg(math.degrees(self._imu_yaw_rad))),
        }

    def truth(self) -> dict[str, float]:
        """Ground truth in SI units: pose in the frame fixed at power-on, speeds, path length."""
        return {
            "t": self.t,
            "x": self._x,
            "y": self._y,
            "theta": wrap_rad(self._theta),
            "theta_unwrapped": self._theta,
            "v": self._speed(),
            "omega": self._omega(),
            "distance": self._distance,
            "left_m_s": self._left.speed_m_s,
            "right_m_s": self._right.speed_m_s,
        }


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _sinc(x: float) -> float:
    """sin(x)/x, with its limit 1 at 0 (straight-line motion)."""
    return math.sin(x) / x if abs(x) > 1e-9 else 1.0
