"""Recorded observations for the export's parity check: what the robot's actor will really see.

A lock-stepped simulated run in one process, deterministic for a spec and a seed: the world of
scenario paper_b (12 oblivious people, 4 static obstacles), depth rendered at 424×240 (the
D435's half-resolution mode, 4× cheaper than 848×480) every other 20 Hz cycle, then exactly
the runtime's path: `WorldModel` (perception → obstacle memory → tracking) →
`PlanningStep.prepare` (goal, track prediction, DWA with its refinement bounded by rounds, not
by a clock) → `SpecObserver.observe` (corridor + the spec's builder). Odometry is the world's
ground truth (the evaluation harness, sim_stub/evaluate.py, adds the base and the EKF).
The robot follows DWA's best command; when an episode ends (goal, collision, time limit) the
next seed starts. Random observations fill the spec's bounds uniformly; these fill it as a run
does: mostly free scan bins, small speeds, goal far away, etc.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from drivers.depth_source import D435_848x480
from runtime.config import Config
from runtime.obs_spec import ObsSpec
from runtime.planning_step import PlanningStep
from runtime.safemove_job import SpecObserver
from runtime.types import DepthFrame, DepthIntrinsics, Odometry
from runtime.world_model import WorldModel, WorldState
from sim_stub.depth_render import DepthRenderer
from sim_stub.scenario import load_scenario
from sim_stub.sim_server import BASE_LINK_HEIGHT_M, scene_from
from sim_stub.world import World

CONTROL_HZ = 20.0
DEPTH_EVERY = 2  # cycles per depth frame (10 fps)
SCENARIO = "paper_b"


def _half_resolution(k: DepthIntrinsics) -> DepthIntrinsics:
    return DepthIntrinsics(k.width // 2, k.height // 2, k.fx / 2, k.fy / 2, (k.cx + 0.5) / 2 - 0.5,
                           (k.cy + 0.5) / 2 - 0.5, k.depth_unit_m)


def recorded_observations(spec: ObsSpec, count: int, seed: int = 0,
                          config: Config | None = None) -> np.ndarray:
    """(count, spec.size) float32 observations from simulated runs (module docs)."""
    cfg = config if config is not None else Config()
    cfg = replace(cfg, perception=replace(cfg.perception, decimation=2))
    scenario = load_scenario(SCENARIO)
    intrinsics = _half_resolution(D435_848x480)
    observer = SpecObserver(spec)
    out = np.empty((count, spec.size), dtype=np.float32)
    dt = 1.0 / CONTROL_HZ
    n, episode = 0, 0
    while n < count:
        world = World(scenario, seed=seed + episode, limits=cfg.limits)
        episode += 1
        renderer = DepthRenderer(intrinsics, base_z=BASE_LINK_HEIGHT_M, seed=world.seed)
        model = WorldModel(cfg, renderer.mount)
        planning = PlanningStep(tuple(world.goal), cfg, None, "DWA")
        state: WorldState | None = None
        cycle = 0
        while n < count and not world.outcome.done:
            r = world.robot
            odom = Odometry(world.t, r.x, r.y, r.theta, r.v, r.omega)
            if cycle % DEPTH_EVERY == 0:
                snap = world.snapshot()
                depth = renderer.render((r.x, r.y, r.theta), scene_from(world, snap))
                state = model.update(DepthFrame(depth, world.t, cycle, intrinsics), odom)
            ctx = planning.prepare(world.t, odom, state)
            v, w = 0.0, 0.0
            if ctx is not None and state is not None:
                out[n] = observer.observe(ctx, odom, state)
                n += 1
                v, w = ctx.dwa.best
            world.step(dt, v, w)
            cycle += 1
    return out


def simulated_observations(spec: ObsSpec, count: int) -> tuple[np.ndarray, str]:
    """`count` recorded observations for the export's parity check, and their provenance."""
    return recorded_observations(spec, count), f"simulated run, scenario {SCENARIO}, seed 0"
