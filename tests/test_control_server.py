"""The control socket server (runtime.process.control_server) on a real Unix socket: replies,
routing, subscriptions, and what a malformed, flooding or hostile client can and cannot cost.

Nothing here asserts a duration: every wait is "until this happens, or fail after a generous
limit"."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from line_client import WAIT_S, LineClient

from runtime.control.protocol import encode, reply
from runtime.errors import UserError
from runtime.process.control_server import (
    MAX_CLIENTS,
    MAX_OUTBOX_BYTES,
    MAX_PENDING,
    ControlHandoff,
    ControlServer,
    peer_credentials,
)

V_MAX = 0.5

pytestmark = pytest.mark.timeout(120)


def wait_until(condition: Callable[[], object], what: str, limit: float = WAIT_S) -> None:
    deadline = time.monotonic() + limit
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {limit} s: {what}")
        time.sleep(0.005)


class RecordingServer(ControlServer):
    """Records the largest outbox any client ever had, right after each message was queued."""

    max_outbox = 0

    def _send(self, client: Any, message: dict[str, Any]) -> None:
        super()._send(client, message)
        self.max_outbox = max(self.max_outbox, len(client.outbox))


@pytest.fixture
def sock_dir() -> Iterator[Path]:
    """A short directory: AF_UNIX paths must be shorter than 108 bytes."""
    path = Path(tempfile.mkdtemp(prefix="sm-", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


class Served:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.handoff = ControlHandoff()
        self.server = RecordingServer(path, self.handoff, V_MAX)
        self.clients: list[LineClient] = []

    def connect(self, hello: bool = True) -> LineClient:
        c = LineClient(self.path, hello)
        self.clients.append(c)
        return c


@pytest.fixture
def served(sock_dir: Path) -> Iterator[Served]:
    s = Served(sock_dir / "control.sock")
    s.server.start()
    yield s
    for c in s.clients:
        c.close()
    s.server.stop()


def alive(s: Served) -> None:
    """The server still answers a new client."""
    c = s.connect()
    assert c.request({"id": "alive", "type": "status"})["ok"]
    c.close()


# --- requests and replies -------------------------------------------------------------------

def test_hello_on_connect(served):
    served.handoff.status = {"state": "RUNNING", "mission": {"planner": "dwa"}}
    c = served.connect(hello=False)
    assert c.recv() == {"v": 1, "type": "hello", "service": "safemove", "planner": "dwa"}


def test_status_is_answered_by_the_server(served):
    served.handoff.status = {"state": "RUNNING", "cycles": 12, "nan": float("nan")}
    c = served.connect()
    r = c.request({"id": 3, "type": "status"})
    assert r == {"v": 1, "type": "reply", "id": 3, "ok": True,
                 "status": {"state": "RUNNING", "cycles": 12, "nan": None}}
    assert list(served.handoff.commands) == []


def test_subscribe_delivers_status_until_unsubscribe(served):
    served.handoff.status = {"state": "RUNNING", "cycles": 0}
    c = served.connect()
    assert c.request({"id": "s", "type": "subscribe", "rate_hz": 20})["rate_hz"] == 20
    for _ in range(3):
        message = c.recv()
        assert message == {"v": 1, "type": "status", "state": "RUNNING", "cycles": 0}
    served.handoff.status = {"state": "RUNNING", "cycles": 1}  # the cycle replaces it
    while (message := c.recv())["cycles"] == 0:  # each message is the latest snapshot
        assert message["type"] == "status"
    assert message == {"v": 1, "type": "status", "state": "RUNNING", "cycles": 1}
    assert c.request({"id": "u", "type": "unsubscribe"})["ok"]
    c.send({"id": "after", "type": "status"})
    message = c.recv()  # nothing published after the unsubscribe reply
    assert message["type"] == "reply" and message["id"] == "after"


def test_a_goal_is_handed_to_the_cycle_and_its_reply_reaches_its_client_only(served):
    a, b = served.connect(), served.connect()
    a.send({"id": "a1", "type": "goal", "x": 1, "y": 2})
    wait_until(lambda: served.handoff.commands, "the goal reaches the hand-off")
    key, req = served.handoff.commands.popleft()
    assert req.type == "goal" and req.id == "a1" and req.waypoints[0].x == 1.0
    served.handoff.post(key, reply("a1", goal_id=1, state="navigating"))
    assert a.recv() == {"v": 1, "type": "reply", "id": "a1", "ok": True, "goal_id": 1,
                        "state": "navigating"}
    b.send({"id": "b1", "type": "status"})
    first = b.recv()  # the goal's reply never went to b
    assert first["type"] == "reply" and first["id"] == "b1"


def test_replies_are_routed_by_client_key(served):
    clients = [served.connect() for _ in range(3)]
    for i, c in enumerate(clients):
        c.send({"id": i, "type": "cancel"})
        wait_until(lambda n=i: len(served.handoff.commands) == n + 1, "the cancel arrives")
    keys = [key for key, _ in served.handoff.commands]
    assert len(set(keys)) == 3
    for key, req in reversed(list(served.handoff.commands)):
        served.handoff.post(key, reply(req.id, answered=req.id))
    for i, c in enumerate(clients):
        assert c.recv() == {"v": 1, "type": "reply", "id": i, "ok": True, "answered": i}


def test_a_reply_to_a_client_that_left_goes_nowhere(served):
    a = served.connect()
    a.send({"id": "x", "type": "cancel"})
    wait_until(lambda: served.handoff.commands, "the cancel arrives")
    key, _ = served.handoff.commands.popleft()
    a.close()
    served.handoff.post(key, reply("x"))
    alive(served)


def test_events_reach_every_client(served):
    clients = [served.connect() for _ in range(3)]
    event = {"v": 1, "type": "event", "event": "finished", "goal_id": 4, "outcome": "reached"}
    served.handoff.post(None, event)
    served.handoff.post_event({**event, "goal_id": 5})  # MissionJob's emit
    for c in clients:
        assert c.recv() == event
        assert c.recv() == {**event, "goal_id": 5}


def test_malformed_json_gets_an_error_and_the_connection_stays_usable(served):
    c = served.connect()
    c.send(b'{"type": "status", oops\n')
    r = c.recv()
    assert r["type"] == "reply" and r["ok"] is False and r["id"] is None
    assert r["error"].startswith("malformed JSON")
    c.send(b'{"id": 9, "type": "goal", "x": 1e999, "y": 0}\n')
    r = c.recv()
    assert r["id"] == 9 and not r["ok"] and "'x' must be finite" in r["error"]
    c.send(b"\n   \n")  # empty lines are skipped
    assert c.request({"id": "ok", "type": "status"})["ok"]
    assert list(served.handoff.commands) == []


def test_deeply_nested_json_is_refused_and_the_server_keeps_serving(served):
    c = served.connect()
    c.send(b"[" * 60000 + b"\n")
    r = c.recv()
    assert not r["ok"] and "nested deeper" in r["error"]
    c.send(b'{"id": 1, "type": "goal", "x": 1' + b"0" * 400 + b', "y": 0}\n')
    r = c.recv()
    assert r["id"] == 1 and "'x' must be finite" in r["error"]
    assert c.request({"id": "ok", "type": "status"})["ok"]
    alive(served)


def test_a_request_split_over_several_writes_is_one_request(served):
    c = served.connect()
    for part in (b'{"id": "sp', b'lit", "type"', b': "status"}', b"\n"):
        c.send(part)
        time.sleep(0.01)
    assert c.recv_reply("split")["ok"]


def test_a_line_over_64_kib_gets_an_error_and_is_closed_and_others_are_served(served):
    other = served.connect()
    c = served.connect()
    failure: list[BaseException] = []

    def flood() -> None:
        try:
            c.sock.sendall(b"x" * 10_000_000)  # no newline: 10 MB of one line
        except OSError as exc:  # the server closed the connection: broken pipe or reset
            failure.append(exc)

    writer = threading.Thread(target=flood, daemon=True)
    writer.start()
    r = c.recv()
    assert r["type"] == "reply" and not r["ok"] and "longer than 65536 bytes" in r["error"]
    assert c.recv_line() is None  # then the connection is closed
    writer.join(WAIT_S)
    assert not writer.is_alive() and failure
    wait_until(lambda: len(served.server._clients) == 1, "the closed client is forgotten")
    assert other.request({"id": "still", "type": "status"})["ok"]
    alive(served)


def test_a_complete_line_over_64_kib_is_refused_too(served):
    c = served.connect()
    c.send(b'{"type": "status", "pad": "' + b"a" * 70000 + b'"}\n')
    r = c.recv()
    assert not r["ok"] and "longer than 65536" in r["error"]
    assert c.recv_line() is None
    alive(served)


def test_a_client_that_never_reads_is_dropped_and_memory_stays_bounded(served):
    served.handoff.status = {"state": "RUNNING", "pad": "p" * 20000}
    one_reply = len(encode(reply("f", status=served.handoff.status)))
    reader = served.connect()
    flooder = served.connect()
    flooder.sock.setblocking(False)
    sent = 0
    try:
        while sent < 5000:  # requests until the server is no longer reading them
            flooder.sock.send(b'{"id": "f", "type": "status"}\n')
            sent += 1
    except (BlockingIOError, BrokenPipeError, ConnectionResetError):
        pass
    wait_until(lambda: served.server.counts["dropped_clients"] == 1, "the flooder is dropped")
    assert served.server.max_outbox <= MAX_OUTBOX_BYTES + one_reply
    wait_until(lambda: len(served.server._clients) == 1, "only the reader is left")
    assert all(len(c.outbox) <= MAX_OUTBOX_BYTES for c in served.server._clients.values())
    assert reader.request({"id": "r", "type": "status"})["ok"]


def test_more_than_max_pending_commands_are_refused_as_busy(served):
    c = served.connect()
    for i in range(MAX_PENDING + 3):
        c.send({"id": i, "type": "cancel"})
    busy = [c.recv() for _ in range(3)]  # nothing drains the hand-off: only the busy replies
    assert [r["id"] for r in busy] == [MAX_PENDING, MAX_PENDING + 1, MAX_PENDING + 2]
    assert all(not r["ok"] and r["error"].startswith("busy") for r in busy)
    assert [req.id for _, req in served.handoff.commands] == list(range(MAX_PENDING))
    served.handoff.commands.clear()
    c.send({"id": "later", "type": "cancel"})
    wait_until(lambda: served.handoff.commands, "a command is accepted again")


def test_a_client_beyond_the_limit_is_refused(served):
    clients = [served.connect() for _ in range(MAX_CLIENTS)]
    extra = LineClient(served.path, hello=False)
    r = extra.recv()
    assert r["type"] == "reply" and not r["ok"] and "too many clients (16)" in r["error"]
    assert extra.recv_line() is None
    extra.close()
    assert served.server.counts["refused"] == 1
    assert served.server.counts["clients"] == MAX_CLIENTS
    assert clients[-1].request({"id": "last", "type": "status"})["ok"]
    clients[0].close()
    wait_until(lambda: len(served.server._clients) == MAX_CLIENTS - 1, "the slot is free")
    alive(served)


def test_the_command_is_logged_with_the_peers_credentials(served, caplog):
    caplog.set_level(logging.INFO, logger="safemove.control")
    c = served.connect()
    c.send({"id": "cred", "type": "pause"})
    wait_until(lambda: served.handoff.commands, "the pause arrives")
    lines = [r.getMessage() for r in caplog.records if "pause request 'cred'" in r.getMessage()]
    assert len(lines) == 1
    assert f"uid {os.getuid()}" in lines[0] and f"pid {os.getpid()}" in lines[0]


def test_peer_credentials_of_a_socket_pair():
    a, b = socket.socketpair(socket.AF_UNIX)
    try:
        assert peer_credentials(a) == f"uid {os.getuid()} pid {os.getpid()}"
    finally:
        a.close()
        b.close()


# --- the socket file ------------------------------------------------------------------------

def test_a_stale_socket_file_is_replaced(sock_dir):
    path = sock_dir / "control.sock"
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(str(path))  # a killed service leaves its socket file behind
    dead.close()
    assert path.is_socket()
    s = Served(path)
    s.server.start()
    try:
        c = s.connect()
        assert c.request({"id": 1, "type": "status"})["ok"]
        assert path.stat().st_mode & 0o777 == 0o660
    finally:
        for c in s.clients:
            c.close()
        s.server.stop()
    assert not path.exists()


def test_a_live_socket_refuses_the_start(sock_dir):
    path = sock_dir / "control.sock"
    live = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    live.bind(str(path))
    live.listen(1)
    try:
        server = ControlServer(path, ControlHandoff(), V_MAX)
        with pytest.raises(UserError, match="another process is serving it"):
            server.start()
        server.stop()
        assert path.is_socket()  # the other service's socket is left alone
    finally:
        live.close()


def test_a_second_server_on_the_same_path_refuses_to_start(served):
    second = ControlServer(served.path, ControlHandoff(), V_MAX)
    with pytest.raises(UserError, match="cannot listen"):
        second.start()
    second.stop()
    alive(served)


def test_a_regular_file_in_the_way_refuses_the_start(sock_dir):
    path = sock_dir / "control.sock"
    path.write_text("not a socket")
    server = ControlServer(path, ControlHandoff(), V_MAX)
    with pytest.raises(UserError, match="not a socket"):
        server.start()
    server.stop()
    assert path.read_text() == "not a socket"


def test_a_missing_directory_refuses_the_start(sock_dir):
    server = ControlServer(sock_dir / "nowhere" / "control.sock", ControlHandoff(), V_MAX)
    with pytest.raises(UserError, match="control.socket"):
        server.start()
    server.stop()


def test_stop_flushes_queued_events_and_removes_the_socket_file(sock_dir):
    s = Served(sock_dir / "control.sock")
    s.server.start()
    c = s.connect()
    s.handoff.post(None, {"v": 1, "type": "event", "event": "finished", "outcome": "failed"})
    s.server.stop()
    assert not s.path.exists()
    assert c.recv()["event"] == "finished"
    assert c.recv_line() is None
    c.close()
    assert s.server._thread is not None and not s.server._thread.is_alive()


def test_a_live_socket_with_a_full_backlog_refuses_the_start_instead_of_hanging(sock_dir):
    path = sock_dir / "control.sock"
    live = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    live.bind(str(path))
    live.listen(0)  # never accepts: its backlog fills
    waiting = []
    try:
        for _ in range(8):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.setblocking(False)
            waiting.append(s)
            try:
                s.connect(str(path))
            except BlockingIOError:  # the backlog is full: a blocking connect would wait
                break
        else:
            pytest.skip("the kernel never reported a full backlog")
        server = ControlServer(path, ControlHandoff(), V_MAX)
        with pytest.raises(UserError, match="cannot listen"):
            server.start()
        server.stop()
        assert path.is_socket()
    finally:
        for s in waiting:
            s.close()
        live.close()


# --- half-closing clients, fairness, the socket's mode ----------------------------------------

def test_a_client_that_half_closes_still_gets_the_cycles_reply(served):
    """`nc -N`, `socat` and scripts shut down their sending side after the request: the reply
    from the control cycle must still reach them, then the server closes."""
    c = served.connect()
    c.send({"id": "g", "type": "goal", "x": 1, "y": 0})
    c.sock.shutdown(socket.SHUT_WR)
    wait_until(lambda: served.handoff.commands, "the goal reaches the hand-off")
    wait_until(lambda: all(cl.eof_at is not None for cl in served.server._clients.values()),
               "the server sees the end of the client's input")
    key, req = served.handoff.commands.popleft()
    served.handoff.post(key, reply(req.id, goal_id=7))
    assert c.recv()["goal_id"] == 7
    assert c.recv_line() is None  # then closed by the server
    alive(served)


def test_a_flood_from_several_clients_does_not_starve_a_polite_one(served):
    flooders = [served.connect() for _ in range(3)]
    for f in flooders:
        f.send(b'{"type":"status"}\n' * 3000)
    polite = served.connect()
    assert polite.request({"id": "me", "type": "status"})["ok"]
    for f in flooders:  # they are served too, just no faster than the limits
        assert f.recv()["type"] == "reply"


def test_the_socket_is_created_for_the_group_only(served):
    assert oct(served.path.stat().st_mode & 0o777) == "0o660"
