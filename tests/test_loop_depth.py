"""The loop's depth input: every frame counted, gaps found, stale depth means DEGRADED."""

from __future__ import annotations

import threading
import time

import numpy as np
from doubles import FreshFeedbackLink

from runtime.config import Calibration, Config
from runtime.drive import HoldJob
from runtime.loop import ControlLoop, DepthStats
from runtime.sdnotify import SystemdNotifier
from runtime.types import DepthFrame, DepthIntrinsics

K = DepthIntrinsics(4, 3, 2.0, 2.0, 2.0, 1.5)


def frame(n: int, t: float) -> DepthFrame:
    return DepthFrame(np.full((3, 4), 1000, np.uint16), t, n, K)  # 1 m: a camera that sees


def test_depth_stats_count_gaps_and_missing_frames():
    stats = DepthStats()
    for n in (5, 6, 7, 10, 11, 13):
        stats.take(frame(n, 0.0))
    assert (stats.frames, stats.gaps, stats.missing, stats.last_frame_number) == (6, 2, 3, 13)


class SwitchableDepth:
    """Unit-test double: a fresh frame per poll while `live` is set, nothing otherwise."""

    def __init__(self) -> None:
        self.live = threading.Event()
        self.live.set()
        self.polls = 0
        self.sent = 0

    def poll(self) -> DepthFrame | None:
        """Every other poll while live (the loop drains until None)."""
        self.polls += 1
        if not self.live.is_set() or self.polls % 2 == 0:
            return None
        self.sent += 1
        return frame(self.sent, time.monotonic())


def test_stale_depth_degrades_the_loop_and_fresh_depth_recovers_it():
    depth = SwitchableDepth()
    loop = ControlLoop(Config(), Calibration(), FreshFeedbackLink(), HoldJob(), SystemdNotifier(None),
                       depth=depth)
    reports = []
    thread = threading.Thread(target=lambda: reports.append(loop.run()), daemon=True)
    thread.start()
    try:
        time.sleep(0.4)
        assert loop.state.value == "RUNNING"
        depth.live.clear()
        time.sleep(0.6)  # max_age_s is 0.25 s
        assert loop.state.value == "DEGRADED"
        depth.live.set()
        time.sleep(0.3)
        assert loop.state.value == "RUNNING"
    finally:
        loop.request_stop("test over")
        thread.join(timeout=5)
    report = reports[0]
    assert [to for _, _, to in report.transitions] == ["RUNNING", "DEGRADED", "RUNNING", "STOPPED"]
    assert report.depth is not None and report.depth.gaps == 0
    assert report.depth.frames == depth.sent


def test_floor_check_without_a_floor_plane_says_so_instead_of_printing_nan(caplog):
    """A wall filling the view leaves no near-vertical plane to fit: no 'tilt nan°'."""
    import math

    from runtime.perception import FloorVerdict

    loop = ControlLoop(Config(), Calibration(), FreshFeedbackLink(), HoldJob(),
                       SystemdNotifier(None), depth=SwitchableDepth())
    verdicts = iter([FloorVerdict(False, math.nan, math.nan, 320),
                     FloorVerdict(True, 0.2, 0.001, 500),
                     FloorVerdict(False, 4.0, -0.03, 500)])
    loop._world_model.check_floor = lambda: next(verdicts)  # type: ignore[method-assign]
    caplog.set_level("WARNING", logger="safemove.loop")
    for _ in range(3):
        loop._check_floor()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "nan" not in lines[0]
    assert "no floor plane among the 320 points" in lines[0]
    assert "tilt 4.0°, height -0.030 m" in lines[1]
