"""`safemove bench cycle`: the replayed recording's clock only advances, the synthesised wheel
travel is the recorded robot's, every cycle decides, and the targets' verdicts agree with their
figures. Behaviour only, never timing values."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from runtime.cli.main import main
from runtime.config.settings import load_config
from runtime.types import Twist
from sim_stub.bench_cycle import MOTION, STAGES, TARGETS, _replayed, _Wheels, bench_cycle
from sim_stub.lockstep import BASE_TICK_S
from sim_stub.recording import record, simulated_frames
from sim_stub.scenario import load_scenario
from sim_stub.world import World

pytest.importorskip("onnx")  # the random actor


def test_the_replay_repeats_the_recording_with_stamps_and_numbers_moving_on(tmp_path):
    loaded = load_config(None, [])
    path = tmp_path / "r.db3"
    frames = list(simulated_frames(load_scenario("paper_d"), 4, 30.0, Twist(0.2, 0.0),
                                   loaded.calibration.camera, loaded.config.limits))
    record(path, iter(frames), 30.0)
    replay = _replayed(path, 4, 30.0)
    played = [next(replay) for _ in range(10)]
    replay.close()
    assert [f.frame_number for f in played] == list(range(10))
    assert np.allclose([f.t for f in played], np.arange(10) / 30.0)
    for k, f in enumerate(played):
        assert np.array_equal(f.depth, frames[k % 4].depth)


def test_the_wheel_increments_move_as_the_recorded_robot_moved():
    """At 25 fps a frame spans two base ticks: the increments must add up to the world robot's
    travel and turn after each frame, its speed-up from rest included, and start from rest
    again at the next pass."""
    loaded = load_config(None, [])
    fps, frames = 25.0, 15  # the speed-up from rest takes 10 frames
    world = World(load_scenario("paper_d"), limits=loaded.config.limits)
    wheels = _Wheels(loaded, frames, fps)
    r = world.robot
    travel = turn = world_travel = world_turn = 0.0
    for k in range(1, frames):
        x, y, theta = r.x, r.y, r.theta
        world.step(1.0 / fps, MOTION.v, MOTION.omega)  # as simulated_frames moves it
        world_travel += math.hypot(r.x - x, r.y - y)
        world_turn += math.remainder(r.theta - theta, 2 * math.pi)
        for inc in wheels.until(k / fps):
            travel += 0.5 * (inc.d_left + inc.d_right)
            turn += (inc.d_right - inc.d_left) / loaded.calibration.odometry.axle_length_m
            assert inc.gyro_z * inc.dt == pytest.approx(
                (inc.d_right - inc.d_left) / loaded.calibration.odometry.axle_length_m)
        assert travel == pytest.approx(world_travel, rel=1e-4)
        assert turn == pytest.approx(world_turn, rel=1e-4)
    assert r.v == pytest.approx(MOTION.v)
    wheels.until(frames / fps)  # up to the seam
    first = wheels.until(frames / fps + BASE_TICK_S)[0]
    assert 0.5 * (first.d_left + first.d_right) == pytest.approx(
        loaded.config.limits.accel_max / fps * BASE_TICK_S)


def test_every_cycle_plans_and_decides_and_the_verdicts_follow_the_figures():
    result = bench_cycle(cycles=40, frames=6, model=None, startup_runs=0)
    assert result["bench"] == "cycle" and result["scenario"] == "paper_d"
    assert result["resolution"] == "848x480" and result["recorded_frames"] == 6
    assert result["cycles"] == result["decided"] == 40 and result["held"] == 0
    assert set(result["stage_ms"]) == set(STAGES)
    for stats in (result["cycle_ms"], *result["stage_ms"].values()):
        assert stats["p50"] <= stats["p99"] <= stats["max"]
    p99 = result["cycle_ms"]["p99"]
    assert result["cycle_p99_share_of_period"] == pytest.approx(
        p99 / result["control_period_ms"], abs=1e-4)
    assert "startup" not in result
    assert result["targets"] == {"cycle_p99_ms": {
        "value": p99, "target": TARGETS["cycle_p99_ms"], "met": p99 <= 5.0}}


@pytest.mark.hil  # starts `safemove sim` and the runtime
def test_the_cli_adds_start_up_with_its_targets(capsys):
    assert main(["bench", "cycle", "--cycles", "5", "--frames", "4", "--startup-runs", "1",
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    startup, targets = result["startup"], result["targets"]
    assert startup["runs"] == 1 and startup["planner"] == "safemove"
    ready, rss = startup["ready_s"]["median"], startup["rss_at_ready_mb"]["median"]
    assert targets["ready_s"] == {"value": ready, "target": 2.0, "met": ready <= 2.0}
    assert targets["rss_at_ready_mb"] == {"value": rss, "target": 200.0, "met": rss <= 200.0}
