"""Pure codec for the NXROBO Spark base's serial protocol (see shared/spark-base-protocol.md).

No I/O here: the host link (`drivers.spark.link`) and the base emulator (`sim_stub.base_emulator`)
both speak through this module, so a change to the wire format is made once.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from dataclasses import dataclass

HEADER = b"SK"
TRAILER = b"\r\n"
MIN_FRAME_LEN = 8  # header 2 + length 1 + command 2 + checksum 1 + trailer 2

CMD_STOP_DOCK = 0x0005
CMD_GO_DOCK = 0x0010
CMD_QUERY = 0x0016
CMD_SEARCH_DOCK = 0x0017
CMD_WHEEL_SPEED = 0x0018
CMD_FEEDBACK = 0x0059

# Frame lengths (header to trailer inclusive) each command may have on the wire.
FRAME_LENGTHS: dict[int, frozenset[int]] = {
    CMD_STOP_DOCK: frozenset({8}),
    CMD_GO_DOCK: frozenset({8}),
    CMD_QUERY: frozenset({8}),
    CMD_SEARCH_DOCK: frozenset({9}),
    CMD_WHEEL_SPEED: frozenset({12}),
    CMD_FEEDBACK: frozenset({25, 73}),
}
HOST_TO_BASE = frozenset({CMD_STOP_DOCK, CMD_GO_DOCK, CMD_QUERY, CMD_SEARCH_DOCK, CMD_WHEEL_SPEED})
BASE_TO_HOST = frozenset({CMD_FEEDBACK})

# The vendor driver's start-up bytes: a query whose length byte says 2. Kept byte for byte
# because it is what the firmware has seen from every Spark host since 2018.
VENDOR_QUERY = bytes.fromhex("534B020016000D0A")

VENDOR_MM_PER_TICK = 0.28885
VENDOR_AXLE_M = 0.266
MAX_WHEEL_MM_S = 500

REJECT_REASONS = ("length", "unknown_command", "trailer", "checksum", "truncated")


def checksum(data: bytes | bytearray | memoryview) -> int:
    """8-bit sum of the bytes (no xor, no complement), as the firmware computes it."""
    return sum(data) & 0xFF


def encode_frame(command: int, payload: bytes = b"") -> bytes:
    """Wrap a payload into a complete frame: header, length, command (big-endian), checksum, trailer."""
    length = MIN_FRAME_LEN + len(payload)
    if length > 0xFF:
        raise ValueError(f"payload of {len(payload)} bytes does not fit a Spark frame")
    body = HEADER + bytes([length]) + command.to_bytes(2, "big") + payload
    return body + bytes([checksum(body)]) + TRAILER


WELLFORMED_QUERY = encode_frame(CMD_QUERY)


def wheel_speed_frame(left_ticks_s: int, right_ticks_s: int) -> bytes:
    """0x0018 frame: int16 little-endian left then right wheel speed, in encoder ticks per second."""
    return encode_frame(CMD_WHEEL_SPEED, struct.pack("<hh", left_ticks_s, right_ticks_s))


STOP_FRAME = wheel_speed_frame(0, 0)


def _trunc(x: float) -> int:
    """Truncate toward zero, forgiving float noise such as 0.57*1000 = 569.999…"""
    return math.trunc(x + math.copysign(1e-9, x))


def twist_to_wheel_ticks(
    v: float,
    omega: float,
    axle_m: float = VENDOR_AXLE_M,
    m_per_tick: float = VENDOR_MM_PER_TICK / 1000.0,
    max_wheel_mm_s: int = MAX_WHEEL_MM_S,
) -> tuple[int, int]:
    """Twist (m/s, rad/s) → (left, right) ticks/s the way the vendor driver does it, but clamped on
    both sides (the vendor clamps only the upper side)."""
    if not (math.isfinite(v) and math.isfinite(omega)):
        raise ValueError(f"twist must be finite, got v={v}, omega={omega}")
    ticks = []
    for wheel_m_s in (v - omega * axle_m / 2.0, v + omega * axle_m / 2.0):
        mm_s = max(-max_wheel_mm_s, min(max_wheel_mm_s, _trunc(wheel_m_s * 1000.0)))
        ticks.append(_trunc(mm_s / (m_per_tick * 1000.0)))
    return ticks[0], ticks[1]


@dataclass(frozen=True)
class Frame:
    """One checked frame off the wire. `vendor_query` marks the vendor's malformed query."""

    command: int
    payload: bytes
    vendor_query: bool = False


