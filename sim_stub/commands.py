"""The commands of the tools around the runtime: the simulator (`sim`, `demo`, `record`,
`base-emulator`), evaluation, the picture of a flight recording (`plot`), soak runs,
benchmarks, training and export (whose parity check uses simulated observations). `safemove`
imports this module only to run one of them."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from runtime.cli.args import (
    add_config_args,
    add_policy_args,
    finite_float,
    int_at_least,
    policy_model,
)
from runtime.cli.output import finish, print_figures, print_json
from runtime.config.settings import load_config
from runtime.errors import UserError

DEMO_GRACE_S = 10.0  # the demo runs this long past its scenario's time limit at most


def add_demo(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("--scenario", default="paper_a",
                   help="scenario to drive in (default paper_a)")
    p.add_argument("--seed", type=int, default=4, help="episode seed (default 4)")
    p.add_argument("--crowd", choices=("scenario", "reactive", "oblivious"), default="reactive",
                   help="whether the people see the robot (default reactive)")
    p.add_argument("--planner", choices=("safemove", "dwa"), default="safemove",
                   help="safemove (default): the TD3 actor, by default the shipped safemove"
                        " policy; dwa: the DWA baseline (both through the shield)")
    p.add_argument("--record", type=Path, metavar="DIR",
                   help="record every cycle to MCAP files in DIR (the flight recorder)")
    add_policy_args(p)
    p.set_defaults(func=demo)


def demo(args: argparse.Namespace) -> int:
    """The main job: the runtime drives the simulated robot (world, depth, base) to the
    scenario's goal with the shipped SafeMove policy (or --model, --variant, --planner dwa),
    every command through the shield."""
    import time

    from runtime.cli.app import run_job
    from runtime.jobs.dwa import DWAJob
    from runtime.jobs.safemove import safemove_job
    from sim_stub.emulator_process import EmulatorProcess
    from sim_stub.scenario import load_scenario
    from sim_stub.world import goal_in_odom

    # a bad scenario or a missing model fails here with its one line, before the sim starts
    scenario = load_scenario(args.scenario)
    model = policy_model(args, "demo", "give --model FILE.onnx, or --planner dwa")
    sim_args = [args.scenario, "--seed", str(args.seed), "--crowd", args.crowd]
    with EmulatorProcess(sim_args, module="sim_stub.sim_server") as sim:
        event = next(e for e in sim.history if e.get("event") == "scenario")
        goal = goal_in_odom(tuple(event["start"]), event["goal"])
        loaded = load_config(args.config, [
            *args.overrides, f"base.port={sim.link}", "depth.source=sim",
            f"depth.sim_socket={sim.depth_socket}",
            *([f"recorder.directory={args.record}"] if args.record else []),
        ])
        job: Any = (DWAJob(goal, loaded.config, time.monotonic) if model is None
                    else safemove_job(model, goal, loaded.config, time.monotonic))
        # the world's verdict comes at its time limit at the latest; a policy that never
        # reaches the goal must not keep the demo running after it
        limit_s = scenario.time_limit_s + DEMO_GRACE_S
        report, link_stats = run_job(loaded, job,
                                     math.ceil(limit_s * loaded.config.loop.control_hz))
        world = sim.request("world", "world")
        truth = sim.truth()
    o = report.odometry
    planner = "DWA planner" if model is None else f"SafeMove actor {model}"
    print(
        f"{planner} in scenario {args.scenario} (seed {args.seed}, {args.crowd} crowd) to the"
        f" goal {goal[0]:+.2f}, {goal[1]:+.2f} m (odom): reached={job.reached}; world says:"
        f" {world['status']}; odometry ({o.x:+.3f}, {o.y:+.3f}) m vs base truth"
        f" ({truth['x']:+.3f}, {truth['y']:+.3f}) m; {report.cycles} cycles,"
        f" {report.misses} missed deadlines, shield interventions"
        f" {job.summary()['shield_interventions']}",
        file=sys.stderr,
    )
    return finish({**report.as_dict(), "job": job.summary(), "link": link_stats, "truth": truth,
                    "world": {k: world[k] for k in ("status", "robot_pose", "min_separation")}},
                   report.exit_code or (0 if world["status"] == "success" else 1))


def add_soak(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="shipped scenario name or scenario file")
    p.add_argument("--minutes", type=finite_float, default=10.0, help="real-time minutes RUNNING")
    p.add_argument("--planner", choices=("dwa", "safemove"), default="dwa")
    add_policy_args(p)
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
    p.set_defaults(func=soak_run)


def soak_run(args: argparse.Namespace) -> int:
    from sim_stub.soak import soak

    print_json(soak(args))
    return 0


def _add_episode_args(p: argparse.ArgumentParser, crowd: str) -> None:
    """How lock-stepped episodes are simulated: depth frame rate and noise, the crowd."""
    p.add_argument("--fps", type=finite_float, default=15.0,
                   help="depth frames per second (default 15)")
    p.add_argument("--no-noise", dest="noise", action="store_false",
                   help="render depth without the D435 noise model")
    p.add_argument("--crowd", choices=("scenario", "reactive", "oblivious"), default=crowd,
                   help="whether the people see and avoid the robot (default: "
                        + ("as the scenario says; the paper scenarios ship oblivious)"
                           if crowd == "scenario" else f"{crowd})"))


def _bench_parser(bsub: Any, name: str, help_text: str, func: Callable[[argparse.Namespace], int]
                  ) -> argparse.ArgumentParser:
    """A `bench` subcommand: every benchmark prints figures and ends with one JSON line."""
    bp = bsub.add_parser(name, help=help_text)
    bp.add_argument("--json", action="store_true", help="print only the JSON line")
    bp.set_defaults(func=func)
    return bp


def add_bench(p: argparse.ArgumentParser) -> None:
    bsub = p.add_subparsers(dest="bench_command", required=True, metavar="WHAT")
    bp = _bench_parser(bsub, "loop", "the drive loop against the emulated base", bench_loop_run)
    add_config_args(bp)
    bp.add_argument("--cycles", type=int_at_least(1), default=400,
                    help="control cycles to run (default 400)")

    bp = _bench_parser(bsub, "sim", "depth rendering, world stepping and playback speed",
                       bench_sim_run)
    bp.add_argument("--frames", type=int_at_least(1), default=60,
                    help="frames to render (default 60)")
    bp.add_argument("--steps", type=int_at_least(1), default=500,
                    help="world steps (default 500)")

    bp = _bench_parser(bsub, "perception", "world-model stages per frame at 848x480",
                       bench_perception_run)
    bp.add_argument("--frames", type=int_at_least(2), default=100,
                    help="frames to process (default 100; the first is not timed)")

    bp = _bench_parser(bsub, "planner", "DWA: vectorised vs per-sample reference, p99, budget",
                       bench_planner_run)
    bp.add_argument("--worlds", type=int_at_least(1), default=20,
                    help="random worlds compared (default 20)")
    bp.add_argument("--calls", type=int_at_least(1), default=10000,
                    help="calls for the budget overshoot (default 10000)")

    bp = _bench_parser(bsub, "policy", "the actor: onnxruntime vs torch eager, batch-1 latency",
                       bench_policy_run)
    bp.add_argument("--runs", type=int_at_least(100), default=5000,
                    help="timed inferences per engine and actor (default 5000)")
    bp = _bench_parser(bsub, "startup", "time from process start to READY=1 and RSS at READY,"
                       " against `safemove sim`", bench_startup_run)
    bp.add_argument("--runs", type=int_at_least(1), default=5, help="starts (default 5)")
    bp.add_argument("--planner", choices=("hold", "dwa", "safemove"), default="safemove")
    add_policy_args(bp)

    bp = _bench_parser(bsub, "episode", "lock-stepped cycles/s of the DWA and SafeMove jobs,"
                       " where the time goes; training env steps/s", bench_episode_run)
    add_config_args(bp)
    bp.add_argument("--scenario", default="paper_b", help="scenario (default paper_b)")
    bp.add_argument("--seed", type=int, default=3,
                    help="seed of the first episode; the next ones count up (default 3)")
    bp.add_argument("--cycles", type=int_at_least(1), default=600,
                    help="control cycles per job, episodes cut at this cap (default 600)")
    _add_episode_args(bp, crowd="reactive")
    bp.add_argument("--model", type=Path, metavar="FILE.onnx",
                    help="the SafeMove job's actor (default: a random 61-400-300-2 one)")
    bp.add_argument("--workers", type=int_at_least(1),
                    help="training envs of the second training figure, beside one (default:"
                         " one per core)")
    bp.add_argument("--learning-starts", type=int_at_least(1), default=200,
                    help="random training steps before the timed updates (default 200)")
    bp.add_argument("--updates", type=int_at_least(1), default=300,
                    help="training steps with gradient updates (default 300)")
    bp.add_argument("--no-train", dest="train", action="store_false",
                    help="leave out the training env (it needs the train extra)")

    bp = _bench_parser(bsub, "cycle", "the whole robot cycle on recorded depth, p50/p99/max;"
                       " start-up to READY and RSS", bench_cycle_run)
    bp.add_argument("--cycles", type=int_at_least(1), default=2000,
                    help="timed control cycles (default 2000)")
    bp.add_argument("--frames", type=int_at_least(1), default=300,
                    help="frames recorded, played again and again (default 300)")
    bp.add_argument("--model", type=Path, metavar="FILE.onnx",
                    help="the actor (default: a random 61-400-300-2 one)")
    bp.add_argument("--startup-runs", type=int_at_least(0), default=3,
                    help="starts of `safemove run --planner safemove` (default 3; 0: none)")
    bp.add_argument("--record", action="store_true",
                    help="also the flight recorder's cost: cycles paced at the control rate"
                         " without and with recording (adds 2 × CYCLES / control_hz seconds)")
    bp = _bench_parser(bsub, "control", "the control cycle with hostile control-socket clients"
                       " (flooding, never reading) against none, in one run", bench_control_run)
    bp.add_argument("--cycles", type=int_at_least(20), default=400,
                    help="control cycles per phase (default 400: 20 s at 20 Hz)")
    bp.add_argument("--clients", type=int_at_least(1), default=4,
                    help="hostile client processes in each hostile phase (default 4)")


def bench_loop_run(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_loop

    return print_figures(bench_loop(args.cycles, args.config, args.overrides), args.json)


def bench_sim_run(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_sim

    return print_figures(bench_sim(args.frames, args.steps), args.json)


def bench_perception_run(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_perception

    return print_figures(bench_perception(args.frames), args.json)


def bench_planner_run(args: argparse.Namespace) -> int:
    from sim_stub.bench import bench_planner

    return print_figures({"bench": "planner", **bench_planner(worlds=args.worlds, calls=args.calls)},
                        args.json)


def bench_policy_run(args: argparse.Namespace) -> int:
    from sim_stub.bench_policy import bench_policy

    return print_figures(bench_policy(args.runs), args.json)


def bench_startup_run(args: argparse.Namespace) -> int:
    from sim_stub.startup_bench import bench_startup

    model = policy_model(args, "bench startup")
    return print_figures(bench_startup(args.runs, args.planner, model), args.json)


def bench_episode_run(args: argparse.Namespace) -> int:
    import os

    from sim_stub.bench_episode import bench_episode

    if not 0 < args.fps <= 90:
        raise UserError(f"bench episode: --fps must be in (0, 90], got {args.fps}")
    workers = sorted({1, args.workers or os.cpu_count() or 1}) if args.train else []
    return print_figures(bench_episode(args.scenario, args.seed, args.cycles, args.fps,
                                       args.noise, args.crowd, args.model, args.config,
                                       args.overrides, workers, args.learning_starts,
                                       args.updates), args.json)


def bench_cycle_run(args: argparse.Namespace) -> int:
    from sim_stub.bench_cycle import bench_cycle

    return print_figures(bench_cycle(args.cycles, args.frames, args.model, args.startup_runs,
                                     args.record), args.json)


def bench_control_run(args: argparse.Namespace) -> int:
    from sim_stub.bench_control import bench_control

    return print_figures(bench_control(args.cycles, args.clients), args.json)


def add_export(p: argparse.ArgumentParser) -> None:
    from export.cli import add_arguments as add_export_arguments

    add_export_arguments(p)
    p.add_argument("--json", action="store_true", help="print only the JSON line")
    p.set_defaults(func=export_run)


def export_run(args: argparse.Namespace) -> int:
    from export.cli import run_export
    from sim_stub.recorded_observations import simulated_observations

    return print_figures(run_export(args, simulated_observations), args.json)


def add_train(p: argparse.ArgumentParser) -> None:
    from sim_stub.train.cli import add_arguments as add_train_arguments

    add_train_arguments(p)
    p.add_argument("--json", action="store_true", help="print only the JSON line")
    p.set_defaults(func=train_run)


def train_run(args: argparse.Namespace) -> int:
    from sim_stub.train.cli import run_train

    return print_figures(run_train(args), args.json)


def add_ship(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", type=Path, help="a `safemove train` run directory")
    p.add_argument("--eval", type=Path, nargs="+", required=True, metavar="RESULT.json",
                   dest="evaluations",
                   help="`safemove eval --planner safemove --model RUN/actor.onnx --json` results"
                        " to carry in the model's metadata")
    p.set_defaults(func=ship_run)


def ship_run(args: argparse.Namespace) -> int:
    from sim_stub.train.ship import ship

    target = ship(args.run, args.evaluations)
    print(f"shipped {args.run / 'actor.onnx'} as {target}")
    return 0


def add_eval(p: argparse.ArgumentParser) -> None:
    add_config_args(p)
    p.add_argument("--planner", choices=("dwa", "safemove"), default="dwa",
                   help="dwa: the DWA baseline; safemove: the TD3 actor, --model or a shipped"
                        " --variant (both through the shield)")
    add_policy_args(p)
    p.add_argument("--scenarios", nargs="+", default=["paper_a", "paper_b", "paper_c", "paper_d"],
                   metavar="NAME", help="shipped scenario names or YAML files (default: the"
                                        " paper's a-d)")
    p.add_argument("--episodes", type=int_at_least(1), default=20,
                   help="episodes per scenario (default 20)")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    p.add_argument("--jobs", type=int_at_least(1), default=1,
                   help="worker processes (default 1)")
    _add_episode_args(p, crowd="scenario")
    p.add_argument("--camera-hfov", type=finite_float, default=None, metavar="DEG",
                   help="what if the depth camera saw this wide (default: the D435's 87 deg):"
                        " renders it this wide (the D435's pixels, more columns); the scan's"
                        " bearing span and bins (of the same width) and the tracker's field of"
                        " view follow unless --set gives them")
    p.add_argument("--surround-people", action="store_true",
                   help="what if the robot saw every person around it: each depth frame comes"
                        " with every person within the perception's range, all around and"
                        " through occlusion, exactly (ground truth), as its tracks")
    p.add_argument("--record", type=Path, metavar="DIR",
                   help="a flight recording of every episode in DIR (<scenario>-seed<N>-….mcap:"
                        " open it in Foxglove, `safemove replay` or `safemove plot` it)")
    p.add_argument("--plots", type=Path, metavar="DIR",
                   help="also draw every episode's path per scenario and the outcome rates as"
                        " PNG files into DIR (created if missing; needs matplotlib)")
    p.add_argument("--json", action="store_true", help="print only the JSON result")
    p.set_defaults(func=eval_run)


def _record_dir(directory: Path) -> Path:
    """eval --record's directory, created and checked before any episode runs."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / ".safemove-record-probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"eval --record: cannot write into {directory}:"
                        f" {exc.strerror or exc}") from None
    return directory.resolve()


