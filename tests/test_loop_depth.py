"""The loop's depth input: every frame counted, gaps found, stale depth means DEGRADED."""

from __future__ import annotations

import math

import numpy as np
from doubles import FreshFeedbackLink, SimClock

from runtime.config.settings import Calibration, Config
from runtime.jobs.drive import HoldJob
from runtime.process.loop import ControlLoop, DepthStats
from runtime.process.sdnotify import SystemdNotifier
from runtime.types import DepthFrame, DepthIntrinsics

K = DepthIntrinsics(4, 3, 2.0, 2.0, 2.0, 1.5)


def frame(n: int, t: float) -> DepthFrame:
    return DepthFrame(np.full((3, 4), 1000, np.uint16), t, n, K)  # 1 m: a camera that sees


def test_depth_stats_count_gaps_and_missing_frames():
    stats = DepthStats()
    for n in (5, 6, 7, 10, 11, 13):
        stats.take(frame(n, 0.0))
    assert (stats.frames, stats.gaps, stats.missing, stats.last_frame_number) == (6, 2, 3, 13)


class ScheduledDepth:
    """Unit-test double: a 15 fps camera on the loop's clock that goes dark between two times."""

    def __init__(self, clock: SimClock, dark: tuple[float, float] = (math.inf, math.inf)) -> None:
        self._clock = clock
        self._dark = dark
        self._last: float | None = None
        self.sent = 0

    def poll(self) -> DepthFrame | None:
        now = self._clock()
        if self._dark[0] <= now < self._dark[1]:
            return None
        if self._last is not None and now - self._last < 1.0 / 15.0:
            return None
        self._last = now
        self.sent += 1
        return frame(self.sent, now)


def test_stale_depth_degrades_the_loop_and_fresh_depth_recovers_it():
    """Stepped on simulated time: the camera goes dark for 0.6 s (depth.max_age_s is 0.25 s)."""
    clock = SimClock()
    t0 = clock.now
    depth = ScheduledDepth(clock, dark=(t0 + 1.0, t0 + 1.6))
    loop = ControlLoop(Config(), Calibration(), FreshFeedbackLink(clock), HoldJob(),
                       SystemdNotifier(None), clock=clock, max_cycles=60, depth=depth,
                       wait=clock.wait)
    report = loop.run()
    steps = [(round(t - t0, 2), to) for t, _, to in report.transitions]
    assert [to for _, to in steps] == ["RUNNING", "DEGRADED", "RUNNING", "STOPPED"]
    assert 1.25 <= steps[1][0] <= 1.35  # the first cycle with the last frame over 0.25 s old
    assert 1.6 <= steps[2][0] <= 1.65  # the first cycle with a frame again
    assert report.degraded_cycles == round((steps[2][0] - steps[1][0]) * 20)
    assert report.depth is not None and report.depth.gaps == 0
    assert report.depth.frames == depth.sent


def test_floor_check_without_a_floor_plane_says_so_instead_of_printing_nan(caplog):
    """A wall filling the view leaves no near-vertical plane to fit: no 'tilt nan°'. A failure
    is reported once it has held for floor_alarm_checks checks in a row (3): in a crowd single
    checks fail and pass by turns, and each turn was a warning."""
    from runtime.perception.depth_points import FloorVerdict

    loop = ControlLoop(Config(), Calibration(), FreshFeedbackLink(), HoldJob(),
                       SystemdNotifier(None), depth=ScheduledDepth(SimClock()))
    no_plane, good, tilted = (FloorVerdict(False, math.nan, math.nan, 320),
                              FloorVerdict(True, 0.2, 0.001, 500),
                              FloorVerdict(False, 4.0, -0.03, 500))
    verdicts = iter([tilted, good, tilted, tilted, good, *[no_plane] * 3, good, *[tilted] * 4])
    loop._pipeline.check_floor = lambda: next(verdicts)  # type: ignore[method-assign]
    caplog.set_level("WARNING", logger="safemove.loop")
    for _ in range(13):
        loop._check_floor()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "nan" not in lines[0]
    assert "no floor plane among the 320 points near the calibrated floor in 3 checks" in lines[0]
    assert "in 3 checks in a row (last: tilt 4.0°, height -0.030 m)" in lines[1]
