"""The control socket's command-line side: where the service listens, what the clients say and
return when the service cannot be reached or the input is wrong, and that the mission file is
checked as the service checks it. The service side is in test_control_server.py and
test_hil_mission.py."""

from __future__ import annotations

import json
import os
import socket
import tempfile
from pathlib import Path

import pytest

from runtime.cli.control_client import EXIT_REFUSED, EXIT_UNREACHABLE
from runtime.cli.main import main
from runtime.control.config import ControlConfig, control_socket_path


@pytest.fixture
def short_dir():
    """AF_UNIX paths must stay under 108 bytes; pytest's tmp_path can be longer."""
    with tempfile.TemporaryDirectory(dir="/tmp", prefix="sm-") as d:
        yield Path(d)


def test_socket_path_from_config_then_systemd_runtime_directory(monkeypatch):
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    assert control_socket_path(ControlConfig()) is None
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/safemove")
    assert control_socket_path(ControlConfig()) == Path("/run/safemove/control.sock")
    assert control_socket_path(ControlConfig(socket="/tmp/x.sock")) == Path("/tmp/x.sock")


def error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


@pytest.mark.parametrize("command", [["status"], ["cancel"], ["goal", "1", "2"]])
def test_no_service_is_one_line_and_exit_3(short_dir, capsys, command):
    code = main([*command, "--socket", str(short_dir / "none.sock")])
    assert code == EXIT_UNREACHABLE
    assert "not found (is the service running" in error_line(capsys)


def test_a_socket_nobody_listens_on_is_refused(short_dir, capsys):
    path = short_dir / "dead.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.close()  # the file stays, as after a killed service
    assert main(["status", "--socket", str(path)]) == EXIT_UNREACHABLE
    assert "connection refused" in error_line(capsys)


@pytest.mark.skipif(os.geteuid() == 0, reason="root is not refused by file modes")
def test_no_permission_names_the_group(short_dir, capsys):
    path = short_dir / "locked.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.listen(1)
    os.chmod(path, 0o600)
    os.chmod(short_dir, 0o100)  # enter, but the socket's mode does not matter: no write
    try:
        os.chmod(path, 0o000)
        assert main(["status", "--socket", str(path)]) == EXIT_UNREACHABLE
        assert "permission denied" in error_line(capsys)
    finally:
        os.chmod(short_dir, 0o700)
        s.close()


def test_a_socket_that_is_not_safemove_is_named(short_dir, capsys):
    import threading

    path = short_dir / "other.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(1)

    def speak() -> None:
        conn, _ = server.accept()
        conn.sendall(b'{"hello": "world"}\n')
        conn.close()

    t = threading.Thread(target=speak)
    t.start()
    assert main(["status", "--socket", str(path)]) == EXIT_UNREACHABLE
    t.join()
    server.close()
    assert "not a SafeMove control socket" in error_line(capsys)


@pytest.mark.parametrize("text, expected", [
    ("waypoints: []\n", "'waypoints' must be a list of 1 to 100"),
    ("waypoints:\n  - {x: 1.0}\n", "waypoint 1: 'y' is required"),
    ("waypoints:\n  - {x: 1, y: 2}\n  - {x: .nan, y: 0}\n", "waypoint 2: 'x' must be finite"),
    ("waypoints:\n  - {x: 1, y: 2, speed: 1}\n", "waypoint 1: unknown field 'speed'"),
    ("waypoints:\n  - {x: 1, y: 2}\nframe: map\n", "'frame' must be one of odom, relative"),
    ("waypoints:\n  - {x: 1, y: 2}\nloop: 1\n", "'loop' must be true or false"),
    ("- {x: 1, y: 2}\n", "a mission file is a mapping"),
    ("waypoints:\n  - {x: 1, y: 2}\n  - {x: 1, y: 2}\nwaypoints: []\n", "key 'waypoints' given twice"),
])
def test_mission_file_mistakes_are_one_line_naming_the_file(tmp_path, capsys, text, expected):
    path = tmp_path / "m.yaml"
    path.write_text(text)
    # checked before connecting: the socket does not exist, yet the answer is about the file
    assert main(["mission", str(path), "--socket", "/nonexistent/control.sock"]) == 2
    line = error_line(capsys)
    assert str(path) in line and expected in line, line