class FrameParser:
    """Incremental parser: feed it whatever bytes arrived, get back the complete frames.

    On any failure it drops exactly one byte and searches for the next header, so noise never
    costs a good frame that follows it (the vendor parser drops the whole claimed length).
    Rejections are counted by reason; bytes skipped while hunting for a header are counted too.
    """

    def __init__(self, accepted: frozenset[int], max_buffer: int = 4096) -> None:
        self._accepted = accepted
        self._lengths = {cmd: FRAME_LENGTHS[cmd] for cmd in accepted}
        self._max_len = max(max(v) for v in self._lengths.values())
        self._max_buffer = max(max_buffer, 2 * self._max_len)
        self._buf = bytearray()
        self.rejected: Counter[str] = Counter({reason: 0 for reason in REJECT_REASONS})
        self.skipped_bytes = 0
        self.frames = 0

    def reset(self) -> None:
        """Forget partial input (after a reconnect the old bytes belong to another stream)."""
        self._buf.clear()

    def feed(self, data: bytes | bytearray) -> list[Frame]:
        """Append bytes and return every frame that is now complete and valid."""
        self._buf += data
        frames: list[Frame] = []
        pos = 0
        buf = self._buf
        while True:
            start = buf.find(HEADER, pos)
            if start < 0:
                keep = 1 if buf.endswith(HEADER[:1]) else 0
                self.skipped_bytes += len(buf) - pos - keep
                pos = len(buf) - keep
                break
            self.skipped_bytes += start - pos
            pos = start
            frame, verdict = self._try_frame(buf, pos)
            if verdict == "incomplete":
                later = self._complete_frame_after(buf, pos)
                if later < 0:
                    break
                self.rejected["truncated"] += 1
                pos = later
                continue
            if frame is None:
                self.rejected[verdict] += 1
                pos += 1
                continue
            frames.append(frame)
            self.frames += 1
            pos += 8 if frame.vendor_query else buf[pos + 2]
        del buf[:pos]
        if len(buf) > self._max_buffer:  # cannot happen with bounded lengths; guard anyway
            self.skipped_bytes += len(buf) - self._max_len
            del buf[: len(buf) - self._max_len]
        return frames

    def _complete_frame_after(self, buf: bytearray, pos: int) -> int:
        """Start of a complete valid frame after `pos`, or -1.

        A header whose claimed length has not arrived yet may be noise (a cut-off frame). If a
        complete, checksummed frame already starts inside its claimed span, the claim was
        truncated: without this look-ahead that good frame would wait for unrelated later bytes,
        or be lost when the stream stops.
        """
        nxt = buf.find(HEADER, pos + 1)
        while nxt >= 0:
            if self._try_frame(buf, nxt)[0] is not None:
                return nxt
            nxt = buf.find(HEADER, nxt + 1)
        return -1

    def _try_frame(self, buf: bytearray, pos: int) -> tuple[Frame | None, str]:
        avail = len(buf) - pos
        if avail < 3:
            return None, "incomplete"
        length = buf[pos + 2]
        if length < MIN_FRAME_LEN:
            if CMD_QUERY in self._accepted and length == VENDOR_QUERY[2]:
                if avail < len(VENDOR_QUERY):
                    if buf[pos:] == VENDOR_QUERY[:avail]:
                        return None, "incomplete"
                elif buf[pos : pos + len(VENDOR_QUERY)] == VENDOR_QUERY:
                    return Frame(CMD_QUERY, b"", vendor_query=True), "ok"
            return None, "length"
        if length > self._max_len:
            return None, "length"
        if avail < 5:
            return None, "incomplete"
        command = int.from_bytes(buf[pos + 3 : pos + 5], "big")
        if command not in self._lengths:
            return None, "unknown_command"
        if length not in self._lengths[command]:
            return None, "length"
        if avail < length:
            return None, "incomplete"
        if buf[pos + length - 2 : pos + length] != TRAILER:
            return None, "trailer"
        if checksum(memoryview(buf)[pos : pos + length - 3]) != buf[pos + length - 3]:
            return None, "checksum"
        return Frame(command, bytes(buf[pos + 5 : pos + length - 3])), "ok"


