"""MissionJob (runtime.jobs.mission): goals and missions from the control socket, driven by a
planner job per waypoint. A fake planner stands in for DWA / SafeMove: it drives forward until a
test says it has arrived."""

from __future__ import annotations

import math
from typing import Any

import pytest

from runtime.control.config import ControlConfig
from runtime.control.protocol import Request, Waypoint
from runtime.jobs.mission import MissionJob
from runtime.types import STOP, Odometry, Prepared, Twist

DRIVE = Twist(0.2, 0.1)
HERE = Odometry()


class FakePlanner:
    """A planner job to one waypoint: drives at DRIVE until `finished` is set."""

    def __init__(self, goal: tuple[float, float], tolerance: float, speed: float | None) -> None:
        self.goal, self.tolerance, self.speed = goal, tolerance, speed
        self.finished = False
        self.shield_changed = False
        self.shield_kinds: dict[str, int] = {}  # what its summary reports
        self.prepared: list[float] = []
        self.paused = 0

    def prepare(self, now: float, odom: Odometry, world: Any) -> Prepared:
        self.prepared.append(now)
        return Prepared("inner")

    def decide(self, prepared: Prepared, action: Any = None) -> Twist:
        assert prepared.context == "inner"
        return DRIVE

    def pause(self) -> None:
        self.paused += 1

    def summary(self) -> dict[str, Any]:
        return {"reached": self.finished, "shield_interventions": dict(self.shield_kinds)}


class Harness:
    """A MissionJob with a recording planner factory and event sink."""

    def __init__(self, **config: Any) -> None:
        self.cfg = ControlConfig(**config)
        self.planners: list[FakePlanner] = []
        self.events: list[dict[str, Any]] = []
        self.job = MissionJob(self.cfg, "dwa", self._make, self.events.append)

    def _make(self, goal: tuple[float, float], tolerance: float,
              speed: float | None) -> FakePlanner:
        self.planners.append(FakePlanner(goal, tolerance, speed))
        return self.planners[-1]

    @property
    def planner(self) -> FakePlanner:
        return self.planners[-1]

    def send(self, kind: str, *points: Waypoint, rid: Any = "r", odom: Odometry = HERE,
             now: float = 0.0, **fields: Any) -> dict[str, Any]:
        return self.job.handle(Request(kind, rid, tuple(points), **fields), now, odom)

    def cycle(self, now: float, odom: Odometry = HERE) -> Twist:
        return self.job.decide(self.job.prepare(now, odom, None))

    def names(self) -> list[str]:
        return [e["event"] for e in self.events]

    def finished(self) -> dict[str, Any]:
        ends = [e for e in self.events if e["event"] == "finished"]
        assert len(ends) == 1, self.events
        return ends[0]


def test_a_goal_is_driven_to_and_ends_reached_and_idle():
    h = Harness()
    r = h.send("goal", Waypoint(1.0, 2.0), rid="g1")
    assert r["ok"] and r["id"] == "g1" and r["goal_id"] == 1 and r["state"] == "navigating"
    assert r["waypoints"] == [{"x": 1.0, "y": 2.0}]
    assert h.job.state == "navigating"
    assert (h.planner.goal, h.planner.tolerance, h.planner.speed) == \
        ((1.0, 2.0), h.cfg.goal_tolerance_m, None)
    assert h.cycle(0.0) == DRIVE and h.cycle(0.05) == DRIVE
    assert h.job.distance == pytest.approx(math.hypot(1.0, 2.0))
    status = h.job.status()
    assert status["state"] == "navigating" and status["goal_id"] == 1
    assert status["goal"] == {"x": 1.0, "y": 2.0, "tolerance": h.cfg.goal_tolerance_m,
                              "max_speed": None}

    h.planner.finished = True
    there = Odometry(x=1.0, y=2.0)
    assert h.cycle(0.1, there) == STOP
    assert h.names() == ["arrived", "finished"]
    arrived, finished = h.events
    assert arrived["goal_id"] == 1 and (arrived["waypoint"], arrived["waypoints"]) == (1, 1)
    assert arrived["pose"] == {"x": 1.0, "y": 2.0, "theta": 0.0}
    assert finished["outcome"] == "reached" and finished["goal_id"] == 1
    assert h.job.state == "idle" and h.job.status()["goal_id"] is None
    assert h.job.last_outcome is not None and h.job.last_outcome["outcome"] == "reached"
    assert h.job.counts["reached"] == 1
    assert h.cycle(0.15) == STOP
    assert len(h.planners) == 1


