"""`safemove bench startup`: time from process start to READY=1 and RSS at READY, for the
service's own command line against `safemove sim`, as systemd would see it.

READY=1 is read from a real NOTIFY_SOCKET (the runtime sends it from its first RUNNING cycle:
base feedback and depth have arrived, the model is loaded and warmed up). The reference, timed
in the same run, is the bare interpreter with numpy (`python -c "import numpy"`): on a loaded
machine both grow, and their ratio says more than either alone.
"""

from __future__ import annotations

import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from runtime.errors import UserError
from sim_stub.emulator_process import EmulatorProcess
from sim_stub.soak import last_line, rss_mb

READY_TIMEOUT_S = 60.0


def _time_reference() -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import numpy"], check=True)
    return time.perf_counter() - t0


def _one_start(cmd: list[str], notify: socket.socket, notify_path: str) -> tuple[float, float]:
    """Seconds to READY=1 and RSS (MB) then, for one start of the runtime."""
    env = {**os.environ, "NOTIFY_SOCKET": notify_path, "PYTHONUNBUFFERED": "1"}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    rss = None
    try:
        notify.settimeout(0.1)  # short waits: a runtime that refuses to start is seen at once
        while proc.poll() is None:
            if time.perf_counter() - t0 > READY_TIMEOUT_S:
                raise UserError(f"bench startup: no READY=1 within {READY_TIMEOUT_S:g} s")
            try:
                msg = notify.recv(4096).decode(errors="replace")
            except TimeoutError:
                continue
            if "READY=1" in msg.split("\n"):
                ready = time.perf_counter() - t0
                rss = rss_mb(proc.pid)
                break
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    if rss is None:
        raise UserError("bench startup: the runtime exited before READY:"
                        f" {last_line(err.decode(errors='replace'))}")
    return ready, rss


def bench_startup(runs: int, planner: str, model: Path | None) -> dict[str, Any]:
    """`runs` starts of `safemove run --planner PLANNER` with `model` as its actor (None: what
    the runtime picks itself, the shipped policy for safemove)."""
    ready_s: list[float] = []
    rss: list[float] = []
    refs: list[float] = []
    with (tempfile.TemporaryDirectory(prefix="safemove-startup-") as tmp,
          EmulatorProcess(["paper_a", "--fps", "15"], module="sim_stub.sim_server") as sim,
          socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify):
        notify_path = str(Path(tmp) / "notify.sock")
        notify.bind(notify_path)
        cmd = [sys.executable, "-m", "runtime.cli.main", "run", "--planner", planner,
               *(["--goal", "50", "0"] if planner != "hold" else []),
               *(["--model", str(model)] if model is not None else []),
               "--set", f"base.port={sim.link}", "--set", "depth.source=sim",
               "--set", f"depth.sim_socket={sim.depth_socket}"]
        for k in range(runs):
            refs.append(_time_reference())
            t, r = _one_start(cmd, notify, notify_path)
            ready_s.append(t)
            rss.append(r)
            print(f"start {k + 1}/{runs}: READY after {t:.3f} s, RSS {r:.1f} MB"
                  f" (reference {refs[-1]:.3f} s)", file=sys.stderr)
    med, ref = statistics.median(ready_s), statistics.median(refs)
    return {
        "bench": "startup", "planner": planner,
        "model": str(model) if model is not None else None, "runs": runs,
        "ready_s": {"median": round(med, 3), "min": round(min(ready_s), 3),
                    "max": round(max(ready_s), 3)},
        "rss_at_ready_mb": {"median": round(statistics.median(rss), 1),
                            "max": round(max(rss), 1)},
        "reference_python_numpy_s": round(ref, 3),
        "ready_over_reference": round(med / ref, 2),
    }