def _plots_dir(directory: Path) -> Path:
    """Check before any episode runs that `eval --plots` can draw (matplotlib) and write into
    `directory` (created if missing); each problem is one line, exit 2."""
    import os
    import tempfile

    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise UserError("eval --plots: matplotlib is not installed; install it with"
                        " pip install 'safemove-rl[plots]'") from None
    directory = directory.expanduser()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".safemove-plots-", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except FileExistsError:
        raise UserError(f"eval --plots: {directory} is a file, not a directory") from None
    except OSError as exc:
        raise UserError(f"eval --plots: cannot write into {directory}:"
                        f" {exc.strerror or exc}") from None
    return directory


def camera_view(args: argparse.Namespace) -> tuple[float, tuple[str, ...]]:
    """eval --camera-hfov: the simulated camera's horizontal view, and the overrides that tell
    the pipeline about it, where the user did not set them: the scan's bearing span and bin
    count (bins of the configured width) and the tracker's field of view (its edges cut
    clusters off)."""
    from drivers.depth_source import D435_HFOV_DEG
    from runtime.config.settings import load_config

    overrides = tuple(args.overrides)
    if args.camera_hfov is None:
        return D435_HFOV_DEG, overrides
    hfov = args.camera_hfov
    if not 10.0 <= hfov <= 160.0:
        raise UserError(f"eval: --camera-hfov must be in [10, 160] deg, got {hfov:g}")
    perception = load_config(args.config, list(overrides)).config.perception
    keys = {o.split("=", 1)[0].strip() for o in overrides}
    if "perception.bearing_span_deg" not in keys:
        overrides += (f"perception.bearing_span_deg={hfov:g}",)
        if "perception.scan_bins" not in keys:
            bins = max(1, round(perception.scan_bins * hfov / perception.bearing_span_deg))
            overrides += (f"perception.scan_bins={bins}",)
    if "tracking.field_of_view_deg" not in keys:
        overrides += (f"tracking.field_of_view_deg={hfov:g}",)
    return hfov, overrides


