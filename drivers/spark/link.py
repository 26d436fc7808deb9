"""pyserial link to the Spark base: start-up query, fixed-rate command resend, stop on timeout,
fault and exit, reconnect with backoff, feedback → SI wheel increments.

One I/O thread owns the port. The control loop never blocks on it: it hands over the latest
command (`set_command`) and drains whatever feedback has arrived (`poll`). The thread keeps
sending even when the loop stalls, and sends stop once the command is older than
`command_timeout_s`, so a hung loop cannot leave the robot driving.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

import serial

from drivers.spark.feedback import FeedbackConverter
from drivers.spark.protocol import (
    BASE_TO_HOST,
    STOP_FRAME,
    VENDOR_QUERY,
    WELLFORMED_QUERY,
    FrameParser,
    decode_feedback,
    twist_to_wheel_ticks,
    wheel_speed_frame,
)
from runtime.config.calibration import OdometryCalibration
from runtime.config.devices import BaseConfig
from runtime.errors import DeviceError
from runtime.types import Twist, WheelIncrement

log = logging.getLogger("safemove.base")

SerialFactory = Callable[..., serial.Serial]
FEEDBACK_QUEUE_LEN = 1000  # 20 s at 50 Hz: only reached if the loop stops draining
REJECT_LOG_INTERVAL_S = 10.0  # rejected frames are logged as one summary line per interval
# The first summary comes early: a start-up that receives only implausible frames says so before
# the loop gives up waiting for feedback.
FIRST_REJECT_LOG_S = 1.0


@dataclass(frozen=True)
class LinkStats:
    """Counters for health reporting; all monotonic over the link's life. `rejected` holds the
    frames dropped by reason: the parser's (framing, checksum) and the feedback converter's
    (implausible content); `conversion` the converter's baseline and recovery events."""

    connected: bool
    connects: int
    disconnects: int
    frames_sent: int
    stops_sent: int
    command_timeouts: int
    write_errors: int
    read_errors: int
    feedback_frames: int
    undecodable: int
    queue_overflows: int
    rejected: dict[str, int]
    skipped_bytes: int
    conversion: dict[str, int]


