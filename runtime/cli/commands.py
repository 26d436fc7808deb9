"""The robot's own commands: `run` (the service's job), `drive` (teleoperation), `config show`.
Each `add_*` fills its command's parser and sets the function that runs it."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from runtime.cli.args import add_config_args, add_policy_args, finite_float, policy_model
from runtime.cli.output import finish
from runtime.config.settings import load_config, render_calibration, render_config
from runtime.errors import UserError

if TYPE_CHECKING:
    from runtime.config.settings import Config
    from runtime.jobs.dwa import DWAJob
    from runtime.jobs.safemove import SafeMoveJob
    from runtime.policy.actor import Policy


def add_run(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("--planner", choices=("hold", "dwa", "safemove"), default=None,
                   help="hold: keep the base stopped with everything else live; dwa: the DWA"
                        " baseline; safemove: the TD3 actor (--model or a shipped --variant);"
                        " both through the shield, to --goal or to the goals of the control"
                        " socket (default: control.planner, or hold when there is neither)")
    p.add_argument("--goal", nargs=2, type=finite_float, metavar=("X", "Y"),
                   help="drive to this goal in the odom frame (m) and exit: the robot starts at"
                        " the origin facing +x (without it, goals come from the control socket)")
    add_policy_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """The service's job. With a control socket (control.socket, or systemd's runtime
    directory) it holds until goals and missions arrive there and drives to them with the
    configured planner; with --goal it drives there once and exits; with neither it holds
    (bring-up: link, odometry, health and watchdog all live)."""
    import time

    from runtime.cli.app import run_job
    from runtime.control.config import control_socket_path
    from runtime.jobs.drive import HoldJob

    loaded = load_config(args.config, args.overrides)
    cfg = loaded.config
    socket_path = (None if args.goal is not None or args.planner == "hold"
                   else control_socket_path(cfg.control))
    if args.planner is None:
        args.planner = ("hold" if args.goal is None and socket_path is None
                        else cfg.control.planner)
    model = policy_model(args, "run")
    if args.planner == "hold":
        if args.goal is not None:
            raise UserError("run --planner hold: takes no --goal (hold keeps the base stopped)")
        report, link_stats = run_job(loaded, HoldJob())
        return finish({**report.as_dict(), "job": {}, "link": link_stats}, report.exit_code)
    if cfg.depth.source == "none":
        raise UserError(f"{loaded.config_path}: key 'depth.source': the {args.planner}"
                        " planner needs depth (d435 or sim), got 'none'")
    if args.goal is None and socket_path is None:
        raise UserError(f"run --planner {args.planner}: give --goal X Y (metres, odom frame),"
                        " or a control socket for goals (control.socket)")
    policy = None
    if model is not None:
        from runtime.jobs.trained_settings import trained_settings_report
        from runtime.policy.actor import Policy

        policy = Policy(model, cfg.policy)  # validated and warmed up before the base opens
        trained_settings_report(policy.training, cfg).log(str(model))
    if args.goal is not None:
        job: Any = _planner_job(tuple(args.goal), cfg, policy, time.monotonic)
        report, link_stats = run_job(loaded, job)
    else:
        from runtime.jobs.mission import MissionJob
        from runtime.process.control_server import ControlHandoff

        assert socket_path is not None
        handoff = ControlHandoff()
        job = MissionJob(
            cfg.control, args.planner,
            lambda goal, tol, speed: _planner_job(goal, cfg, policy, time.monotonic,
                                                  arrival_radius_m=tol, speed_limit=speed),
            handoff.post_event, None if model is None else str(model))
        handoff.status = {"state": "INIT", "mission": job.status()}
        report, link_stats = run_job(loaded, job, control=(socket_path, handoff))
    return finish({**report.as_dict(), "job": job.summary(), "link": link_stats},
                  report.exit_code)


def _planner_job(goal: tuple[float, float], cfg: Config, policy: Policy | None,
                 clock: Callable[[], float], **limits: Any) -> DWAJob | SafeMoveJob:
    """The DWA job, or the SafeMove job with `policy`, to one goal; `limits`: PlanningStep's
    arrival_radius_m and speed_limit."""
    from runtime.jobs.dwa import DWAJob

    if policy is None:
        return DWAJob(goal, cfg, clock, **limits)
    from runtime.jobs.safemove import SafeMoveJob

    return SafeMoveJob(goal, cfg, policy, clock, **limits)


def add_replay(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", type=Path, metavar="LOG.mcap", help="a flight recording")
    p.add_argument("--model", type=Path, metavar="FILE.onnx",
                   help="the actor, where the recorded file is not on this machine")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="replay with a config key changed (what-if), e.g. --set"
                        " dwa.weight_heading=0.5 (repeatable)")
    p.add_argument("--cycles", type=int, default=None, help="replay only the first N cycles")
    p.add_argument("--json", action="store_true", help="print only the JSON result")
    p.set_defaults(func=replay)


def replay(args: argparse.Namespace) -> int:
    """Every recorded cycle through today's Pipeline.step; where the commands differ. Exit 0
    when every command is reproduced, 1 when some differ."""
    from runtime.cli.output import print_figures
    from runtime.process.replay import replay as run_replay

    result = run_replay(args.log, args.model, args.cycles, args.overrides)
    print_figures(result, args.json)
    return 0 if result["differing_commands"] == 0 else 1


def add_drive(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("--twist", nargs=2, type=finite_float, metavar=("V", "OMEGA"), default=(0.0, 0.0),
                   help="body velocity: V m/s forward, OMEGA rad/s counter-clockwise")
    p.add_argument("--duration", type=finite_float, help="seconds to hold --twist")
    p.add_argument("--script", type=Path, help="YAML list of {v, omega, duration} segments")
    p.set_defaults(func=drive)


def _drive_segments(args: argparse.Namespace) -> list:
    from runtime.jobs.drive import Segment, parse_script
    from runtime.types import Twist

    if args.script is not None:
        return parse_script(args.script)
    if args.duration is None or args.duration <= 0:
        raise UserError("drive: give --twist V OMEGA with --duration SECONDS > 0, or --script FILE")
    v, omega = args.twist
    return [Segment(Twist(v, omega), args.duration)]


def drive(args: argparse.Namespace) -> int:
    from runtime.cli.app import run_job
    from runtime.jobs.drive import DriveJob

    loaded = load_config(args.config, args.overrides)
    job = DriveJob(_drive_segments(args), 1.0 / loaded.config.loop.control_hz)
    report, link_stats = run_job(loaded, job)
    return finish({**report.as_dict(), "job": job.summary(), "link": link_stats}, report.exit_code)


def add_config(p: argparse.ArgumentParser) -> None:
    csub = p.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    cp = csub.add_parser("show", help="validate and print the effective config and calibration")
    add_config_args(cp)
    cp.set_defaults(func=config_show)


def config_show(args: argparse.Namespace) -> int:
    loaded = load_config(args.config, args.overrides)
    print(f"# config file: {loaded.config_path}")
    print(render_config(loaded.config))
    print(f"# calibration file: {loaded.calibration_path}")
    print(render_calibration(loaded.calibration))
    return 0
