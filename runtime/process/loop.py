"""The control loop: the rate keeper, the device I/O and the safety state machine around
`Pipeline.step`.

Each cycle: drain base feedback and depth → `Pipeline.step` (odometry, world model, health,
the job, NaN guard, limits) → base. A cycle the pipeline holds is a DEGRADED cycle.
INIT → RUNNING ⇄ DEGRADED → STOPPED | FAULT. The clock and the wait between cycles are
injected, so a test steps the loop on simulated time without sleeping.
"""

from __future__ import annotations

import enum
import gc
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

from runtime.config.settings import Calibration, Config
from runtime.control.protocol import Request
from runtime.errors import DeviceError
from runtime.perception.world_model import WorldState
from runtime.pipeline import PIPELINE_STAGES, CycleInput, CycleResult, Job, Pipeline
from runtime.process.control_server import MAX_PENDING, ControlHandoff
from runtime.process.cycle_record import CycleRecord
from runtime.process.recorder import Recorder
from runtime.process.sdnotify import SystemdNotifier
from runtime.process.timing import RateKeeper, RingStats
from runtime.types import STOP, DecisionTrace, DepthFrame, Odometry, Twist, WheelIncrement

log = logging.getLogger("safemove.loop")


class State(str, enum.Enum):
    INIT = "INIT"
    RUNNING = "RUNNING"
    DEGRADED = "DEGRADED"
    STOPPED = "STOPPED"
    FAULT = "FAULT"


class BaseLink(Protocol):
    """What the loop needs from the base driver (drivers.spark.link.SparkBaseLink)."""

    @property
    def last_feedback_time(self) -> float | None: ...

    def poll(self) -> list[WheelIncrement]: ...

    def set_command(self, twist: Twist, now: float) -> None: ...


class CommandedJob(Job, Protocol):
    """A job that takes commands from the control socket (runtime.jobs.mission.MissionJob)."""

    interventions: int

    def handle(self, request: Request, now: float, odom: Odometry) -> dict[str, Any]: ...

    def held(self, now: float, reason: str, odom: Odometry) -> None: ...

    def shutdown(self, reason: str, odom: Odometry) -> None: ...

    def status(self) -> dict[str, Any]: ...


class DepthInput(Protocol):
    """What the loop needs from a depth source (drivers.depth_source.DepthSource)."""

    def poll(self) -> DepthFrame | None: ...


@dataclass
class DepthStats:
    """Every depth frame the loop received: count, frame-number gaps, the latest frame's age,
    and the frames the guard dropped, by reason."""

    frames: int = 0
    gaps: int = 0
    missing: int = 0
    last_frame_number: int | None = None
    last_t: float | None = None
    rejected: dict[str, int] = field(default_factory=dict)  # the guard's live counts

    def take(self, frame: DepthFrame) -> None:
        if self.last_frame_number is not None and frame.frame_number != self.last_frame_number + 1:
            self.gaps += 1
            self.missing += max(0, frame.frame_number - self.last_frame_number - 1)
        self.frames += 1
        self.last_frame_number = frame.frame_number
        self.last_t = frame.t


STAGES = ("base_read", "depth_read", *PIPELINE_STAGES, "base_write", "cycle", "floor_check",
          "control", "record", "gc")
GC_FULL_EVERY = 600  # cycles between full collections (30 s at 20 Hz)


