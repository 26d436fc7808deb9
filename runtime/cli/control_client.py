"""A client of the service's control socket, for `safemove goal`, `mission`, `cancel`, `pause`,
`resume` and `status`.

Exit codes a script can use: 0 done (accepted; with --wait, reached), 1 the service refused the
request or the goal ended otherwise (failed, cancelled, pre-empted), 2 a mistake on the command
line or in the mission file, 3 the service cannot be reached (not running, no permission, not
answering, or it closed the connection).
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from runtime.control.protocol import MAX_LINE_BYTES, VERSION
from runtime.errors import UserError

DEFAULT_SOCKET = Path("/run/safemove/control.sock")
SOCKET_ENV = "SAFEMOVE_CONTROL_SOCKET"
REPLY_TIMEOUT_S = 5.0

EXIT_OK, EXIT_REFUSED, EXIT_USAGE, EXIT_UNREACHABLE = 0, 1, 2, 3


class Unreachable(UserError):
    """The service's socket cannot be used; one line, exit code 3."""

    exit_code = EXIT_UNREACHABLE


def default_socket() -> Path:
    return Path(os.environ.get(SOCKET_ENV) or DEFAULT_SOCKET)


class ControlClient:
    """One connection: requests with ids, replies matched to them, other messages queued."""

    def __init__(self, path: Path, timeout_s: float = REPLY_TIMEOUT_S) -> None:
        self.path = path
        self._timeout = timeout_s
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        self._buffer = b""
        self._pending: list[dict[str, Any]] = []
        self._next_id = 1
        try:
            self._sock.connect(str(path))
        except FileNotFoundError:
            raise Unreachable(f"control socket {path}: not found (is the service running,"
                              " and is this its control.socket?)") from None
        except PermissionError:
            raise Unreachable(f"control socket {path}: permission denied (only the service's"
                              " group may use it: add yourself to group safemove)") from None
        except ConnectionRefusedError:
            raise Unreachable(f"control socket {path}: connection refused (the service is not"
                              " running)") from None
        except OSError as exc:
            raise Unreachable(f"control socket {path}: {exc.strerror or exc}") from None
        hello = self.receive(timeout_s)
        if hello.get("type") != "hello" or hello.get("v") != VERSION:
            raise Unreachable(f"control socket {path}: not a SafeMove control socket of"
                              f" protocol version {VERSION} (it said {json.dumps(hello)[:80]})")
        self.hello = hello

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> ControlClient:  # noqa: PYI034 (the runtime supports 3.10)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def request(self, kind: str, **fields: Any) -> dict[str, Any]:
        """Send one request; its reply (other messages that arrive first are kept)."""
        rid = self._next_id
        self._next_id += 1
        line = json.dumps({"v": VERSION, "id": rid, "type": kind, **fields}) + "\n"
        try:
            self._sock.sendall(line.encode())
        except OSError as exc:
            raise Unreachable(f"control socket {self.path}: {exc.strerror or exc}") from None
        deadline = time.monotonic() + self._timeout
        while True:
            message = self._read(deadline)
            if message.get("type") == "reply" and message.get("id") in (rid, None):
                return message
            self._pending.append(message)

    def receive(self, timeout_s: float | None = None) -> dict[str, Any]:
        """The next message that is not a reply to a request (an event or a status);
        `timeout_s` None waits as long as it takes."""
        if self._pending:
            return self._pending.pop(0)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        return self._read(deadline)

    def messages(self) -> Iterator[dict[str, Any]]:
        """Events and status messages as they come, until the service closes."""
        while True:
            yield self.receive(None)

    def _read(self, deadline: float | None) -> dict[str, Any]:
        while b"\n" not in self._buffer:
            wait = None if deadline is None else deadline - time.monotonic()
            if wait is not None and wait <= 0:
                raise Unreachable(f"control socket {self.path}: no answer within"
                                  f" {self._timeout:g} s (is the service stuck?)")
            self._sock.settimeout(wait)
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
                continue
            except OSError as exc:
                raise Unreachable(f"control socket {self.path}: {exc.strerror or exc}") from None
            if not data:
                raise Unreachable(f"control socket {self.path}: the service closed the"
                                  " connection (did it stop?)")
            self._buffer += data
            if len(self._buffer) > 4 * MAX_LINE_BYTES and b"\n" not in self._buffer:
                raise Unreachable(f"control socket {self.path}: a message without end")
        line, _, self._buffer = self._buffer.partition(b"\n")
        try:
            message = json.loads(line)
        except ValueError:
            raise Unreachable(f"control socket {self.path}: not JSON: {line[:60]!r}") from None
        if not isinstance(message, dict):
            raise Unreachable(f"control socket {self.path}: not a JSON object: {line[:60]!r}")
        return message
