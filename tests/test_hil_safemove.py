"""HIL: the real `safemove run --planner safemove` process with an exported, RANDOMLY INITIALISED
actor (untrained: it proposes arbitrary commands) driving `safemove sim` in scenario (b) for 60 s.
What is tested is the shield: no collision may be the robot's fault, whatever the actor says.

The crowd is made reactive (the people see the robot and avoid it, as the DWA HIL test's). With
scenario (b)'s shipped oblivious crowd, people walk into the robot whether it stands or moves,
and one standing or walking slowly at the edge of the camera's view at contact range (33-38°
from the robot's heading: outside the 87° view, or inside its 0.17 m minimum range) can be
touched by a robot creeping at 0.04-0.10 m/s: `safemove soak` measured about one such at-fault
contact per 10 real-time minutes (README, "Long real-time runs"), so a 60 s run with that crowd
would fail by chance, not by a defect of the process under test. That limit is measured there.
The sim judges every contact from ground truth at each base tick, also after its first outcome
has latched, and says who was at fault (sim_stub/world.py): the robot is, if it moved and either
drove into the person (toward them, within ±45° of its heading) or the person was not coming at
it. The scenario file is paper_b with its time limit raised, so the world does not time out
inside the 60 s run.
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
from hil_judge import contacts, odom_goal

from sim_stub.emulator_process import EmulatorProcess

pytestmark = pytest.mark.hil

RUN_S = 60.0
SCENARIOS = Path(__file__).resolve().parent.parent / "sim_stub" / "scenarios"


def random_actor(tmp_path: Path) -> Path:
    """A randomly initialised SafeMove-preset actor (400/300), exported as the CLI does."""
    torch = pytest.importorskip("torch")
    from export.checkpoint import load_checkpoint, save_actor_checkpoint
    from export.mlp import MLPActor
    from export.onnx_export import export_actor
    from runtime.obs_spec import PRESETS
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


def test_random_actor_drives_60_s_in_scenario_b_with_no_collision_at_fault(tmp_path):
    model = random_actor(tmp_path)
    scenario = tmp_path / "paper_b_long.yaml"
    text = (SCENARIOS / "paper_b.yaml").read_text()
    scenario.write_text(text.replace("time_limit_s: 60.0", "time_limit_s: 600.0"))
    log_path = tmp_path / "run.err"
    with EmulatorProcess([str(scenario), "--fps", "15", "--crowd", "reactive"],
                         module="sim_stub.sim_server") as sim:
        event = next(e for e in sim.history if e.get("event") == "scenario")
        gx, gy = odom_goal(event)
        args = ["run", "--planner", "safemove", "--model", str(model), "--goal", f"{gx}",
                f"{gy}", "--set", f"base.port={sim.link}", "--set", "depth.source=sim",
                "--set", f"depth.sim_socket={sim.depth_socket}",
                "--set", "loop.stats_interval_s=0"]
        with log_path.open("w") as err:
            proc = subprocess.Popen([sys.executable, "-m", "runtime.cli", *args],
                                    stdout=subprocess.PIPE, stderr=err, text=True,
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            started = None
            deadline = time.monotonic() + 30.0  # start-up: model warm-up, base, first depth
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
            stdout, _ = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        world = sim.request("world", "world")
        touched = contacts(sim)
    stderr = log_path.read_text()
    assert proc.returncode == 0, stderr[-3000:]
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
               "min_gap_m": round(world["min_separation"], 3), "reached": job["reached"]}
    print("HIL safemove (randomly initialised actor):", json.dumps(summary))
    assert job["policy"]["provenance"]["note"] == "randomly initialised (untrained)"
    assert job["nonfinite_safe_stops"] == {}
    assert report["state"] == "STOPPED"
    assert running_s >= RUN_S or job["reached"], summary
    assert report["odometry"]["distance"] > 0.5, summary  # the actor did drive
    assert sum(job["shield_interventions"].values()) > 0, summary  # the shield had work
    assert not [c for c in touched if c["at_fault"]], {**summary, "contacts": touched}
