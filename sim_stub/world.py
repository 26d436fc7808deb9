"""The simulated 2D world: static obstacles, an ORCA crowd and the diff-drive robot, judged from
ground truth.

Everything is deterministic from the seed: one `numpy.random.Generator` draws the robot's start,
its goal (unless given), the agents' positions, goals and speeds; goal re-draws on arrival use a
second generator spawned from the same seed.

People behave as people: they choose a new velocity every `crowd.decision_period_s` by ORCA
(seeing the robot as a non-reactive neighbour, widened by their comfort distance, when the
scenario's crowd is reactive), change velocity no faster than `crowd.max_accel_m_s2`, and walk
straight in between. Order inside `World.step(dt, v, omega)`: the crowd walks dt (deciding when
a decision falls due), the robot applies the command through its acceleration limits and moves,
the clock advances, then the episode is judged: collision, else success, else timeout. Contacts are checked
at step ends only (no sweeping), which at dt = 0.1 s and these speeds cannot skip a contact of
0.47 m combined radius by more than a few centimetres of overlap.

Every contact is recorded (`World.contacts`), also after the outcome has latched, with who was at
fault (`judge_contact`). The robot is at fault when it moved at contact (|v| > 0.01 m/s) and
either drove into the other body (its own speed toward it > 0.01 m/s with the body within
±45 degrees of its heading, the front it looks at and is responsible for), or the other body was
not coming at it (a static obstacle, a person standing or walking away). A person who walks into
the side or back of a moving robot is not the robot's fault, as in traffic rules; such contacts
are still counted (`Contact.moving`), because strict passive safety (never moving at any contact)
is the stronger property, and with one forward camera it cannot be guaranteed: a person walking
at up to 1 m/s from outside the 87-degree view can reach the robot's side before it stops from any
speed above zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.config.settings import LimitsConfig, RobotConfig
from runtime.errors import ConfigError
from sim_stub.orca import Body, Circle, Crowd, OrcaParams, Shape, rectangle, segment_box
from sim_stub.scenario import BoxSpec, CylinderSpec, Scenario, WallSpec

ROBOT_RADIUS_M = RobotConfig().radius_m  # the simulated Spark is the robot the config describes
MOVING_SPEED_M_S = 0.01  # a speed (or speed toward the other body) above this counts as moving
FRONT_HALF_ANGLE_DEG = 45.0  # the robot drives into what it meets within this of its heading
_SPAWN_TRIES = 2000


@dataclass
class RobotState:
    """Diff-drive robot ground truth: pose in the world frame and body velocity."""

    x: float
    y: float
    theta: float
    v: float = 0.0
    omega: float = 0.0


@dataclass(frozen=True)
class Contact:
    """The start of one contact, judged from ground truth (see the module docs for fault)."""

    t: float
    with_: str  # "agent 3" or "obstacle 1"
    robot_speed: float  # |v| of the robot, m/s
    robot_closing: float  # the robot's own speed toward the other body, m/s (< 0: moving away)
    other_closing: float  # the other body's speed toward the robot, m/s (0 for obstacles)
    bearing_deg: float | None  # where the other body was: 0 ahead, + left (None: obstacles)
    moving: bool  # the robot moved at contact (a strict passive-safety violation)
    at_fault: bool


def judge_contact(t: float, with_: str, robot: RobotState, towards: np.ndarray | None,
                  other_velocity: np.ndarray) -> Contact:
    """Fault for a contact beginning now. towards: unit vector from the robot to the other body
    (None for a static obstacle: only whether the robot moved matters, the obstacle did not)."""
    heading = np.array([math.cos(robot.theta), math.sin(robot.theta)])
    moving = abs(robot.v) > MOVING_SPEED_M_S
    if towards is None:
        return Contact(t, with_, abs(robot.v), abs(robot.v), 0.0, None, moving, moving)
    robot_closing = float(robot.v * heading @ towards)
    other_closing = float(-np.asarray(other_velocity, dtype=float) @ towards)
    bearing = math.degrees(math.atan2(heading[0] * towards[1] - heading[1] * towards[0],
                                      heading @ towards))
    drove_into = robot_closing > MOVING_SPEED_M_S and abs(bearing) <= FRONT_HALF_ANGLE_DEG
    came_at_robot = other_closing > MOVING_SPEED_M_S
    return Contact(t, with_, abs(robot.v), robot_closing, other_closing, bearing, moving,
                   moving and (drove_into or not came_at_robot))


@dataclass(frozen=True)
class Outcome:
    """Judgement of the episode so far. status: running | success | collision | timeout."""

    status: str
    t: float
    contact: Contact | None = None  # collisions only: the first contact

    @property
    def done(self) -> bool:
        return self.status != "running"

    @property
    def collided_with(self) -> str | None:
        return None if self.contact is None else self.contact.with_

    @property
    def at_fault(self) -> bool | None:
        return None if self.contact is None else self.contact.at_fault


@dataclass(frozen=True)
class Snapshot:
    """Plain arrays for the renderer and the tracker's ground truth."""

    t: float
    agent_positions: np.ndarray  # (N, 2) m
    agent_velocities: np.ndarray  # (N, 2) m/s
    agent_radii: np.ndarray  # (N,) m
    robot_pose: np.ndarray  # (3,) x, y, theta
    robot_velocity: np.ndarray  # (2,) v, omega
    robot_radius: float
    goal: np.ndarray  # (2,)


