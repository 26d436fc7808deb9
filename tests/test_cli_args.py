"""Numbers on the command line: NaN/inf never reach a command, counts that make no sense are
refused by the parser (one line, exit 2) before any device or benchmark starts."""

from __future__ import annotations

import pytest

from runtime.cli.main import COMMANDS, main, parse_args


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["drive", "--twist", "nan", "0", "--duration", "1"], "--twist: must be finite"),
        (["drive", "--twist", "0.1", "0", "--duration", "inf"], "--duration: must be finite"),
        (["run", "--planner", "dwa", "--goal", "1", "nan"], "--goal: must be finite"),
        (["record", "paper_a", "-o", "x.db3", "--fps", "inf"], "--fps: must be finite"),
        (["record", "paper_a", "-o", "x.db3", "--frames", "0"], "--frames: must be at least 1"),
        (["bench", "perception", "--frames", "1"], "--frames: must be at least 2"),
        (["bench", "loop", "--cycles", "0"], "--cycles: must be at least 1"),
        (["bench", "planner", "--worlds", "zero"], "--worlds: not an integer"),
    ],
)
def test_bad_numbers_are_refused_by_the_parser(args, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


def test_pass_through_commands_keep_their_leading_options(capsys):
    """`safemove base-emulator --link P` reaches the emulator's own parser (argparse's REMAINDER
    alone refused a leading option); other commands still refuse unknown options."""
    args = parse_args(["base-emulator", "--link", "/tmp/spark", "--gyro-bias", "0.01"])
    assert args.emulator_args == ["--link", "/tmp/spark", "--gyro-bias", "0.01"]
    assert parse_args(["sim", "paper_a", "--fps", "5"]).sim_args == ["paper_a", "--fps", "5"]
    with pytest.raises(SystemExit) as exc:
        parse_args(["config", "show", "--no-such-option"])
    assert exc.value.code == 2 and "--no-such-option" in capsys.readouterr().err


def test_demo_refuses_an_unknown_scenario_before_starting_anything(capsys):
    assert main(["demo", "--scenario", "no_such_room"]) == 2
    err = capsys.readouterr().err
    assert "no_such_room" in err and "Traceback" not in err


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_every_help_page_prints(command, capsys):
    """`safemove --help` and each command's `--help` print their page and exit 0 (a bare `%` in a
    help string made argparse raise instead)."""
    with pytest.raises(SystemExit) as exc:
        main(["--help"] if command is None else [command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: safemove")
    if command is None:
        assert all(name in out for name in COMMANDS)
