"""The control socket: a Unix stream socket served by one thread, never by the control cycle.

The cycle and the server meet only in a `ControlHandoff`: bounded deques (append and popleft
are atomic in CPython, so no lock is ever taken by the cycle) and a status snapshot the cycle
replaces by assignment. The server validates every request (control_protocol) before it is
handed over; the cycle applies at most `MAX_PENDING` of them between two cycles and answers
through the hand-off. What a client can cost is bounded per connection: a request line is at
most 64 KiB, replies it does not read are at most `MAX_OUTBOX_BYTES` (then it is dropped), and
it is read at most `REQUESTS_PER_S` requests a second (beyond that the server stops reading
it, so the kernel's socket buffer pushes back on the writer). A flooding, hostile or stuck
client therefore cannot delay a cycle, grow memory without bound, or reach the wheels.
"""

from __future__ import annotations

import errno
import logging
import os
import selectors
import socket
import stat
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from runtime.control.protocol import (
    CYCLE_TYPES,
    MAX_LINE_BYTES,
    VERSION,
    ProtocolError,
    Request,
    encode,
    parse_request,
    reply,
)
from runtime.errors import UserError

log = logging.getLogger("safemove.control")

MAX_PENDING = 8  # commands waiting for the cycle; more are refused as busy
MAX_OUTBOX_BYTES = 1 << 20  # unread replies and events per client before it is dropped
MAX_CLIENTS = 16
REQUESTS_PER_S = 100.0  # per client; the burst allowance is one second's worth
TOTAL_REQUESTS_PER_S = 300.0  # all clients together (reconnecting does not buy a new burst)
BYTES_PER_TOKEN = 4096  # a long line costs more: 1 token + 1 per 4 KiB
EOF_LINGER_S = 5.0  # a client that half-closed waits this long at most for its replies
LINES_PER_PASS = 8  # lines taken from one client before the others get their turn
SOCKET_MODE = 0o660  # the service's group may command the robot; others may not connect


@dataclass
class ControlHandoff:
    """Between the server thread and the control cycle. `commands`: (client, request) for the
    cycle; `outgoing`: (client or None for every client, message) for the server; `status`:
    the latest status message, replaced whole by the cycle."""

    commands: deque[tuple[int, Request]] = field(default_factory=deque)
    outgoing: deque[tuple[int | None, dict[str, Any]]] = field(
        default_factory=lambda: deque(maxlen=256))
    status: dict[str, Any] = field(default_factory=lambda: {"state": "INIT"})
    _wake_w: socket.socket | None = None

    def post(self, client: int | None, message: dict[str, Any]) -> None:
        """From the cycle: a reply to `client`, or an event for every client (None). Never
        blocks: when the server lags 256 messages behind, the oldest are dropped."""
        self.outgoing.append((client, message))
        if self._wake_w is not None:
            try:
                self._wake_w.send(b"\0")
            except OSError:  # the wake-up pipe is full: the server is awake anyway
                pass

    def post_event(self, event: dict[str, Any]) -> None:
        """From the cycle: an event for every client (MissionJob's `emit`)."""
        self.post(None, event)


@dataclass
class _Client:
    sock: socket.socket
    key: int
    peer: str
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)
    tokens: float = REQUESTS_PER_S
    refilled: float = 0.0
    subscribe_period: float | None = None
    next_status: float = 0.0
    closing: bool = False
    inflight: int = 0  # its commands handed to the cycle and not yet answered
    eof_at: float | None = None  # when it half-closed (shutdown(SHUT_WR), `nc -N`, socat)