def obstacle_shape(spec: BoxSpec | CylinderSpec | WallSpec) -> Shape:
    """The 2D footprint of a static obstacle."""
    if isinstance(spec, CylinderSpec):
        return Circle(spec.center, spec.radius)
    if isinstance(spec, BoxSpec):
        return rectangle(spec.center, spec.size, math.radians(spec.yaw_deg))
    return segment_box(spec.start, spec.end, spec.thickness)


def _bounding_box(shape: Shape) -> tuple[float, float, float, float]:
    """x_min, y_min, x_max, y_max of a footprint."""
    if isinstance(shape, Circle):
        (x, y), r = shape.center, shape.radius
        return x - r, y - r, x + r, y + r
    lo, hi = shape.vertices.min(axis=0), shape.vertices.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def base_to_world(start: tuple[float, float, float], x: float, y: float, theta: float
                  ) -> tuple[float, float, float]:
    """A pose from the base model's own frame (the origin at power-on) to the world, where the
    robot started at `start`; the odom frame the runtime keeps starts there too."""
    x0, y0, th0 = start
    c, s = math.cos(th0), math.sin(th0)
    return x0 + c * x - s * y, y0 + s * x + c * y, th0 + theta


def goal_in_odom(start: tuple[float, float, float], goal: np.ndarray) -> tuple[float, float]:
    """A world point in the odom frame, which starts at the robot's start pose (the inverse of
    `base_to_world` for a point)."""
    x0, y0, th0 = start
    dx, dy = float(goal[0]) - x0, float(goal[1]) - y0
    c, s = math.cos(th0), math.sin(th0)
    return c * dx + s * dy, -s * dx + c * dy


def _approach(current: float, target: float, accel: float, decel: float, dt: float) -> float:
    """Move `current` towards `target`; speeding up limited by accel, slowing down by decel."""
    speeding_up = abs(target) > abs(current) and current * target >= 0.0
    step = (accel if speeding_up else decel) * dt
    return current + max(-step, min(step, target - current))


