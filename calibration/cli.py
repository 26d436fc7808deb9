"""`safemove calibrate camera | odometry | check`: the I/O edge of the calibration tools.

Gathers frames or drives the base, calls the pure estimators, prints what changed and writes
the calibration file (backup kept, atomic). Any mistake or cut-short run is one line and exit
code 2 with the file untouched; the last line of output is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from calibration.calibration_file import output_path, write_calibration
from runtime.cli.app import on_stop_signals
from runtime.cli.args import add_config_args, finite_float, int_at_least
from runtime.config.calibration import Calibration
from runtime.config.settings import LoadedConfig, load_config
from runtime.errors import UserError

MIN_FRAMES = 5


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, separators=(",", ":")), flush=True)


def _positive(text: str) -> float:
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be greater than 0, got {text!r}")
    return value


def _load(args: argparse.Namespace) -> LoadedConfig:
    return load_config(args.config, args.overrides)


def _write(args: argparse.Namespace, loaded: LoadedConfig, new: Calibration,
           summary: dict[str, Any], notes: list[str]) -> int:
    """Print the result and the difference; write the file unless --dry-run."""
    for note in notes:
        print(note)
    if args.dry_run:
        from calibration.calibration_file import differences, rounded

        changes = differences(loaded.calibration, rounded(new))
        print("dry run: nothing written; would change:" if changes else "dry run: no change")
        for line in changes:
            print(f"  {line}")
        _print_json({**summary, "written": None, "backup": None, "changes": changes})
        return 0
    path = output_path(loaded.calibration_path, args.output)
    backup, changes = write_calibration(path, new, loaded.calibration)
    print(f"wrote {path}" + (f" (previous file kept as {backup})" if backup else ""))
    for line in changes or ["no value changed"]:
        print(f"  {line}")
    _print_json({**summary, "written": str(path), "backup": None if backup is None
                 else str(backup), "changes": changes})
    return 0


# --- camera ------------------------------------------------------------------------------------


def _enough(frames: Any, wanted: int, where: str, timeout_s: float, what: str = "depth") -> None:
    if len(frames.images) < wanted:
        why = "the recording ended" if frames.ended else f"{timeout_s:g} s passed"
        raise UserError(f"{where}: {why} after {len(frames.images)} {what} frames; need"
                        f" {wanted} (--frames, at least {MIN_FRAMES})")


def _depth_frames(args: argparse.Namespace, loaded: LoadedConfig):
    """Depth frames from --recording or the configured source; UserError when too few."""
    from calibration.frames import collect_depth

    if args.recording is not None:
        from drivers.realsense.playback import PlaybackDepthSource

        source: Any = PlaybackDepthSource(args.recording)
        where, skip = str(args.recording), 0
    else:
        from runtime.cli.app import open_depth_source

        source = open_depth_source(loaded.config.depth, str(loaded.config_path))
        if source is None:
            raise UserError(f"{loaded.config_path}: key 'depth.source' is 'none': give"
                            " --recording FILE or set depth.source (d435 or sim)")
        where, skip = f"depth source {loaded.config.depth.source}", 5
    frames = collect_depth(source, args.frames, args.timeout, skip,
                           drain=args.recording is not None)
    _enough(frames, args.frames, where, args.timeout)
    return frames


def _board_input(args: argparse.Namespace, loaded: LoadedConfig, ir: Any = None):
    """The board's images (`ir` when the recording's pass already read them) and geometry."""
    from calibration.camera import BoardInput
    from calibration.charuco import BoardPlacement, BoardSpec
    from calibration.frames import infrared_from_d435

    spec = BoardSpec(args.board_squares[0], args.board_squares[1], args.board_square_m,
                     args.board_marker_m, args.board_dict)
    try:
        spec.board()
    except ValueError as exc:
        raise UserError(f"board: {exc}") from None
    if ir is None and loaded.config.depth.source == "d435":
        ir = infrared_from_d435(loaded.config.depth, args.frames)
    elif ir is None:
        raise UserError(f"{loaded.config_path}: key 'depth.source': the {loaded.config.depth.source}"
                        " depth link carries no infrared image; --board needs the D435 or a"
                        " recording with an infrared stream")
    if not ir.images:
        raise UserError("board: no infrared frames arrived")
    x, y, z, yaw = args.board_pose
    return BoardInput(ir.images, ir.intrinsics, spec, BoardPlacement(x, y, z, yaw))


def cmd_camera(args: argparse.Namespace) -> int:
    from calibration.camera import calibrate_camera

    loaded = _load(args)
    if args.output is None:
        output_path(loaded.calibration_path, None)  # refuse the shipped file before any work
    previous = loaded.calibration.camera
    if args.recording is not None and args.board_pose is not None:
        from calibration.frames import recording_with_infrared

        frames, ir = recording_with_infrared(args.recording, args.frames)
        _enough(frames, args.frames, str(args.recording), args.timeout)
        board = _board_input(args, loaded, ir)
    else:
        frames = _depth_frames(args, loaded)
        board = _board_input(args, loaded) if args.board_pose is not None else None
    result = calibrate_camera(frames.images, frames.intrinsics, previous, board)
    mount = result.mount
    notes = [(f"floor: camera {result.floor.height_m:.4f} m high, pitch {mount.rpy_deg[1]:+.3f}"
             f" deg, roll {mount.rpy_deg[0]:+.3f} deg ({result.floor.inliers} of"
             f" {result.floor.points} points on the floor, RMS"
             f" {result.floor.rms_m * 1000:.1f} mm, {len(frames.images)} frames)")]
    if result.board is None:
        notes.append("no board: translation x, y and yaw kept from the previous calibration"
                     f" ({previous.translation_m[0]}, {previous.translation_m[1]} m,"
                     f" {previous.rpy_deg[2]} deg); use --board-pose to measure them")
    else:
        notes.append(f"board: x {mount.translation_m[0]:+.4f} m, y {mount.translation_m[1]:+.4f}"
                     f" m, yaw {mount.rpy_deg[2]:+.3f} deg (reprojection RMS"
                     f" {result.board.rms_px:.2f} px over {len(board.images)} frames)")
    notes += [f"warning: {w}" for w in result.warnings()]
    new = Calibration(mount, loaded.calibration.odometry)
    return _write(args, loaded, new, {"calibrate": "camera", **result.summary()}, notes)


# --- odometry ----------------------------------------------------------------------------------


class ConsoleOperator:
    """Instructions and questions on stderr, answers from stdin (a terminal or a pipe)."""

    def _ask(self, question: str) -> str:
        print(f"? {question}", file=sys.stderr, flush=True)
        line = sys.stdin.readline()
        if not line:
            from calibration.odometry_runs import RunCutShort

            raise RunCutShort("no answer (stdin closed): calibration stopped, the file is left"
                              " as it was")
        return line.strip()

    def _numbers(self, question: str, count: int) -> tuple[float, ...]:
        while True:
            parts = self._ask(question).replace(",", " ").split()
            try:
                values = tuple(float(p) for p in parts)
            except ValueError:
                values = ()
            if len(values) == count and all(math.isfinite(v) for v in values):
                return values
            print(f"  please give {count} number(s)", file=sys.stderr)

    def prepare(self, instruction: str) -> None:
        self._ask(f"{instruction} Press Enter when ready.")

    def measured_length(self, odometry_m: float) -> float:
        return self._numbers(f"Measure the straight-line distance from the start mark to the"
                             f" robot now, in metres (odometry says {odometry_m:.3f}):", 1)[0]

    def measured_end(self, square: str) -> tuple[float, float]:
        x, y = self._numbers(f"{square} done. Measure where the robot ended from the start"
                             " mark, in the start direction: forward and left offsets in metres"
                             " (e.g. 0.012 -0.030):", 2)
        return x, y

    def measured_turn_deg(self, commanded_deg: float) -> float:
        return self._numbers(f"How many degrees did the robot turn (counter-clockwise positive;"
                             f" odometry says {commanded_deg:+.1f})?", 1)[0]


def _open_runner(loaded: LoadedConfig):
    from calibration.odometry_runs import BaseRunner, RunConfig
    from drivers.spark.link import SparkBaseLink

    link = SparkBaseLink(loaded.config.base, loaded.calibration.odometry)
    link.open()
    cfg = RunConfig(feedback_max_age_s=max(0.5, loaded.config.loop.feedback_max_age_s))
    return link, BaseRunner(link, loaded.calibration.odometry, cfg)


def cmd_odometry(args: argparse.Namespace) -> int:
    from calibration.odometry_runs import OdometryPlan, calibrate_odometry

    loaded = _load(args)
    if args.output is None:
        output_path(loaded.calibration_path, None)
    plan = OdometryPlan(args.length, args.turns, args.squares, args.side)
    link, runner = _open_runner(loaded)
    try:
        with on_stop_signals(lambda _name: runner.abort.set()):
            result = calibrate_odometry(runner, ConsoleOperator(), loaded.calibration.odometry,
                                        plan)
    finally:
        link.close()
    s = result.summary()
    notes = [f"metres per tick {s['m_per_tick']:.6g} ({s['m_per_tick_change_pct']:+.2f} %),"
             f" axle {s['axle_length_m']:.4f} m (turns by {s['turns_by']}:"
             f" {s['axle_turns_m']:.4f} m), left encoder at offset {s['left_encoder_offset']}"
             + (" (SWAPPED from the previous calibration)" if s["encoders_swapped"] else "")]
    if result.umbmark is not None:
        notes.append(f"UMBmark over {result.umbmark.runs} squares: wheel diameter ratio"
                     f" {result.umbmark.ed:.5f} (not stored: the calibration file has one m/tick"
                     f" for both wheels), wheelbase factor {result.umbmark.eb:.5f}")
    new = Calibration(loaded.calibration.camera, result.calibration)
    return _write(args, loaded, new, {"calibrate": "odometry", **s}, notes)


# --- check -------------------------------------------------------------------------------------


def cmd_check(args: argparse.Namespace) -> int:
    from calibration.check import check_camera, check_mapping

    loaded = _load(args)
    items = []
    if args.recording is not None or loaded.config.depth.source != "none":
        frames = _depth_frames(args, loaded)
        items += check_camera(frames.images, frames.intrinsics, loaded.calibration.camera)
    if not args.no_motion:
        from calibration.odometry_runs import Estimates
        from runtime.types import Twist

        odo = loaded.calibration.odometry
        link, runner = _open_runner(loaded)
        try:
            with on_stop_signals(lambda _name: runner.abort.set()):
                est = Estimates(odo.m_per_tick, odo.axle_length_m, odo.left_encoder_offset)
                runner.start(est)
                turn = runner.drive(est, runner.timed(Twist(0.0, 0.8), 1.0))
                items.append(check_mapping(runner.totals(turn), odo))
        finally:
            link.close()
    if not items:
        raise UserError("check: nothing to check: give --recording FILE or set depth.source,"
                        " and/or leave out --no-motion")
    for item in items:
        print(item.line())
    failed = [i.name for i in items if i.ok is False]
    _print_json({"calibrate": "check", "ok": not failed, "failed": failed,
                 "items": [i.as_dict() for i in items]})
    return 1 if failed else 0


# --- parser ------------------------------------------------------------------------------------


def _add_depth_args(p: argparse.ArgumentParser, frames: int) -> None:
    p.add_argument("--recording", type=Path,
                   help="a .db3 recording instead of the configured depth source")
    p.add_argument("--frames", type=int_at_least(MIN_FRAMES), default=frames,
                   help=f"depth frames to average (default {frames}, at least {MIN_FRAMES})")
    p.add_argument("--timeout", type=_positive, default=20.0,
                   help="seconds to wait for frames from a live source (default 20)")


def _add_output_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--output", type=Path,
                   help="calibration file to write (default: the one the config uses; the"
                        " shipped vendor file is never overwritten)")
    p.add_argument("--dry-run", action="store_true", help="print the result, write nothing")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """`safemove calibrate` and its actions."""
    csub = p.add_subparsers(dest="calibrate_command", required=True, metavar="WHAT")

    cp = csub.add_parser(
        "camera", help="camera height, pitch, roll from the floor; x, y, yaw from a ChArUco"
                       " board at a measured pose (--board-pose)")
    add_config_args(cp)
    _add_depth_args(cp, 30)
    _add_output_args(cp)
    cp.add_argument("--board-pose", nargs=4, type=finite_float, metavar=("X", "Y", "Z", "YAW"),
                    help="the board pattern's centre in base_link (m) and its yaw (deg; 0 ="
                         " upright, facing the robot squarely)")
    cp.add_argument("--board-squares", nargs=2, type=int_at_least(2), default=(7, 5),
                    metavar=("NX", "NY"), help="squares across and down (default 7 5)")
    cp.add_argument("--board-square-m", type=_positive, default=0.055,
                    help="square side as printed (m, default 0.055)")
    cp.add_argument("--board-marker-m", type=_positive, default=0.041,
                    help="marker side as printed (m, default 0.041)")
    cp.add_argument("--board-dict", default="DICT_4X4_50",
                    help="ArUco dictionary (default DICT_4X4_50)")
    cp.set_defaults(func=cmd_camera)

    op = csub.add_parser(
        "odometry", help="guided runs: encoder mapping, straight run (you measure it), turns in"
                         " place, UMBmark squares; writes m/tick, axle, mapping")
    add_config_args(op)
    _add_output_args(op)
    op.add_argument("--length", type=_positive, default=2.0,
                    help="straight run length (m, default 2)")
    op.add_argument("--turns", type=int_at_least(1), default=2,
                    help="full in-place turns each way (default 2)")
    op.add_argument("--squares", type=int_at_least(0), default=5,
                    help="UMBmark squares per direction (default 5; 0 skips UMBmark)")
    op.add_argument("--side", type=_positive, default=1.0,
                    help="UMBmark square side (m, default 1)")
    op.set_defaults(func=cmd_odometry)

    kp = csub.add_parser("check", help="pass/fail health check of the current calibration")
    add_config_args(kp)
    _add_depth_args(kp, 10)
    kp.add_argument("--no-motion", action="store_true",
                    help="skip the encoder check (it turns the robot left for a second)")
    kp.set_defaults(func=cmd_check)