# --- feedback (0x0059) -------------------------------------------------------------------------

_FEEDBACK_BASE = struct.Struct("<BBBBBIII")  # offsets 5..21
_FEEDBACK_IMU = struct.Struct("<12f")  # offsets 22..69
FEEDBACK_LEN_IMU = 73
FEEDBACK_LEN_NO_IMU = 25


@dataclass(frozen=True)
class Feedback:
    """A decoded 0x0059 frame, still in wire units (ticks, 0.1 ms, g, deg/s, degrees).

    `encoder_10` and `encoder_14` are named by their byte offset because which one is physically
    left is a per-robot calibration fact, not something the codec may assume.
    """

    cliff_bits: int
    bumper_bits: int
    status_bits: int
    dock_ir_bits: int
    unused: int
    encoder_10: int
    encoder_14: int
    base_time: int
    accel_g: tuple[float, float, float] | None = None
    gyro_dps: tuple[float, float, float] | None = None
    mag: tuple[float, float, float] | None = None
    rpy_deg: tuple[float, float, float] | None = None


def decode_feedback(payload: bytes) -> Feedback:
    """Decode the payload of a 0x0059 frame (17 bytes without IMU, 65 with)."""
    if len(payload) not in (FEEDBACK_LEN_NO_IMU - 8, FEEDBACK_LEN_IMU - 8):
        raise ValueError(f"feedback payload has {len(payload)} bytes, expected 17 or 65")
    base = _FEEDBACK_BASE.unpack_from(payload, 0)
    if len(payload) == FEEDBACK_LEN_NO_IMU - 8:
        return Feedback(*base)
    ax, ay, az, gx, gy, gz, mx, my, mz, roll, pitch, yaw = _FEEDBACK_IMU.unpack_from(
        payload, _FEEDBACK_BASE.size
    )
    cliff, bumper, status, dock_ir, unused, encoder_10, encoder_14, base_time = base
    return Feedback(
        cliff, bumper, status, dock_ir, unused, encoder_10, encoder_14, base_time,
        accel_g=(ax, ay, az),
        gyro_dps=(gx, gy, gz),
        mag=(mx, my, mz),
        rpy_deg=(roll, pitch, yaw),
    )


def encode_feedback(fb: Feedback) -> bytes:
    """Complete 0x0059 frame for a Feedback (73 bytes with IMU fields, 25 without)."""
    payload = _FEEDBACK_BASE.pack(
        fb.cliff_bits,
        fb.bumper_bits,
        fb.status_bits,
        fb.dock_ir_bits,
        fb.unused,
        fb.encoder_10 & 0xFFFFFFFF,
        fb.encoder_14 & 0xFFFFFFFF,
        fb.base_time & 0xFFFFFFFF,
    )
    if fb.accel_g is not None:
        if fb.gyro_dps is None or fb.mag is None or fb.rpy_deg is None:
            raise TypeError("Feedback IMU fields must be all set or all None")
        imu = (*fb.accel_g, *fb.gyro_dps, *fb.mag, *fb.rpy_deg)
        payload += _FEEDBACK_IMU.pack(*imu)
    return encode_frame(CMD_FEEDBACK, payload)


def decode_wheel_speed(payload: bytes) -> tuple[int, int]:
    """(left, right) ticks/s from a 0x0018 payload."""
    left, right = struct.unpack("<hh", payload)
    return left, right


def signed_delta32(now: int, last: int) -> int:
    """Signed difference of two free-running u32 counters: ((now − last + 2³¹) mod 2³²) − 2³¹."""
    return ((now - last + (1 << 31)) % (1 << 32)) - (1 << 31)
