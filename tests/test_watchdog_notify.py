"""systemd integration: READY=1 and WATCHDOG=1 reach a fake NOTIFY_SOCKET, and WATCHDOG=1 comes
only from healthy cycles, so a stalled loop is noticed (and restarted) by systemd."""

from __future__ import annotations

import socket
import threading
import time

import pytest
from doubles import FreshFeedbackLink

from runtime.config.settings import Calibration, Config
from runtime.process.loop import ControlLoop
from runtime.process.sdnotify import SystemdNotifier
from runtime.types import Odometry, Prepared, Twist

pytestmark = pytest.mark.hil


class NotifyListener:
    """A datagram socket standing in for systemd's notify socket; records (time, message)."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            self.messages.append((time.monotonic(), data.decode()))

    def times_of(self, line: str, since: float = 0.0, until: float = float("inf")) -> list[float]:
        return [t for t, m in self.messages if line in m.split("\n") and since <= t <= until]

    def wait_for(self, line: str, timeout: float = 10.0) -> float:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = self.times_of(line)
            if found:
                return found[0]
            time.sleep(0.01)
        raise AssertionError(f"{line!r} never arrived; got {[m for _, m in self.messages]}")

    def close(self) -> None:
        """Stop the reader, then take whatever is still queued (the last message, STOPPING=1,
        may have been sent a moment before)."""
        self._stop.set()
        self._thread.join()
        self.sock.setblocking(False)
        while True:
            try:
                data = self.sock.recv(4096)
            except BlockingIOError:
                break
            self.messages.append((time.monotonic(), data.decode()))
        self.sock.close()


class StallableJob:
    """Drives forward; blocks inside prepare() while `stall` is set, like a hung stage."""

    name = "stallable"
    finished = False

    def __init__(self) -> None:
        self.stall = threading.Event()
        self.release = threading.Event()

    def prepare(self, now: float, odom: Odometry, world: object = None) -> Prepared:
        if self.stall.is_set():
            self.release.wait()
        return Prepared(Twist(0.1, 0.0))

    def decide(self, prepared: Prepared, action: object = None) -> Twist:
        return prepared.context

    def pause(self) -> None:
        pass

    def summary(self) -> dict:
        return {}


def test_watchdog_stops_while_a_cycle_stalls_and_resumes_after(tmp_path):
    listener = NotifyListener(str(tmp_path / "notify.sock"))
    notifier = SystemdNotifier.from_environ(
        {"NOTIFY_SOCKET": listener.path, "WATCHDOG_USEC": "100000"}  # kick every 50 ms
    )
    job = StallableJob()
    loop = ControlLoop(Config(), Calibration(), FreshFeedbackLink(), job, notifier)
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    try:
        listener.wait_for("READY=1")
        time.sleep(0.5)
        healthy = listener.times_of("WATCHDOG=1")
        assert len(healthy) >= 5
        job.stall.set()
        time.sleep(0.1)  # let the cycle in flight reach the stall
        stalled_from = time.monotonic()
        time.sleep(0.6)
        stalled_until = time.monotonic()
        assert listener.times_of("WATCHDOG=1", stalled_from, stalled_until) == []
        job.stall.clear()
        job.release.set()
        time.sleep(0.4)
        assert len(listener.times_of("WATCHDOG=1", since=stalled_until)) >= 3
    finally:
        job.release.set()
        loop.request_stop("test over")
        thread.join(timeout=5)
        listener.close()
    assert not thread.is_alive()
    assert any("STOPPING=1" in m for _, m in listener.messages)


def test_real_process_notifies_ready_watchdog_and_stopping(tmp_path, emulator, safemove):
    listener = NotifyListener(str(tmp_path / "notify.sock"))
    try:
        run = safemove(
            ["drive", "--set", f"base.port={emulator.link}", "--twist", "0.1", "0",
             "--duration", "1.0"],
            env={"NOTIFY_SOCKET": listener.path, "WATCHDOG_USEC": "2000000"},
        )
        assert run.wait(timeout=20) == 0, run.stderr[-2000:]
    finally:
        listener.close()
    ready = listener.times_of("READY=1")
    kicks = listener.times_of("WATCHDOG=1")
    assert len(ready) == 1 and kicks and min(kicks) >= ready[0]
    statuses = [m for _, m in listener.messages if m.startswith("STATUS=") or "\nSTATUS=" in m]
    assert any("RUNNING" in s for s in statuses)
    assert "STOPPING=1" in listener.messages[-1][1]