def peer_credentials(sock: socket.socket) -> str:
    """'uid U pid P' of a Unix socket peer (SO_PEERCRED), for the log of every command."""
    try:
        pid, uid, _gid = struct.unpack("3i", sock.getsockopt(
            socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    except OSError:
        return "uid ? pid ?"
    return f"uid {uid} pid {pid}"


class ControlServer:
    """Serves the control socket at `path` from its own thread until `stop()`."""

    def __init__(self, path: Path, handoff: ControlHandoff, max_speed_limit: float) -> None:
        self.path = path
        self.handoff = handoff
        self._v_max = max_speed_limit
        self._sel = selectors.DefaultSelector()
        self._clients: dict[int, _Client] = {}
        self._next_key = 1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listener: socket.socket | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        self._flush_deadline = 0.0
        self._tokens = TOTAL_REQUESTS_PER_S
        self._refilled = time.monotonic()
        self.counts = {"clients": 0, "requests": 0, "refused": 0, "dropped_clients": 0}

    # --- life cycle ------------------------------------------------------------------------

    def start(self) -> None:
        """Bind (replacing a stale socket file, refusing a live one), then serve."""
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._clear_stale()
            # created with its mode: no moment in which the umask's mode lets others connect
            # (start-up runs before any other thread of this process creates files)
            umask = os.umask(0o777 & ~SOCKET_MODE)
            try:
                listener.bind(str(self.path))
            finally:
                os.umask(umask)
            os.chmod(self.path, SOCKET_MODE)
            listener.listen(MAX_CLIENTS)
        except OSError as exc:
            listener.close()
            raise UserError(f"control socket {self.path}: cannot listen: {exc.strerror or exc}"
                            " (control.socket)") from None
        listener.setblocking(False)
        self._listener = listener
        for s in (self._wake_r, self._wake_w):
            s.setblocking(False)
        self._sel.register(listener, selectors.EVENT_READ, None)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self.handoff._wake_w = self._wake_w
        self._thread = threading.Thread(target=self._serve, name="control-socket", daemon=True)
        self._thread.start()
        log.info("control socket listening at %s (mode %o)", self.path, SOCKET_MODE)

    def _clear_stale(self) -> None:
        try:
            mode = os.lstat(self.path).st_mode
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(mode):
            raise OSError(errno.EEXIST, "a file that is not a socket is in the way")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)  # a live server with a full backlog would block connect()
        try:
            probe.connect(str(self.path))
        except ConnectionRefusedError:  # nobody listens: left by a killed service
            os.unlink(self.path)
            return
        except OSError:
            return  # bind will say what is wrong
        finally:
            probe.close()
        raise OSError(errno.EADDRINUSE, "another process is serving it (a second safemove run?)")

    def stop(self, flush_s: float = 0.2) -> None:
        """Send what is queued (for up to `flush_s`), close every client, remove the socket."""
        self._flush_deadline = time.monotonic() + flush_s
        self._stop.set()
        self.handoff._wake_w = None
        try:
            self._wake_w.send(b"\0")
        except OSError:
            pass
        if self._thread is not None:
            self._thread.join(timeout=flush_s + 1.0)
        for c in list(self._clients.values()):
            self._close(c)
        if self._listener is not None:
            self._sel.unregister(self._listener)
            self._listener.close()
            try:
                os.unlink(self.path)
            except OSError:
                pass
        self._wake_r.close()
        self._wake_w.close()
        self._sel.close()

    # --- the thread --------------------------------------------------------------------------

    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                for key, events in self._sel.select(self._timeout(now)):
                    self._on_ready(key.fileobj, key.data, events)
                now = time.monotonic()
                self._deliver()
                self._publish_status(now)
                self._refill(now)
                for client in list(self._clients.values()):  # each client's turn, in order
                    if client.inbox.find(b"\n") >= 0:
                        self._take_lines(client)
            self._drain_before_exit()
        except Exception:  # the robot must keep running; the socket is gone, say so loudly
            log.exception("control socket server failed; goals can no longer be given")

    def _timeout(self, now: float) -> float:
        due = [c.next_status for c in self._clients.values() if c.subscribe_period]
        due += [c.refilled + 1.0 / REQUESTS_PER_S for c in self._clients.values() if c.tokens < 1]
        if self._tokens < 1:
            due.append(self._refilled + 1.0 / TOTAL_REQUESTS_PER_S)
        elif any(self._may_take(c) and c.inbox.find(b"\n") >= 0 for c in self._clients.values()):
            return 0.0  # lines are waiting for their turn
        return 0.25 if not due else min(0.25, max(0.0, min(due) - now))

    def _on_ready(self, sock: Any, client: _Client | None, events: int) -> None:
        if sock is self._listener:
            self._accept()
        elif sock is self._wake_r:
            try:
                while self._wake_r.recv(4096):
                    pass
            except BlockingIOError:
                pass
        elif client is not None:
            if events & selectors.EVENT_READ:
                self._read(client)
            if events & selectors.EVENT_WRITE and client.key in self._clients:
                self._write(client)

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()  # type: ignore[union-attr]
        except OSError:
            return
        sock.setblocking(False)
        peer = peer_credentials(sock)
        if len(self._clients) >= MAX_CLIENTS:
            self.counts["refused"] += 1
            log.warning("control: refused a client (%s): %d clients already", peer, MAX_CLIENTS)
            try:
                sock.send(encode(reply(None, False, f"too many clients ({MAX_CLIENTS})")))
            except OSError:
                pass
            sock.close()
            return
        client = _Client(sock, self._next_key, peer, refilled=time.monotonic())
        self._next_key += 1
        self._clients[client.key] = client
        self.counts["clients"] += 1
        self._sel.register(sock, selectors.EVENT_READ, client)
        self._send(client, {"v": VERSION, "type": "hello", "service": "safemove",
                            "planner": self.handoff.status.get("mission", {}).get("planner")})

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the client is done sending; its replies may still be on their way
            client.eof_at = time.monotonic()
            self._take_lines(client)
            self._finish_if_done(client)
            return
        client.inbox += data
        self._take_lines(client)

    def _may_take(self, client: _Client) -> bool:
        return client.tokens >= 1 and self._tokens >= 1 and not client.closing

    def _readable(self, client: _Client) -> bool:
        """Read more only when every complete line read so far has been handled: the inbox
        stays below one read plus one line."""
        return (self._may_take(client) and client.eof_at is None
                and client.inbox.find(b"\n") < 0)

    def _finish_if_done(self, client: _Client) -> None:
        """A half-closed client is closed once it has every reply it is owed."""
        if (client.eof_at is not None and client.key in self._clients and not client.outbox
                and client.inflight == 0 and client.inbox.find(b"\n") < 0):
            self._close(client)

    def _take_lines(self, client: _Client) -> None:
        """Complete lines, as far as the tokens and this pass's share allow; the rest waits
        in the inbox (read again next pass, or when the tokens refill)."""
        for _ in range(LINES_PER_PASS):
            if not self._may_take(client):
                break
            end = client.inbox.find(b"\n")
            if end < 0 or end > MAX_LINE_BYTES:
                break
            line = bytes(client.inbox[:end])
            del client.inbox[:end + 1]
            cost = 1 + len(line) // BYTES_PER_TOKEN
            client.tokens -= cost
            self._tokens -= cost
            if line.strip():
                self._request(client, line)
            time.sleep(0)  # hand the GIL to the control cycle if it is waiting for it
        end = client.inbox.find(b"\n")
        if not client.closing and (end > MAX_LINE_BYTES or (
                end < 0 and len(client.inbox) > MAX_LINE_BYTES)):
            self._refuse_and_close(client, f"request line longer than {MAX_LINE_BYTES} bytes")
            return
        if client.sock.fileno() >= 0:
            self._interest(client)  # stop reading it while its tokens are out

    def _request(self, client: _Client, line: bytes) -> None:
        self.counts["requests"] += 1
        try:
            req = parse_request(line, self._v_max)
        except ProtocolError as exc:
            self._send(client, reply(exc.request_id, False, str(exc)))
            return
        except Exception:  # a bug in validation: refuse the request, keep serving
            log.exception("control: validating a request from %s failed", client.peer)
            self._send(client, reply(None, False, "internal error validating the request"))
            return
        if req.type == "status":
            self._send(client, reply(req.id, status=self.handoff.status))
        elif req.type == "subscribe":
            client.subscribe_period = 1.0 / req.rate_hz
            client.next_status = time.monotonic()
            self._send(client, reply(req.id, rate_hz=req.rate_hz))
        elif req.type == "unsubscribe":
            client.subscribe_period = None
            self._send(client, reply(req.id))
        elif req.type in CYCLE_TYPES:
            if len(self.handoff.commands) >= MAX_PENDING:
                self._send(client, reply(req.id, False, "busy: too many commands waiting for"
                                         " the control cycle; retry"))
                return
            log.info("control: %s request %r from %s", req.type, req.id, client.peer)
            client.inflight += 1
            self.handoff.commands.append((client.key, req))

    def _refuse_and_close(self, client: _Client, why: str) -> None:
        log.warning("control: closing a client (%s): %s", client.peer, why)
        client.inbox.clear()
        client.closing = True  # before the reply: once it has left, _write closes the socket
        self._send(client, reply(None, False, why))

    def _send(self, client: _Client, message: dict[str, Any]) -> None:
        if client.sock.fileno() < 0:
            return
        client.outbox += encode(message)
        if len(client.outbox) > MAX_OUTBOX_BYTES:
            self.counts["dropped_clients"] += 1
            log.warning("control: dropping a client that does not read its replies (%s): %d"
                        " bytes unread", client.peer, len(client.outbox))
            self._close(client)
            return
        self._write(client)

    def _write(self, client: _Client) -> None:
        try:
            sent = client.sock.send(client.outbox)
        except BlockingIOError:
            sent = 0
        except OSError:
            self._close(client)
            return
        del client.outbox[:sent]
        if client.closing and not client.outbox:
            self._close(client)
            return
        self._finish_if_done(client)
        self._interest(client)

    def _interest(self, client: _Client) -> None:
        if client.sock.fileno() < 0:  # closed meanwhile (dropped, or its peer went away)
            return
        events = selectors.EVENT_WRITE if client.outbox else 0
        if self._readable(client):
            events |= selectors.EVENT_READ
        if events:
            self._sel.modify(client.sock, events, client) if self._registered(client) else \
                self._sel.register(client.sock, events, client)
        elif self._registered(client):
            self._sel.unregister(client.sock)

    def _registered(self, client: _Client) -> bool:
        try:
            self._sel.get_key(client.sock)
        except (KeyError, ValueError):  # ValueError: the socket is closed (fileno -1)
            return False
        return True

    def _close(self, client: _Client) -> None:
        """Idempotent; `closing` also ends `_take_lines` on what the client had sent."""
        self._clients.pop(client.key, None)
        client.closing = True
        if client.sock.fileno() < 0:
            return
        if self._registered(client):
            self._sel.unregister(client.sock)
        client.sock.close()

    def _deliver(self) -> None:
        """Replies and events the cycle posted."""
        out = self.handoff.outgoing
        while out:
            key, message = out.popleft()
            if key is not None and key in self._clients:
                owed = self._clients[key]
                owed.inflight = max(0, owed.inflight - 1)
            targets = self._clients.values() if key is None else (
                [self._clients[key]] if key in self._clients else [])
            for client in list(targets):
                self._send(client, message)

    def _publish_status(self, now: float) -> None:
        for client in list(self._clients.values()):
            if client.subscribe_period and now >= client.next_status:
                client.next_status = max(client.next_status + client.subscribe_period, now)
                self._send(client, {"v": VERSION, "type": "status", **self.handoff.status})

    def _refill(self, now: float) -> None:
        was_dry = self._tokens < 1
        self._tokens = min(TOTAL_REQUESTS_PER_S,
                           self._tokens + (now - self._refilled) * TOTAL_REQUESTS_PER_S)
        self._refilled = now
        for client in list(self._clients.values()):
            was_empty = client.tokens < 1 or was_dry
            client.tokens = min(REQUESTS_PER_S,
                                client.tokens + (now - client.refilled) * REQUESTS_PER_S)
            client.refilled = now
            if was_empty and self._may_take(client):
                self._interest(client)  # reading it again
            if client.eof_at is not None:
                if now - client.eof_at > EOF_LINGER_S:
                    self._close(client)
                else:
                    self._finish_if_done(client)

    def _drain_before_exit(self) -> None:
        """Last replies and events (a goal failed by the shutdown) reach their clients."""
        self._deliver()
        while (any(c.outbox for c in self._clients.values())
               and time.monotonic() < self._flush_deadline):
            for c in list(self._clients.values()):
                if c.outbox:
                    self._write(c)
            time.sleep(0.005)
