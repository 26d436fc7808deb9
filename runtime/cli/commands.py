"""The robot's own commands: `run` (the service's job), `drive` (teleoperation), `config show`.
Each `add_*` fills its command's parser and sets the function that runs it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from runtime.cli.args import add_config_args, add_policy_args, finite_float, policy_model
from runtime.cli.output import finish
from runtime.config.settings import load_config, render_calibration, render_config
from runtime.errors import UserError


def add_run(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("--planner", choices=("hold", "dwa", "safemove"), default="hold",
                   help="hold: keep the base stopped with everything else live; dwa: the DWA"
                        " baseline to --goal, through the shield; safemove: the TD3 actor"
                        " (--model or a shipped --variant) to --goal, through the shield")
    p.add_argument("--goal", nargs=2, type=finite_float, metavar=("X", "Y"),
                   help="goal in the odom frame (m): the robot starts at the origin facing +x")
    add_policy_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """The service's job: `hold` keeps the base stopped; `dwa` drives to --goal with the DWA
    baseline through the shield; `safemove` with the TD3 actor (--model, a shipped --variant,
    by default the shipped safemove one), through the shield."""
    import time

    from runtime.cli.app import run_job
    from runtime.jobs.drive import HoldJob
    from runtime.jobs.dwa import DWAJob

    loaded = load_config(args.config, args.overrides)
    model = policy_model(args, "run")
    if args.planner == "hold":
        job: Any = HoldJob()
    else:
        if args.goal is None:
            raise UserError(f"run --planner {args.planner}: give --goal X Y (metres, odom frame:"
                            " the robot starts at the origin facing +x)")
        if loaded.config.depth.source == "none":
            raise UserError(f"{loaded.config_path}: key 'depth.source': the {args.planner}"
                            " planner needs depth (d435 or sim), got 'none'")
        if model is not None:
            from runtime.jobs.safemove import safemove_job

            job = safemove_job(model, tuple(args.goal), loaded.config, time.monotonic)
        else:
            job = DWAJob(tuple(args.goal), loaded.config, time.monotonic)
    report, link_stats = run_job(loaded, job)
    return finish({**report.as_dict(), "job": job.summary(), "link": link_stats},
                   report.exit_code)


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
