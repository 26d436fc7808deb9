"""HIL: the real `safemove run --planner safemove` process driving `safemove sim` in scenario (b)
for 60 s, once with an exported, RANDOMLY INITIALISED actor (untrained: it proposes arbitrary
commands) and once with the shipped SafeMove policy. What is tested with the random actor is the
shield: whatever the actor says, the robot must not drive into anything the camera can see; the
shipped policy must also have no contact the sim puts at the robot's fault.

Real time is not deterministic (when each frame and command lands depends on the machine's
load), so instead of a deterministic setup the test judges only what the shield can be
responsible for. The sim judges every contact from ground truth at each base tick, also after
its first outcome has latched (sim_stub/world.py, `judge_contact`), and its `at_fault` is
broader than the shield: it blames a moving robot also for a person who was not coming at it,
at any bearing, e.g. one the robot's flank met while turning, or who walked in from outside the
camera's 87° view and was slowing as they touched it. A forward camera cannot see that, and a
robot already moving cannot always stop before a person walking in from outside its view at up
to 1 m/s reaches it.
So a contact fails the test when (`shields_to_prevent`):
- it is with a static obstacle while the robot moved (the robot drove into it: walls and boxes
  never come at it), or
- the robot moved and drove toward the person (its own speed toward them > 0.01 m/s) while
  their centre was inside the camera's field of view, ±43.5° at the camera (the camera sits
  0.094 m ahead of and 0.018 m left of the robot's centre: at contact range, 0.47 m from the
  centre, that is from 37° left to 34° right of the robot's heading), or
- the robot reversed into them: the shield never certifies reversing into space the camera has
  not seen (`shield.reverse_into_unseen` is off), and it sees nothing behind the robot.
A shield that lets the robot drive into a person in front of it, back into one, or drive into
an obstacle fails it. A person coming at a slow robot from outside the view does not.

The crowd is also made reactive (the people see the robot and avoid it, as the DWA HIL test's).
With scenario (b)'s shipped oblivious crowd, people walk into the robot whether it stands or
moves, and one standing at the edge of the view at contact range (33-38° from the robot's
heading) can be touched by a robot creeping at 0.04-0.10 m/s, some of them inside the view as
judged here: `safemove soak` measured about one per 10 real-time minutes before the shield's
and memory's fixes and one in the 40 minutes of the latest runs (README, "Long real-time
runs"), rates a 60 s test cannot tell from zero; that limit is measured there.
The scenario file is paper_b with its time limit raised, so the world does not time out inside
the 60 s run.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hil_judge import contacts, odom_goal

from drivers.depth_source import D435_848x480
from runtime.config.calibration import CameraMount
from sim_stub.emulator_process import EmulatorProcess
from sim_stub.scenario import load_scenario
from sim_stub.sim_server import contact_fields
from sim_stub.world import MOVING_SPEED_M_S, ROBOT_RADIUS_M, RobotState, judge_contact

pytestmark = pytest.mark.hil

RUN_S = 60.0
SCENARIOS = Path(__file__).resolve().parent.parent / "sim_stub" / "scenarios"
CAMERA = CameraMount()  # no calibration file is given: the sim renders and the runtime sees with it
HALF_VIEW_DEG = math.degrees(math.atan2(D435_848x480.cx, D435_848x480.fx))  # 43.5°


def bearing_at_camera(bearing_deg: float, distance_m: float) -> float:
    """Where a point at `bearing_deg` (0 ahead, + left) and `distance_m` from the robot's centre
    lies from the camera's optical axis, degrees."""
    b = math.radians(bearing_deg)
    x, y, _ = CAMERA.translation_m
    return math.degrees(math.atan2(distance_m * math.sin(b) - y,
                                   distance_m * math.cos(b) - x)) - CAMERA.rpy_deg[2]


def shields_to_prevent(contact: dict, person_radius_m: float) -> bool:
    """The robot drove into something it could see (the module's docs say why only that).
    The person's centre is taken at contact range, robot radius + theirs: contacts are judged
    at 50 Hz ticks, so the actual centre is at most a few cm closer, which only moves it
    further out of the view; the range used is the one that counts most contacts in."""
    if not contact["moving"]:
        return False
    if contact["bearing_deg"] is None:  # a static obstacle
        return True
    if contact["robot_closing"] <= MOVING_SPEED_M_S:
        return False
    if abs(contact["bearing_deg"]) > 90.0:  # closing on someone behind it: reversing
        return True
    at_camera = bearing_at_camera(contact["bearing_deg"], ROBOT_RADIUS_M + person_radius_m)
    return abs(at_camera) <= HALF_VIEW_DEG


def test_the_judge_blames_driving_into_what_the_camera_sees():
    """`shields_to_prevent` on contacts as the sim judges and reports them (no process)."""

    def contact(v: float, bearing_deg: float | None, person_v: tuple[float, float] = (0.0, 0.0)):
        robot = RobotState(0.0, 0.0, 0.0, v=v)
        if bearing_deg is None:
            return contact_fields(judge_contact(1.0, "obstacle 0", robot, None, np.zeros(2)))
        towards = np.array([math.cos(math.radians(bearing_deg)),
                            math.sin(math.radians(bearing_deg))])
        return contact_fields(judge_contact(1.0, "agent 0", robot, towards, np.array(person_v)))

    blamed = [
        contact(0.2, 0.0),  # drove at a person standing dead ahead
        contact(0.05, 30.0),  # crept into one standing in view, front left
        contact(0.2, -30.0, (-0.5, 0.0)),  # and one walking at it from in front, right
        contact(0.1, None),  # drove into an obstacle
        contact(-0.05, 170.0),  # backed into a person behind it
    ]
    spared = [
        contact(0.0, 0.0, (-0.8, 0.0)),  # a person walked into the standing robot
        contact(0.05, 40.0),  # at the edge of view: the sim blames the robot; 47° at the camera
        contact(0.05, -36.0),  # likewise on the right, -46° (the camera sits left of the centre)
        contact(0.1, 90.0),  # beside the robot: the robot was not closing on them
        contact(-0.05, 0.0),  # the robot was backing away from them
        contact(0.05, 160.0, (0.8, -0.3)),  # walked into its back as it crept forward
    ]
    assert all(shields_to_prevent(c, 0.3) for c in blamed), blamed
    assert not any(shields_to_prevent(c, 0.3) for c in spared), spared
    assert spared[1]["at_fault"] and spared[2]["at_fault"]


