"""`safemove eval`: seeded episodes per scenario, lock-stepped in one process, scored as in the
paper's table.

Each episode runs the runtime's `Pipeline.step` on simulated time (`LockstepEpisode`: the base
model through the real codec, rendered D435 frames; the cycle's command back to the base), with
the planner job (the DWA baseline or the SafeMove policy, each through the shield) deciding each
cycle. Only the serial and socket I/O and the wall clock are left out: the planner budgets (DWA
refinement, shield candidate search) are their count limits, so an episode is deterministic from
its seed and does not depend on the machine's load.

The world judges each episode from ground truth: success (within the scenario's goal tolerance),
collision, or timeout. A collision is at fault when the robot drove into the other body or the
body was not coming at it; `moving` counts every collision where the robot was moving at all
(sim_stub/world.py has the rule and why). Path length and speed come from the true trajectory.

With `EvalSettings.trajectories` each episode also keeps that trajectory (`Trajectory`: the
robot's true position in the world frame at every control cycle, where the people were at the
end) for `safemove eval --plots` (sim_stub/plots.py); it is not part of the JSON result.
"""

from __future__ import annotations

import logging
from array import array
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from drivers.depth_source import D435_HFOV_DEG
from runtime.config.settings import LoadedConfig, load_config
from runtime.jobs.trained_settings import trained_settings_report
from runtime.pipeline import Pipeline
from runtime.policy.actor import Policy
from runtime.policy.shipped import variant_of
from runtime.process.cycle_record import CycleRecord
from runtime.process.recorder import Recorder, recording_metadata
from sim_stub.binomial import wilson_interval
from sim_stub.lockstep import LockstepEpisode
from sim_stub.provenance import source_commit
from sim_stub.scenario import load_scenario
from sim_stub.view_clock import ViewClock

PLANNERS = ("dwa", "safemove")


@dataclass(frozen=True)
class EvalSettings:
    """What every episode shares (picklable: episodes may run in worker processes)."""

    planner: str
    config_path: Path | None
    overrides: tuple[str, ...]
    model: Path | None  # the actor for safemove (the command line resolves --variant to its file)
    fps: float
    noise: bool
    crowd: str = "scenario"  # scenario | reactive | oblivious: whether agents see the robot
    trajectories: bool = False  # keep each episode's Trajectory (for --plots)
    record: Path | None = None  # a flight recording of each episode in this directory
    camera_hfov_deg: float = D435_HFOV_DEG  # the simulated depth camera's horizontal view
    surround_people: bool = False  # every person around as a sighting (sim_stub.surround_people)


@dataclass(frozen=True)
class Trajectory:
    """An episode's ground truth for pictures, in the world frame: the robot's position at the
    start and at every control cycle, then where the world judged the episode over (float32,
    shape (N, 2), m); the goal it was sent to; the people's positions at the end (at the
    contact for a collision) and their radius."""

    xy: np.ndarray
    goal: tuple[float, float]
    people_xy: np.ndarray  # (M, 2)
    people_radius: float


