"""`safemove sim SCENARIO`: the simulated robot that the real runtime process drives.

One process holds the world (crowd, obstacles, judging), the Spark base emulator on its pty
(whose kinematics move the robot), and a renderer that serves synthetic D435 depth on a Unix
socket. The base loop (50 Hz) steps the world in its tick; a render thread renders the latest
world snapshot at the configured rate and sends each frame to every connected client, so a slow
render never delays base feedback. Events are JSON lines on stdout as for the base emulator;
the world adds `contact` (each contact as it begins, with who was at fault: see world.py) and
`outcome` (the latched verdict: success, collision with its contact, or timeout).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import socket
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from drivers.depth_source import D435_848x480
from drivers.sim_depth_link import encode_frame, frame_digest
from runtime.config.settings import load_config
from runtime.errors import UserError
from runtime.types import DepthFrame
from sim_stub.base_emulator import PtyBaseEmulator
from sim_stub.base_sim import BasePhysics, SparkBaseSim
from sim_stub.depth_render import Box, Cylinder, DepthRenderer, Scene, wall
from sim_stub.scenario import CROWD_MODES, BoxSpec, CylinderSpec, load_scenario, with_crowd
from sim_stub.world import Contact, Snapshot, World, base_to_world

log = logging.getLogger("safemove.sim")

PERSON_HEIGHT_M = 1.7
BASE_LINK_HEIGHT_M = 0.01  # base_link above the floor (protocol sheet)
SEND_TIMEOUT_S = 1.0  # a client that reads nothing for this long is dropped, never waited for


@dataclass
class _Client:
    sock: socket.socket
    frames: int = 0
    digest: int = 0


class DepthServer:
    """Unix stream socket that sends every frame to every connected client."""

    def __init__(self, path: Path, emit: Any, log_frames: bool = False) -> None:
        self.path = path
        self._emit = emit
        self._log_frames = log_frames
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(str(path))
        self._listener.listen(4)
        self._listener.setblocking(False)
        self._clients: list[_Client] = []

    def accept_pending(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except BlockingIOError:
                return
            sock.setblocking(True)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
            sock.settimeout(SEND_TIMEOUT_S)
            self._clients.append(_Client(sock))
            self._emit({"event": "depth_client", "t": time.monotonic(), "clients": len(self._clients)})

    def send(self, data: bytes, frame_number: int, crc: int) -> None:
        for client in list(self._clients):
            try:
                client.sock.sendall(data)
            except OSError as exc:  # gone, or not reading (timeout): drop it, never stall
                self._drop(client, f"{type(exc).__name__}: {exc}")
                continue
            client.frames += 1
            client.digest = frame_digest(client.digest, frame_number, crc)
            if self._log_frames:  # lets a test compare any prefix of the stream, not just all
                self._emit({"event": "depth_sent", "client": client.sock.fileno(),
                            "frames": client.frames, "frame_number": frame_number,
                            "digest": client.digest})

    def _drop(self, client: _Client, why: str) -> None:
        self._clients.remove(client)
        client.sock.close()
        self._emit({"event": "depth_client_closed", "t": time.monotonic(), "why": why,
                    "frames": client.frames, "digest": client.digest})

    def close(self) -> None:
        for client in list(self._clients):
            self._drop(client, "simulator exiting")
        self._listener.close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()


def contact_fields(contact: Contact) -> dict[str, Any]:
    """A contact as event fields; `collided_with` names the other body, as outcomes always have."""
    fields = asdict(contact)
    fields["collided_with"] = fields.pop("with_")
    fields["world_t"] = fields.pop("t")  # the event's own t is the host clock
    return fields


def scene_from(world: World, snap: Snapshot) -> Scene:
    """Renderer scene for a world snapshot: static obstacles plus people as cylinders."""
    cylinders = [Cylinder(float(p[0]), float(p[1]), float(r), PERSON_HEIGHT_M)
                 for p, r in zip(snap.agent_positions, snap.agent_radii)]
    boxes: list[Box] = []
    for o in world.obstacles:
        if isinstance(o, CylinderSpec):
            cylinders.append(Cylinder(o.center[0], o.center[1], o.radius, o.height))
        elif isinstance(o, BoxSpec):
            boxes.append(Box(o.center[0], o.center[1], o.size[0], o.size[1],
                             math.radians(o.yaw_deg), o.height))
        else:
            boxes.append(wall(*o.start, *o.end, thickness=o.thickness, height=o.height))
    return Scene(cylinders=cylinders, boxes=boxes)


class SimWorldLink:
    """Keeps the world's robot on the emulated base's ground truth and renders depth."""

    def __init__(self, world: World, base: SparkBaseSim, renderer: DepthRenderer,
                 server: DepthServer, fps: float, noise: bool) -> None:
        self.world = world
        self._base = base
        self._renderer = renderer
        self._server = server
        self._period = 1.0 / fps
        self._noise = noise
        self._start = (world.robot.x, world.robot.y, world.robot.theta)
        self._last_t: float | None = None
        self._lock = threading.Lock()
        self._snapshot: tuple[float, Snapshot] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._render_loop, name="sim-render", daemon=True)
        self.frames = 0
        self.render_overruns = 0
        self.last_outcome = world.outcome.status
        self.emit: Any = None

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def on_tick(self, now: float) -> None:
        """Base tick: put the robot where the base's kinematics took it, step the crowd."""
        truth = self._base.truth()
        pose = base_to_world(self._start, truth["x"], truth["y"], truth["theta"])
        dt = 0.0 if self._last_t is None else now - self._last_t
        self._last_t = now
        seen = len(self.world.contacts)
        outcome = self.world.follow_robot(dt, *pose, truth["v"], truth["omega"])
        if self.emit is not None:
            for contact in self.world.contacts[seen:]:
                self.emit({"event": "contact", "t": now, **contact_fields(contact)})
            if outcome.status != self.last_outcome:
                self.last_outcome = outcome.status
                self.emit({"event": "outcome", "t": now, "status": outcome.status,
                           **(contact_fields(outcome.contact) if outcome.contact else {})})
        with self._lock:
            self._snapshot = (now, self.world.snapshot())

    def _render_loop(self) -> None:
        deadline = time.monotonic()
        while not self._stop.is_set():
            self._server.accept_pending()
            with self._lock:
                taken = self._snapshot
            if taken is not None:
                stamp, snap = taken
                depth = self._renderer.render(tuple(snap.robot_pose), scene_from(self.world, snap),
                                              noise=self._noise)
                frame = DepthFrame(depth, stamp, self.frames, self._renderer.intrinsics)
                data, crc = encode_frame(frame)
                self._server.send(data, frame.frame_number, crc)
                self.frames += 1
            deadline += self._period
            now = time.monotonic()
            if now > deadline:
                self.render_overruns += 1
                deadline = now
            self._stop.wait(max(0.0, deadline - now))

    def world_event(self, _args: dict[str, Any], now: float) -> None:
        snap = self.world.snapshot()
        self.emit({"event": "world", "t": now, "status": self.world.outcome.status,
                   "robot_pose": snap.robot_pose.tolist(), "goal": snap.goal.tolist(),
                   "agents": snap.agent_positions.tolist(), "depth_frames": self.frames,
                   "render_overruns": self.render_overruns,
                   "min_separation": self.world.min_separation})


