"""HIL: the real service process (`safemove run` with a control socket and no --goal) under
`safemove sim`, given a three-waypoint mission by the real `safemove mission` client and then a
goal that a `cancel` stops mid-way.

The world is the judge of arrival: at each 'arrived' event the simulator's ground truth must be
within the waypoint's tolerance (plus the odometry drift a few metres allow). The cancel is
judged by the ground truth too: the robot comes to a standstill; the time from the request to
standstill is printed (on this machine about 0.3-0.5 s: one cycle, then braking at
limits.decel_max from ≤ 0.3 m/s), and asserted only with a bound no loaded machine reaches.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from runtime.cli.control_client import ControlClient, Unreachable
from sim_stub.emulator_process import EmulatorProcess

pytestmark = pytest.mark.hil

# A 10 m room with four obstacles in view and nobody in it: arrival is about the mission,
# not the crowd (the planner's crowd behaviour has its own HIL tests).
ROOM = """
name: mission_room
description: "10 m room, four static obstacles, no people"
seed: 3
time_limit_s: 3600.0
area: {x_min: -5.0, x_max: 5.0, y_min: -5.0, y_max: 5.0}
robot:
  area: {x_min: -3.01, x_max: -2.99, y_min: -0.01, y_max: 0.01}
  heading_deg: 0.0
goals:
  - [4.0, 4.0]
crowd: {count: 0}
obstacles:
  - {type: box, center: [1.0, 0.0], size: [0.6, 1.4], yaw_deg: 0.0, height: 0.8}
  - {type: cylinder, center: [-1.0, 2.5], radius: 0.3, height: 1.0}
  - {type: cylinder, center: [-1.0, -2.5], radius: 0.3, height: 1.0}
  - {type: wall, start: [-4.8, -3.0], end: [-4.8, 3.0], thickness: 0.15, height: 2.0}