def test_goal_refuses_a_non_finite_number_before_sending(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["goal", "nan", "1", "--socket", "/nonexistent/control.sock"])
    assert exc.value.code == 2
    assert "must be finite" in capsys.readouterr().err


def test_run_with_a_planner_but_neither_goal_nor_socket_is_refused(capsys, monkeypatch):
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    code = main(["run", "--planner", "dwa", "--set", "depth.source=sim",
                 "--set", "depth.sim_socket=/tmp/none.sock"])
    assert code == 2
    assert "give --goal X Y (metres, odom frame), or a control socket" in error_line(capsys)


def test_run_refuses_a_socket_it_cannot_create_before_touching_the_base(capsys, monkeypatch):
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    code = main(["run", "--planner", "dwa", "--set", "control.socket=/nonexistent/dir/c.sock",
                 "--set", "depth.source=sim", "--set", "depth.sim_socket=/tmp/none.sock",
                 "--set", "base.port=/nonexistent/tty"])
    assert code == 2
    line = error_line(capsys)
    assert "control socket /nonexistent/dir/c.sock: cannot listen" in line, line


def test_a_refused_request_exits_1(short_dir, capsys):
    """The service's own refusal (here: pause with nothing to pause) is exit 1, its message
    printed; with a real server and a loop-less hand-off answered by a tiny thread."""
    import threading

    from runtime.control.protocol import reply
    from runtime.process.control_server import ControlHandoff, ControlServer

    handoff = ControlHandoff()
    server = ControlServer(short_dir / "c.sock", handoff, 0.3)
    server.start()
    stop = threading.Event()

    def cycle() -> None:  # what the control loop does with a command, minus the robot
        while not stop.is_set():
            while handoff.commands:
                client, request = handoff.commands.popleft()
                handoff.post(client, reply(request.id, False, "nothing to pause: idle"))
            stop.wait(0.01)

    t = threading.Thread(target=cycle)
    t.start()
    try:
        assert main(["pause", "--socket", str(short_dir / "c.sock")]) == EXIT_REFUSED
        assert "refused: nothing to pause: idle" in capsys.readouterr().out
    finally:
        stop.set()
        t.join()
        server.stop()


def test_status_follow_prints_each_status_until_interrupted(short_dir):
    """`status --follow --json`: a status line at the asked rate, events as they come; Ctrl-C
    ends it with exit 0."""
    import signal
    import subprocess
    import sys

    from runtime.process.control_server import ControlHandoff, ControlServer

    handoff = ControlHandoff()
    handoff.status = {"state": "RUNNING", "cycles": 1, "mission": {"state": "idle"}}
    server = ControlServer(short_dir / "c.sock", handoff, 0.3)
    server.start()
    # Ctrl-C as from a terminal: a test run started in the background (`pytest &`) hands its
    # children SIGINT ignored
    as_from_a_terminal = ("import runpy, signal; signal.signal(signal.SIGINT,"
                          " signal.default_int_handler); runpy.run_module('runtime.cli.main',"
                          " run_name='__main__')")
    proc = subprocess.Popen([sys.executable, "-c", as_from_a_terminal, "status", "--follow",
                             "--json", "--rate", "20", "--socket", str(short_dir / "c.sock")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        first = json.loads(proc.stdout.readline())
        assert first["type"] == "status" and first["state"] == "RUNNING"
        handoff.post_event({"v": 1, "type": "event", "event": "finished", "goal_id": 3,
                            "outcome": "reached", "reason": "all 1 waypoint(s) reached"})
        while (message := json.loads(proc.stdout.readline()))["type"] != "event":
            assert message["type"] == "status"
        assert message["goal_id"] == 3 and message["outcome"] == "reached"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
        server.stop()
