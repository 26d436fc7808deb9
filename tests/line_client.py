"""Unit-test client of the control socket (tests/test_control_server.py, test_control_fuzz.py):
raw lines out, JSON lines in, nothing checked on the way, so hostile input reaches the server
as sent. The CLI's own client is runtime.cli.control_client."""

from __future__ import annotations

import json
import socket
from pathlib import Path
from typing import Any

WAIT_S = 20.0  # the limit of every wait: generous, a wait ends as soon as its condition holds


class LineClient:
    """One blocking connection; `hello`: read and check the server's greeting first."""

    def __init__(self, path: Path, hello: bool = True) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(WAIT_S)
        self.sock.connect(str(path))
        self.buf = b""
        if hello:
            assert self.recv()["type"] == "hello"

    def send(self, message: dict[str, Any] | bytes) -> None:
        data = message if isinstance(message, bytes) else json.dumps(message).encode() + b"\n"
        self.sock.sendall(data)

    def recv_line(self) -> bytes | None:
        """One line, or None at the end of the stream (EOF or reset by the server)."""
        while b"\n" not in self.buf:
            try:
                data = self.sock.recv(65536)
            except ConnectionResetError:
                data = b""
            if not data:
                return None
            self.buf += data
        line, self.buf = self.buf.split(b"\n", 1)
        return line

    def recv(self) -> dict[str, Any]:
        line = self.recv_line()
        assert line is not None, "the server closed the connection"
        return json.loads(line)

    def until_reply(self, rid: Any) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
        """Every message until the reply to `rid` (None: the server closed the connection)."""
        seen = []
        while (line := self.recv_line()) is not None:
            message = json.loads(line)  # whatever the server sends is JSON
            if message.get("type") == "reply" and message.get("id") == rid:
                return message, seen
            seen.append(message)
        return None, seen

    def recv_reply(self, rid: Any) -> dict[str, Any]:
        """The reply to request `rid`, skipping status messages and events."""
        reply, _ = self.until_reply(rid)
        assert reply is not None, "the server closed the connection"
        return reply

    def request(self, message: dict[str, Any]) -> dict[str, Any]:
        self.send(message)
        return self.recv_reply(message.get("id"))

    def close(self) -> None:
        self.sock.close()