def build_arg_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="safemove sim", description=__doc__.splitlines()[0])
    p.add_argument("scenario", help="a shipped scenario name (e.g. paper_a) or a YAML file")
    p.add_argument("--link", type=Path, required=True, help="stable symlink to the base's pty")
    p.add_argument("--depth-socket", type=Path, default=None,
                   help="Unix socket for depth (default: depth.sock beside --link)")
    p.add_argument("--fps", type=float, default=15.0, help="depth frames per second (default 15)")
    p.add_argument("--noise", action="store_true", help="D435-like range noise and edge dropout")
    p.add_argument("--log-depth", action="store_true",
                   help="an event per depth frame sent, with the running digest (for tests)")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's)")
    p.add_argument("--crowd", choices=CROWD_MODES, default="scenario",
                   help="whether the agents see and avoid the robot (default: as the scenario"
                        " says)")
    p.add_argument("--goal", type=int, default=None, help="goal index (default: drawn from seed)")
    p.add_argument("--watchdog-s", type=float, default=0.5, help="the base's own command watchdog")
    p.add_argument("--config", type=Path, default=None,
                   help="config whose calibration gives the TRUE camera mount and limits")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_arg_parser().parse_args(argv)
    if args.depth_socket is None:
        args.depth_socket = args.link.with_name("depth.sock")
    if not 0 < args.fps <= 90:
        print(f"safemove sim: error: --fps must be in (0, 90], got {args.fps}", file=sys.stderr)
        return 2
    try:
        loaded = load_config(args.config, args.overrides)
        scenario = with_crowd(load_scenario(args.scenario), args.crowd)
        world = World(scenario, seed=args.seed, goal_index=args.goal, limits=loaded.config.limits)
    except UserError as exc:
        print(f"safemove sim: error: {exc}", file=sys.stderr)
        return exc.exit_code
    base = SparkBaseSim(BasePhysics(seed=world.seed), "stream", args.watchdog_s, t0=time.monotonic())
    renderer = DepthRenderer(D435_848x480, loaded.calibration.camera, base_z=BASE_LINK_HEIGHT_M,
                             seed=world.seed)
    emulator_box: list[PtyBaseEmulator] = []
    try:
        server = DepthServer(args.depth_socket, lambda e: emulator_box[0].emit(e), args.log_depth)
    except OSError as exc:
        print(f"safemove sim: error: depth socket {args.depth_socket}: {exc.strerror or exc}",
              file=sys.stderr)
        return 2
    link = SimWorldLink(world, base, renderer, server, args.fps, args.noise)
    emulator = PtyBaseEmulator(base, 50.0, args.link, seed=world.seed, on_tick=link.on_tick,
                               extra_ops={"world": link.world_event})
    emulator_box.append(emulator)
    link.emit = emulator.emit
    emulator.emit({"event": "scenario", "name": scenario.name, "seed": world.seed,
                   "goal": world.goal.tolist(),
                   "start": [world.robot.x, world.robot.y, world.robot.theta],
                   "depth_socket": str(args.depth_socket), "fps": args.fps,
                   "crowd_reactive": scenario.crowd.reactive})
    link.start()
    try:
        return emulator.run(sys.stdin.fileno())
    except OSError as exc:
        print(f"safemove sim: cannot run: {exc}", file=sys.stderr)
        return 2
    finally:
        link.stop()
        server.close()


if __name__ == "__main__":
    sys.exit(main())