class SparkBaseLink:
    """The host side of the Spark base serial protocol over pyserial."""

    def __init__(
        self,
        cfg: BaseConfig,
        calibration: OdometryCalibration,
        clock: Callable[[], float] = time.monotonic,
        serial_factory: SerialFactory = serial.Serial,
    ) -> None:
        self._cfg = cfg
        self._calibration = calibration
        self._clock = clock
        self._serial_factory = serial_factory
        self._parser = FrameParser(BASE_TO_HOST)
        self._converter = FeedbackConverter(calibration, cfg)
        self._incoming: deque[WheelIncrement] = deque()
        self._lock = threading.Lock()  # guards the port for writes and the command fields
        self._port: serial.Serial | None = None
        self._frame = STOP_FRAME
        self._command_time = -float("inf")
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._counts: Counter[str] = Counter()
        self._last_feedback_time: float | None = None
        self._feedback_since_connect = False
        self._reject_log_due = clock() + FIRST_REJECT_LOG_S
        self._rejects_logged: dict[str, int] = {}

    # --- called from the control loop ----------------------------------------------------------

    def open(self) -> None:
        """Open the port and start the I/O thread; a port that cannot be opened is a DeviceError."""
        try:
            self._connect()
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"base device {self._cfg.port}: cannot open: {_reason(exc)}") from None
        self._thread = threading.Thread(target=self._run, name="spark-base-io", daemon=True)
        self._thread.start()

    def set_command(self, twist: Twist, now: float) -> None:
        """Hand over the command to send until the next one; `now` stamps it for the timeout."""
        left, right = twist_to_wheel_ticks(
            twist.v,
            twist.omega,
            self._calibration.axle_length_m,
            self._calibration.m_per_tick,
            round(self._cfg.max_wheel_speed_m_s * 1000),
        )
        with self._lock:
            self._frame = wheel_speed_frame(left, right)
            self._command_time = now

    def poll(self) -> list[WheelIncrement]:
        """Every increment that arrived since the last call; never blocks."""
        out = []
        while self._incoming:
            out.append(self._incoming.popleft())
        return out

    @property
    def connected(self) -> bool:
        return self._port is not None

    @property
    def last_feedback_time(self) -> float | None:
        """Host time of the latest usable feedback frame (an increment or a new baseline);
        frames the converter rejects do not count as fresh."""
        return self._last_feedback_time

    def stats(self) -> LinkStats:
        c = self._counts
        return LinkStats(
            connected=self.connected,
            connects=c["connects"],
            disconnects=c["disconnects"],
            frames_sent=c["frames_sent"],
            stops_sent=c["stops_sent"],
            command_timeouts=c["command_timeouts"],
            write_errors=c["write_errors"],
            read_errors=c["read_errors"],
            feedback_frames=c["feedback_frames"],
            undecodable=c["undecodable"],
            queue_overflows=c["queue_overflows"],
            rejected=self._rejected(),
            skipped_bytes=self._parser.skipped_bytes,
            conversion=dict(self._converter.counts),
        )

    def close(self) -> None:
        """Send stop at once, stop the I/O thread, send stop again, close the port."""
        with self._lock:
            self._frame = STOP_FRAME
            self._command_time = -float("inf")
            self._write_locked(STOP_FRAME)
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self._lock:
            self._write_locked(STOP_FRAME)
            if self._port is not None:
                try:
                    self._port.flush()
                except (serial.SerialException, OSError):
                    pass  # the port is going away; the stop was already attempted and counted
                self._disconnect_locked("closed")

    # --- I/O thread ----------------------------------------------------------------------------

    def _connect(self) -> None:
        port = self._serial_factory(
            port=self._cfg.port,
            baudrate=self._cfg.baud,
            bytesize=serial.EIGHTBITS,
            parity=serial.PARITY_NONE,
            stopbits=serial.STOPBITS_ONE,
            timeout=0,
            write_timeout=0.1,
            exclusive=True,
        )
        port.reset_input_buffer()  # bytes queued before we opened belong to nobody
        self._parser.reset()
        self._feedback_since_connect = False
        with self._lock:
            self._port = port
            self._counts["connects"] += 1
            # A fresh connection starts stopped; the loop's next command takes over.
            self._write_locked(STOP_FRAME)
            self._write_locked(VENDOR_QUERY)
        log.info("base connected on %s", self._cfg.port)

    def _disconnect_locked(self, why: str) -> None:
        port, self._port = self._port, None
        if port is None:
            return
        self._counts["disconnects"] += 1
        if why != "closed":
            log.warning("base link on %s lost: %s; reconnecting", self._cfg.port, why)
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass  # closing a port that has vanished can fail; it is gone either way

    def _write_locked(self, frame: bytes) -> bool:
        if self._port is None:
            return False
        try:
            self._port.write(frame)
        except (serial.SerialException, OSError) as exc:
            self._counts["write_errors"] += 1
            self._disconnect_locked(f"write failed: {_reason(exc)}")
            return False
        self._counts["frames_sent"] += 1
        if frame == STOP_FRAME:
            self._counts["stops_sent"] += 1
        return True

    def _run(self) -> None:
        period = 1.0 / self._cfg.resend_hz
        next_write = self._clock()
        backoff = self._cfg.reconnect_min_s
        query_due = self._clock() + self._cfg.query_retry_s
        wellformed_next = True
        while not self._closing.is_set():
            if self._port is None:
                if self._closing.wait(backoff):
                    return
                try:
                    self._connect()
                except (serial.SerialException, OSError) as exc:
                    log.debug("reconnect to %s failed: %s", self._cfg.port, _reason(exc))
                    backoff = min(self._cfg.reconnect_max_s, backoff * 2.0)
                    continue
                backoff = self._cfg.reconnect_min_s
                query_due = self._clock() + self._cfg.query_retry_s
                wellformed_next = True
                next_write = self._clock()
            now = self._clock()
            if now >= next_write:
                self._send_command(now)
                next_write += period
                if next_write < now:  # fell behind (stall): resume the schedule from now
                    next_write = now + period
            if not self._feedback_since_connect and now >= query_due:
                query = WELLFORMED_QUERY if wellformed_next else VENDOR_QUERY
                with self._lock:
                    self._write_locked(query)
                log.info("no feedback on %s yet: sent the %s query", self._cfg.port,
                         "well-formed" if wellformed_next else "vendor")
                wellformed_next = not wellformed_next
                query_due = now + self._cfg.query_retry_s
            self._read(max(0.0, min(next_write - self._clock(), period)))

    def _send_command(self, now: float) -> None:
        with self._lock:
            frame = self._frame
            if now - self._command_time > self._cfg.command_timeout_s and frame != STOP_FRAME:
                if self._command_time > -float("inf"):
                    self._counts["command_timeouts"] += 1
                    log.warning("no command from the loop for %.0f ms: sending stop",
                                (now - self._command_time) * 1000)
                self._frame = frame = STOP_FRAME
            self._write_locked(frame)

    def _read(self, timeout: float) -> None:
        port = self._port
        if port is None:
            return
        try:
            readable, _, _ = select.select([port.fileno()], [], [], timeout)
            data = port.read(port.in_waiting or 1) if readable else b""
        except (serial.SerialException, OSError, TypeError, ValueError) as exc:
            # TypeError/ValueError: pyserial's fd went away under it (closed from another thread)
            with self._lock:
                self._disconnect_locked(f"read failed: {_reason(exc)}")
                self._counts["read_errors"] += 1
            return
        if not data:
            return
        t = self._clock()
        for frame in self._parser.feed(data):
            try:
                fb = decode_feedback(frame.payload)
            except ValueError:
                self._counts["undecodable"] += 1
                continue
            self._counts["feedback_frames"] += 1
            self._feedback_since_connect = True
            rebaselines = self._converter.counts["rebaseline"]
            inc = self._converter.convert(fb, t)
            if self._converter.usable:
                self._last_feedback_time = t
            if self._converter.counts["rebaseline"] > rebaselines:
                log.warning("base encoder counts restarted (base reboot?): odometry continues from"
                            " the new counts; the travel since the last good frame is lost")
            if inc is None:
                continue
            if len(self._incoming) >= FEEDBACK_QUEUE_LEN:
                self._incoming.popleft()
                self._counts["queue_overflows"] += 1
            self._incoming.append(inc)
        if t >= self._reject_log_due:
            self._log_rejects(t)

    def _rejected(self) -> dict[str, int]:
        return {**self._parser.rejected, **self._converter.rejected}

    def _log_rejects(self, now: float) -> None:
        """One line per interval for the feedback frames dropped since the last line, by reason
        (at 50 Hz a line per frame would flood the journal exactly when the link is bad)."""
        self._reject_log_due = now + REJECT_LOG_INTERVAL_S
        rejected = self._rejected()
        new = {k: n - self._rejects_logged.get(k, 0) for k, n in rejected.items()}
        self._rejects_logged = rejected
        if any(new.values()):
            events = sorted(self._converter.counts.items())
            log.warning("base feedback: frames dropped since the last report: %s (odometry so far:"
                        " %s)", ", ".join(f"{n} {k}" for k, n in new.items() if n),
                        ", ".join(f"{n} {k}" for k, n in events) or "no baseline yet")


def _reason(exc: BaseException) -> str:
    text = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
    return text.splitlines()[0]