def random_actor(tmp_path: Path) -> Path:
    """A randomly initialised SafeMove-preset actor (400/300), exported as the CLI does."""
    torch = pytest.importorskip("torch")
    from export.checkpoint import load_checkpoint, save_actor_checkpoint
    from export.mlp import MLPActor
    from export.onnx_export import export_actor
    from runtime.policy.obs_spec import PRESETS
    from sim_stub.recorded_observations import recorded_observations

    spec = PRESETS["safemove"]
    torch.manual_seed(0)
    ckpt = tmp_path / "random_actor.pt"
    save_actor_checkpoint(ckpt, MLPActor([spec.size, 400, 300, 2]), spec,
                          "randomly initialised (untrained)")
    out = tmp_path / "random_actor.onnx"
    export_actor(load_checkpoint(ckpt, None), ckpt, out, recorded_observations(spec, 200),
                 "simulated run")
    return out


@pytest.mark.timeout(600)  # ~90 s idle (export, start-up, 60 s of real time, shut-down)
@pytest.mark.parametrize("actor", ["random", "shipped"])
def test_actor_drives_60_s_in_scenario_b_without_driving_into_what_it_sees(tmp_path, actor):
    """A random actor tests the shield alone; the shipped SafeMove policy (no --model: the
    service's default) must also have no contact the sim blames on the robot at all."""
    model = ["--model", str(random_actor(tmp_path))] if actor == "random" else []
    scenario = tmp_path / "paper_b_long.yaml"
    text = (SCENARIOS / "paper_b.yaml").read_text()
    scenario.write_text(text.replace("time_limit_s: 60.0", "time_limit_s: 600.0"))
    log_path = tmp_path / "run.err"
    with EmulatorProcess([str(scenario), "--fps", "15", "--crowd", "reactive"],
                         module="sim_stub.sim_server") as sim:
        event = next(e for e in sim.history if e.get("event") == "scenario")
        gx, gy = odom_goal(event)
        args = ["run", "--planner", "safemove", *model, "--goal", f"{gx}",
                f"{gy}", "--set", f"base.port={sim.link}", "--set", "depth.source=sim",
                "--set", f"depth.sim_socket={sim.depth_socket}",
                "--set", "loop.stats_interval_s=0"]
        with log_path.open("w") as err:
            proc = subprocess.Popen([sys.executable, "-m", "runtime.cli.main", *args],
                                    stdout=subprocess.PIPE, stderr=err, text=True,
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            started = None
            # start-up: model warm-up, base, first depth; ~5 s idle, the limit is for a hang
            deadline = time.monotonic() + 120.0
            while proc.poll() is None:
                now = time.monotonic()
                if started is None:
                    if "INIT -> RUNNING" in log_path.read_text():
                        started = now
                    elif now > deadline:
                        raise AssertionError("never RUNNING:\n" + log_path.read_text()[-3000:])
                elif now - started >= RUN_S + 0.5:
                    proc.send_signal(signal.SIGINT)
                    break
                time.sleep(0.1)
            stdout, _ = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        world = sim.request("world", "world")
        touched = contacts(sim)
    stderr = log_path.read_text()
    assert proc.returncode == 0, stderr[-3000:]
    person_radius = load_scenario(str(scenario)).crowd.radius
    its_fault = [c for c in touched if shields_to_prevent(c, person_radius)]
    report = json.loads(stdout.strip().splitlines()[-1])
    job = report["job"]
    first = {}
    for tr in report["transitions"]:
        first.setdefault(tr["to"], tr["t"])
    running_s = first["STOPPED"] - first["RUNNING"]  # RUNNING ⇄ DEGRADED in between counts
    summary = {"running_s": round(running_s, 1), "cycles": report["cycles"],
               "misses": report["misses"], "degraded_cycles": report["degraded_cycles"],
               "distance_m": round(report["odometry"]["distance"], 2),
               "shield_interventions": job["shield_interventions"],
               "dwa_inadmissible": job["dwa_inadmissible"], "contacts": len(touched),
               "moving_contacts": [c for c in touched if c["moving"]],
               "sim_at_fault": sum(c["at_fault"] for c in touched), "shields": len(its_fault),
               "min_gap_m": round(world["min_separation"], 3), "reached": job["reached"]}
    print(f"HIL safemove ({actor} actor):", json.dumps(summary))
    assert job["nonfinite_safe_stops"] == {}
    assert report["state"] == "STOPPED"
    assert running_s >= RUN_S or job["reached"], summary
    assert report["odometry"]["distance"] > 0.5, summary  # the actor did drive
    assert "Traceback" not in stderr, stderr[-3000:]
    assert not its_fault, {**summary, "contacts": touched}
    if actor == "random":
        assert job["policy"]["provenance"]["note"] == "randomly initialised (untrained)"
        assert sum(job["shield_interventions"].values()) > 0, summary  # the shield had work
    else:
        assert job["policy"]["variant"] == "safemove" and job["policy"]["training"]
        assert summary["sim_at_fault"] == 0, {**summary, "contacts": touched}
