"""The Spark base on a pseudo-terminal: the hardware stand-in for hardware-in-the-loop tests.

Runs `SparkBaseSim` in real time on the host's monotonic clock and speaks the base's wire
protocol on a pty, so the real host driver opens it like /dev/sparkBase. Control and events
are JSON lines on stdin/stdout (see `PtyBaseEmulator`); logs go to stderr.

    python -m sim_stub.base_emulator --link /tmp/sparkBase
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import math
import os
import random
import selectors
import signal
import sys
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from runtime.cli.args import finite_float
from sim_stub.base_sim import START_MODES, BasePhysics, Event, SparkBaseSim, noise_bytes

READ_CHUNK = 4096


class ControlError(Exception):
    """A control line the emulator cannot act on; answered with an error event."""


class PtyBaseEmulator:
    """Real-time loop around a `SparkBaseSim`, on a pty, driven by JSON lines on a control fd.

    Each tick (on absolute monotonic deadlines) steps the physics and writes one feedback frame
    while the base streams. Host bytes are read between ticks and stamped with
    `time.monotonic()` on arrival, so tests can compare them with times in other processes.
    A write that would block (no host reading) drops the frame rather than stall the loop.

    Control ops (stdin): truth, stats, noise{bytes}, drop{frames}, glitch{ticks},
    reopen{down_s}, quit. Events (stdout): ready, command, query, ignored, watchdog_stop,
    truth, stats, ack, closed, reopened, error.
    """

    def __init__(
        self,
        sim: SparkBaseSim,
        rate_hz: float = 50.0,
        link: Path | None = None,
        out: TextIO | None = None,
        seed: int = 0,
        on_tick: Callable[[float], None] | None = None,
        extra_ops: dict[str, Callable[[dict[str, Any], float], None]] | None = None,
    ) -> None:
        """`on_tick(now)` runs after each physics step (the simulator moves its world there);
        `extra_ops` adds control ops next to the emulator's own."""
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.sim = sim
        self.period_s = 1.0 / rate_hz
        self.link = link
        self.pty_path: str | None = None
        self.frames_sent = 0
        self.frames_dropped = 0  # the host was not reading: the write would have blocked
        self.frames_withheld = 0  # not sent on purpose (the drop op)
        self.overruns = 0
        self._out = out or sys.stdout
        self._rng = random.Random(seed)
        self._selector = selectors.PollSelector()  # poll, not epoll: stdin may be a plain file
        self._master: int | None = None
        self._slave: int | None = None
        self._pending = b""  # tail of a partial write, sent before anything else
        self._noise = b""
        self._withhold = 0
        self._reopen_at: float | None = None
        self._control_buf = b""
        self._exit_code: int | None = None
        self._parent_pid = os.getppid()
        self._ops: dict[str, Callable[[dict[str, Any], float], None]] = {
            "truth": self._op_truth,
            "stats": self._op_stats,
            "noise": self._op_noise,
            "drop": self._op_drop,
            "glitch": self._op_glitch,
            "reopen": self._op_reopen,
            "quit": self._op_quit,
            **(extra_ops or {}),
        }
        self._on_tick = on_tick
        self._emit_lock = threading.Lock()

    # --- main loop -------------------------------------------------------------------------

    def run(self, control_fd: int) -> int:
        """Open the pty, print the ready line and loop until quit or SIGTERM/SIGINT; return the
        exit code. Must run on the main thread (it installs signal handlers)."""
        wake_r, wake_w = os.pipe()
        os.set_blocking(wake_w, False)
        old_handlers = {sig: signal.signal(sig, self._on_signal) for sig in _EXIT_SIGNALS}
        old_wakeup = signal.set_wakeup_fd(wake_w)
        try:
            self._selector.register(wake_r, selectors.EVENT_READ, self._drain_wakeup)
            self._selector.register(control_fd, selectors.EVENT_READ, self._on_control)
            self._open_pty()
            self.emit({"event": "ready", "pty": self.pty_path, "link": _str(self.link),
                        "pid": os.getpid()})
            self._loop()
        finally:
            self._close_pty()
            signal.set_wakeup_fd(old_wakeup)
            for sig, handler in old_handlers.items():
                signal.signal(sig, handler)
            os.close(wake_r)
            os.close(wake_w)
            self._selector.close()
        return self._exit_code or 0

    def _loop(self) -> None:
        next_tick = time.monotonic() + self.period_s
        while self._exit_code is None:
            wake_at = min(next_tick, self._reopen_at if self._reopen_at is not None else math.inf)
            for key, _ in self._selector.select(max(0.0, wake_at - time.monotonic())):
                if key.fd in self._selector.get_map():  # a reopen may have closed it just now
                    key.data(key.fd)
            now = time.monotonic()
            if self._reopen_at is not None and now >= self._reopen_at:
                self._reopen(now)
            if now >= next_tick:
                self._tick(now)
                next_tick = self._next_deadline(next_tick, now)

    def _next_deadline(self, deadline: float, now: float) -> float:
        """Keep absolute deadlines (no drift); after missing a whole period, restart from now
        rather than burst frames to catch up."""
        if now - deadline >= self.period_s:
            self.overruns += 1
            return now + self.period_s
        return deadline + self.period_s

    def _tick(self, now: float) -> None:
        if os.getppid() != self._parent_pid:  # whoever started us died: don't linger orphaned
            print("base emulator: parent process gone, exiting", file=sys.stderr)
            self._exit_code = 1
            return
        self._advance(now)
        if self._on_tick is not None:
            self._on_tick(now)
        if self._master is None:
            return
        chunk, self._noise = self._noise, b""
        frame = self._next_frame()
        self._write(chunk + frame, has_frame=bool(frame))

    def _advance(self, now: float) -> None:
        """Bring the physics up to `now` before anything is read from or written to it."""
        self._emit_all(self.sim.step(max(0.0, now - self.sim.t)))

    def _on_signal(self, signum: int, _frame: object) -> None:
        print(f"base emulator: signal {signum}, exiting", file=sys.stderr)
        self._exit_code = 0

    def _drain_wakeup(self, fd: int) -> None:
        os.read(fd, READ_CHUNK)

    # --- pty -------------------------------------------------------------------------------

    def _open_pty(self) -> None:
        """New pty pair. The slave goes raw at once (echo or CR/LF translation would corrupt
        frames) and stays open here, so the master never sees EIO while no host is attached."""
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.pty_path = os.ttyname(slave)
        self._selector.register(master, selectors.EVENT_READ, self._on_pty_readable)
        self._update_link()

    def _close_pty(self) -> None:
        """Close both ends, like a USB unplug: the host's open port gets EIO/hangup."""
        if self._master is None or self._slave is None:
            return
        self._selector.unregister(self._master)
        os.close(self._master)
        os.close(self._slave)
        self._master = self._slave = None
        self._pending = b""
        self._remove_link()
        self.sim.reset_input()

    def _reopen(self, now: float) -> None:
        self._reopen_at = None
        self._open_pty()
        self.emit({"event": "reopened", "pty": self.pty_path, "link": _str(self.link), "t": now})

    def _update_link(self) -> None:
        """Point the stable link at the current pty atomically, as udev does for /dev/sparkBase."""
        if self.link is None or self.pty_path is None:
            return
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(self.pty_path, tmp)
        os.replace(tmp, self.link)

    def _remove_link(self) -> None:
        """Remove the link only while it still points at our pty (never someone else's)."""
        if self.link is None or not self.link.is_symlink():
            return
        if os.readlink(self.link) == self.pty_path:
            self.link.unlink()

    def _on_pty_readable(self, fd: int) -> None:
        try:
            data = os.read(fd, READ_CHUNK)
        except BlockingIOError:
            return
        except OSError as exc:
            print(f"base emulator: pty read failed: {exc}", file=sys.stderr)
            return
        now = time.monotonic()
        self._advance(now)
        self._emit_all(self.sim.receive(data, now))

    def _next_frame(self) -> bytes:
        if not self.sim.streaming:
            return b""
        if self._withhold > 0:
            self._withhold -= 1
            self.frames_withheld += 1
            return b""
        return self.sim.feedback_frame()

    def _write(self, chunk: bytes, has_frame: bool) -> None:
        """Send the tail of an earlier partial write first, so frames stay whole; if the host
        is not reading, drop the new frame instead of queueing stale ones."""
        if self._pending:
            self._pending = self._pending[self._write_some(self._pending) :]
        written = 0 if self._pending or not chunk else self._write_some(chunk)
        if written:
            self._pending = chunk[written:]
        if has_frame:
            if written:
                self.frames_sent += 1
            else:
                self.frames_dropped += 1

    def _write_some(self, data: bytes) -> int:
        assert self._master is not None
        try:
            return os.write(self._master, data)
        except BlockingIOError:
            return 0
        except OSError as exc:
            if exc.errno != errno.EIO:
                raise
            return 0

    # --- control ---------------------------------------------------------------------------

    def _on_control(self, fd: int) -> None:
        chunk = os.read(fd, READ_CHUNK)
        if not chunk:  # EOF: tests may close stdin; keep running until quit or a signal
            self._selector.unregister(fd)
            return
        self._control_buf += chunk
        *lines, self._control_buf = self._control_buf.split(b"\n")
        for line in lines:
            if line.strip():
                self.control(line.decode("utf-8", errors="replace"), time.monotonic())

    def control(self, line: str, now: float) -> None:
        """Act on one JSON control line; answer a bad one with an error event."""
        try:
            msg = json.loads(line)
            if not isinstance(msg, dict) or not isinstance(msg.get("op"), str):
                raise ControlError('a control line must be a JSON object with a string "op"')
            op = self._ops.get(msg["op"])
            if op is None:
                raise ControlError(f"unknown op {msg['op']!r}; known: {sorted(self._ops)}")
            op(msg, now)
        except (ControlError, json.JSONDecodeError) as exc:
            self.emit({"event": "error", "message": str(exc), "line": line.strip()})

    def _op_truth(self, _msg: dict[str, Any], now: float) -> None:
        self._advance(now)
        self.emit({"event": "truth", **self.sim.truth()})

    def _op_stats(self, _msg: dict[str, Any], now: float) -> None:
        self.emit({
            "event": "stats",
            "t": now,
            "frames_sent": self.frames_sent,
            "frames_dropped": self.frames_dropped,
            "frames_withheld": self.frames_withheld,
            "overruns": self.overruns,
            "streaming": self.sim.streaming,
            **self.sim.rx_stats(),
        })

    def _op_noise(self, msg: dict[str, Any], now: float) -> None:
        self._noise += noise_bytes(self._rng, _int_arg(msg, "bytes", 64, minimum=0))
        self._ack(msg, now)

    def _op_drop(self, msg: dict[str, Any], now: float) -> None:
        self._withhold += _int_arg(msg, "frames", 1, minimum=0)
        self._ack(msg, now)

    def _op_glitch(self, msg: dict[str, Any], now: float) -> None:
        self.sim.glitch_next_frame(_int_arg(msg, "ticks", 5000))
        self._ack(msg, now)

    def _op_reopen(self, msg: dict[str, Any], now: float) -> None:
        down_s = msg.get("down_s", 0.5)
        if isinstance(down_s, bool) or not isinstance(down_s, (int, float)) or not down_s >= 0:
            raise ControlError(f'"down_s" must be a number >= 0, got {down_s!r}')
        if self._master is None:
            raise ControlError("reopen: the port is already closed")
        self._close_pty()
        self.emit({"event": "closed", "t": now})
        self._reopen_at = now + float(down_s)

    def _op_quit(self, _msg: dict[str, Any], _now: float) -> None:
        self._exit_code = 0

    def _ack(self, msg: dict[str, Any], now: float) -> None:
        self.emit({"event": "ack", "op": msg["op"], "t": now})

    # --- output ----------------------------------------------------------------------------

    def _emit_all(self, events: list[Event]) -> None:
        for event in events:
            self.emit(event)

    def emit(self, event: Event) -> None:
        """One JSON line, flushed at once: tests read events while the emulator runs. Safe from
        other threads (the simulator's renderer reports from its own)."""
        try:
            with self._emit_lock:
                self._out.write(json.dumps(event) + "\n")
                self._out.flush()
        except BrokenPipeError:  # whoever read our events is gone: stop, don't run orphaned
            print("base emulator: stdout closed, exiting", file=sys.stderr)
            with contextlib.suppress(OSError, ValueError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), self._out.fileno())
            self._exit_code = 1


