"""`safemove record`: rendered simulator depth written as a real pyrealsense2 recording.

Lock-stepped in one process (no pty, no sockets): the world advances exactly 1/fps per frame
with the robot driven by a fixed twist, so the same arguments always give the same frames and
tests can regenerate what a recording must contain.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from drivers.depth_source import D435_848x480
from drivers.realsense.record import DepthRecorder
from runtime.config.settings import CameraMount, LimitsConfig
from runtime.types import DepthFrame, Twist
from sim_stub.depth_render import DepthRenderer
from sim_stub.scenario import Scenario
from sim_stub.sim_server import BASE_LINK_HEIGHT_M, scene_from
from sim_stub.world import World


def simulated_frames(
    scenario: Scenario,
    frames: int,
    fps: float,
    twist: Twist,
    mount: CameraMount,
    limits: LimitsConfig,
    seed: int | None = None,
    noise: bool = False,
) -> Iterator[DepthFrame]:
    """Deterministic frames: frame k shows the world at t = k / fps (timestamps in seconds)."""
    world = World(scenario, seed=seed, limits=limits)
    renderer = DepthRenderer(D435_848x480, mount, base_z=BASE_LINK_HEIGHT_M, seed=world.seed)
    dt = 1.0 / fps
    for k in range(frames):
        if k:
            world.step(dt, twist.v, twist.omega)
        snap = world.snapshot()
        depth = renderer.render(tuple(snap.robot_pose), scene_from(world, snap), noise=noise)
        yield DepthFrame(depth, k * dt, k, renderer.intrinsics)


def record(path: Path, frames: Iterator[DepthFrame], fps: float) -> int:
    """Write frames to a .db3 recording (uncompressed); returns how many were written."""
    count = 0
    with DepthRecorder(path, D435_848x480, fps=round(fps)) as recorder:
        for frame in frames:
            recorder.write(frame.depth, frame.t * 1000.0, frame.frame_number)
            count += 1
    return count
