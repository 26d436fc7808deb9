"""`safemove bench control`: what hostile control-socket clients cost the control cycle.

The real loop (the mission job with the DWA planner navigating in `safemove sim`, depth and
base over their real links) runs three phases of the same length, one after another: no
client; FLOOD clients in other processes sending status requests and valid-looking goals 10 km
away as fast as the socket takes them (and reading the replies); SLOW clients that subscribe at
20 Hz and send requests but never read (the service drops each at 1 MiB unread; it
reconnects). Per phase: missed deadlines, cycle and period-jitter p50/p99/max, the control
stage (hand-off drain, status snapshot) p99, requests served, clients dropped, and the
process's resident memory at the end of the phase. The quiet phase is the same-run reference.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

FAR_GOAL = json.dumps({"type": "goal", "x": 10000.0, "y": 0.0}).encode() + b"\n"
STATUS = b'{"type":"status"}\n'


def hostile_client(path: str, mode: str, seconds: float) -> None:
    """Run in a separate process: `flood` or `slow` for `seconds`."""
    end = time.monotonic() + seconds
    batch = (STATUS * 40 + FAR_GOAL * 2) * 10
    while time.monotonic() < end:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(path)
            if mode == "slow":
                s.sendall(b'{"type":"subscribe","rate_hz":20}\n')
            s.settimeout(0.2)
            while time.monotonic() < end:
                s.sendall(batch)
                if mode == "flood":
                    try:
                        while s.recv(1 << 20):
                            pass
                    except TimeoutError:
                        pass
        except OSError:  # dropped by the service (slow) or pushed back: connect again
            time.sleep(0.05)
        finally:
            s.close()


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def bench_control(cycles: int, clients: int) -> dict[str, Any]:
    import tempfile

    from runtime.cli.app import run_job
    from runtime.config.settings import load_config
    from runtime.control.protocol import Request, Waypoint
    from runtime.jobs.dwa import DWAJob
    from runtime.jobs.mission import MissionJob
    from runtime.process.control_server import ControlHandoff
    from sim_stub.emulator_process import EmulatorProcess

    phases: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="sm-bench-", dir="/tmp") as tmp, \
            EmulatorProcess(["paper_b", "--crowd", "reactive"], module="sim_stub.sim_server") as sim:
        path = Path(tmp) / "control.sock"
        loaded = load_config(None, [f"base.port={sim.link}", "depth.source=sim",
                                    f"depth.sim_socket={sim.depth_socket}",
                                    "loop.stats_interval_s=0"])
        cfg = loaded.config
        period = 1.0 / cfg.loop.control_hz
        for phase in ("quiet", "flood", "slow"):
            handoff = ControlHandoff()
            job = MissionJob(cfg.control, "dwa",
                             lambda g, tol, v: DWAJob(g, cfg, time.monotonic,
                                                      arrival_radius_m=tol, speed_limit=v),
                             handoff.post_event)
            # the robot keeps navigating (towards a point it circles back from) all phase long
            handoff.commands.append((0, Request("mission", None, (
                Waypoint(2.0, 0.0), Waypoint(0.0, 0.0)), loop=True)))
            procs = []
            if phase != "quiet":
                seconds = cycles * period + 10.0  # outlives the phase, killed at its end
                code = ("import sys; from sim_stub.bench_control import hostile_client;"
                        " hostile_client(sys.argv[1], sys.argv[2], float(sys.argv[3]))")
                procs = [subprocess.Popen([sys.executable, "-c", code, str(path), phase,
                                           str(seconds)]) for _ in range(clients)]
            try:
                report, link = run_job(loaded, job, max_cycles=cycles,
                                       control=(path, handoff))
            finally:
                for p in procs:
                    p.kill()
                    p.wait()
            full = report.as_dict()
            phases[phase] = {
                "cycles": report.cycles, "misses": report.misses,
                "cycle_ms": full["cycle_ms"], "period_jitter_ms": full["period_jitter_ms"],
                "control_stage_ms": full["stage_ms"]["control"],
                "socket": link.get("control_socket"), "rss_mb_at_end": round(_rss_mb(), 1),
                "goals": job.summary()["goals"],
            }
    return {"bench": "control", "control_hz": 1.0 / period, "hostile_clients": clients,
            "phases": phases}
