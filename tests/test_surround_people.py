"""The pipeline with the simulator's ground-truth people sighting (`safemove eval
--surround-people`, sim_stub.surround_people): every person around reaches the world where the
truth has them, a malformed sighting is dropped and counted with the camera's tracks kept, and
DWA sees the person its camera cannot."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from runtime.config.settings import load_config
from runtime.geometry import into_frame
from runtime.jobs.dwa import DWAJob
from runtime.perception.people_sighting import PeopleSighting
from runtime.pipeline import Pipeline
from sim_stub.lockstep import LockstepEpisode
from sim_stub.view_clock import ViewClock


def _run(seed: int, surround: bool, until_s: float, alter=None, check=None):
    """DWA in paper_cal_d with the D435's frames, and every person around when `surround`;
    `alter(inp)` may replace a cycle's input, `check(ep, inp, pipeline)` looks after its step."""
    loaded = load_config(None, [])
    ep = LockstepEpisode("paper_cal_d", seed, loaded.config, loaded.calibration, 15.0, True,
                         surround_people=surround)
    pipeline = Pipeline(ep.config, loaded.calibration, DWAJob(ep.goal_odom, loaded.config, None))
    while ep.t < until_s and (inp := ep.cycle()) is not None:
        if alter is not None:
            inp = alter(inp)
        command = pipeline.step(inp).command
        if check is not None:
            check(ep, inp, pipeline)
        ep.send(command)
    return ep, pipeline


def test_every_person_around_reaches_the_world_where_the_truth_has_them():
    loaded = load_config(None, [])
    cam = loaded.calibration.camera.translation_m[:2]
    out_of_view = []

    def check(ep, inp, pipeline):
        if not inp.people:
            return
        sighted = inp.people[-1].ids.tolist()
        world = pipeline.world
        assert sorted(tr.id for tr in world.tracks) == sighted
        # the truth now (the sighting came with the frame, a little earlier), in base_link
        snap = ep.world.snapshot()
        x, y, th = snap.robot_pose
        dx, dy = into_frame(snap.agent_positions[:, 0] - x, snap.agent_positions[:, 1] - y, th)
        near = np.flatnonzero(np.hypot(dx, dy) - snap.agent_radii <= 4.0)
        assert set(sighted) ^ set(near.tolist()) <= set(np.flatnonzero(
            np.abs(np.hypot(dx, dy) - snap.agent_radii - 4.0) < 0.1).tolist())  # at the edge
        seen = ViewClock(cam, 87.0, 4.0, len(sighted)).in_view(
            tuple(snap.robot_pose), snap.agent_positions[sighted], snap.agent_radii[sighted])
        out_of_view.extend(np.array(sighted)[~seen].tolist())
        pose, ahead = pipeline.odom, inp.t - world.t
        for tr in world.tracks:
            ox, oy = tr.position + tr.velocity * ahead
            bx, by = into_frame(ox - pose.x, oy - pose.y, pose.theta)
            assert (bx, by) == pytest.approx((dx[tr.id], dy[tr.id]), abs=0.05)

    _run(1081, True, 6.0, check=check)
    assert out_of_view, "no one around was outside the camera's view: the test shows nothing"


def test_without_the_sighting_only_the_camera_tracks_people():
    def check(ep, inp, pipeline):
        assert inp.people == ()

    _run(1081, False, 1.0, check=check)


def test_a_malformed_sighting_is_dropped_and_counted_and_the_camera_tracks_stay():
    bad = PeopleSighting(0.0, np.array([[0.5, math.nan]]), np.zeros((1, 2)), np.full(1, 0.25),
                         np.arange(1))
    lies = []

    def lie(inp):
        if not inp.frames:
            return inp
        lies.append(inp.t)
        return replace(inp, people=(replace(bad, t=inp.t),))

    ep, pipeline = _run(1081, False, 7.0, alter=lie)
    assert pipeline.people_dropped == len(lies) > 0
    assert "not finite" in pipeline.people_dropped_why
    honest_ep, honest = _run(1081, False, 7.0)  # the camera alone: the same episode
    assert [(tr.id, tr.position.tolist()) for tr in pipeline.world.tracks] == [
        (tr.id, tr.position.tolist()) for tr in honest.world.tracks]
    assert pipeline.world.tracks, "no camera track to keep: the test shows nothing"
    assert ep.path_length_m == honest_ep.path_length_m > 1.0


def test_seeing_the_person_from_the_blind_side_keeps_dwa_clear_of_them():
    # paper_cal_d seed 1081: agent 5 crosses from the robot's right, out of the camera's view,
    # and walks into DWA's side at 7.7 s; seen all around, DWA gives way
    camera_only, _ = _run(1081, False, 10.0)
    assert camera_only.world.outcome.collided_with == "agent 5"
    surround, _ = _run(1081, True, 10.0)
    assert surround.world.outcome.status == "running" and surround.world.min_separation > 0.0