_EXIT_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def _int_arg(msg: dict[str, Any], key: str, default: int, minimum: int | None = None) -> int:
    value = msg.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ControlError(f"{key!r} must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        raise ControlError(f"{key!r} must be >= {minimum}, got {value}")
    return value


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)


# --- command line ------------------------------------------------------------------------------


def _positive_float(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _nonneg_float(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _u32(text: str) -> int:
    value = int(text, 0)
    if not 0 <= value <= 0xFFFFFFFF:
        raise argparse.ArgumentTypeError(f"must be a u32 (0 … 0xFFFFFFFF), got {text}")
    return value


def build_arg_parser() -> argparse.ArgumentParser:
    """Options of `safemove base-emulator`; physics defaults come from `BasePhysics`."""
    d = BasePhysics()
    p = argparse.ArgumentParser(
        prog="safemove base-emulator",
        description="Emulate the NXROBO Spark base on a pseudo-terminal (JSON lines on stdio).",
    )
    p.add_argument("--link", type=Path, help="stable symlink to the pty, like /dev/sparkBase")
    p.add_argument("--rate-hz", type=_positive_float, default=50.0, help="feedback rate (Hz)")
    p.add_argument("--watchdog-s", type=_nonneg_float, default=0.5,
                   help="stop when no wheel-speed frame for this long (s); 0 disables")
    p.add_argument("--start-mode", choices=START_MODES, default="stream",
                   help="when feedback starts: at power-on, after any query, or only after the "
                        "well-formed query")
    p.add_argument("--no-imu", action="store_true", help="send 25-byte frames without IMU")
    p.add_argument("--m-per-tick", type=_positive_float, default=d.m_per_tick,
                   help="true wheel travel per encoder tick (m)")
    p.add_argument("--axle-m", type=_positive_float, default=d.axle_m, help="true axle length (m)")
    p.add_argument("--swap-encoders", action="store_true",
                   help="physical left wheel on wire offset 10 instead of 14")
    p.add_argument("--max-accel", type=_positive_float, default=d.max_wheel_accel_m_s2,
                   help="per-wheel acceleration limit (m/s²)")
    p.add_argument("--gyro-bias", type=finite_float, default=d.gyro_bias_rad_s,
                   help="gyro z bias (rad/s)")
    p.add_argument("--encoder-noise", type=_nonneg_float, default=d.encoder_noise_ticks,
                   help="std-dev of noise on reported encoder counts (ticks)")
    p.add_argument("--encoder-start", type=_u32, default=d.encoder_start,
                   help="initial raw encoder counts (u32; 0x… accepted)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed for encoder noise and line noise")
    return p


def main(argv: list[str] | None = None) -> int:
    """CLI entry: build the model from the options and run the emulator until told to stop."""
    parser = build_arg_parser()
    args = parser.parse_args(argv)
    physics = BasePhysics(
        m_per_tick=args.m_per_tick,
        axle_m=args.axle_m,
        left_encoder_offset=10 if args.swap_encoders else 14,
        max_wheel_accel_m_s2=args.max_accel,
        gyro_bias_rad_s=args.gyro_bias,
        encoder_noise_ticks=args.encoder_noise,
        encoder_start=args.encoder_start,
        imu=not args.no_imu,
        seed=args.seed,
    )
    sim = SparkBaseSim(physics, args.start_mode, args.watchdog_s, t0=time.monotonic())
    emulator = PtyBaseEmulator(sim, args.rate_hz, args.link, seed=args.seed)
    try:
        return emulator.run(sys.stdin.fileno())
    except OSError as exc:
        print(f"base emulator: cannot run: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
