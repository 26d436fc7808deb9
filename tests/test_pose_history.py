"""A depth frame is placed from where the robot was at its stamp, not where it is when the loop
gets to it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.depth_source import D435_848x480
from runtime.config.settings import CameraMount, Config
from runtime.odometry.pose_history import PoseHistory
from runtime.perception.world_model import WorldModel
from runtime.types import DepthFrame, Odometry
from sim_stub.depth_render import DepthRenderer, Scene, wall
from sim_stub.sim_server import BASE_LINK_HEIGHT_M


def test_interpolates_between_the_poses_around_a_stamp_across_the_angle_wrap():
    h = PoseHistory(span_s=1.0)
    latest = Odometry(t=0.2, x=0.2, theta=-3.1)
    assert h.at(0.1, latest) is latest  # no history yet
    h.add(Odometry(t=0.0, x=0.0, y=0.0, theta=3.1))
    h.add(Odometry(t=0.1, x=0.1, y=0.02, theta=-3.1))  # turned left across +pi
    mid = h.at(0.05, latest)
    assert (mid.x, mid.y) == pytest.approx((0.05, 0.01))
    assert abs(mid.theta) == pytest.approx(math.pi, abs=1e-9)
    assert h.at(-1.0, latest).t == 0.0  # older than the span: the oldest pose
    assert h.at(5.0, latest).t == 0.1  # newer than any: the newest
    assert h.at(float("nan"), latest) is latest


def test_keeps_only_its_span():
    h = PoseHistory(span_s=0.5)
    for k in range(100):
        h.add(Odometry(t=0.02 * k, x=0.01 * k))
    assert h.at(0.0, Odometry()).t >= 1.98 - 0.5 - 0.02


def test_world_model_places_points_from_the_pose_at_the_frame_stamp():
    """The robot drove 0.1 m since the frame: a wall 2.2 m ahead in the frame is 2.1 m ahead
    now (placed from the current pose instead, it would stay 2.2 m ahead: 10 cm too far)."""
    mount = CameraMount()
    depth = DepthRenderer(D435_848x480, mount, base_z=BASE_LINK_HEIGHT_M).render(
        (0.0, 0.0, 0.0), Scene(boxes=[wall(2.2, -1.5, 2.2, 1.5)]))
    frame = DepthFrame(depth, 0.0, 0, D435_848x480)
    then, now = Odometry(t=0.0), Odometry(t=0.08, x=0.1)
    placed = WorldModel(Config(), mount).update(frame, now, seen_from=then)
    naive = WorldModel(Config(), mount).update(frame, now)
    ahead = np.abs(placed.points_base[:, 1]) < 0.3
    assert np.median(placed.points_base[ahead, 0]) == pytest.approx(2.05, abs=0.03)  # its face
    assert np.median(placed.points_base[ahead, 0]) + 0.09 < np.median(
        naive.points_base[np.abs(naive.points_base[:, 1]) < 0.3, 0])
