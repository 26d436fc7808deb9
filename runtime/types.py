"""Plain typed data passed between stages, drivers and the loop. SI units, host monotonic seconds."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True, slots=True)
class Twist:
    """Body velocity command: v forward (m/s), omega counter-clockwise (rad/s)."""

    v: float = 0.0
    omega: float = 0.0

    def is_finite(self) -> bool:
        return math.isfinite(self.v) and math.isfinite(self.omega)


STOP = Twist(0.0, 0.0)

# Below this speed (m/s) the robot stands still: a job has stopped, the robot is not closing on
# anything. Wheel-encoder quantisation shows up as a few mm/s while turning in place.
STILL_M_S = 0.01


class CliffSensor(enum.IntFlag):
    """Cliff sensors as reported by the base (already inverted from the wire's active-low)."""

    RIGHT = 1
    FRONT_RIGHT = 2
    FRONT_LEFT = 4
    LEFT = 8
    BACK_RIGHT = 16
    BACK_LEFT = 32


class Proximity(enum.IntFlag):
    """IR proximity 'bumpers' (active-high on the wire)."""

    RIGHT = 1
    FRONT_RIGHT = 2
    FRONT = 4
    FRONT_LEFT = 8
    LEFT = 16
    BACK_RIGHT = 32
    BACK_LEFT = 64


class BaseStatus(enum.IntFlag):
    """Status byte of the base's feedback."""

    WHEEL_DROP_RIGHT = 1
    WHEEL_DROP_LEFT = 2
    OVER_CURRENT_RIGHT = 4
    OVER_CURRENT_LEFT = 8
    UNDER_CONTROL = 16
    SEARCHING_DOCK = 32
    ON_DOCK = 64
    CHARGER_PLUGGED = 128


# An increment spanning longer than this (frames lost or rejected in between) is released by the
# base driver only once two frames in a row agreed on its end reading, so odometry may take its
# travel as a displacement: a constant-velocity prediction cannot know what happened in a gap.
MAX_UNCONFIRMED_DT_S = 0.5


@dataclass(frozen=True, slots=True)
class WheelIncrement:
    """One feedback frame turned into SI motion since the previous accepted frame.

    `t` is the host monotonic arrival time; `dt` the base's own clock difference, which is what
    speeds are computed from (arrival jitter would otherwise show up as speed noise).
    """

    t: float
    dt: float
    d_left: float
    d_right: float
    gyro_z: float | None
    yaw: float | None
    cliffs: CliffSensor
    proximity: Proximity
    status: BaseStatus

    @property
    def hazard(self) -> str | None:
        """A reason to stop at once that the base itself reports, or None."""
        if self.cliffs:
            return f"cliff detected ({self.cliffs!r})"
        drop = self.status & (BaseStatus.WHEEL_DROP_LEFT | BaseStatus.WHEEL_DROP_RIGHT)
        if drop:
            return f"wheel drop ({BaseStatus(drop)!r})"
        return None


@dataclass(frozen=True, slots=True)
class Odometry:
    """Pose in the odom frame and body velocity, as of host time `t` (0 before any feedback)."""

    t: float = 0.0
    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0
    v: float = 0.0
    omega: float = 0.0
    distance: float = 0.0


@dataclass(frozen=True)
class DepthIntrinsics:
    """Pinhole intrinsics of a depth stream (D435 depth has zero distortion)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_unit_m: float = 0.001


@dataclass
class DepthFrame:
    """One depth image, owned by us (copied out of any SDK buffer)."""

    depth: np.ndarray  # uint16, shape (height, width), Z16 in intrinsics.depth_unit_m
    t: float  # seconds (host monotonic; in playback the recorded timestamps)
    frame_number: int
    intrinsics: DepthIntrinsics
    # `depth` is every decimation-th pixel of the camera's image both ways (a replayed flight
    # recording holds what the world model read); the intrinsics are the camera's
    decimation: int = 1

    @property
    def image_shape(self) -> tuple[int, int]:
        """The shape `depth` must have: the intrinsics' image, decimated."""
        d = self.decimation
        return -(-self.intrinsics.height // d), -(-self.intrinsics.width // d)

    def depth_m(self) -> np.ndarray:
        """Depth in metres as float32 (0 stays 0 = invalid)."""
        return self.depth.astype(np.float32) * np.float32(self.intrinsics.depth_unit_m)


@dataclass(frozen=True)
class Prepared:
    """A planner job's preparation of one cycle's decision (`Job.prepare`): its own context
    (None: the job holds still this cycle) and, for a job with an actor, the actor's input."""

    context: Any = None
    observation: np.ndarray | None = None


@dataclass(frozen=True)
class DecisionTrace:
    """What a planner job decided in its last cycle, for the flight recorder (None where a job
    has no such stage): the planning context (DWA's result, the tracks' predictions), the
    observation and the actor's output, the shield's decision, the safe corridor, the goal."""

    context: Any = None  # runtime.planning.planning_step.PlanningContext
    observation: np.ndarray | None = None
    action: np.ndarray | None = None
    shield: Any = None  # runtime.safety.shield.ShieldDecision
    corridor: Any = None  # runtime.planning.corridor.Corridor
    goal_odom: tuple[float, float] | None = None
    budgets: dict[str, tuple[int, bool]] | None = None  # per anytime stage: steps allowed, cut
