"""HIL: the real `safemove drive` process with depth from `safemove sim` and odometry from its
emulated base, both over real links (a pty and a Unix socket)."""

from __future__ import annotations

import pytest
from fault_run import empty_room

from sim_stub.emulator_process import EmulatorProcess

pytestmark = pytest.mark.hil



def sim_args(sim, *extra: str) -> list[str]:
    return [
        "drive", "--set", f"base.port={sim.link}", "--set", "depth.source=sim",
        "--set", f"depth.sim_socket={sim.depth_socket}", "--set", "loop.stats_interval_s=0",
        *extra,
    ]


@pytest.fixture
def sim_without_people(tmp_path):
    with EmulatorProcess([str(empty_room(tmp_path)), "--fps", "15", "--log-depth"],
                         module="sim_stub.sim_server") as proc:
        yield proc


def test_depth_and_odometry_together_for_10_s_with_no_frame_lost(sim_without_people, safemove):
    sim = sim_without_people
    run = safemove(sim_args(sim, "--twist", "0.1", "0.2", "--duration", "10"))
    assert run.wait(timeout=40) == 0, run.stderr[-3000:]
    report = run.report()
    sim.wait_for("depth_client_closed", timeout_s=5)
    truth = sim.truth()
    depth = report["depth"]
    received = report["link"]["depth_source"]
    # ~10.5 s at 15 fps; the renderer skips ahead rather than queue when the machine is loaded,
    # so the count is a sanity bound, and the gap count is what proves nothing was lost
    assert depth["frames"] >= 75
    assert depth["gaps"] == 0 and depth["missing"] == 0
    # the loop took every frame the link received, bar at most one in flight when it stopped
    assert received["frames"] - 1 <= depth["frames"] <= received["frames"]
    # what the link received is, byte for byte and in order, what the sim rendered from its
    # ground truth and sent: the sim's running digest after that many frames equals ours
    sent = {e["frames"]: e["digest"] for e in sim.history if e.get("event") == "depth_sent"}
    assert sent[received["frames"]] == received["digest"]
    # both inputs stayed fresh the whole run: never DEGRADED
    assert report["degraded_cycles"] == 0
    assert [t["to"] for t in report["transitions"]] == ["RUNNING", "STOPPED"]
    # and odometry agrees with the emulated base's ground truth
    assert report["odometry"]["distance"] > 0.9
    assert report["odometry"]["x"] == pytest.approx(truth["x"], abs=0.01)
    assert report["odometry"]["y"] == pytest.approx(truth["y"], abs=0.01)


def test_missing_sim_depth_socket_refuses_to_start(emulator, safemove, tmp_path):
    run = safemove(["drive", "--set", f"base.port={emulator.link}", "--set", "depth.source=sim",
                    "--set", f"depth.sim_socket={tmp_path / 'none.sock'}",
                    "--twist", "0", "0", "--duration", "1"])
    assert run.wait(timeout=15) == 2
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("safemove: error: sim depth link") and "none.sock" in last
    assert "Traceback" not in run.stderr
    # the base was opened first and must have been left stopped
    assert emulator.request("stats", "stats")["commands_received"] >= 1


def test_absent_d435_refuses_to_start_with_a_clear_message(emulator, safemove):
    run = safemove(["drive", "--set", f"base.port={emulator.link}", "--set", "depth.source=d435",
                    "--twist", "0", "0", "--duration", "1"])
    assert run.wait(timeout=30) == 2
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("safemove: error: D435") and "Traceback" not in run.stderr


def test_the_readme_main_command_runs(safemove):
    """`safemove demo`: the runtime drives the simulated robot to the scenario's goal."""
    run = safemove(["demo", "--set", "loop.stats_interval_s=0"])
    assert run.wait(timeout=120) == 0, run.stderr[-3000:]
    report = run.report()
    assert report["state"] == "STOPPED" and report["reason"] == "job finished"
    assert report["job"]["reached"] and report["world"]["status"] == "success"
    assert report["depth"]["frames"] > 300 and report["depth"]["gaps"] == 0
    # ~7 m driven: the fused odometry stays within a few centimetres of the base's truth
    assert report["odometry"]["x"] == pytest.approx(report["truth"]["x"], abs=0.05)
    assert report["odometry"]["y"] == pytest.approx(report["truth"]["y"], abs=0.05)
