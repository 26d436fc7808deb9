"""The `safemove` command line: one function per command.

A command that runs a tool (the simulator, evaluation, training, export, calibration, the
benchmarks) imports the tool's module inside its function, when it runs, so the runtime does
not depend on the tools (import-linter checks it) and the robot image needs only what the
command it runs uses; runtime.cli.app builds the drivers. User mistakes are one line on stderr
and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from runtime.cli.args import add_config_args, finite_float, int_at_least
from runtime.config.settings import LoadedConfig, load_config, render_calibration, render_config
from runtime.errors import UserError

log = logging.getLogger("safemove")


def _load(args: argparse.Namespace) -> LoadedConfig:
    return load_config(args.config, args.overrides)


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, separators=(",", ":")), flush=True)


# --- subcommands -------------------------------------------------------------------------------


def cmd_config_show(args: argparse.Namespace) -> int:
    loaded = _load(args)
    print(f"# config file: {loaded.config_path}")
    print(render_config(loaded.config))
    print(f"# calibration file: {loaded.calibration_path}")
    print(render_calibration(loaded.calibration))
    return 0


def _drive_segments(args: argparse.Namespace) -> list:
    from runtime.jobs.drive import Segment, parse_script
    from runtime.types import Twist

    if args.script is not None:
        return parse_script(args.script)
    if args.duration is None or args.duration <= 0:
        raise UserError("drive: give --twist V OMEGA with --duration SECONDS > 0, or --script FILE")
    v, omega = args.twist
    return [Segment(Twist(v, omega), args.duration)]


def _print_bench(result: dict[str, Any], json_only: bool) -> int:
    """Figures one per line (unless --json), then the whole result as the last line."""
    if not json_only:
        for key, value in result.items():
            print(f"{key}: {value}")
    _print_json(result)
    return 0


def _finish(report_dict: dict[str, Any], exit_code: int) -> int:
    _print_json(report_dict)
    return exit_code


def cmd_drive(args: argparse.Namespace) -> int:
    from runtime.cli.app import run_job
    from runtime.jobs.drive import DriveJob

    loaded = _load(args)
    job = DriveJob(_drive_segments(args), 1.0 / loaded.config.loop.control_hz)
    report, link_stats = run_job(loaded, job)
    return _finish({**report.as_dict(), "job": job.summary(), "link": link_stats}, report.exit_code)


def cmd_run(args: argparse.Namespace) -> int:
    """The service's job: `hold` keeps the base stopped; `dwa` drives to --goal with the DWA
    baseline through the shield; `safemove` with the TD3 actor --model, through the shield."""
    import time

    from runtime.cli.app import run_job
    from runtime.jobs.drive import HoldJob
    from runtime.jobs.dwa import DWAJob

    loaded = _load(args)
    if args.model is not None and args.planner != "safemove":
        raise UserError(f"run: --model is for --planner safemove, not {args.planner}")
    if args.planner == "hold":
        job: Any = HoldJob()
    else:
        if args.goal is None:
            raise UserError(f"run --planner {args.planner}: give --goal X Y (metres, odom frame:"
                            " the robot starts at the origin facing +x)")
        if loaded.config.depth.source == "none":
            raise UserError(f"{loaded.config_path}: key 'depth.source': the {args.planner}"
                            " planner needs depth (d435 or sim), got 'none'")
        if args.planner == "safemove":
            from runtime.jobs.safemove import safemove_job

            job = safemove_job(args.model, tuple(args.goal), loaded.config, time.monotonic)
        else:
            job = DWAJob(tuple(args.goal), loaded.config, time.monotonic)
    report, link_stats = run_job(loaded, job)
    return _finish({**report.as_dict(), "job": job.summary(), "link": link_stats},
                   report.exit_code)


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job: the runtime drives the simulated robot (world, depth, base) to the
    scenario's goal with the DWA planner, every command through the shield. No trained policy
    ships yet; `run --planner safemove --model` runs one."""
    import time

    from runtime.cli.app import run_job
    from runtime.jobs.dwa import DWAJob
    from sim_stub.emulator_process import EmulatorProcess
    from sim_stub.scenario import load_scenario
    from sim_stub.world import goal_in_odom

    load_scenario(args.scenario)  # a bad name or file fails here with its one line, not in the sim
    sim_args = [args.scenario, "--seed", str(args.seed), "--crowd", args.crowd]
    with EmulatorProcess(sim_args, module="sim_stub.sim_server") as sim:
        event = next(e for e in sim.history if e.get("event") == "scenario")
        goal = goal_in_odom(tuple(event["start"]), event["goal"])
        loaded = load_config(args.config, [
            *args.overrides, f"base.port={sim.link}", "depth.source=sim",
            f"depth.sim_socket={sim.depth_socket}",
        ])
        job = DWAJob(goal, loaded.config, time.monotonic)
        report, link_stats = run_job(loaded, job)
        world = sim.request("world", "world")
        truth = sim.truth()
    o = report.odometry
    print(
        f"DWA planner in scenario {args.scenario} (seed {args.seed}, {args.crowd} crowd) to the"
        f" goal {goal[0]:+.2f}, {goal[1]:+.2f} m (odom): reached={job.reached}; world says:"
        f" {world['status']}; odometry ({o.x:+.3f}, {o.y:+.3f}) m vs base truth"
        f" ({truth['x']:+.3f}, {truth['y']:+.3f}) m; {report.cycles} cycles,"
        f" {report.misses} missed deadlines, shield interventions"
        f" {job.summary()['shield_interventions']}",
        file=sys.stderr,
    )
    return _finish({**report.as_dict(), "job": job.summary(), "link": link_stats, "truth": truth,
                    "world": {k: world[k] for k in ("status", "robot_pose", "min_separation")}},
                   report.exit_code)


