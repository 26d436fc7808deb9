"""`safemove soak`: a long real-time run of the real service process against `safemove sim`,
reporting what only long runs show: contacts and who was at fault, shield interventions, missed
deadlines, memory growth and log volume.

The runtime runs as on the robot (`safemove run`, a separate process, real time, the sim's pty
and depth socket) toward a goal that may be unreachable (`--goal-world` inside an obstacle keeps
it manoeuvring among people for the whole run). The scenario's time limit is lifted so the world
never times out; every contact the sim judges is counted, at fault or not. RSS is read from
/proc every `--rss-every` seconds; the slope is a least-squares fit after the warm-up.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from runtime.cli.args import policy_model
from runtime.errors import UserError
from sim_stub.emulator_process import EmulatorProcess
from sim_stub.provenance import source_commit
from sim_stub.scenario import SCENARIO_DIR, load_scenario
from sim_stub.world import goal_in_odom

STARTUP_S = 60.0
AT_FAULT_KEYS = ("t", "world_t", "collided_with", "robot_speed", "robot_closing", "other_closing",
                 "bearing_deg")


def rss_mb(pid: int) -> float | None:
    """Resident set size of a live process, MB (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def last_line(stderr: str) -> str:
    """The runtime's last stderr line without its own `safemove: error:` prefix: what it said
    when it refused to start, for one line of ours."""
    lines = stderr.strip().splitlines()
    return lines[-1].removeprefix("safemove: error: ") if lines else "no output"


def slope_mb_per_h(samples: list[tuple[float, float]], warmup_s: float) -> float | None:
    """Least-squares RSS slope after the warm-up (None with fewer than 3 samples)."""
    pts = np.array([(t, r) for t, r in samples if t >= warmup_s])
    if len(pts) < 3:
        return None
    return float(np.polyfit(pts[:, 0] / 3600.0, pts[:, 1], 1)[0])


def lifted_scenario(name: str, minutes: float, directory: Path) -> Path:
    """The scenario with its time limit beyond the run, so the world never times out."""
    scenario = load_scenario(name)  # a bad name or file fails here with its one line
    path = (Path(name) if "/" in name or name.endswith((".yaml", ".yml"))
            else SCENARIO_DIR / f"{name}.yaml")
    data = yaml.safe_load(path.read_text())
    data["time_limit_s"] = float(minutes * 60.0 + STARTUP_S + 60.0)
    out = directory / f"{scenario.name}_soak.yaml"
    out.write_text(yaml.safe_dump(data))
    return out


def soak(args: argparse.Namespace) -> dict[str, Any]:
    # before anything starts: an actor for the DWA planner, or no shipped policy, is one line
    model = policy_model(args, "soak")
    commit = source_commit()
    with tempfile.TemporaryDirectory(prefix="safemove-soak-") as tmp:
        scenario = lifted_scenario(args.scenario, args.minutes, Path(tmp))
        sim_args = [str(scenario), "--seed", str(args.seed), "--crowd", args.crowd,
                    "--fps", str(args.fps)]
        with EmulatorProcess(sim_args, module="sim_stub.sim_server") as sim:
            event = next(e for e in sim.history if e.get("event") == "scenario")
            goal_world = args.goal_world if args.goal_world is not None else event["goal"]
            gx, gy = goal_in_odom(tuple(event["start"]), goal_world)
            cmd = [sys.executable, "-m", "runtime.cli.main", "run", "--planner", args.planner,
                   "--goal", f"{gx}", f"{gy}", "--set", f"base.port={sim.link}",
                   "--set", "depth.source=sim", "--set", f"depth.sim_socket={sim.depth_socket}",
                   *(["--model", str(model)] if model is not None else []),
                   *(a for kv in args.overrides for a in ("--set", kv))]
            err_path = Path(args.log) if args.log else Path(tmp) / "run.err"
            with err_path.open("w") as err:
                proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True,
                                        env={**os.environ, "PYTHONUNBUFFERED": "1"})
            rss: list[tuple[float, float]] = []
            t_start = time.monotonic()
            try:
                running_at = _wait_running(proc, err_path)
                next_rss = running_at
                while proc.poll() is None and time.monotonic() - running_at < args.minutes * 60:
                    now = time.monotonic()
                    if now >= next_rss:
                        r = rss_mb(proc.pid)
                        if r is not None:
                            rss.append((now - running_at, r))
                        next_rss += args.rss_every
                    time.sleep(0.2)
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
                stdout, _ = proc.communicate(timeout=30)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.communicate()
            wall_s = time.monotonic() - t_start
            world = sim.request("world", "world")
            touched = [e for e in sim.history if e.get("event") == "contact"]
        stderr = err_path.read_text()
    lines = [ln for ln in stdout.splitlines() if ln.strip()]
    report = json.loads(lines[-1]) if lines else {}
    job = report.get("job", {})
    log_lines = stderr.splitlines()
    minutes_run = max(wall_s / 60.0, 1e-9)
    kinds = Counter(" ".join(ln.split()[2:4]) for ln in log_lines if len(ln.split()) > 3)
    return {
        "scenario": args.scenario, "seed": args.seed, "crowd": args.crowd,
        "planner": args.planner, "model": str(model) if model is not None else None,
        "commit": commit, "minutes": args.minutes, "exit_code": proc.returncode,
        "state": report.get("state"), "reason": report.get("reason"),
        "cycles": report.get("cycles"), "misses": report.get("misses"),
        "degraded_cycles": report.get("degraded_cycles"),
        "cycle_ms": report.get("cycle_ms"),
        "distance_m": (report.get("odometry") or {}).get("distance"),
        "shield_interventions": job.get("shield_interventions"),
        "contacts": len(touched),
        "contacts_at_fault": sum(1 for c in touched if c.get("at_fault")),
        "contacts_moving": sum(1 for c in touched if c.get("moving")),
        "at_fault": [{k: c[k] for k in AT_FAULT_KEYS if k in c}
                     for c in touched if c.get("at_fault")],
        "min_separation_m": world.get("min_separation"),
        "rss_mb": {"first": rss[0][1] if rss else None, "last": rss[-1][1] if rss else None,
                   "max": max((r for _, r in rss), default=None),
                   "slope_mb_per_h_after_warmup": slope_mb_per_h(rss, args.warmup_s),
                   # a settling heap flattens out, a leak does not: the later half alone
                   "slope_mb_per_h_second_half": slope_mb_per_h(
                       rss, max(args.warmup_s, rss[-1][0] / 2.0) if rss else 0.0),
                   "samples_s_mb": [[round(t, 1), round(r, 2)] for t, r in rss]},
        "log_lines": len(log_lines), "log_lines_per_min": round(len(log_lines) / minutes_run, 1),
        "log_lines_by_level_logger": dict(kinds.most_common(8)),
        "tracebacks": stderr.count("Traceback"),
    }


def _wait_running(proc: subprocess.Popen, err_path: Path) -> float:
    deadline = time.monotonic() + STARTUP_S
    while proc.poll() is None:
        if "-> RUNNING" in err_path.read_text():
            return time.monotonic()
        if time.monotonic() > deadline:
            break
        time.sleep(0.1)
    raise UserError(f"soak: the runtime never reached RUNNING: {last_line(err_path.read_text())}")