@dataclass
class LoopReport:
    """What a finished run reports (printed as JSON by the CLI and the benchmarks)."""

    state: State
    exit_code: int
    reason: str
    cycles: int
    misses: int
    degraded_cycles: int
    nonfinite_commands: int
    odometry: Odometry
    timings: RingStats
    depth: DepthStats | None = None
    world: WorldState | None = None
    transitions: list[tuple[float, str, str]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        o = self.odometry
        return {
            "state": self.state.value,
            "exit_code": self.exit_code,
            "reason": self.reason,
            "cycles": self.cycles,
            "misses": self.misses,
            "degraded_cycles": self.degraded_cycles,
            "nonfinite_commands": self.nonfinite_commands,
            "odometry": {
                "x": o.x, "y": o.y, "theta": o.theta, "distance": o.distance, "v": o.v,
                "omega": o.omega,
            },
            "cycle_ms": self.timings.summary("cycle"),
            "period_jitter_ms": self.timings.summary("period_jitter"),
            "stage_ms": {s: self.timings.summary(s) for s in STAGES if s != "cycle"},
            "world": None if self.world is None else {
                "tracks_confirmed": sum(t.confirmed for t in self.world.tracks),
                "memory_points": len(self.world.points_base),
                "floor_ok": self.world.floor_ok,
            },
            "depth": None if self.depth is None else {
                "frames": self.depth.frames, "gaps": self.depth.gaps,
                "missing": self.depth.missing, "last_frame_number": self.depth.last_frame_number,
                "rejected": dict(self.depth.rejected),
            },
            "transitions": [{"t": t, "from": a, "to": b} for t, a, b in self.transitions],
        }


class ControlLoop:
    """Runs a job against the base at `control_hz` until it finishes, is stopped, or faults."""

    def __init__(
        self,
        config: Config,
        calibration: Calibration,
        link: BaseLink,
        job: Job,
        notifier: SystemdNotifier,
        clock: Callable[[], float] = time.monotonic,
        max_cycles: int | None = None,
        depth: DepthInput | None = None,
        wait: Callable[[float], bool] | None = None,
        control: ControlHandoff | None = None,
        recorder: Recorder | None = None,
    ) -> None:
        """`wait(seconds)`: sleep, True when a stop was requested meanwhile (default: on the
        loop's stop event, so a signal handler ends the sleep at once). `control`: the hand-off
        of the control socket; the job must then be a CommandedJob. `recorder`: the flight
        recorder, handed every cycle after its command."""
        self._cfg = config
        self._depth = depth
        self._pipeline = Pipeline(config, calibration, job, depth=depth is not None, clock=clock)
        self.depth_stats = (DepthStats(rejected=self._pipeline.depth_guard.rejected)
                            if depth is not None else None)
        self._floor_ok: bool | None = None
        self._floor_failed = 0  # failed floor checks in a row
        self._link = link
        self._job = job
        self._notifier = notifier
        self._clock = clock
        self._max_cycles = max_cycles
        self._stop = threading.Event()
        self._wait = wait if wait is not None else self._stop.wait
        self._stop_reason = ""
        self.state = State.INIT
        self.timings = RingStats((*STAGES, "period_jitter"))
        self._ch = {name: self.timings.channel(name) for name in self.timings.names}
        self._transitions: list[tuple[float, str, str]] = []
        self._rate = RateKeeper(1.0 / config.loop.control_hz, clock, self._wait)
        self._control = control
        self._recorder = recorder
        self._applied: list[dict[str, Any]] = []  # control commands applied after this cycle
        self._startup_depth: DepthFrame | None = None  # see _run_cycles
        self._startup_control: list[dict[str, Any]] = []  # see _wait_for_inputs
        self._control_t: float | None = None
        self._last_fault: dict[str, Any] | None = None
        self._counters = {"cycles": 0, "degraded": 0, "nonfinite": 0}

    @property
    def odometry(self) -> Odometry:
        return self._pipeline.odom

    @property
    def world(self) -> WorldState | None:
        return self._pipeline.world

    @property
    def latest_depth(self) -> DepthFrame | None:
        return self._pipeline.latest_depth

    def request_stop(self, reason: str) -> None:
        """Ask the loop to stop at once; safe to call from a signal handler."""
        self._stop_reason = self._stop_reason or reason
        self._stop.set()

    def _set_state(self, state: State, now: float, why: str) -> None:
        if state is self.state:
            return
        log.log(
            logging.WARNING if state in (State.DEGRADED, State.FAULT) else logging.INFO,
            "state %s -> %s: %s", self.state.value, state.value, why,
        )
        self._transitions.append((now, self.state.value, state.value))
        if state in (State.DEGRADED, State.FAULT):
            self._last_fault = {"t": now, "state": state.value, "reason": why}
        self.state = state
        self._notifier.status(f"{state.value}: {why}")

    def _wait_for_inputs(self, period: float) -> bool:
        """INIT: keep the base stopped until base feedback (and depth, if configured) arrive;
        False if stopped meanwhile."""
        timeout = self._cfg.loop.startup_timeout_s
        deadline = self._clock() + timeout
        while self._link.last_feedback_time is None or (
            self._depth is not None and self.latest_depth is None
        ):
            now = self._clock()
            self._pipeline.admit(self._drain_depth(), now)
            if now > deadline:
                if self._link.last_feedback_time is None:
                    raise DeviceError(
                        f"base device {self._cfg.base.port}: no feedback within {timeout:g} s"
                        " (sent the vendor and the well-formed query); is the base powered on"
                        " and is this its port?"
                    )
                raise DeviceError(
                    f"depth source '{self._cfg.depth.source}': no frame within {timeout:g} s"
                )
            self._link.set_command(STOP, now)
            if self._control is not None:
                why = "INIT: waiting for base feedback and depth"
                self._serve_control(now, why)
                if self._recorder is not None and (self._applied or self._startup_control):
                    # the first cycle's record carries them: a goal given now is replayed now
                    self._startup_control.append({"t": now, "hold": why,
                                                  "commands": self._applied})
                    self._applied = []
            if self._wait(period):
                return False
        return True

    def _drain_depth(self) -> list[DepthFrame]:
        """Every frame that arrived, counted."""
        frames: list[DepthFrame] = []
        if self._depth is None or self.depth_stats is None:
            return frames
        while (frame := self._depth.poll()) is not None:
            self.depth_stats.take(frame)
            frames.append(frame)
        return frames

    def run(self) -> LoopReport:
        """Run to the end. Exceptions inside a cycle become FAULT (exit 1) with the stop sent by
        the link's close(), which the caller does in a finally."""
        period = self._rate.period
        counters = self._counters
        exit_code, reason = 0, ""
        self._notifier.status("INIT: waiting for base feedback")
        try:
            if self._wait_for_inputs(period):
                self._run_cycles(period, counters)
            if self._job.finished:
                reason = "job finished"
            else:
                reason = self._stop_reason or "stopped"
            self._set_state(State.STOPPED, self._clock(), reason)
        except DeviceError:
            raise
        except Exception as exc:  # a fault: log it whole, stop the robot, exit non-zero
            log.exception("fault in the control loop")
            reason = f"fault: {type(exc).__name__}: {exc}"
            self._set_state(State.FAULT, self._clock(), reason)
            exit_code = 1
        finally:
            gc.enable()
        if self._control is not None:
            self._commanded.shutdown(f"{self.state.value}: {reason}", self.odometry)
            self._publish_status(self._clock(), None)
        self._notifier.stopping(f"{self.state.value}: {reason}")
        return LoopReport(
            state=self.state,
            exit_code=exit_code,
            reason=reason,
            cycles=counters["cycles"],
            misses=self._rate.misses,
            degraded_cycles=counters["degraded"],
            nonfinite_commands=counters["nonfinite"],
            odometry=self.odometry,
            timings=self.timings,
            depth=self.depth_stats,
            world=self.world,
            transitions=self._transitions,
        )

    def _run_cycles(self, period: float, counters: dict[str, int]) -> None:
        cfg = self._cfg
        clock, ch, rec, rate = self._clock, self._ch, self.timings.record, self._rate
        pipeline = self._pipeline
        # the frame INIT admitted: the first cycle plans on it, so its record must carry it
        self._startup_depth = pipeline.latest_depth
        gc.collect()
        gc.freeze()  # start-up objects never need scanning again
        gc.disable()  # collections run between cycles, below, never in the middle of one
        rate.deadline = clock() + period
        self._notifier.ready(f"RUNNING: {self._job.name}")
        self._set_state(State.RUNNING, clock(), "base feedback arrived")
        next_stats = clock() + cfg.loop.stats_interval_s
        last_start: float | None = None
        last_full_gc = 0
        while not self._stop.is_set():
            t0 = clock()
            if last_start is not None:
                rec(ch["period_jitter"], abs((t0 - last_start) - period))
            last_start = t0

            increments = self._link.poll()
            t1 = clock()
            rec(ch["base_read"], t1 - t0)
            frames = self._drain_depth()
            t2 = clock()
            rec(ch["depth_read"], t2 - t1)
            inp = CycleInput(t2, increments, frames, self._link.last_feedback_time)
            out = pipeline.step(inp)
            for stage, seconds in out.stage_s.items():
                rec(ch[stage], seconds)
            if out.hold is None:
                self._set_state(State.RUNNING, t2, "inputs fresh")
            else:
                self._set_state(State.DEGRADED, t2, out.hold)
                counters["degraded"] += 1
            if out.nonfinite is not None:
                counters["nonfinite"] += 1
                log.error("%s: safe stop this cycle", out.nonfinite)
            t4 = clock()
            self._link.set_command(out.command, t4)
            t5 = clock()
            rec(ch["base_write"], t5 - t4)
            rec(ch["cycle"], t5 - t0)
            counters["cycles"] += 1

            if t5 - t0 < period:
                self._notifier.kick_watchdog(t5)
            self._check_floor()
            t5_floor = clock()
            rec(ch["floor_check"], t5_floor - t5)
            t5 = t5_floor
            # the decision of the planner that drove this cycle, taken before the control
            # socket's commands can replace or drop that planner (a cancel, a new goal)
            decided = self._decision_trace(out) if self._recorder is not None else None
            if self._control is not None:
                self._serve_control(t5, out.hold)
                t5_control = clock()
                rec(ch["control"], t5_control - t5)
                t5 = t5_control
            if self._recorder is not None:
                self._record(inp, out, decided)
                t5_record = clock()
                rec(ch["record"], t5_record - t5)
                t5 = t5_record
            if self._job.finished:
                break
            if self._max_cycles is not None and counters["cycles"] >= self._max_cycles:
                self.request_stop("cycle limit reached")
                break
            if cfg.loop.stats_interval_s > 0 and t5 >= next_stats:
                next_stats = t5 + cfg.loop.stats_interval_s
                self._log_stats(counters, rate)
            # A full collection can take ~10 ms: run it only with at least half a period of slack.
            full = counters["cycles"] - last_full_gc >= GC_FULL_EVERY and rate.deadline - t5 > 0.5 * period
            if full:
                last_full_gc = counters["cycles"]
            gc.collect(2 if full else 0)
            rec(ch["gc"], clock() - t5)
            rate.sleep()

    @property
    def _commanded(self) -> CommandedJob:
        return self._job  # type: ignore[return-value]

    def _serve_control(self, now: float, hold: str | None) -> None:
        """In the slack after the command: the hold time of a goal, the commands the control
        socket handed over (at most MAX_PENDING; each takes effect next cycle), and the status
        snapshot. Nothing here waits: the hand-off is deques and one assignment."""
        control, job, odom = self._control, self._commanded, self.odometry
        assert control is not None
        self._control_t = now
        if hold is not None:
            job.held(now, hold, odom)
        for _ in range(MAX_PENDING):
            try:
                client, request = control.commands.popleft()
            except IndexError:
                break
            answer = job.handle(request, now, odom)
            control.post(client, answer)
            if self._recorder is not None:
                self._applied.append({"request": asdict(request), "ok": answer.get("ok")})
        self._publish_status(now, hold)

    def _decision_trace(self, out: CycleResult) -> DecisionTrace | None:
        """The job's trace of this cycle's decision (None: the cycle held, or a job without
        one)."""
        trace = getattr(self._job, "trace", None)
        return trace() if trace is not None and out.hold is None else None

    def _record(self, inp: CycleInput, out: CycleResult, decided: DecisionTrace | None) -> None:
        """Hand the cycle to the recorder: references only (see flight_messages.CycleRecord)."""
        assert self._recorder is not None
        applied, self._applied = tuple(self._applied), []
        frames = tuple(inp.frames)
        if self._startup_depth is not None:
            frames, self._startup_depth = (self._startup_depth, *frames), None
        startup, self._startup_control = tuple(self._startup_control), []
        self._recorder.offer(CycleRecord(
            inp.t, self.state.value, tuple(inp.increments), frames,
            self._pipeline.perceived_now, inp.feedback_t, out,
            decided, applied,
            self._control_t, startup))

    def _publish_status(self, now: float, hold: str | None) -> None:
        if self._control is None:
            return
        o, c = self.odometry, self._counters
        self._control.status = {
            "t": now, "state": self.state.value, "hold_reason": hold,
            "pose": {"x": o.x, "y": o.y, "theta": o.theta},
            "velocity": {"v": o.v, "omega": o.omega},
            "mission": self._commanded.status(),
            "shield_interventions": self._commanded.interventions,
            "missed_deadlines": self._rate.misses, "cycles": c["cycles"],
            "degraded_cycles": c["degraded"], "last_fault": self._last_fault,
        }

    def _check_floor(self) -> None:
        """Health check of the camera's calibration, run in the slack after the command: it
        never delays one. Logged when the verdict changes, a failure only once it has held for
        `perception.floor_alarm_checks` checks in a row: in a crowd, single checks failed and
        passed by turns (14 false alarms in 4 real-time minutes)."""
        verdict = self._pipeline.check_floor()
        if verdict is None or verdict.ok is None:
            return
        self._floor_failed = 0 if verdict.ok else self._floor_failed + 1
        if not verdict.ok and self._floor_failed < self._cfg.perception.floor_alarm_checks:
            return
        if verdict.ok != self._floor_ok:
            self._floor_ok = verdict.ok
            if verdict.ok:
                return
            if math.isnan(verdict.tilt_deg):
                log.warning("no floor plane among the %d points near the calibrated floor in %d"
                            " checks in a row (a wall filling the view, or the camera moved?)",
                            verdict.points, self._floor_failed)
            else:
                log.warning("the floor is not where the calibration puts it in %d checks in a"
                            " row (last: tilt %.1f°, height %.3f m): has the camera moved?",
                            self._floor_failed, verdict.tilt_deg, verdict.height_m)

    def _log_stats(self, counters: dict[str, int], rate: RateKeeper) -> None:
        """The periodic statistics line: per-cycle events are counted here, not logged one by
        one (a journal rate-limits a flood and drops what matters with it)."""
        cyc = self.timings.summary("cycle")
        shield = self._job.summary().get("shield_interventions")
        rejected = self.depth_stats.rejected if self.depth_stats is not None else {}
        log.info(
            "%s: %d cycles, %d missed deadlines, %d degraded; cycle p50 %.2f ms p99 %.2f ms"
            " max %.2f ms%s%s", self.state.value, counters["cycles"], rate.misses,
            counters["degraded"], cyc["p50"], cyc["p99"], cyc["max"],
            "" if shield is None else f"; shield interventions {dict(shield) or 'none'}",
            f"; depth frames dropped {dict(rejected)}" if rejected else "",
        )