def cmd_bench_loop(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_loop

    return _print_bench(bench_loop(args.cycles, args.config, args.overrides), args.json)


def cmd_bench_sim(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_sim

    return _print_bench(bench_sim(args.frames, args.steps), args.json)


def cmd_bench_perception(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_perception

    return _print_bench(bench_perception(args.frames), args.json)


def cmd_bench_planner(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_planner

    return _print_bench({"bench": "planner", **bench_planner(worlds=args.worlds, calls=args.calls)},
                        args.json)


def cmd_bench_policy(args: argparse.Namespace) -> int:
    from sim_stub.bench_policy import bench_policy

    return _print_bench(bench_policy(args.runs), args.json)


def cmd_bench_startup(args: argparse.Namespace) -> int:
    from sim_stub.startup_bench import bench_startup

    return _print_bench(bench_startup(args.runs, args.planner, args.model), args.json)


def cmd_train(args: argparse.Namespace) -> int:
    from sim_stub.train.cli import run_train

    return _print_bench(run_train(args), False)


def cmd_export(args: argparse.Namespace) -> int:
    from export.cli import run_export
    from sim_stub.recorded_observations import simulated_observations

    return _print_bench(run_export(args, simulated_observations), args.json)


def cmd_eval(args: argparse.Namespace) -> int:
    """Seeded episodes per scenario, lock-stepped through the runtime's pipeline code."""
    from sim_stub.evaluate import EvalSettings, evaluate, table

    if args.planner == "safemove" and args.model is None:
        raise UserError("eval --planner safemove: give --model FILE.onnx")
    if not 0 < args.fps <= 90:
        raise UserError(f"eval: --fps must be in (0, 90], got {args.fps}")
    settings = EvalSettings(args.planner, args.config, tuple(args.overrides), args.model,
                            args.fps, args.noise, args.crowd)

    def progress(r: Any) -> None:
        if not args.json:
            fault = ""
            if r.status == "collision":
                fault = (" (at fault)" if r.at_fault
                         else " (moving, not at fault)" if r.moving_at_contact else "")
                if r.contact_bearing_deg is not None:
                    fault += f" with {r.collided_with} at {r.contact_bearing_deg:+.0f}°"
            print(f"{r.scenario} seed {r.seed}: {r.status} at {r.time_s:.1f} s{fault},"
                  f" {r.path_length_m:.2f} m, {r.shield_interventions} shield interventions",
                  file=sys.stderr)

    result = evaluate(args.scenarios, args.episodes, args.seed, settings, args.jobs, progress)
    if not args.json:
        print(table(result), file=sys.stderr)
    _print_json(result)
    return 0


def cmd_soak(args: argparse.Namespace) -> int:
    from sim_stub.soak import soak

    _print_json(soak(args))
    return 0


def cmd_sim(args: argparse.Namespace) -> int:
    from sim_stub.sim_server import main as sim_main

    return sim_main(args.sim_args)


def cmd_record(args: argparse.Namespace) -> int:
    from runtime.types import Twist
    from sim_stub.recording import record, simulated_frames
    from sim_stub.scenario import load_scenario

    if args.frames < 1 or not 0 < args.fps <= 90:
        raise UserError("record: --frames must be ≥ 1 and --fps in (0, 90]")
    loaded = _load(args)
    scenario = load_scenario(args.scenario)
    frames = simulated_frames(scenario, args.frames, args.fps, Twist(*args.twist),
                              loaded.calibration.camera, loaded.config.limits, args.seed,
                              args.noise)
    written = record(args.output, frames, args.fps)
    _print_json({"recording": str(args.output), "frames": written, "fps": args.fps,
                 "scenario": scenario.name})
    return 0


def cmd_base_emulator(args: argparse.Namespace) -> int:
    from sim_stub.base_emulator import main as emulator_main

    return emulator_main(args.emulator_args)


# --- parser ------------------------------------------------------------------------------------


def _bench_parser(bsub: Any, name: str, help_text: str, func: Callable[[argparse.Namespace], int]
                  ) -> argparse.ArgumentParser:
    """A `bench` subcommand: every benchmark prints figures and ends with one JSON line."""
    bp = bsub.add_parser(name, help=help_text)
    bp.add_argument("--json", action="store_true", help="print only the JSON line")
    bp.set_defaults(func=func)
    return bp


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="safemove",
        description="SafeMove-RL local planner runtime for the NXROBO Spark.",
    )
    parser.add_argument("--log-level", default="INFO",
                        choices=("DEBUG", "INFO", "WARNING", "ERROR"), help="stderr log level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run the control loop as the service does")
    add_config_args(p)
    p.add_argument("--planner", choices=("hold", "dwa", "safemove"), default="hold",
                   help="hold: keep the base stopped with everything else live; dwa: the DWA"
                        " baseline to --goal, through the shield; safemove: the TD3 actor"
                        " --model to --goal, through the shield")
    p.add_argument("--goal", nargs=2, type=finite_float, metavar=("X", "Y"),
                   help="goal in the odom frame (m): the robot starts at the origin facing +x")
    p.add_argument("--model", type=Path, metavar="FILE.onnx",
                   help="the actor for --planner safemove, written by `safemove export`")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("drive", help="teleoperate the base: a fixed twist or a scripted list")
    add_config_args(p)
    p.add_argument("--twist", nargs=2, type=finite_float, metavar=("V", "OMEGA"), default=(0.0, 0.0),
                   help="body velocity: V m/s forward, OMEGA rad/s counter-clockwise")
    p.add_argument("--duration", type=finite_float, help="seconds to hold --twist")
    p.add_argument("--script", type=Path, help="YAML list of {v, omega, duration} segments")
    p.set_defaults(func=cmd_drive)

    p = sub.add_parser("demo", help="the runtime driving the simulated robot to a goal (DWA"
                                     " planner through the shield)")
    add_config_args(p)
    p.add_argument("--scenario", default="paper_a",
                   help="scenario to drive in (default paper_a)")
    p.add_argument("--seed", type=int, default=4, help="episode seed (default 4)")
    p.add_argument("--crowd", choices=("scenario", "reactive", "oblivious"), default="reactive",
                   help="whether the people see the robot (default reactive)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("soak", help="a long real-time run of `safemove run` against `safemove"
                                     " sim`: contacts, interventions, misses, RSS slope, log rate")
    p.add_argument("scenario", help="shipped scenario name or scenario file")
    p.add_argument("--minutes", type=finite_float, default=10.0, help="real-time minutes RUNNING")
    p.add_argument("--planner", choices=("dwa", "safemove"), default="dwa")
    p.add_argument("--model", type=Path, help="the actor for --planner safemove")
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--crowd", choices=("scenario", "reactive", "oblivious"), default="scenario")
    p.add_argument("--fps", type=finite_float, default=15.0, help="depth frames per second")
    p.add_argument("--goal-world", nargs=2, type=finite_float, metavar=("X", "Y"),
                   help="goal in the world frame (default: the scenario's); inside an obstacle"
                        " it is unreachable and the robot keeps manoeuvring")
    p.add_argument("--rss-every", type=finite_float, default=10.0, help="seconds between RSS samples")
    p.add_argument("--warmup-s", type=finite_float, default=120.0,
                   help="RSS samples before this are left out of the slope")
    p.add_argument("--log", help="keep the runtime's stderr in this file")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for the runtime (repeatable)")
    p.set_defaults(func=cmd_soak)

    p = sub.add_parser("config", help="inspect the configuration")
    csub = p.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    cp = csub.add_parser("show", help="validate and print the effective config and calibration")
    add_config_args(cp)
    cp.set_defaults(func=cmd_config_show)

    p = sub.add_parser("bench", help="benchmarks; the last line of output is one JSON object")
    bsub = p.add_subparsers(dest="bench_command", required=True, metavar="WHAT")
    bp = _bench_parser(bsub, "loop", "the drive loop against the emulated base", cmd_bench_loop)
    add_config_args(bp)
    bp.add_argument("--cycles", type=int_at_least(1), default=400,
                    help="control cycles to run (default 400)")

    bp = _bench_parser(bsub, "sim", "depth rendering, world stepping and playback speed",
                       cmd_bench_sim)
    bp.add_argument("--frames", type=int_at_least(1), default=60,
                    help="frames to render (default 60)")
    bp.add_argument("--steps", type=int_at_least(1), default=500,
                    help="world steps (default 500)")

    bp = _bench_parser(bsub, "perception", "world-model stages per frame at 848x480",
                       cmd_bench_perception)
    bp.add_argument("--frames", type=int_at_least(2), default=100,
                    help="frames to process (default 100; the first is not timed)")

    bp = _bench_parser(bsub, "planner", "DWA: vectorised vs per-sample reference, p99, budget",
                       cmd_bench_planner)
    bp.add_argument("--worlds", type=int_at_least(1), default=20,
                    help="random worlds compared (default 20)")
    bp.add_argument("--calls", type=int_at_least(1), default=10000,
                    help="calls for the budget overshoot (default 10000)")

    bp = _bench_parser(bsub, "policy", "the actor: onnxruntime vs torch eager, batch-1 latency",
                       cmd_bench_policy)
    bp.add_argument("--runs", type=int_at_least(100), default=5000,
                    help="timed inferences per engine and actor (default 5000)")
    bp = _bench_parser(bsub, "startup", "time from process start to READY=1 and RSS at READY,"
                       " against `safemove sim`", cmd_bench_startup)
    bp.add_argument("--runs", type=int_at_least(1), default=5, help="starts (default 5)")
    bp.add_argument("--planner", choices=("hold", "dwa", "safemove"), default="safemove")
    bp.add_argument("--model", type=Path, metavar="FILE.onnx", help="the actor for safemove")

    p = sub.add_parser("export", help="torch checkpoint -> ONNX actor with its spec, verified")
    from export.cli import add_arguments as add_export_arguments

    add_export_arguments(p)
    p.add_argument("--json", action="store_true", help="print only the JSON line")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("train", help="TD3 (stable-baselines3) on the lock-stepped simulated"
                                      " robot, shield in the loop; exports the actor")
    from sim_stub.train.cli import add_arguments as add_train_arguments

    add_train_arguments(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="seeded episodes per scenario, lock-stepped, scored as in"
                                     " the paper's table")
    add_config_args(p)
    p.add_argument("--planner", choices=("dwa", "safemove"), default="dwa",
                   help="dwa: the DWA baseline; safemove: the TD3 actor --model (both through"
                        " the shield)")
    p.add_argument("--model", type=Path, metavar="FILE.onnx", help="the actor for safemove")
    p.add_argument("--scenarios", nargs="+", default=["paper_a", "paper_b", "paper_c", "paper_d"],
                   metavar="NAME", help="shipped scenario names or YAML files (default: the"
                                        " paper's a-d)")
    p.add_argument("--episodes", type=int_at_least(1), default=20,
                   help="episodes per scenario (default 20)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    p.add_argument("--jobs", type=int_at_least(1), default=1,
                   help="worker processes (default 1)")
    p.add_argument("--fps", type=finite_float, default=15.0,
                   help="depth frames per second (default 15)")
    p.add_argument("--no-noise", dest="noise", action="store_false",
                   help="render depth without the D435 noise model")
    p.add_argument("--crowd", choices=("scenario", "reactive", "oblivious"), default="scenario",
                   help="whether the agents see and avoid the robot (default: as the scenario"
                        " says; the paper scenarios ship oblivious)")
    p.add_argument("--json", action="store_true", help="print only the JSON result")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("sim", add_help=False,
                       help="the simulated world + base on a pty + depth on a socket (see --help)")
    p.add_argument("sim_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_sim, passthrough="sim_args")

    p = sub.add_parser("record", help="write simulated depth as a pyrealsense2 .db3 recording")
    add_config_args(p)
    p.add_argument("scenario", help="a shipped scenario name or a scenario YAML file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output file (.db3)")
    p.add_argument("--frames", type=int_at_least(1), default=90,
                   help="frames to record (default 90)")
    p.add_argument("--fps", type=finite_float, default=30.0, help="frame rate (default 30)")
    p.add_argument("--twist", nargs=2, type=finite_float, metavar=("V", "OMEGA"), default=(0.2, 0.0),
                   help="the robot's body velocity while recording (default 0.2 0)")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's)")
    p.add_argument("--noise", action="store_true", help="D435-like noise and edge dropout")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("base-emulator", add_help=False,
                       help="the emulated Spark base on a pseudo-terminal (see --help)")
    p.add_argument("emulator_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_base_emulator, passthrough="emulator_args")

    from calibration.cli import add_calibrate_parser

    add_calibrate_parser(sub)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line. `sim` and `base-emulator` hand everything after their name to their
    own parsers: argparse's REMAINDER alone drops a leading option (`base-emulator --link P`
    was refused as unrecognized), so those are collected here."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    dest = getattr(args, "passthrough", None)
    if extra:
        if dest is None:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        setattr(args, dest, [*extra, *getattr(args, dest)])
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(
        level=args.log_level,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        code = args.func(args)
    except UserError as exc:
        print(f"safemove: error: {exc}", file=sys.stderr)
        return exc.exit_code
    if "runtime.cli.app" in sys.modules:  # a run that drove the base: a fatal signal ends it
        sys.modules["runtime.cli.app"].exit_by_fatal_signal()
    return code


if __name__ == "__main__":
    sys.exit(main())