def test_a_mission_of_three_waypoints_arrives_three_times_then_is_reached():
    h = Harness()
    points = (Waypoint(1, 0), Waypoint(1, 1, 0.3, 0.2), Waypoint(0, 1))
    assert h.send("mission", *points)["ok"]
    for k in range(3):
        assert h.cycle(k) == DRIVE
        assert h.job.status()["waypoint"] == k + 1
        h.planner.finished = True
        assert h.cycle(k + 0.5) == STOP
    assert h.names() == ["arrived", "arrived", "arrived", "finished"]
    assert [e["waypoint"] for e in h.events[:3]] == [1, 2, 3]
    assert h.finished()["outcome"] == "reached"
    assert [p.goal for p in h.planners] == [(1, 0), (1, 1), (0, 1)]
    assert [(p.tolerance, p.speed) for p in h.planners] == [
        (h.cfg.goal_tolerance_m, None), (0.3, 0.2), (h.cfg.goal_tolerance_m, None)]
    assert h.job.state == "idle"


def test_a_looping_mission_wraps_to_its_first_waypoint():
    h = Harness()
    assert h.send("mission", Waypoint(1, 0), Waypoint(0, 1), loop=True)["ok"]
    for k in range(5):
        h.cycle(k)
        h.planner.finished = True
        h.cycle(k + 0.5)
    assert [p.goal for p in h.planners] == [(1, 0), (0, 1), (1, 0), (0, 1), (1, 0), (0, 1)]
    assert h.names() == ["arrived"] * 5
    assert h.job.state == "navigating" and h.job.status()["loop"] is True
    assert h.cycle(10) == DRIVE


def test_a_relative_goal_is_resolved_with_the_robots_pose():
    h = Harness()
    pose = Odometry(x=1.0, y=2.0, theta=math.pi / 2)  # facing +y
    r = h.send("mission", Waypoint(1.0, 0.0), Waypoint(0.0, 1.0), Waypoint(2.0, -1.0),
               frame="relative", odom=pose)
    assert r["ok"]
    expected = [(1.0, 3.0), (0.0, 2.0), (2.0, 4.0)]  # ahead is +y, left is -x
    for got, want in zip(r["waypoints"], expected):
        assert (got["x"], got["y"]) == pytest.approx(want)
    assert h.planner.goal == pytest.approx(expected[0])


def test_an_odom_goal_ignores_the_robots_heading():
    h = Harness()
    assert h.send("goal", Waypoint(3.0, 4.0), odom=Odometry(x=1, y=1, theta=2.0))["waypoints"] \
        == [{"x": 3.0, "y": 4.0}]


def test_a_goal_too_far_away_is_refused_with_its_distance():
    h = Harness(max_goal_distance_m=50.0)
    r = h.send("goal", Waypoint(60.0, 0.0), rid="far")
    assert not r["ok"] and r["id"] == "far"
    assert "the goal is 60.0 m from the robot" in r["error"]
    assert "max_goal_distance_m = 50 m" in r["error"]
    r = h.send("goal", Waypoint(30.0, 0.0), odom=Odometry(x=-25.0))  # measured from the robot
    assert not r["ok"] and "the goal is 55.0 m from the robot" in r["error"]
    r = h.send("mission", Waypoint(1, 0), Waypoint(10_000, 0))
    assert not r["ok"] and "waypoint 2 is 10000.0 m" in r["error"]
    assert h.planners == [] and h.events == [] and h.job.state == "idle"
    r = h.send("goal", Waypoint(30.0, 0.0), odom=Odometry(x=25.0))
    assert r["ok"] and h.job.state == "navigating"


def test_a_refused_goal_does_not_disturb_the_goal_being_driven():
    h = Harness()
    h.send("goal", Waypoint(1, 0))
    assert not h.send("goal", Waypoint(100, 0))["ok"]
    assert h.job.state == "navigating" and h.job.goal_id == 1 and h.events == []
    assert h.cycle(0) == DRIVE


def test_a_goal_is_refused_while_the_pose_is_not_known():
    h = Harness()
    r = h.send("goal", Waypoint(1, 0), odom=Odometry(x=math.nan))
    assert not r["ok"] and "not known" in r["error"] and h.planners == []