"""
WAYPOINTS = [(1.5, 0.0), (1.5, 1.2), (0.3, 0.6)]  # odom: the robot starts at 0, 0 facing +x
TOLERANCE_M = 0.2
DRIFT_M = 0.05  # odometry against ground truth over a few metres (tests/test_hil_drive.py)


def cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "runtime.cli.main", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, **kw)


def wait_running(sock: Path, proc: subprocess.Popen, log: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text()[-3000:]
        if sock.exists():
            try:
                with ControlClient(sock) as c:
                    if c.request("status")["status"].get("state") == "RUNNING":
                        return
            except Unreachable:
                pass
        time.sleep(0.2)
    raise AssertionError("service never RUNNING:\n" + log.read_text()[-3000:])


@pytest.mark.timeout(600)  # ~30 s idle each: start-up, a ~5 m mission, a goal and its cancel
@pytest.mark.parametrize("planner", ["dwa", "safemove"])
def test_service_takes_a_mission_and_a_cancel(tmp_path, planner):
    """The planner comes from the config (control.planner), as on the robot; safemove is the
    shipped policy."""
    scenario = tmp_path / "room.yaml"
    scenario.write_text(ROOM)
    sock = tmp_path / "control.sock"
    mission_file = tmp_path / "mission.yaml"
    mission_file.write_text("waypoints:\n" + "".join(
        f"  - {{x: {x}, y: {y}, tolerance: {TOLERANCE_M}}}\n" for x, y in WAYPOINTS))
    log = tmp_path / "service.err"
    with EmulatorProcess([str(scenario), "--fps", "15"], module="sim_stub.sim_server") as sim:
        with log.open("w") as err:
            service = subprocess.Popen(
                [sys.executable, "-m", "runtime.cli.main", "run",
                 "--set", f"control.planner={planner}", "--set", f"control.socket={sock}", "--set", f"base.port={sim.link}",
                 "--set", "depth.source=sim", "--set", f"depth.sim_socket={sim.depth_socket}",
                 "--set", "loop.stats_interval_s=5",
                 "--set", f"recorder.directory={tmp_path / 'rec'}",
                 # the replay below needs every cycle: a loaded machine must not drop one
                 "--set", "recorder.queue_cycles=10000"],
                stdout=subprocess.PIPE, stderr=err, text=True,
                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            wait_running(sock, service, log, 120.0)
            assert oct(sock.stat().st_mode & 0o777) == "0o660"

            # --- the mission, through the real client, judged by the world at each arrival
            client = cli("mission", str(mission_file), "--wait", "--json", "--socket", str(sock))
            assert client.stdout is not None
            accepted = json.loads(client.stdout.readline())
            assert accepted["ok"] and len(accepted["waypoints"]) == 3, accepted
            arrivals, finished = [], None
            for line in client.stdout:
                event = json.loads(line)
                if event["event"] == "arrived":
                    truth = sim.truth()
                    x, y = WAYPOINTS[event["waypoint"] - 1]
                    arrivals.append((event["waypoint"], round(truth["x"], 3),
                                     round(truth["y"], 3),
                                     round(((truth["x"] - x) ** 2 + (truth["y"] - y) ** 2) ** 0.5, 3)))
                elif event["event"] == "finished":
                    finished = event
            assert client.wait(timeout=30) == 0, (client.stderr.read(), arrivals, finished)
            print(f"HIL mission ({planner}) arrivals (waypoint, true x, true y, miss m):",
                  arrivals)
            assert [a[0] for a in arrivals] == [1, 2, 3]
            assert all(a[3] <= TOLERANCE_M + DRIFT_M for a in arrivals), arrivals
            assert finished is not None and finished["outcome"] == "reached"

            # --- a goal 2.5 m ahead, cancelled at speed
            goal = cli("goal", "2.5", "0", "--relative", "--json", "--socket", str(sock))
            out, errs = goal.communicate(timeout=30)
            assert goal.returncode == 0, errs
            gid = json.loads(out.splitlines()[-1])["goal_id"]
            deadline = time.monotonic() + 30.0
            while sim.truth()["v"] < 0.15:
                assert time.monotonic() < deadline, "the robot never got going"
                time.sleep(0.05)
            with ControlClient(sock) as c:
                asked = time.monotonic()
                answer = c.request("cancel")
                while abs((t := sim.truth())["v"]) > 0.005 or abs(t["omega"]) > 0.02:
                    assert time.monotonic() - asked < 10.0, "never stopped"
                    time.sleep(0.01)
                stopped_s = time.monotonic() - asked
            assert answer["ok"] and answer["cancelled"] == gid, answer
            print(f"HIL cancel ({planner}): request to standstill {stopped_s:.3f} s")
            assert stopped_s < 3.0  # braking from 0.3 m/s takes 0.3 s; this bounds a stuck loop

            status = cli("status", "--json", "--socket", str(sock))
            out, _ = status.communicate(timeout=30)
            state = json.loads(out.splitlines()[-1])
            assert state["state"] == "RUNNING" and state["mission"]["state"] == "idle"
            assert state["mission"]["last_outcome"]["outcome"] == "cancelled"
        finally:
            service.send_signal(signal.SIGTERM)
            out, _ = service.communicate(timeout=30)
    stderr = log.read_text()
    assert service.returncode == 0, stderr[-3000:]
    assert "Traceback" not in stderr
    assert not sock.exists()  # removed on the way out
    report = json.loads(out.strip().splitlines()[-1])
    assert report["job"]["outcomes"] == {"reached": 1, "cancelled": 1, "preempted": 0,
                                         "failed": 0}
    assert report["job"]["planner"] == planner
    # the flight recording of the whole service run replays bit for bit: the mission's
    # commands are applied at the cycles they were, the planners' budgets spent as they were
    from runtime.process.replay import replay

    [log] = (tmp_path / "rec").glob("safemove-*.mcap")
    replayed = replay(log)
    assert replayed["job"] == "mission" and replayed["cycles"] > 200
    assert replayed["differing_commands"] == 0, replayed
    assert f"mission request 1 from uid {os.getuid()} pid" in stderr  # SO_PEERCRED, logged
