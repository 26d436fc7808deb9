"""Depth frame + pose → WorldState: perception → obstacle memory → tracker, in one place.

The control loop and the lock-stepped evaluation harness both call this, so what the planner
sees in an evaluation is what it sees on the robot. Pure of I/O; the clock passed in only times
the stages.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from runtime.config.calibration import CameraMount
from runtime.perception.depth_points import FloorVerdict, Perception, PerceptionConfig
from runtime.perception.obstacle_memory import ObstacleMemory, ObstacleMemoryConfig
from runtime.perception.tracking import Track, Tracker, TrackerConfig
from runtime.types import DepthFrame, Odometry


@dataclass(frozen=True)
class WorldState:
    """What the planner and the policy see after a depth frame: the scan (min range per bearing
    bin; `unknown` bins are not free), remembered obstacle points in base_link, and tracks."""

    t: float
    scan: np.ndarray
    unknown: np.ndarray
    bin_angles: np.ndarray
    points_base: np.ndarray
    tracks: list[Track]
    floor_ok: bool | None
    valid_fraction: float = 1.0  # of the frame's (decimated) pixels; near 0: the camera is blind
    blind_range: np.ndarray | None = None  # (bins,) base_link range of the camera's minimum range


class PerceptionSections(Protocol):
    """The config sections the world model reads (runtime.config.settings.Config has them)."""

    @property
    def perception(self) -> PerceptionConfig: ...

    @property
    def memory(self) -> ObstacleMemoryConfig: ...

    @property
    def tracking(self) -> TrackerConfig: ...


class WorldModel:
    """Keeps perception (rebuilt when the intrinsics change), the obstacle memory and the
    tracker; `stage_s` holds the last update's seconds per stage."""

    def __init__(self, config: PerceptionSections, mount: CameraMount,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self._cfg = config
        self._mount = mount
        self._clock = clock
        self._perception: Perception | None = None
        self._memory = ObstacleMemory(config.memory)
        self._tracker = Tracker(config.tracking)
        self.stage_s = {"perception": 0.0, "memory": 0.0, "tracking": 0.0}

    def update(self, frame: DepthFrame, odom: Odometry,
               seen_from: Odometry | None = None) -> WorldState:
        """The world after `frame`, in base_link at `odom`'s pose. `seen_from`: where the robot
        was at the frame's stamp (default `odom`), which places the frame's points in odom.
        The tracker clusters the frame's points as the memory binned them, one per cell."""
        clock = self._clock
        if self._perception is None or self._perception.intrinsics != frame.intrinsics:
            self._perception = Perception(frame.intrinsics, self._mount, self._cfg.perception)
        t0 = clock()
        if frame.decimation not in (1, self._cfg.perception.decimation):
            raise ValueError(f"frame {frame.frame_number} is decimated by {frame.decimation},"
                             f" perception.decimation is {self._cfg.perception.decimation}")
        out = self._perception.process(frame.depth, decimated=frame.decimation > 1)
        t1 = clock()
        at = seen_from if seen_from is not None else odom
        sensor = (at.x, at.y, at.theta)
        self._memory.update_from(out, sensor, frame.t, view=self._perception.view)
        remembered = self._memory.points_base((odom.x, odom.y, odom.theta), frame.t)
        t2 = clock()
        tracks = self._tracker.update(self._memory.frame_points, frame.t,
                                      sensor_pose=np.array(sensor))
        # confirmed, moving and hit this frame: where a person walks now, nothing static stands
        walking = [tr for tr in tracks
                   if tr.confirmed and not tr.stationary and tr.misses == 0 and not tr.coasting]
        if walking:
            self._memory.mark_moving(np.array([tr.position for tr in walking]),
                                     np.array([tr.radius for tr in walking]))
        t3 = clock()
        self.stage_s.update(perception=t1 - t0, memory=t2 - t1, tracking=t3 - t2)
        return WorldState(frame.t, out.scan.copy(), out.unknown.copy(), out.bin_angles,
                          remembered, tracks, out.floor_ok, out.valid_fraction,
                          out.blind_range.copy())

    def check_floor(self) -> FloorVerdict | None:
        """The floor check when one is due (the loop runs it in its slack), else None."""
        if self._perception is None or not self._perception.floor_check_due:
            return None
        return self._perception.check_floor()