def test_a_new_goal_preempts_the_current_one():
    h = Harness()
    h.send("goal", Waypoint(1, 0), rid="a")
    h.cycle(0)
    r = h.send("goal", Waypoint(0, 1), rid="b")
    assert r["ok"] and r["goal_id"] == 2
    ended = h.finished()
    assert ended["goal_id"] == 1 and ended["outcome"] == "preempted"
    assert "goal 2" in ended["reason"]
    assert h.job.state == "navigating" and h.job.goal_id == 2 and h.planner.goal == (0, 1)
    assert h.job.counts["preempted"] == 1


def test_cancel_stops_and_returns_to_idle():
    h = Harness()
    h.send("goal", Waypoint(1, 0))
    assert h.cycle(0) == DRIVE
    r = h.send("cancel", rid="c")
    assert r["ok"] and r["cancelled"] == 1 and r["state"] == "idle"
    ended = h.finished()
    assert ended["outcome"] == "cancelled" and ended["goal_id"] == 1
    assert h.job.state == "idle"
    prepared = h.job.prepare(0.05, HERE, None)
    assert prepared.context == STOP
    assert h.job.decide(prepared) == STOP
    assert h.planners[0].prepared == [0.0]  # the planner is never asked again
    r = h.send("cancel", rid="again")
    assert r["ok"] and r["cancelled"] is None and len(h.events) == 1


def test_pause_holds_still_and_resume_drives_on():
    h = Harness()
    assert not h.send("pause")["ok"]  # nothing to pause while idle
    h.send("goal", Waypoint(1, 0))
    assert h.cycle(0) == DRIVE
    r = h.send("pause", rid="p")
    assert r["ok"] and r["state"] == "paused" and r["goal_id"] == 1
    assert h.cycle(0.05) == STOP and h.cycle(0.1) == STOP
    assert h.planner.prepared == [0.0]
    r = h.send("pause")
    assert not r["ok"] and "nothing to pause: paused" in r["error"]
    r = h.send("resume", rid="q")
    assert r["ok"] and r["state"] == "navigating"
    assert h.cycle(0.15) == DRIVE
    assert not h.send("resume")["ok"]
    assert h.names() == ["paused", "resumed"]
    assert all(e["goal_id"] == 1 for e in h.events)


def test_a_waypoint_times_out_on_navigating_time_and_paused_time_does_not_count():
    h = Harness(blocked_timeout_s=1000.0)
    h.send("goal", Waypoint(1, 0), timeout_s=5.0)
    for k in range(31):  # 0 .. 3 s
        assert h.cycle(k * 0.1) == DRIVE
    h.send("pause")
    for k in range(100):  # a long pause
        h.cycle(3.0 + k)
    h.send("resume")
    t = 200.0
    while h.job.state == "navigating":
        assert t < 203.0, "should have timed out after 2 more seconds of navigating"
        last = h.cycle(t)
        t += 0.1
    assert last == STOP
    assert t == pytest.approx(202.1, abs=0.15)  # 3 s + 2 s of navigating time
    ended = h.finished()
    assert ended["outcome"] == "failed" and ended["reason"].startswith("timeout: waypoint 1")
    assert "5 s" in ended["reason"] and h.job.state == "idle"


def test_the_configured_waypoint_timeout_applies_without_one_in_the_request():
    h = Harness(waypoint_timeout_s=2.0, blocked_timeout_s=1000.0)
    h.send("goal", Waypoint(1, 0))
    t = 0.0
    while h.job.state == "navigating" and t < 10:
        h.cycle(t)
        t += 0.5
    assert t == pytest.approx(3.0)
    assert h.finished()["reason"].startswith("timeout")


def test_no_progress_for_the_blocked_timeout_fails_the_goal():
    h = Harness(blocked_timeout_s=3.0)
    h.send("goal", Waypoint(2, 0))
    t = 0.0
    while h.job.state == "navigating" and t < 10:
        h.cycle(t)  # the robot stays where it is
        t += 0.25
    assert t == pytest.approx(3.5)  # the first cycle more than 3 s after the last progress
    ended = h.finished()
    assert ended["outcome"] == "failed" and ended["reason"].startswith("blocked: no progress")
    assert "2.00 m to go" in ended["reason"]


