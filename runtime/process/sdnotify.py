"""systemd readiness and watchdog notifications (sd_notify), written against the protocol.

Protocol (sd_notify(3)): systemd passes ``NOTIFY_SOCKET``, either a filesystem path or, when it
starts with ``@``, a Linux abstract socket name (the ``@`` stands for a leading NUL byte). Each
message is one AF_UNIX/SOCK_DGRAM datagram of newline-separated ``KEY=VALUE`` lines. With
``WatchdogSec=`` set, systemd also passes ``WATCHDOG_USEC`` (the period) and ``WATCHDOG_PID`` (the
process the watchdog is meant for); the service must send ``WATCHDOG=1`` more often than that.
We do not use the ``sdnotify`` package: it swallows send errors silently.

Design rule that callers follow:
    ``WATCHDOG=1`` is sent only from the control loop, after a healthy cycle, never from a
    keep-alive thread. A stalled or hung loop then stops the pings, and systemd kills and
    restarts the service. "Healthy" means the loop ran its cycle to the end and the safety state
    machine is alive (RUNNING or DEGRADED: braking while inputs are stale still counts, because
    that state recovers by itself); FAULT and STOPPED do not ping. The loop calls
    ``kick_watchdog(now)`` every cycle; it sends at half the watchdog period (every 1 s for
    ``WatchdogSec=2s``), not every 50 ms cycle.

systemd arms the watchdog when ``READY=1`` arrives, so a slow start (model warm-up, camera start)
is bounded by ``TimeoutStartSec=`` instead; send ``ready()`` only once the loop can run.

Sending never blocks the control loop: the socket is created once and is non-blocking. A failed
send is counted in ``send_errors`` and logged (the first failure, then every 100th) on the
``safemove.sdnotify`` logger, naming the socket and the OSError. Without ``NOTIFY_SOCKET``
(run by hand, in tests) every method is a cheap no-op and ``enabled`` is False.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

__all__ = ["SystemdNotifier"]

log = logging.getLogger("safemove.sdnotify")

#: After the first failed send, every this-many-th failure is logged again.
LOG_EVERY_N_ERRORS = 100


def _one_line(text: str) -> str:
    """A value must stay on its line: newlines would start a new KEY=VALUE assignment."""
    return " ".join(str(text).splitlines())


class SystemdNotifier:
    """Sends sd_notify messages to systemd; see the module docstring for the rules."""

    def __init__(
        self,
        notify_socket: str | None,
        watchdog_usec: int | None = None,
    ) -> None:
        """``notify_socket`` as in ``NOTIFY_SOCKET`` (path or ``@abstract``; None: disabled).

        ``watchdog_usec``: the watchdog period in microseconds for this process, or None.
        Prefer ``from_environ``, which also applies ``WATCHDOG_PID``.
        """
        self._display: str | None = None
        self._address: str | None = None
        self._sock: socket.socket | None = None
        self.send_errors = 0
        self.messages_sent = 0
        self._watchdog_period_s: float | None = None
        self._last_kick: float | None = None

        if notify_socket:
            if notify_socket.startswith("@"):
                self._address = "\0" + notify_socket[1:]
            elif notify_socket.startswith("/"):
                self._address = notify_socket
            else:
                log.warning(
                    "NOTIFY_SOCKET=%r is neither an absolute path nor an @abstract name: "
                    "systemd notifications disabled",
                    notify_socket,
                )
        if self._address is not None:
            self._display = notify_socket
            try:
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                sock.setblocking(False)
                self._sock = sock
            except OSError as exc:
                # Stay enabled so that every later send is counted as an error.
                self._record_error(exc, "creating the notify socket")

        if watchdog_usec is not None:
            if watchdog_usec <= 0:
                raise ValueError(f"watchdog_usec must be > 0, got {watchdog_usec}")
            self._watchdog_period_s = watchdog_usec / 1e6

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_environ(cls, environ: Mapping[str, str] = os.environ) -> SystemdNotifier:
        """Build from ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID``.

        An unparsable ``WATCHDOG_USEC``/``WATCHDOG_PID`` disables the watchdog with a warning.
        ``WATCHDOG_PID`` naming another process also disables it (the watchdog is not ours).
        """
        notify_socket = environ.get("NOTIFY_SOCKET") or None
        watchdog_usec: int | None = None
        raw_usec = environ.get("WATCHDOG_USEC")
        if raw_usec:
            try:
                watchdog_usec = int(raw_usec)
                if watchdog_usec <= 0:
                    raise ValueError("not positive")
            except ValueError:
                log.warning("ignoring WATCHDOG_USEC=%r: not a positive integer", raw_usec)
                watchdog_usec = None
        raw_pid = environ.get("WATCHDOG_PID")
        if watchdog_usec is not None and raw_pid:
            try:
                pid = int(raw_pid)
            except ValueError:
                log.warning("ignoring the watchdog: WATCHDOG_PID=%r is not a pid", raw_pid)
                watchdog_usec = None
            else:
                if pid != os.getpid():
                    watchdog_usec = None  # the watchdog is meant for another process
        return cls(notify_socket, watchdog_usec)

    # ------------------------------------------------------------------- properties
    @property
    def enabled(self) -> bool:
        """True when NOTIFY_SOCKET named a usable address (messages are attempted)."""
        return self._address is not None

    @property
    def socket_name(self) -> str | None:
        """The address as given in NOTIFY_SOCKET (``@name`` for abstract sockets)."""
        return self._display

    @property
    def watchdog_period_s(self) -> float | None:
        """WATCHDOG_USEC in seconds, or None when no watchdog is meant for this process."""
        if not self.enabled:
            return None
        return self._watchdog_period_s

    # ------------------------------------------------------------------- messages
    def notify(self, fields: Mapping[str, str]) -> bool:
        """Send one datagram of ``KEY=VALUE`` lines in the given order.

        Returns True when the datagram was sent, False when disabled or the send failed (the
        failure is counted and logged, never raised).
        """
        address = self._address
        if address is None:
            return False
        for key in fields:
            if not key or "=" in key or "\n" in key:
                raise ValueError(f"invalid sd_notify key {key!r}")
        payload = "\n".join(f"{k}={_one_line(v)}" for k, v in fields.items()).encode()
        return self._send(address, payload)

    def ready(self, status: str) -> bool:
        """READY=1 plus STATUS: startup is complete and the control loop is running."""
        return self.notify({"READY": "1", "STATUS": status})

    def status(self, text: str) -> bool:
        """STATUS=text (shown by ``systemctl status``)."""
        return self.notify({"STATUS": text})

    def watchdog(self) -> bool:
        """WATCHDOG=1 now. Call only from the control loop after a healthy cycle."""
        return self.notify({"WATCHDOG": "1"})

    def stopping(self, status: str | None = None) -> bool:
        """STOPPING=1 (plus STATUS when given): shutdown has begun."""
        fields = {"STOPPING": "1"}
        if status is not None:
            fields["STATUS"] = status
        return self.notify(fields)

    # ------------------------------------------------------------------- watchdog
    def watchdog_due(self, now: float) -> bool:
        """True when a watchdog is active and half its period has passed since the last ping.

        ``now`` is host monotonic seconds. Before the first ping it is always due.
        """
        period = self.watchdog_period_s
        if period is None:
            return False
        if self._last_kick is None:
            return True
        return now - self._last_kick >= period / 2.0

    def kick_watchdog(self, now: float) -> bool:
        """Send WATCHDOG=1 if due (see ``watchdog_due``); True when a ping was sent.

        A failed send does not move the schedule, so the next cycle tries again.
        """
        if not self.watchdog_due(now):
            return False
        if self.watchdog():
            self._last_kick = now
            return True
        return False

    # ------------------------------------------------------------------- lifecycle
    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __repr__(self) -> str:
        return (
            f"SystemdNotifier(socket={self._display!r}, "
            f"watchdog_period_s={self.watchdog_period_s!r}, send_errors={self.send_errors})"
        )

    # ------------------------------------------------------------------- internals
    def _send(self, address: str, payload: bytes) -> bool:
        sock = self._sock
        if sock is None:
            self._record_error(OSError("notify socket is closed or could not be created"))
            return False
        try:
            sock.sendto(payload, address)
        except OSError as exc:  # includes BlockingIOError: never wait on systemd
            self._record_error(exc)
            return False
        self.messages_sent += 1
        return True

    def _record_error(self, exc: OSError, what: str = "sending") -> None:
        self.send_errors += 1
        n = self.send_errors
        if n == 1 or n % LOG_EVERY_N_ERRORS == 0:
            log.warning(
                "sd_notify: %s to NOTIFY_SOCKET %s failed (%d failure%s so far): %r",
                what,
                self._display,
                n,
                "" if n == 1 else "s",
                exc,
            )