@dataclass(frozen=True)
class EpisodeResult:
    scenario: str
    seed: int
    status: str  # success | collision | timeout
    time_s: float
    path_length_m: float
    at_fault: bool
    moving_at_contact: bool  # strict passive safety: the robot moved at the collision
    collided_with: str | None
    contact_bearing_deg: float | None  # where the other body was: 0 ahead, + left
    min_separation_m: float
    shield_interventions: int
    cycles: int
    job_p99_ms: float
    # a contact with a person: how long they had been inside the camera's view without a break
    # (sim_stub.view_clock; 0: they came from outside it); None for other episodes
    contact_in_view_s: float | None = None
    # the stall recovery (runtime.planning.stall_recovery): escapes, and takeovers of a policy
    stall_escapes: int = 0
    dwa_takeovers: int = 0
    # shield_interventions by kind (replaced by a certified candidate, turned in place, braked)
    shield_kinds: dict[str, int] = field(default_factory=dict)
    # with EvalSettings.trajectories only; never in the JSON result (`episode_dict`)
    trajectory: Trajectory | None = field(default=None, repr=False, compare=False)

    def episode_dict(self) -> dict[str, Any]:
        """The JSON result's entry for this episode: every field but the trajectory."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "trajectory"}


def make_job(settings: EvalSettings, goal_odom: tuple[float, float], loaded: LoadedConfig
             ) -> Any:
    """The planner job `safemove run --planner …` would run, with its budgets counted in
    refinement rounds and shield candidates instead of wall time (no clock): an episode's
    result does not depend on how busy the machine is."""
    if settings.planner == "dwa":
        from runtime.jobs.dwa import DWAJob

        return DWAJob(goal_odom, loaded.config, None)
    from runtime.jobs.safemove import safemove_job

    if settings.model is None:
        raise ValueError("EvalSettings: the safemove planner needs a model")
    return safemove_job(settings.model, goal_odom, loaded.config, None)


def run_episode(scenario_name: str, seed: int, settings: EvalSettings) -> EpisodeResult:
    """One seeded episode to its judged end (see the module docs)."""
    loaded = load_config(settings.config_path, list(settings.overrides))
    episode = LockstepEpisode(scenario_name, seed, loaded.config, loaded.calibration,
                              settings.fps, settings.noise, settings.crowd,
                              settings.camera_hfov_deg, settings.surround_people)
    job = make_job(settings, episode.goal_odom, loaded)
    pipeline = Pipeline(episode.config, loaded.calibration, job)
    recorder = None
    if settings.record is not None:
        recorder = _episode_recorder(settings.record, scenario_name, seed, loaded, episode, job)
    job_s: list[float] = []
    robot = episode.world.robot  # the world's ground truth, updated in place
    crowd = episode.world.crowd
    radii = np.full(len(crowd.positions), float(episode.world.scenario.crowd.radius))
    in_view = ViewClock(loaded.calibration.camera.translation_m[:2], settings.camera_hfov_deg,
                        loaded.config.perception.range_max_m, len(radii))
    xy: array[float] | None = array("f", (robot.x, robot.y)) if settings.trajectories else None
    while (inp := episode.cycle()) is not None:
        if xy is not None:
            xy.extend((robot.x, robot.y))
        in_view.update(inp.t, (robot.x, robot.y, robot.theta), crowd.positions, radii)
        cycle = pipeline.step(inp)
        job_s.append(cycle.stage_s["job"])
        episode.send(cycle.command)
        if recorder is not None:
            recorder.offer(CycleRecord(inp.t, "DEGRADED" if cycle.hold else "RUNNING",
                                       tuple(inp.increments), tuple(inp.frames),
                                       pipeline.perceived_now, inp.feedback_t, cycle,
                                       job.trace() if cycle.hold is None else None))
        episode.looking = not job.finished
    if recorder is not None:
        recorder.stop()
    world = episode.world
    out = world.outcome
    summary = job.summary()
    shield_kinds = {k: int(n) for k, n in summary.get("shield_interventions", {}).items()}
    trajectory = None
    if xy is not None:
        xy.extend((robot.x, robot.y))  # where the episode was judged over (the contact)
        trajectory = Trajectory(
            np.frombuffer(xy, dtype=np.float32).reshape(-1, 2).copy(),
            (float(world.goal[0]), float(world.goal[1])),
            world.crowd.positions.astype(np.float32), float(world.scenario.crowd.radius))
    return EpisodeResult(
        scenario=scenario_name, seed=seed, status=out.status, time_s=out.t,
        path_length_m=episode.path_length_m, at_fault=bool(out.at_fault),
        moving_at_contact=out.contact is not None and out.contact.moving,
        collided_with=out.collided_with,
        contact_bearing_deg=None if out.contact is None else out.contact.bearing_deg,
        min_separation_m=float(world.min_separation),
        shield_interventions=sum(shield_kinds.values()),
        cycles=episode.cycles,
        job_p99_ms=float(np.percentile(1e3 * np.array(job_s), 99)) if job_s else 0.0,
        contact_in_view_s=(in_view.seen_for(int(out.collided_with.split()[1]), out.t)
                           if out.collided_with and out.collided_with.startswith("agent ")
                           else None),
        stall_escapes=int(summary.get("stall_escapes", 0)),
        dwa_takeovers=int(summary.get("dwa_takeovers", 0)),
        shield_kinds=shield_kinds,
        trajectory=trajectory)


def _episode_recorder(directory: Path, scenario: str, seed: int, loaded: LoadedConfig,
                      episode: LockstepEpisode, job: Any) -> Recorder:
    """One file per episode, `<scenario>-seed<N>-….mcap`; the episode waits for the writer
    rather than lose a cycle (it has no deadline), and its budgets are counts (no clock)."""
    cfg = episode.config  # the one the episode's pipeline runs (it renders what is read)
    name = Path(scenario).stem if scenario.endswith((".yaml", ".yml")) else scenario
    rec_cfg = replace(cfg.recorder, file_max_mb=100000.0, file_max_s=86400.0,
                      total_max_mb=1000000.0)
    as_run = replace(loaded, config=cfg)
    recorder = Recorder(directory, rec_cfg, loaded.calibration.camera,
                        cfg.perception.decimation,
                        recording_metadata(as_run, job, scenario=scenario, seed=str(seed)),
                        prefix=f"{name}-seed{seed}", block=True)
    recorder.start()
    return recorder


def _run_one(task: tuple[str, int, EvalSettings]) -> EpisodeResult:
    logging.getLogger("safemove").setLevel(logging.WARNING)  # per-cycle shield logs are noise here
    return run_episode(*task)


def summarise(results: list[EpisodeResult]) -> dict[str, Any]:
    """The paper's columns for one scenario (path length and speed over successes), plus
    at-fault collisions and shield interventions."""
    n = len(results)
    ok = [r for r in results if r.status == "success"]
    coll = [r for r in results if r.status == "collision"]
    return {
        "episodes": n,
        "success_rate": len(ok) / n,
        "success_ci95": list(wilson_interval(len(ok), n)),
        "collision_rate": len(coll) / n,
        "timeout_rate": sum(r.status == "timeout" for r in results) / n,
        "at_fault_collisions": sum(r.at_fault for r in coll),
        "moving_collisions": sum(r.moving_at_contact for r in coll),
        "avg_path_length_m": float(np.mean([r.path_length_m for r in ok])) if ok else None,
        "avg_speed_m_s": (float(np.mean([r.path_length_m / r.time_s for r in ok if r.time_s > 0]))
                          if ok else None),
        "avg_time_s": float(np.mean([r.time_s for r in ok])) if ok else None,
        "shield_interventions": sum(r.shield_interventions for r in results),
        "shield_interventions_per_episode": sum(r.shield_interventions for r in results) / n,
        "shield_interventions_by_kind": dict(sum((Counter(r.shield_kinds) for r in results),
                                                 Counter())),
        "min_separation_m": float(min(r.min_separation_m for r in results)),
        "stall_escapes": sum(r.stall_escapes for r in results),
        "dwa_takeovers": sum(r.dwa_takeovers for r in results),
        "job_p99_ms": float(max(r.job_p99_ms for r in results)),
    }


def evaluate(scenarios: list[str], episodes: int, seed: int, settings: EvalSettings,
             jobs: int = 1, progress: Callable[[EpisodeResult], None] | None = None,
             trajectories: list[Trajectory | None] | None = None) -> dict[str, Any]:
    """`episodes` seeded episodes (seeds seed, seed+1, …) of each scenario; `jobs` worker
    processes. `progress` gets each episode as it ends (with workers: in the order they end).
    Returns the per-scenario summaries and every episode, in task order; `trajectories`, when
    given, gets each episode's trajectory in the same order (None unless
    `settings.trajectories`)."""
    commit = source_commit()  # the code that runs, taken before it does
    for name in scenarios:
        load_scenario(name)  # a bad name or file fails here, once, with its message
    loaded = load_config(settings.config_path, list(settings.overrides))
    model = settings.model if settings.planner == "safemove" else None
    trained = None
    if model is not None:  # a bad model refuses here, once, before any episode
        policy = Policy(model, loaded.config.policy)
        trained = trained_settings_report(policy.training, loaded.config)
        trained.log(str(model))
    tasks = [(name, seed + i, settings) for name in scenarios for i in range(episodes)]
    results: list[EpisodeResult] = []
    if jobs <= 1:
        for task in tasks:
            results.append(_run_one(task))
            if progress is not None:
                progress(results[-1])
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_run_one, task) for task in tasks]
            for done in as_completed(futures):
                if progress is not None:
                    progress(done.result())
            results = [f.result() for f in futures]
    if trajectories is not None:
        trajectories.extend(r.trajectory for r in results)
    return {
        "commit": commit,
        "planner": settings.planner,
        "model": None if model is None else str(model),
        "variant": None if model is None else variant_of(model),
        "fps": settings.fps,
        "noise": settings.noise,
        "crowd": settings.crowd,
        "camera_hfov_deg": settings.camera_hfov_deg,
        "surround_people": settings.surround_people,
        "config": None if settings.config_path is None else str(settings.config_path),
        "overrides": list(settings.overrides),
        # the settings that shape the policy's loop where they differ from its training's
        "trained_settings": None if trained is None else trained.as_dict(),
        "scenarios": {name: summarise([r for r in results if r.scenario == name])
                      for name in scenarios},
        "episodes": [r.episode_dict() for r in results],
    }


def table(result: dict[str, Any]) -> str:
    """The per-scenario table as text (rates in %)."""

    def cell(x: float | None, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    rows = [(f"{'scenario':<16}{'success':>9}{'95 % CI':>10}{'collision':>10}{'timeout':>9}"
             f"{'at fault':>9}{'moving':>7}{'path m':>8}{'speed m/s':>10}{'shield':>8}")]
    for name, s in result["scenarios"].items():
        ci = f"{100 * s['success_ci95'][0]:.0f}-{100 * s['success_ci95'][1]:.0f}%"
        rows.append(f"{name:<16}{100 * s['success_rate']:>8.0f}%{ci:>10}"
                    f"{100 * s['collision_rate']:>9.0f}%"
                    f"{100 * s['timeout_rate']:>8.0f}%{s['at_fault_collisions']:>9d}"
                    f"{s['moving_collisions']:>7d}"
                    f"{cell(s['avg_path_length_m'], '.2f'):>8}{cell(s['avg_speed_m_s'], '.3f'):>10}"
                    f"{s['shield_interventions']:>8d}")
    return "\n".join(rows)
