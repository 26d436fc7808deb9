"""runtime.process.sdnotify against a real AF_UNIX datagram socket standing in for systemd."""

from __future__ import annotations

import logging
import os
import socket
import sys
import tempfile
from pathlib import Path

import pytest

from runtime.process.sdnotify import LOG_EVERY_N_ERRORS, SystemdNotifier

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="sd_notify (abstract sockets) is Linux-only"
)


@pytest.fixture
def fake_systemd(tmp_path):
    """A bound datagram socket like systemd's /run/systemd/notify; yields (path, recv)."""
    path = tmp_path / "notify.sock"
    if len(str(path)) > 100:  # AF_UNIX paths are limited to 107 bytes
        path = Path(tempfile.mkdtemp(prefix="sdn")) / "notify.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(path))
    server.settimeout(2.0)  # only guards against a hang if a message never comes

    def recv() -> bytes:
        return server.recv(4096)

    yield str(path), recv, server
    server.close()


def pending(server: socket.socket) -> list[bytes]:
    """Everything queued on the fake systemd socket right now, without waiting."""
    out = []
    server.setblocking(False)
    try:
        while True:
            out.append(server.recv(4096))
    except BlockingIOError:
        pass
    finally:
        server.settimeout(2.0)
    return out


def test_ready_status_watchdog_stopping_exact_bytes(fake_systemd):
    path, recv, _ = fake_systemd
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.socket_name == path

    assert n.ready("running at 20 Hz") is True
    assert recv() == b"READY=1\nSTATUS=running at 20 Hz"
    assert n.status("DEGRADED: depth stale") is True
    assert recv() == b"STATUS=DEGRADED: depth stale"
    assert n.watchdog() is True
    assert recv() == b"WATCHDOG=1"
    assert n.stopping("SIGTERM: stop frame sent") is True
    assert recv() == b"STOPPING=1\nSTATUS=SIGTERM: stop frame sent"
    assert n.stopping() is True
    assert recv() == b"STOPPING=1"
    assert n.send_errors == 0
    assert n.messages_sent == 5
    n.close()


def test_status_newlines_cannot_inject_assignments(fake_systemd):
    path, recv, _ = fake_systemd
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path})
    n.status("bad\nREADY=1")
    n.close()
    assert recv() == b"STATUS=bad READY=1"


def test_abstract_socket_name(tmp_path):
    name = f"safemove-test-{os.getpid()}-{tmp_path.name}"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind("\0" + name)
    server.settimeout(2.0)
    try:
        n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": "@" + name, "WATCHDOG_USEC": "2000000"})
        assert n.enabled
        assert n.socket_name == "@" + name
        assert n.ready("up")
        assert server.recv(4096) == b"READY=1\nSTATUS=up"
        assert n.kick_watchdog(10.0)
        assert server.recv(4096) == b"WATCHDOG=1"
        n.close()
    finally:
        server.close()


def test_watchdog_period_from_environ(fake_systemd):
    path, _, _ = fake_systemd
    n = SystemdNotifier.from_environ(
        {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}
    )
    assert n.watchdog_period_s == pytest.approx(2.0)


def test_watchdog_pid_of_another_process_disables_watchdog(fake_systemd):
    path, _, server = fake_systemd
    n = SystemdNotifier.from_environ(
        {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid() + 1)}
    )
    assert n.enabled  # READY/STATUS still go to systemd
    assert n.watchdog_period_s is None
    assert n.watchdog_due(100.0) is False
    assert n.kick_watchdog(100.0) is False
    assert pending(server) == []


@pytest.mark.parametrize("bad", ["abc", "0", "-5", "1.5"])
def test_bad_watchdog_usec_disables_watchdog_with_warning(fake_systemd, caplog, bad):
    path, _, _ = fake_systemd
    with caplog.at_level(logging.WARNING, logger="safemove.sdnotify"):
        n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": bad})
    assert n.watchdog_period_s is None
    assert "WATCHDOG_USEC" in caplog.text