def test_coming_closer_keeps_a_slow_goal_alive():
    h = Harness(blocked_timeout_s=3.0)
    h.send("goal", Waypoint(5, 0))
    for k in range(80):  # 0.15 m closer every 2 s for 20 s
        t = k * 0.25
        assert h.cycle(t, Odometry(x=0.15 * (t // 2))) == DRIVE
    assert h.job.state == "navigating"


def test_holding_longer_than_the_degraded_timeout_fails_the_goal():
    h = Harness(degraded_timeout_s=2.0)
    h.send("goal", Waypoint(1, 0))
    h.cycle(0.0)
    for t in (1.0, 2.0, 3.0):  # held 2 s: not yet
        h.job.held(t, "depth stale", HERE)
    assert h.job.state == "navigating"
    h.cycle(3.05)  # a cycle that did not hold restarts the count
    for t in (3.1, 4.0, 5.1):
        h.job.held(t, "depth stale", HERE)
    assert h.job.state == "navigating"
    h.job.held(5.2, "depth stale (300 ms old)", HERE)
    ended = h.finished()
    assert ended["outcome"] == "failed"
    assert ended["reason"] == "degraded too long: held 2.1 s (depth stale (300 ms old))"
    assert h.job.state == "idle"


def test_holding_while_idle_or_paused_fails_nothing():
    h = Harness(degraded_timeout_s=1.0)
    for t in range(5):
        h.job.held(float(t), "cliff", HERE)
    h.send("goal", Waypoint(1, 0))
    h.send("pause")
    for t in range(5, 10):
        h.job.held(float(t), "cliff", HERE)
    assert h.job.state == "paused" and h.names() == ["paused"]


def test_the_loop_pausing_the_job_pauses_the_planner_and_the_clock():
    h = Harness(blocked_timeout_s=1000.0)
    h.send("goal", Waypoint(1, 0), timeout_s=2.0)
    h.cycle(0.0)
    h.cycle(1.0)
    h.job.pause()  # the pipeline starts holding
    assert h.planner.paused == 1
    h.cycle(50.0)  # it stops holding 49 s later: those were not navigating time
    assert h.job.state == "navigating" and h.job.status()["waypoint_elapsed_s"] == 1.0
    h.cycle(51.5)
    assert h.job.state == "idle" and h.finished()["reason"].startswith("timeout")


def test_prepare_while_idle_holds_still():
    h = Harness()
    prepared = h.job.prepare(0.0, HERE, None)
    assert prepared == Prepared(STOP)
    assert h.job.decide(prepared) == STOP
    assert h.job.decide(prepared, action=None) == STOP


def test_shield_interventions_are_counted_and_summed_by_kind_over_the_waypoints():
    h = Harness()
    h.send("mission", Waypoint(1, 0), Waypoint(2, 0))
    h.planner.shield_changed = True
    h.cycle(0.0)
    h.cycle(0.05)
    h.planner.shield_changed = False
    h.cycle(0.1)
    assert h.job.interventions == 2
    h.planner.shield_kinds = {"slowed": 2}
    assert h.job.summary()["shield_interventions"] == {"slowed": 2}
    h.planner.finished = True
    h.cycle(0.15)  # on to waypoint 2: its planner's counts are added to the first one's
    h.planner.shield_kinds = {"slowed": 1, "stopped": 1}
    summary = h.job.summary()
    assert summary["shield_interventions"] == {"slowed": 3, "stopped": 1}
    assert summary["shield_changed_cycles"] == 2
    h.planner.finished = True
    h.cycle(0.2)
    assert h.job.state == "idle"
    assert h.job.summary()["shield_interventions"] == {"slowed": 3, "stopped": 1}


def test_shutdown_fails_an_active_goal_only():
    h = Harness()
    h.job.shutdown("STOPPED: signal", HERE)
    assert h.events == []
    h.send("goal", Waypoint(1, 0))
    h.job.shutdown("STOPPED: signal", HERE)
    assert h.finished()["reason"] == "service stopping: STOPPED: signal"
    assert h.job.summary()["outcomes"]["failed"] == 1


def test_a_request_the_cycle_does_not_apply_gets_an_error_reply():
    h = Harness()
    r = h.send("status", rid=3)
    assert not r["ok"] and r["id"] == 3


def test_goal_ids_increase_and_the_summary_counts_them():
    h = Harness()
    ids = [h.send("goal", Waypoint(1, 0))["goal_id"] for _ in range(3)]
    assert ids == [1, 2, 3]
    h.send("cancel")
    assert h.job.summary()["goals"] == 3
    assert h.job.counts == {"reached": 0, "cancelled": 1, "preempted": 2, "failed": 0}



def test_a_looping_mission_that_never_needs_to_move_ends_instead_of_lapping_every_cycle():
    """Waypoints each reached where the robot stands (one waypoint, or all within each other's
    tolerance) would make a lap per cycle, an 'arrived' event every cycle for ever."""
    h = Harness()
    original = h._make

    def already_there(goal, tolerance, speed):
        planner = original(goal, tolerance, speed)
        planner.finished = True  # reached and still on its first cycle
        return planner

    h.job._make = already_there
    assert h.send("mission", Waypoint(1, 0), Waypoint(1.05, 0), loop=True)["ok"]
    assert [h.cycle(t) for t in (0.0, 0.05, 0.1)] == [STOP] * 3
    assert h.names() == ["arrived", "arrived", "finished"]
    ended = h.finished()
    assert ended["outcome"] == "failed" and "without moving" in ended["reason"]
    assert h.job.state == "idle" and len(h.planners) == 2


def test_a_looping_mission_that_drives_once_per_lap_keeps_lapping():
    h = Harness()
    assert h.send("mission", Waypoint(1, 0), loop=True)["ok"]
    for lap in range(3):
        assert h.cycle(lap) == DRIVE  # one driven cycle per lap
        h.planner.finished = True
        assert h.cycle(lap + 0.5) == STOP
    assert h.names() == ["arrived"] * 3 and h.job.state == "navigating"


# --- in the control loop --------------------------------------------------------------------

def test_the_loop_drives_a_goal_from_the_hand_off_and_reports_past_its_stats_interval():
    """ControlLoop with MissionJob on simulated time, for longer than loop.stats_interval_s
    (the periodic statistics line reads the job's summary: it once faulted the loop here)."""
    from doubles import FreshFeedbackLink, SimClock

    from runtime.config.settings import Calibration, Config
    from runtime.process.control_server import ControlHandoff
    from runtime.process.loop import ControlLoop, State
    from runtime.process.sdnotify import SystemdNotifier

    cfg = Config()
    clock = SimClock()
    handoff = ControlHandoff()
    planners: list[FakePlanner] = []

    class Arriving(FakePlanner):
        """Arrives on its 21st cycle."""

        def prepare(self, now: float, odom: Odometry, world: Any) -> Prepared:
            self.finished = len(self.prepared) >= 20
            return super().prepare(now, odom, world)

    def make(goal, tolerance, speed):
        planners.append(Arriving(goal, tolerance, speed))
        return planners[-1]

    job = MissionJob(cfg.control, "dwa", make, handoff.post_event)
    link = FreshFeedbackLink(clock)
    cycles = int(cfg.loop.stats_interval_s * cfg.loop.control_hz) + 50
    loop = ControlLoop(cfg, Calibration(), link, job, SystemdNotifier(None), clock=clock,
                       max_cycles=cycles, wait=clock.wait, control=handoff)
    handoff.commands.append((7, Request("goal", "g", (Waypoint(1.0, 0.0),))))
    report = loop.run()
    assert report.state is State.STOPPED and report.exit_code == 0, report.reason
    assert report.cycles == cycles
    assert len(planners) == 1 and planners[0].goal == (1.0, 0.0)
    moving = [c for c in link.commands if c != STOP]
    assert moving and all(c.v > 0 for c in moving)  # it drove (through the limits)
    assert link.commands[-1] == STOP
    sent = list(handoff.outgoing)
    assert sent[0] == (7, {"v": 1, "type": "reply", "id": "g", "ok": True, "goal_id": 1,
                           "state": "navigating", "waypoints": [{"x": 1.0, "y": 0.0}]})
    events = [m["event"] for key, m in sent[1:] if key is None]
    assert events == ["arrived", "finished"]
    assert job.summary()["outcomes"]["reached"] == 1
    assert handoff.status["mission"]["state"] == "idle"
    assert handoff.status["state"] == "STOPPED"
