"""HIL: the real `safemove run --planner safemove` process with an exported, RANDOMLY INITIALISED
actor (untrained: it proposes arbitrary commands) driving `safemove sim` in scenario (b) for 60 s.
What is tested is the shield: no collision may be the robot's fault, whatever the actor says.

The sim judges from ground truth but latches its first outcome, and in scenario (b) the crowd is
oblivious, so a person may walk into the robot while it stands (not its fault) and hide what
follows. So this test also judges every contact itself, polling the sim's ground truth at
~10 Hz (a contact lasts ~1 s at the crowd's speeds): a contact is the robot's fault when the
robot moves at it (|v| > the sim's 0.01 m/s), as the sim judges. The scenario file is paper_b
with its time limit raised, so the world does not time out inside the 60 s run.

Every check is strict except the last: at-fault contacts end the test as an expected failure
(with the contacts in the reason) while the blind-side problem (issue 6) is open.
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
from hil_judge import ContactJudge, odom_goal

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
    judge = ContactJudge(scenario)
    log_path = tmp_path / "run.err"
    with EmulatorProcess([str(scenario), "--fps", "15"], module="sim_stub.sim_server") as sim:
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
                else:
                    judge.poll(sim, now - started)
                    if now - started >= RUN_S + 0.5:
                        proc.send_signal(signal.SIGINT)
                        break
                time.sleep(0.1)
            stdout, _ = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        outcomes = [e for e in sim.history if e.get("event") == "outcome"]
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
               "dwa_inadmissible": job["dwa_inadmissible"], "contacts": judge.contacts,
               "polls": judge.polls, "min_gap_m": round(judge.min_gap, 3),
               "sim_outcomes": [{k: e.get(k) for k in ("status", "collided_with", "at_fault")}
                                for e in outcomes],
               "reached": job["reached"]}
    print("HIL safemove (randomly initialised actor):", json.dumps(summary))
    assert job["policy"]["provenance"]["note"] == "randomly initialised (untrained)"
    assert job["nonfinite_safe_stops"] == {}
    assert report["state"] == "STOPPED"
    assert running_s >= RUN_S or job["reached"], summary
    assert judge.polls >= 10 * RUN_S * 0.5, summary  # the judge really watched
    assert report["odometry"]["distance"] > 0.5, summary  # the actor did drive
    assert isinstance(job["shield_interventions"], dict)
    at_fault = [c for c in judge.contacts if c["at_fault"]] + [
        e for e in outcomes if e.get("status") == "collision" and e.get("at_fault")]
    if at_fault:  # everything above must hold; this part is the known open problem
        pytest.xfail(
            f"known, open (issue 6): {len(at_fault)} contacts while the robot moved (the sim's"
            f" at-fault rule; bearing 0° = ahead, the camera sees ±43.5°): {at_fault}")