class World:
    """One episode of a scenario: crowd + obstacles + robot, judged from ground truth."""

    def __init__(
        self,
        scenario: Scenario,
        seed: int | None = None,
        goal_index: int | None = None,
        limits: LimitsConfig = LimitsConfig(),  # noqa: B008 - frozen dataclass
        robot_radius: float = ROBOT_RADIUS_M,
    ) -> None:
        self.scenario = scenario
        self.seed = scenario.seed if seed is None else seed
        self.limits = limits
        self.robot_radius = robot_radius
        self.obstacles = scenario.obstacles
        self.shapes: list[Shape] = [obstacle_shape(o) for o in scenario.obstacles]
        self._shape_boxes = np.array([_bounding_box(s) for s in self.shapes]).reshape(-1, 4)
        self.t = 0.0
        self._next_decision = 0.0  # the crowd's next velocity choice (s)
        self.min_separation = math.inf  # smallest robot-agent gap seen (m)
        self.contacts: list[Contact] = []  # every contact's start, also after the outcome
        self._touching: set[str] = set()
        rng = np.random.default_rng(self.seed)
        self._goal_rng = np.random.default_rng([self.seed, 1])

        if goal_index is None:
            goal_index = int(rng.integers(len(scenario.goals)))
        if not 0 <= goal_index < len(scenario.goals):
            raise ConfigError(
                f"{scenario.source}: goal index {goal_index} out of range"
                f" (scenario has {len(scenario.goals)} goals)"
            )
        self.goal = np.array(scenario.goals[goal_index], dtype=float)
        self.robot = self._place_robot(rng)
        self.crowd = self._make_crowd(rng)
        self.outcome = Outcome("running", 0.0)

    # --- construction ----------------------------------------------------------------------------

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance from each point (K, 2) to the nearest static obstacle (inf when none)."""
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        out = np.full(len(points), np.inf)
        for shape in self.shapes:
            out = np.minimum(out, shape.distance(points))
        return out

    def _uniform(self, rng: np.random.Generator, rect: object, margin: float) -> np.ndarray:
        x0, x1 = rect.x_min + margin, rect.x_max - margin  # type: ignore[attr-defined]
        y0, y1 = rect.y_min + margin, rect.y_max - margin  # type: ignore[attr-defined]
        if x0 > x1:
            x0 = x1 = 0.5 * (x0 + x1)
        if y0 > y1:
            y0 = y1 = 0.5 * (y0 + y1)
        return np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])

    def _place_robot(self, rng: np.random.Generator) -> RobotState:
        spec = self.scenario.robot
        for _ in range(_SPAWN_TRIES):
            p = self._uniform(rng, spec.area, 0.0)
            if self.clearance(p)[0] >= self.robot_radius + 0.05:
                break
        else:
            raise ConfigError(f"{self.scenario.source}: key 'robot.area': no free start position")
        jitter = math.radians(spec.heading_jitter_deg)
        theta = math.radians(spec.heading_deg) + rng.uniform(-jitter, jitter)
        return RobotState(float(p[0]), float(p[1]), math.atan2(math.sin(theta), math.cos(theta)))

    def _free_point(
        self, rng: np.random.Generator, radius: float, taken: list, gap: float
    ) -> np.ndarray:
        for _ in range(_SPAWN_TRIES):
            p = self._uniform(rng, self.scenario.area, radius)
            if self.clearance(p)[0] < radius + 0.1:
                continue
            if all(np.hypot(*(p - q)) >= r + radius + gap for q, r in taken):
                return p
        raise ConfigError(
            f"{self.scenario.source}: key 'crowd.count': cannot place {self.scenario.crowd.count}"
            " agents in the free area"
        )

    def _make_crowd(self, rng: np.random.Generator) -> Crowd:
        spec = self.scenario.crowd
        n = spec.count
        taken: list = [((self.robot.x, self.robot.y), self.robot_radius + 1.0)]
        positions = np.zeros((n, 2))
        for i in range(n):
            positions[i] = self._free_point(rng, spec.radius, taken, 0.2)
            taken.append((positions[i], spec.radius))
        goals = np.array([self._draw_goal(rng, positions[i]) for i in range(n)]).reshape(n, 2)
        speeds = rng.uniform(spec.speed_range[0], spec.speed_range[1], size=n)
        params = OrcaParams(
            time_horizon=spec.time_horizon_s,
            obstacle_time_horizon=spec.obstacle_time_horizon_s,
            neighbour_distance=spec.neighbour_distance_m,
            max_neighbours=spec.max_neighbours,
            safety_margin=spec.safety_margin_m,
            max_accel=spec.max_accel_m_s2 if spec.max_accel_m_s2 > 0 else math.inf,
        )
        return Crowd(
            positions,
            goals,
            spec.radius,
            speeds,
            params=params,
            goal_sampler=lambda i, p: self._draw_goal(self._goal_rng, p),
        )

    def _draw_goal(self, rng: np.random.Generator, position: np.ndarray) -> np.ndarray:
        spec = self.scenario.crowd
        best, best_d = None, -1.0
        for _ in range(200):
            g = self._uniform(rng, self.scenario.area, spec.radius)
            if self.clearance(g)[0] < spec.radius + 0.1:
                continue
            d = float(np.hypot(*(g - position)))
            if d >= spec.goal_min_distance_m:
                return g
            if d > best_d:
                best, best_d = g, d
        if best is None:
            raise ConfigError(f"{self.scenario.source}: key 'area': no free goal for the crowd")
        return best

    # --- stepping --------------------------------------------------------------------------------

    def robot_body(self) -> Body:
        """The robot as reactive people see it: its disc widened by their comfort distance."""
        r = self.robot
        vel = (r.v * math.cos(r.theta), r.v * math.sin(r.theta))
        return Body((r.x, r.y), vel, self.robot_radius + self.scenario.crowd.comfort_distance_m)

    def step(self, dt: float, v_cmd: float, omega_cmd: float) -> Outcome:
        """Advance the world by dt with the robot's body-velocity command; returns the judgement.

        Once the episode is over the world no longer moves and the final outcome is returned.
        """
        if self.outcome.done:
            return self.outcome
        self._advance_crowd(dt)
        self._move_robot(dt, v_cmd, omega_cmd)
        self.t += dt
        self.outcome = self.judge()
        return self.outcome

    def _advance_crowd(self, dt: float) -> None:
        """The crowd walks dt from self.t: people decide every `crowd.decision_period_s` (ORCA,
        seeing the robot where it is at that moment when they are reactive) and walk straight
        in between; a period of 0 decides at every step, over that step."""
        period = self.scenario.crowd.decision_period_s
        others = [self.robot_body()] if self.scenario.crowd.reactive else []
        if period <= 0.0:
            self.crowd.step(dt, self.shapes, others)
            return
        t, end = self.t, self.t + dt
        while True:
            if t >= self._next_decision - 1e-9:
                self.crowd.decide(period, self.shapes, others)
                self._next_decision += period
            to = min(end, self._next_decision)
            self.crowd.move(to - t)
            t = to
            if t >= end - 1e-9:
                return

    def follow_robot(
        self, dt: float, x: float, y: float, theta: float, v: float, omega: float
    ) -> Outcome:
        """Advance the crowd by dt with the robot where an outside model (the emulated base's
        kinematics) put it. Unlike `step`, the world keeps moving after the first outcome, which
        stays latched: the runtime driving the simulated robot does not stop existing."""
        r = self.robot
        r.x, r.y, r.theta, r.v, r.omega = x, y, theta, v, omega
        if dt > 0.0:
            self._advance_crowd(dt)
            self.t += dt
        now = self.judge()
        if not self.outcome.done:
            self.outcome = now
        return self.outcome

    def _move_robot(self, dt: float, v_cmd: float, omega_cmd: float) -> None:
        lim, r = self.limits, self.robot
        r.v = _approach(r.v, v_cmd, lim.accel_max, lim.decel_max, dt)
        r.omega = _approach(r.omega, omega_cmd, lim.alpha_max, lim.alpha_max, dt)
        dth = r.omega * dt
        if abs(dth) < 1e-9:
            r.x += r.v * dt * math.cos(r.theta)
            r.y += r.v * dt * math.sin(r.theta)
        else:  # exact arc
            rad = r.v / r.omega
            r.x += rad * (math.sin(r.theta + dth) - math.sin(r.theta))
            r.y -= rad * (math.cos(r.theta + dth) - math.cos(r.theta))
        r.theta = math.atan2(math.sin(r.theta + dth), math.cos(r.theta + dth))

    def judge(self) -> Outcome:
        """Collision (with fault), success, timeout or running, from the current ground truth.
        Records the contacts that begin now in `contacts`."""
        p = np.array([self.robot.x, self.robot.y])
        touching: list[str] = []
        new: list[Contact] = []
        if len(self.crowd):
            rel = self.crowd.positions - p
            dist = np.hypot(*rel.T)
            gaps = dist - self.crowd.radii - self.robot_radius
            self.min_separation = min(self.min_separation, float(gaps.min()))
            for k in np.argsort(gaps)[: int(np.count_nonzero(gaps < 0.0))]:
                who = f"agent {k}"
                touching.append(who)
                if who not in self._touching:
                    towards = rel[k] / max(float(dist[k]), 1e-9)
                    new.append(judge_contact(self.t, who, self.robot, towards,
                                             self.crowd.velocities[k]))
        lo, hi = self._shape_boxes[:, :2], self._shape_boxes[:, 2:]
        reach = self.robot_radius
        near = np.flatnonzero(np.all((p >= lo - reach) & (p <= hi + reach), axis=1))
        for o in near:  # only shapes whose bounding box is within reach can touch
            if self.shapes[o].distance(p[None])[0] < self.robot_radius:
                who = f"obstacle {o}"
                touching.append(who)
                if who not in self._touching:
                    new.append(judge_contact(self.t, who, self.robot, None, np.zeros(2)))
        self._touching = set(touching)
        self.contacts.extend(new)
        if touching:
            first = next((c for c in new if c.with_ == touching[0]), None)
            if first is None:  # touching since before: judged when it began
                first = next(c for c in reversed(self.contacts) if c.with_ == touching[0])
            return Outcome("collision", self.t, first)
        if np.hypot(*(self.goal - p)) <= self.scenario.goal_tolerance_m:
            return Outcome("success", self.t)
        if self.t >= self.scenario.time_limit_s - 1e-9:
            return Outcome("timeout", self.t)
        return Outcome("running", self.t)

    def snapshot(self) -> Snapshot:
        r = self.robot
        return Snapshot(
            t=self.t,
            agent_positions=self.crowd.positions.copy(),
            agent_velocities=self.crowd.velocities.copy(),
            agent_radii=self.crowd.radii.copy(),
            robot_pose=np.array([r.x, r.y, r.theta]),
            robot_velocity=np.array([r.v, r.omega]),
            robot_radius=self.robot_radius,
            goal=self.goal.copy(),
        )