def test_no_notify_socket_is_a_noop(caplog):
    with caplog.at_level(logging.DEBUG, logger="safemove.sdnotify"):
        n = SystemdNotifier.from_environ({"WATCHDOG_USEC": "2000000"})
        assert not n.enabled
        assert n.watchdog_period_s is None
        assert n.ready("x") is False
        assert n.status("x") is False
        assert n.watchdog() is False
        assert n.stopping("x") is False
        assert n.watchdog_due(0.0) is False
        assert n.kick_watchdog(0.0) is False
    assert n.send_errors == 0
    assert n.messages_sent == 0
    assert caplog.records == []


def test_empty_notify_socket_is_a_noop():
    assert not SystemdNotifier.from_environ({"NOTIFY_SOCKET": ""}).enabled


def test_relative_notify_socket_is_refused_with_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="safemove.sdnotify"):
        n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": "relative/notify"})
    assert not n.enabled
    assert "relative/notify" in caplog.text


def test_missing_socket_counts_and_logs_but_does_not_raise(tmp_path, caplog):
    missing = str(tmp_path / "gone.sock")
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": missing, "WATCHDOG_USEC": "2000000"})
    assert n.enabled
    with caplog.at_level(logging.WARNING, logger="safemove.sdnotify"):
        assert n.ready("up") is False
    assert n.send_errors == 1
    assert n.messages_sent == 0
    [rec] = [r for r in caplog.records if r.name == "safemove.sdnotify"]
    assert rec.levelno == logging.WARNING
    assert missing in rec.getMessage()
    assert "FileNotFoundError" in rec.getMessage() or "No such file" in rec.getMessage()

    # A failed ping does not move the schedule: the next cycle tries again.
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="safemove.sdnotify"):
        assert n.kick_watchdog(1.0) is False
        assert n.watchdog_due(1.05) is True
        for i in range(LOG_EVERY_N_ERRORS - 2):
            n.kick_watchdog(1.05 + i * 0.05)
    assert n.send_errors == LOG_EVERY_N_ERRORS
    # Errors 2..99 stay quiet; the 100th is logged again.
    msgs = [r.getMessage() for r in caplog.records if r.name == "safemove.sdnotify"]
    assert len(msgs) == 1
    assert f"({LOG_EVERY_N_ERRORS} failures so far)" in msgs[0]


def test_watchdog_due_at_half_period(fake_systemd):
    path, recv, server = fake_systemd
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
    assert n.watchdog_period_s == pytest.approx(2.0)

    # Before the first ping it is due at once.
    assert n.watchdog_due(100.0)
    assert n.kick_watchdog(100.0)
    assert recv() == b"WATCHDOG=1"

    # 20 Hz cycles: nothing until half the period (1 s) has passed.
    for k in range(1, 20):
        now = 100.0 + k * 0.05
        assert not n.watchdog_due(now), now
        assert not n.kick_watchdog(now)
    assert pending(server) == []

    assert n.watchdog_due(101.0)
    assert n.kick_watchdog(101.0)
    assert recv() == b"WATCHDOG=1"
    # The schedule restarts from the ping actually sent, even if it was late.
    assert n.kick_watchdog(102.3)
    assert recv() == b"WATCHDOG=1"
    assert not n.watchdog_due(103.29)
    assert n.watchdog_due(103.3)
    assert n.messages_sent == 3


def test_watchdog_without_watchdog_usec_is_never_due(fake_systemd):
    path, _, server = fake_systemd
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path})
    assert n.watchdog_period_s is None
    assert not n.watchdog_due(0.0)
    assert not n.kick_watchdog(1e9)
    assert pending(server) == []


def test_send_does_not_block_when_systemd_does_not_read(tmp_path):
    # A receiver that never reads: the queue fills and sendto must fail at once
    # (EAGAIN, counted) instead of blocking the control loop.
    path = str(tmp_path / "full.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    try:
        n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path})
        logging.getLogger("safemove.sdnotify").disabled = True
        try:
            for _ in range(5000):
                if not n.status("x" * 1000):
                    break
        finally:
            logging.getLogger("safemove.sdnotify").disabled = False
        assert n.send_errors >= 1
        n.close()
    finally:
        server.close()


def test_closed_notifier_counts_sends_as_errors(fake_systemd):
    path, _, _ = fake_systemd
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path})
    n.close()
    assert n.status("after close") is False
    assert n.send_errors == 1


def test_invalid_key_is_refused(fake_systemd):
    path, _, _ = fake_systemd
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": path})
    with pytest.raises(ValueError):
        n.notify({"A=B": "1"})
