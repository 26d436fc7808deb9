"""The `safemove` command line: a table of commands, each filled in by the module that runs it.

A command's module is imported only when that command runs (`importlib`, by name), so the
runtime does not depend on the tools around it (the simulator, evaluation, training, export,
calibration: import-linter checks it) and `safemove run` on the robot loads only what running
needs; runtime.cli.app builds the drivers. User mistakes are one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable

from runtime.errors import UserError

# name: ("module:function that fills its parser", whether the command takes its own --help and
# everything after its name (sim and base-emulator hand their arguments to their own
# parsers), help)
COMMANDS: dict[str, tuple[str, bool, str]] = {
    "run": ("runtime.cli.commands:add_run", False,
             "run the control loop as the service does"),
    "drive": ("runtime.cli.commands:add_drive", False,
               "teleoperate the base: a fixed twist or a scripted list"),
    "demo": ("sim_stub.commands:add_demo", False,
              ("the runtime driving the simulated robot to a goal (the shipped SafeMove policy"
               " through the shield)")),
    "soak": ("sim_stub.commands:add_soak", False,
              ("a long real-time run of `safemove run` against `safemove sim`: contacts,"
               " interventions, misses, RSS slope, log rate")),
    "goal": ("runtime.cli.control_commands:add_goal", False,
              "send the running service to a place (its control socket)"),
    "mission": ("runtime.cli.control_commands:add_mission", False,
                 "send the running service through waypoints from a YAML file"),
    "cancel": ("runtime.cli.control_commands:add_simple", False,
                "stop the running service's goal (it brakes and holds)"),
    "pause": ("runtime.cli.control_commands:add_simple", False,
               "hold the running service's goal (resume goes on)"),
    "resume": ("runtime.cli.control_commands:add_simple", False,
                "go on with a paused goal"),
    "status": ("runtime.cli.control_commands:add_status", False,
                "the running service's state, goal, pose and counters (--follow)"),
    "replay": ("runtime.cli.commands:add_replay", False,
                "a flight recording through today's pipeline: where the commands differ"),
    "plot": ("sim_stub.commands:add_plot", False,
              ("a picture of a flight recording: the path, obstacles and people in odom;"
               " speed, shield and timings against time")),
    "config": ("runtime.cli.commands:add_config", False,
                "inspect the configuration"),
    "bench": ("sim_stub.commands:add_bench", False,
               "benchmarks; the last line of output is one JSON object"),
    "export": ("sim_stub.commands:add_export", False,
                "torch checkpoint -> ONNX actor with its spec, verified"),
    "train": ("sim_stub.commands:add_train", False,
               ("TD3 (stable-baselines3) on the lock-stepped simulated robot, shield in the"
                " loop; exports the actor")),
    "ship": ("sim_stub.commands:add_ship", False,
              ("install a trained run's actor as its variant's shipped policy, with its training"
               " and evaluation records")),
    "eval": ("sim_stub.commands:add_eval", False,
              "seeded episodes per scenario, lock-stepped, scored as in the paper's table"),
    "curves": ("sim_stub.commands:add_curves", False,
               ("training runs' learning curves in one figure: success rate and return against"
                " environment steps")),
    "compare": ("sim_stub.commands:add_compare", False,
                 ("eval results on the same episodes: success with 95 %% intervals, each against"
                  " the first (paired by episode, or between training runs)")),
    "sim": ("sim_stub.commands:add_sim", True,
             "the simulated world + base on a pty + depth on a socket (see --help)"),
    "record": ("sim_stub.commands:add_record", False,
                "write simulated depth as a pyrealsense2 .db3 recording"),
    "base-emulator": ("sim_stub.commands:add_base_emulator", True,
                       "the emulated Spark base on a pseudo-terminal (see --help)"),
    "calibrate": ("calibration.cli:add_arguments", False,
                   "measure this robot: camera extrinsics, wheel odometry; check the calibration"),
}


log = logging.getLogger("safemove")


def _filler(name: str) -> Callable[[argparse.ArgumentParser], None]:
    module, _, function = COMMANDS[name][0].partition(":")
    filler: Callable[[argparse.ArgumentParser], None] = getattr(
        importlib.import_module(module), function)
    return filler


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Every command listed; only `command`'s parser filled in (its module imported)."""
    parser = argparse.ArgumentParser(
        prog="safemove",
        description="SafeMove-RL local planner runtime for the NXROBO Spark.",
    )
    parser.add_argument("--log-level", default="INFO",
                        choices=("DEBUG", "INFO", "WARNING", "ERROR"), help="stderr log level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, passthrough, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, add_help=not passthrough)
        if name == command:
            _filler(name)(p)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line. `sim` and `base-emulator` hand everything after their name to their
    own parsers: argparse's REMAINDER alone drops a leading option (`base-emulator --link P`
    was refused as unrecognized), so those are collected here."""
    argv = sys.argv[1:] if argv is None else argv
    command = next((a for a in argv if a in COMMANDS), None)  # global options come first
    parser = build_parser(command)
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
