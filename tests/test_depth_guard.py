"""Depth frames that cannot be trusted never reach the world model, and a camera that returns
nothing usable is never read as free space."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivers.depth_source import D435_848x480
from runtime.config.settings import CameraMount, Config
from runtime.perception.depth_guard import DepthGuard
from runtime.perception.world_model import WorldModel
from runtime.types import DepthFrame, Odometry
from sim_stub.depth_render import DepthRenderer, Scene, wall
from sim_stub.sim_server import BASE_LINK_HEIGHT_M


def frame(t: float, number: int = 0, fill: int = 1000) -> DepthFrame:
    k = D435_848x480
    return DepthFrame(np.full((k.height, k.width), fill, dtype=np.uint16), t, number, k)


def test_good_frames_are_admitted_in_order():
    guard = DepthGuard(max_future_s=0.1)
    assert guard.admit(frame(10.0, 0), now=10.05)
    assert guard.admit(frame(10.0, 1), now=10.1)  # same stamp: not backwards
    assert guard.admit(frame(10.2, 2), now=10.15)  # 50 ms ahead: within tolerance
    assert not guard.rejected


@pytest.mark.parametrize(
    ("t", "kind", "logged"),
    [(float("nan"), "bad_stamp", "stamp nan is not a time"),
     (float("inf"), "bad_stamp", "stamp inf is not a time"),
     (10.0 + 3600.0, "clock_jump", "+3600.000 s ahead of the host clock"),
     (10.0 - 3600.0, "clock_jump", "before the previous frame")],
    ids=["nan", "inf", "plus-hour", "minus-hour"],
)
def test_bad_stamps_are_dropped_counted_and_logged_once(caplog, t, kind, logged):
    guard = DepthGuard(max_future_s=0.1)
    assert guard.admit(frame(9.95, 0), now=10.0)
    caplog.set_level("WARNING", logger="safemove.depth")
    assert not guard.admit(frame(t, 1), now=10.0)
    assert not guard.admit(frame(t, 2), now=10.0)
    assert guard.rejected == {kind: 2}
    assert guard.last_t == 9.95  # the clock downstream never saw them
    dropped = [r.getMessage() for r in caplog.records]
    assert len(dropped) == 1 and logged in dropped[0] and "frame 1" in dropped[0]
    assert guard.admit(frame(10.0, 3), now=10.05)
    assert "admitted again" in caplog.records[-1].getMessage()


@pytest.mark.parametrize(
    ("change", "kind"),
    [({"intrinsics": dataclasses.replace(D435_848x480, fx=float("nan"))}, "bad_intrinsics"),
     ({"intrinsics": dataclasses.replace(D435_848x480, depth_unit_m=0.0)}, "bad_intrinsics"),
     ({"depth": np.zeros((480, 847), dtype=np.uint16)}, "bad_image"),
     ({"depth": np.zeros((480, 848), dtype=np.float32)}, "bad_image")],
    ids=["nan-fx", "zero-unit", "shape", "dtype"],
)
def test_malformed_frames_are_dropped(change, kind):
    guard = DepthGuard(max_future_s=0.1)
    assert not guard.admit(dataclasses.replace(frame(1.0), **change), now=1.0)
    assert guard.rejected == {kind: 1}


def test_saturated_and_blind_frames_are_unknown_not_free_and_keep_obstacle_memory():
    """All 65535 (beyond any range the camera gives) or all 0: no bin is free, nothing is
    cleared, and the frame says how little of it was valid."""
    cfg = Config()
    mount = CameraMount()
    renderer = DepthRenderer(D435_848x480, mount, base_z=BASE_LINK_HEIGHT_M)
    model = WorldModel(cfg, mount)
    still = Odometry()
    seen = renderer.render((0.0, 0.0, 0.0), Scene(boxes=[wall(2.2, -1.5, 2.2, 1.5)]))
    k = D435_848x480
    before = model.update(DepthFrame(seen, 0.0, 0, k), still)
    assert before.valid_fraction > 0.5 and len(before.points_base) > 20
    for n, fill in enumerate((0xFFFF, 0), start=1):
        after = model.update(frame(0.1 * n, n, fill), still)
        assert after.valid_fraction == 0.0
        assert after.unknown.all()
        assert np.isinf(after.scan).all()
        # the wall 2.2 m ahead is still remembered: nothing was seen free in front of it
        assert len(after.points_base) == len(before.points_base)