def eval_run(args: argparse.Namespace) -> int:
    """Seeded episodes per scenario, lock-stepped through the runtime's pipeline code."""
    from sim_stub.evaluate import EvalSettings, evaluate, table
    from sim_stub.progress import Progress

    model = policy_model(args, "eval")
    if not 0 < args.fps <= 90:
        raise UserError(f"eval: --fps must be in (0, 90], got {args.fps}")
    if args.surround_people and args.record is not None:
        raise UserError("eval: --record cannot be used with --surround-people (a recording"
                        " holds the camera's input only: its replay would not see the people)")
    plots = None if args.plots is None else _plots_dir(args.plots)
    hfov, overrides = camera_view(args)
    settings = EvalSettings(args.planner, args.config, overrides, model,
                            args.fps, args.noise, args.crowd, trajectories=plots is not None,
                            record=None if args.record is None else _record_dir(args.record),
                            camera_hfov_deg=hfov, surround_people=args.surround_people)

    counts: dict[str, int] = {}

    def episode_ended(r: Any) -> None:
        """Without a terminal (unless --json): a line per episode. With one: a bar with the
        outcomes so far, the collisions' lines above it."""
        counts[r.status] = counts.get(r.status, 0) + 1
        if not args.json and (bar.plain or r.status == "collision"):
            fault = ""
            if r.status == "collision":
                fault = (" (at fault)" if r.at_fault
                         else " (moving, not at fault)" if r.moving_at_contact else "")
                if r.contact_bearing_deg is not None:
                    fault += f" with {r.collided_with} at {r.contact_bearing_deg:+.0f}°"
            bar.line(f"{r.scenario} seed {r.seed}: {r.status} at {r.time_s:.1f} s{fault},"
                     f" {r.path_length_m:.2f} m, {r.shield_interventions} shield interventions")
        bar.advance(1, **counts)

    total = len(args.scenarios) * args.episodes
    trajectories: list[Any] = []
    # --json keeps stdout to the result; without a terminal, stderr still gets status lines
    with Progress(total, "eval", "episode",
                  line_every=max(total // 20, 1) if args.json else None) as bar:
        result = evaluate(args.scenarios, args.episodes, args.seed, settings, args.jobs,
                          episode_ended, trajectories)
    if not args.json:
        print(table(result), file=sys.stderr)
    print_json(result)  # before the pictures: a failure drawing them loses no result
    if plots is not None:
        from sim_stub.plots import plot_eval

        for path in plot_eval(result, trajectories, plots):
            print(f"eval: wrote {path}", file=sys.stderr)
    return 0


def _labelled_runs(text: str) -> tuple[str, list[list[Path]]]:
    """compare's `[LABEL=]RUN[,RUN...]`, a RUN being `FILE[+FILE...]`; the label defaults to
    the first file's path."""
    label, sep, spec = text.rpartition("=")
    runs = [[Path(f) for f in run.split("+") if f] for run in (spec if sep else text).split(",")]
    if not runs or not all(runs) or (sep and not label):
        raise argparse.ArgumentTypeError(
            f"expected [LABEL=]FILE[+FILE...][,FILE...], got {text!r}")
    return (label if sep else str(runs[0][0])), runs


def add_compare(p: argparse.ArgumentParser) -> None:
    from sim_stub.compare import OUTCOMES, Outcome

    p.add_argument("results", type=_labelled_runs, nargs="+",
                   metavar="[LABEL=]FILE[+FILE...][,FILE...]",
                   help="`safemove eval --json` results on the same scenarios and seeds, the"
                        " first the reference; FILE+FILE pools one policy's episodes (the test"
                        " and the validation seeds), commas separate training runs (seeds) of"
                        " one planner")
    p.add_argument("--outcome", choices=OUTCOMES, default="success",
                   help="what is counted per episode (default success); seen-collision: a"
                        " collision with a person who had been in the camera's view for"
                        " --seen-s or more, unseen-collision: any other collision")
    p.add_argument("--seen-s", type=float, default=Outcome().seen_s, metavar="S",
                   help="seconds in view that make a person seen coming (default %(default)g)")
    p.add_argument("--json", action="store_true", help="print only the JSON result")
    p.set_defaults(func=compare_run)


def compare_run(args: argparse.Namespace) -> int:
    """Rates of the outcome with their 95 % intervals; each planner against the first: one run
    each paired by episode (McNemar's exact test), several each between runs (Welch's
    t-test)."""
    from sim_stub.compare import Outcome, compare, load_evaluation, table

    labels = [label for label, _ in args.results]
    if len(set(labels)) < len(labels):
        raise UserError(f"compare: a label appears twice in {labels}: name them LABEL=FILE")
    if not (math.isfinite(args.seen_s) and args.seen_s >= 0.0):
        raise UserError(f"compare: --seen-s {args.seen_s}: give seconds, 0 or more")
    outcome = Outcome(args.outcome, args.seen_s)
    result = compare([load_evaluation(label, runs, outcome) for label, runs in args.results])
    if not args.json:
        print(table(result), file=sys.stderr)
    print_json(result)
    return 0


def add_plot(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", type=Path, metavar="LOG.mcap", help="a flight recording")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.png",
                   help="the PNG file to write (its folder must exist)")
    p.add_argument("--json", action="store_true", help="print only the JSON summary")
    p.set_defaults(func=plot_run)


def plot_run(args: argparse.Namespace) -> int:
    """A picture of one flight recording: the path, the remembered obstacles, the people and
    the plans in odom; speed, shield interventions and stage times against time."""
    out = _png_output("plot", args.output)
    from sim_stub.log_plot import plot_log

    return print_figures(plot_log(args.log.expanduser(), out), args.json)


def _png_output(command: str, path: Path) -> Path:
    """The picture's path, once matplotlib is known to be there and the file writable: a
    command that would fail there fails before its work, in one line."""
    import os

    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise UserError(f"{command}: matplotlib is not installed; install it with"
                        " pip install 'safemove-rl[plots]'") from None
    out = path.expanduser()
    folder = out.parent if str(out.parent) else Path(".")
    if out.is_dir():
        raise UserError(f"{command}: {out} is a directory, not a file")
    if not folder.is_dir():
        raise UserError(f"{command}: cannot write {out}: {folder} is not a directory")
    if not os.access(folder, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        raise UserError(f"{command}: cannot write {out}: permission denied")
    return out


def _labelled_run_dir(text: str) -> tuple[str, Path]:
    """curves' `[LABEL=]DIR`; the label defaults to the directory's name."""
    label, sep, folder = text.rpartition("=")
    if not (folder and (label or not sep)):
        raise argparse.ArgumentTypeError(f"expected [LABEL=]DIR, got {text!r}")
    path = Path(folder).expanduser()
    return (label if sep else path.resolve().name or str(path)), path


def add_curves(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", type=_labelled_run_dir, nargs="+", metavar="[LABEL=]DIR",
                   help="`safemove train` run directories (their monitor.csv; one still"
                        " training is drawn as far as it has got)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.png",
                   help="the PNG file to write (its folder must exist)")
    p.add_argument("--window", type=int_at_least(1), default=50,
                   help="episodes each point averages (default 50)")
    p.add_argument("--json", action="store_true", help="print only the JSON summary")
    p.set_defaults(func=curves_run)


def curves_run(args: argparse.Namespace) -> int:
    """Several training runs' learning curves in one figure (success rate and return against
    environment steps), to compare variants, seeds or recipes; each run's last window in
    figures."""
    from sim_stub.train.curves import plot_curves, run_figures

    labels = [label for label, _ in args.runs]
    if len(set(labels)) < len(labels):
        raise UserError(f"curves: a label appears twice in {labels}: name them LABEL=DIR")
    out = _png_output("curves", args.output)
    runs = {label: folder for label, folder in args.runs}
    figures = run_figures(runs, args.window)  # reads and checks every monitor before drawing
    starts = {f["td3_from"] for f in figures.values()}
    plot_curves({label: folder / "monitor.csv" for label, folder in runs.items()}, out,
                args.window, td3_from=starts.pop() if len(starts) == 1 else None)
    return print_figures({"output": str(out), "window": args.window, "runs": figures},
                         args.json)


def add_sim(p: argparse.ArgumentParser) -> None:
    p.add_argument("sim_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=sim_run, passthrough="sim_args")


def sim_run(args: argparse.Namespace) -> int:
    from sim_stub.sim_server import main as sim_main

    return sim_main(args.sim_args)


def add_record(p: argparse.ArgumentParser) -> None:
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
    p.set_defaults(func=record_run)


def record_run(args: argparse.Namespace) -> int:
    from runtime.types import Twist
    from sim_stub.recording import record, simulated_frames
    from sim_stub.scenario import load_scenario

    if args.frames < 1 or not 0 < args.fps <= 90:
        raise UserError("record: --frames must be ≥ 1 and --fps in (0, 90]")
    loaded = load_config(args.config, args.overrides)
    scenario = load_scenario(args.scenario)
    frames = simulated_frames(scenario, args.frames, args.fps, Twist(*args.twist),
                              loaded.calibration.camera, loaded.config.limits, args.seed,
                              args.noise)
    written = record(args.output, frames, args.fps)
    print_json({"recording": str(args.output), "frames": written, "fps": args.fps,
                 "scenario": scenario.name})
    return 0


def add_base_emulator(p: argparse.ArgumentParser) -> None:
    p.add_argument("emulator_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=base_emulator_run, passthrough="emulator_args")


def base_emulator_run(args: argparse.Namespace) -> int:
    from sim_stub.base_emulator import main as emulator_main

    return emulator_main(args.emulator_args)
