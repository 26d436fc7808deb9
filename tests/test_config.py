"""Config, calibration, --set and drive-script mistakes: one test per class of mistake.

Every user mistake must end as exit code 2 with exactly one stderr line
`safemove: error: ...` that names the file (or the --set argument) and the key, and no
traceback. Driven through the real CLI entry point, in-process.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import typing
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

import pytest

from runtime.cli.main import main
from runtime.config.settings import (
    DEFAULT_CALIBRATION_PATH,
    DEFAULT_CONFIG_PATH,
    Calibration,
    Config,
    load_calibration,
    load_config,
    render_calibration,
    render_config,
)

# --- helpers -------------------------------------------------------------------------------------


@pytest.fixture(autouse=True)
def _logging_not_on_captured_stderr():
    """main() calls logging.basicConfig(stream=sys.stderr); with a root handler present that is a
    no-op, so log records (e.g. the vendor-calibration warning) never land in capsys's stderr
    or on a stream a later test has closed, whatever pytest logging plugin is active."""
    root = logging.getLogger()
    handler = logging.NullHandler()
    root.addHandler(handler)
    yield
    root.removeHandler(handler)


def cli_error(capsys: pytest.CaptureFixture[str], argv: list[str], *fragments: str) -> str:
    """Run the CLI, assert a one-line user error (exit 2) containing every fragment; return it."""
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2, f"exit code {code}; stderr:\n{err}"
    assert "Traceback" not in err and "Traceback" not in out
    assert out == "", f"nothing may reach stdout before the error, got:\n{out}"
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one stderr line, got {len(lines)}:\n{err}"
    msg = lines[0]
    assert msg.startswith("safemove: error: "), msg
    for fragment in fragments:
        assert fragment in msg, f"{fragment!r} not in {msg!r}"
    return msg


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def show(config: Path, *extra: str) -> list[str]:
    return ["config", "show", "--config", str(config), *extra]


def leaf_paths(cls: type, prefix: str = "") -> list[str]:
    out: list[str] = []
    hints = typing.get_type_hints(cls)
    for f in fields(cls):
        if f.metadata.get("derived"):
            continue  # set by another key (schema.derived), not in the file
        if is_dataclass(hints[f.name]):
            out += leaf_paths(hints[f.name], f"{prefix}{f.name}.")
        else:
            out.append(f"{prefix}{f.name}")
    return out


# --- config file: each class of mistake ----------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("bogus: 1\n", ["unknown key 'bogus'"]),
        ("lop:\n  control_hz: 5\n", ["unknown key 'lop'", "did you mean 'loop'"]),
        ("base:\n  bawd: 115200\n", ["unknown key 'base.bawd'", "did you mean 'base.baud'"]),
        ("limits:\n  acel_max: 0.4\n", ["unknown key 'limits.acel_max'", "'limits.accel_max'"]),
    ],
    ids=["top-level", "top-level-hint", "nested-hint", "nested-hint-2"],
)
def test_unknown_key_is_named_with_a_hint(tmp_path, capsys, text, fragments) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), *fragments)


@pytest.mark.parametrize(
    ("text", "key", "origin"),
    [
        ("dwa:\n  robot_radius_m: 0.18\n", "dwa.robot_radius_m", "robot.radius_m"),
        ("shield:\n  robot_radius: 0.18\n", "shield.robot_radius", "robot.radius_m"),
        ("shield:\n  period: 0.1\n", "shield.period", "loop.control_hz"),
        ("dwa:\n  window_dt: 0.1\n", "dwa.window_dt", "loop.control_hz"),
    ],
)
def test_a_shared_value_is_set_in_one_place_only(tmp_path, capsys, text, key, origin) -> None:
    """The footprint and the control period exist once; the stages' copies follow them."""
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), f"'{key}' is not set here", f"'{origin}'")
    cli_error(capsys, show(DEFAULT_CONFIG_PATH, "--set", f"{key}=0.1"),
              f"'{key}' follows '{origin}'")


def test_the_stages_follow_the_footprint_and_the_control_rate(tmp_path) -> None:
    cfg = write(tmp_path / "robot.yaml", "robot:\n  radius_m: 0.25\nloop:\n  control_hz: 10\n")
    c = load_config(cfg).config
    assert c.dwa.robot_radius_m == c.shield.robot_radius == 0.25
    assert c.dwa.window_dt == c.shield.period == pytest.approx(0.1)
    assert Config().dwa.robot_radius_m == Config().shield.robot_radius == Config().robot.radius_m


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        ("loop:\n  control_hz: fast\n", "loop.control_hz", "expected a number, got 'fast'"),
        ('loop:\n  control_hz: "20"\n', "loop.control_hz", "expected a number, got '20'"),
        ("loop:\n  control_hz: true\n", "loop.control_hz", "expected a number, got True"),
        ("limits:\n  v_max: no\n", "limits.v_max", "expected a number, got False"),
        ("base:\n  glitch_ticks: true\n", "base.glitch_ticks", "expected an integer, got True"),
        ("base:\n  glitch_ticks: 1000.5\n", "base.glitch_ticks", "expected an integer"),
        ("base:\n  baud: 115200.0\n", "base.baud", "expected an integer"),
        ("base:\n  port: 5\n", "base.port", "expected a string, got 5"),
        ("base:\n  port:\n", "base.port", "expected a string, got None"),
        ("calibration_file: [a.yaml]\n", "calibration_file", "expected a string"),
        ("loop:\n  stop_on_cliff: 1\n", "loop.stop_on_cliff", "expected true or false, got 1"),
        ("loop:\n  control_hz: [20]\n", "loop.control_hz", "expected a number"),
    ],
    ids=[
        "str-for-float", "quoted-number", "bool-for-float", "yaml11-no-for-float", "bool-for-int",
        "float-for-int", "integral-float-for-int", "number-for-str", "null-for-str", "list-for-str",
        "int-for-bool", "list-for-float",
    ],
)
def test_wrong_type(tmp_path, capsys, text, key, problem) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), f"key '{key}'", problem)


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        ("loop:\n  control_hz: 0.5\n", "loop.control_hz", "must be at least 1.0 Hz, got 0.5"),
        ("limits:\n  v_max: 0.6\n", "limits.v_max", "must be at most 0.5 m/s, got 0.6"),
        ("limits:\n  v_min: 0.1\n", "limits.v_min", "must be at most 0.0 m/s"),
        ("limits:\n  accel_max: 0\n", "limits.accel_max", "must be greater than 0.0 m/s^2, got 0"),
        ("limits:\n  decel_max: -1\n", "limits.decel_max", "must be greater than 0.0"),
        ("base:\n  glitch_ticks: 9\n", "base.glitch_ticks", "must be at least 10 ticks, got 9"),
        ("loop:\n  stats_interval_s: -0.1\n", "loop.stats_interval_s", "must be at least 0.0 s"),
    ],
    ids=["below-min", "above-max", "above-max-0", "exclusive-min-hit", "exclusive-min-below",
         "int-below-min", "below-zero"],
)
def test_out_of_range(tmp_path, capsys, text, key, problem) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), f"key '{key}'", problem)


def test_range_bounds_themselves_are_accepted(tmp_path) -> None:
    cfg = write(
        tmp_path / "robot.yaml",
        "loop:\n  control_hz: 1\n  stats_interval_s: 0\nlimits:\n  v_max: 0.5\n  accel_max: 5\n"
        "base:\n  glitch_ticks: 10\n",
    )
    loaded = load_config(cfg)
    assert loaded.config.loop.control_hz == 1.0 and isinstance(loaded.config.loop.control_hz, float)
    assert loaded.config.limits.accel_max == 5.0
    assert loaded.config.base.glitch_ticks == 10


def test_value_not_among_choices(tmp_path, capsys) -> None:
    cfg = write(tmp_path / "robot.yaml", "base:\n  baud: 12345\n")
    cli_error(
        capsys, show(cfg), str(cfg), "key 'base.baud'", "must be one of 9600, 57600, 115200, 230400",
        "got 12345",
    )


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        ("loop:\n  control_hz: .nan\n", "loop.control_hz", "must be finite, got nan"),
        ("loop:\n  startup_timeout_s: .inf\n", "loop.startup_timeout_s", "must be finite, got inf"),
        ("limits:\n  v_min: -.inf\n", "limits.v_min", "must be finite, got -inf"),
        ("base:\n  glitch_ticks: .inf\n", "base.glitch_ticks", "expected an integer, got inf"),
    ],
    ids=["nan", "inf", "minus-inf", "inf-for-int"],
)
def test_non_finite_number(tmp_path, capsys, text, key, problem) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), f"key '{key}'", problem)


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("loop:\n  control_hz: 20\n\tstop_on_cliff: true\n", 3),
        ("base:\n  port: /dev/x\n  baud: 115200\n bad: 1\n", 4),
        ("limits:\n  v_max: 0.3\n  v_min: [1, 2\n", 4),
    ],
    ids=["tab", "bad-indent", "unclosed-flow"],
)
def test_invalid_yaml_names_the_line(tmp_path, capsys, text, line) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), f"{cfg}: line {line}: invalid YAML")


def test_yaml_with_a_control_character_is_one_line(tmp_path, capsys) -> None:
    cfg = tmp_path / "robot.yaml"
    cfg.write_bytes(b"loop:\n  control_hz: 20\x00\n")
    cli_error(capsys, show(cfg), str(cfg), "invalid YAML")


def test_config_file_missing(tmp_path, capsys) -> None:
    cfg = tmp_path / "nope.yaml"
    cli_error(capsys, show(cfg), f"{cfg}: config file not found")


def test_config_file_is_a_directory(tmp_path, capsys) -> None:
    cli_error(capsys, show(tmp_path), f"{tmp_path}: cannot read config file")


def test_config_file_not_utf8(tmp_path, capsys) -> None:
    cfg = tmp_path / "robot.yaml"
    cfg.write_bytes(b"base:\n  port: /dev/caf\xe9\n")  # Latin-1 e-acute
    cli_error(capsys, show(cfg), f"{cfg}: config file is not UTF-8 text")


@pytest.mark.parametrize(
    ("text", "got"),
    [("- loop\n- base\n", "got list"), ("just a string\n", "got str"), ("42\n", "got int")],
    ids=["list", "string", "number"],
)
def test_top_level_not_a_mapping(tmp_path, capsys, text, got) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), "key '<top level>'", "expected a mapping", got)


@pytest.mark.parametrize(
    ("text", "key", "got"),
    [("loop: 5\n", "loop", "got int"), ("base: [1, 2]\n", "base", "got list"),
     ("limits: fast\n", "limits", "got str")],
    ids=["int", "list", "string"],
)
def test_section_given_a_scalar(tmp_path, capsys, text, key, got) -> None:
    cfg = write(tmp_path / "robot.yaml", text)
    cli_error(capsys, show(cfg), str(cfg), f"key '{key}'", "expected a mapping of keys", got)


def test_set_does_not_hide_a_section_given_a_scalar(tmp_path, capsys) -> None:
    cfg = write(tmp_path / "robot.yaml", "base: 5\n")
    cli_error(capsys, show(cfg, "--set", "base.port=/dev/ttyUSB9"), str(cfg), "key 'base'")


def test_empty_config_file_means_all_defaults(tmp_path) -> None:
    cfg = write(tmp_path / "robot.yaml", "# nothing set\n")
    assert load_config(cfg).config == Config()


# --- --set ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("assignment", "fragments"),
    [
        ("base.port", ["--set 'base.port'", "expected KEY=VALUE"]),
        ("=5", ["--set '=5'", "expected KEY=VALUE"]),
        ("base.bawd=9600", ["--set base.bawd", "unknown key 'base.bawd'",
                            "did you mean 'base.baud'"]),
        ("lop.control_hz=5", ["--set lop.control_hz", "unknown key 'lop'",
                              "did you mean 'loop'"]),
        ("loop=3", ["--set loop", "'loop' is a section"]),
        ("base.port.name=x", ["--set base.port.name", "'base.port' is not a section"]),
        ("loop.control_hz=[1", ["--set loop.control_hz", "cannot parse value '[1'"]),
    ],
    ids=["missing-equals", "missing-key", "unknown-nested", "unknown-section", "whole-section",
         "below-a-leaf", "unparsable-value"],
)
def test_set_mistakes(capsys, assignment, fragments) -> None:
    cli_error(capsys, ["config", "show", "--set", assignment], *fragments)


@pytest.mark.parametrize(
    ("assignment", "key", "problem"),
    [
        ("base.baud=fast", "base.baud", "expected an integer, got 'fast'"),
        ("base.baud=12345", "base.baud", "must be one of"),
        ("limits.accel_max=0", "limits.accel_max", "must be greater than 0.0"),
        ("loop.control_hz=.nan", "loop.control_hz", "must be finite"),
        ("loop.control_hz=", "loop.control_hz", "expected a number, got ''"),
    ],
    ids=["type", "choices", "range", "nan", "empty-value"],
)
def test_set_bad_value_names_the_key_and_the_file(capsys, assignment, key, problem) -> None:
    argv = ["config", "show", "--set", assignment]
    cli_error(capsys, argv, str(DEFAULT_CONFIG_PATH), f"--set {assignment}", f"key '{key}'", problem)


def test_set_is_applied_over_the_file(tmp_path) -> None:
    cfg = write(tmp_path / "robot.yaml", "base:\n  port: /dev/a\n  baud: 9600\n")
    loaded = load_config(cfg, ["base.port=/dev/b", "limits.v_max=0.2"])
    assert loaded.config.base.port == "/dev/b"
    assert loaded.config.base.baud == 9600
    assert loaded.config.limits.v_max == 0.2


# --- calibration file ----------------------------------------------------------------------------


def test_calibration_file_missing(tmp_path, capsys) -> None:
    cfg = write(tmp_path / "robot.yaml", "calibration_file: cal/robot1.yaml\n")
    cal = tmp_path / "cal" / "robot1.yaml"
    msg = cli_error(capsys, show(cfg), f"{cal}: calibration file not found")
    assert "config file" not in msg


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("odometry:\n  m_per_tik: 0.0003\n",
         ["unknown key 'odometry.m_per_tik'", "did you mean 'odometry.m_per_tick'"]),
        ("camera:\n  translation_m: [0.1, 0.2]\n",
         ["key 'camera.translation_m'", "expected a list of 3 numbers, got [0.1, 0.2]"]),
        ("camera:\n  translation_m: [0.1, true, 0.5]\n",
         ["key 'camera.translation_m'", "expected a number, got True"]),
        ("camera:\n  translation_m: 0.1\n",
         ["key 'camera.translation_m'", "expected a list of 3 numbers"]),
        ("camera:\n  rpy_deg: [0, 0, 200]\n",
         ["key 'camera.rpy_deg'", "must be at most 180.0 deg, got 200.0"]),
        ("odometry:\n  left_encoder_offset: 12\n",
         ["key 'odometry.left_encoder_offset'", "must be one of 10, 14, got 12"]),
        ("odometry:\n  m_per_tick: 0\n",
         ["key 'odometry.m_per_tick'", "must be greater than 0.0 m/tick"]),
        ("odometry: 0.0003\n", ["key 'odometry'", "expected a mapping of keys"]),
    ],
    ids=["unknown-key", "wrong-length", "bool-element", "scalar-for-list", "element-range",
         "choices", "exclusive-min", "section-scalar"],
)
def test_bad_calibration_file(tmp_path, capsys, text, fragments) -> None:
    cal = write(tmp_path / "cal.yaml", text)
    cfg = write(tmp_path / "robot.yaml", f"calibration_file: {cal}\n")
    cli_error(capsys, show(cfg), str(cal), *fragments)


@pytest.mark.parametrize("text", ["", "# nothing here\n", "{}\n"], ids=["empty", "comment", "braces"])
def test_empty_calibration_file_is_refused_not_read_as_vendor_defaults(tmp_path, capsys, text):
    cal = write(tmp_path / "cal.yaml", text)
    cfg = write(tmp_path / "robot.yaml", f"calibration_file: {cal}\n")
    cli_error(capsys, show(cfg), f"{cal}: calibration file is empty")


@pytest.mark.parametrize(
    ("where", "text", "fragments"),
    [
        ("config", "loop:\n  control_hz: 20\n  control_hz: 10\n",
         ["line 3: key 'control_hz' given twice (first on line 2)"]),
        ("config", "limits:\n  v_max: 0.3\nlimits:\n  v_max: 0.5\n",
         ["line 3: key 'limits' given twice (first on line 1)"]),
        ("calibration", "odometry:\n  m_per_tick: 0.0003\n  m_per_tick: 0.0004\n",
         ["line 3: key 'm_per_tick' given twice"]),
    ],
    ids=["config-key", "config-section", "calibration-key"],
)
def test_duplicate_yaml_key_is_refused_naming_file_and_lines(tmp_path, capsys, where, text,
                                                             fragments):
    if where == "config":
        path = write(tmp_path / "robot.yaml", text)
        cfg = path
    else:
        path = write(tmp_path / "cal.yaml", text)
        cfg = write(tmp_path / "robot.yaml", f"calibration_file: {path}\n")
    cli_error(capsys, show(cfg), str(path), *fragments)


def test_relative_calibration_file_resolves_against_the_config_directory(
    tmp_path, monkeypatch, capsys
) -> None:
    conf_dir = tmp_path / "etc" / "safemove"
    cfg = write(conf_dir / "robot.yaml", "calibration_file: cal/robot1.yaml\n")
    write(conf_dir / "cal" / "robot1.yaml", "odometry:\n  m_per_tick: 0.0003\n")
    # A decoy relative to the working directory must not be the one that is read.
    work = tmp_path / "work"
    write(work / "cal" / "robot1.yaml", "odometry:\n  m_per_tick: 0.0009\n")
    monkeypatch.chdir(work)

    loaded = load_config(Path("../etc/safemove/robot.yaml"))
    assert loaded.calibration_path.resolve() == (conf_dir / "cal" / "robot1.yaml").resolve()
    assert loaded.calibration.odometry.m_per_tick == 0.0003

    assert main(show(cfg)) == 0
    out = capsys.readouterr().out
    assert f"# calibration file: {conf_dir / 'cal' / 'robot1.yaml'}" in out
    assert "m_per_tick: 0.0003\n" in out


# --- drive scripts: rejected before any device is touched ----------------------------------------


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("v: 0.1\nduration: 1\n", ["a drive script is a non-empty list"]),
        ("[]\n", ["a drive script is a non-empty list"]),
        ("- 5\n", ["entry 1: expected a mapping"]),
        ("- {v: 0.1, duration: 1}\n- {v: 0.1, omega: 0.2}\n",
         ["entry 2: key 'duration' is required"]),
        ("- {v: 0.1, duration: -1}\n", ["entry 1: key 'duration' must be positive, got -1.0"]),
        ("- {v: 0.1, duration: 0}\n", ["entry 1: key 'duration' must be positive"]),
        ("- {v: 0.1, duration: 1}\n- {v: 0.1, duration: 1, speed: 2}\n",
         ["entry 2: unknown key 'speed'"]),
        ("- {v: fast, duration: 1}\n", ["entry 1: key 'v': expected a finite number, got 'fast'"]),
        ("- {omega: true, duration: 1}\n", ["entry 1: key 'omega': expected a finite number"]),
        ("- {v: .nan, duration: 1}\n", ["entry 1: key 'v': expected a finite number, got nan"]),
        ("- {v: 0.1, duration: .inf}\n", ["entry 1: key 'duration': expected a finite number"]),
        ("- {v: 0.1, duration: 1\n", ["line 2: invalid YAML"]),
    ],
    ids=["not-a-list", "empty-list", "entry-not-mapping", "missing-duration", "negative-duration",
         "zero-duration", "unknown-key", "non-number", "bool", "nan", "inf-duration", "bad-yaml"],
)
def test_bad_drive_script_is_rejected_before_the_device(tmp_path, capsys, text, fragments) -> None:
    script = write(tmp_path / "square.yaml", text)
    msg = cli_error(
        capsys,
        ["drive", "--set", "base.port=/nonexistent", "--script", str(script)],
        str(script),
        *fragments,
    )
    assert "/nonexistent" not in msg and "base device" not in msg


def test_missing_drive_script(tmp_path, capsys) -> None:
    script = tmp_path / "nope.yaml"
    cli_error(capsys, ["drive", "--set", "base.port=/nonexistent", "--script", str(script)],
              f"{script}: drive script not found")


def test_valid_drive_script_reaches_the_device(tmp_path, capsys) -> None:
    """The contrast case: with a good script the same command fails on the device instead."""
    script = write(tmp_path / "ok.yaml", "- {v: 0.1, duration: 1}\n")
    cli_error(capsys, ["drive", "--set", "base.port=/nonexistent", "--script", str(script)],
              "base device /nonexistent: cannot open")


def test_drive_without_duration_or_script(capsys) -> None:
    cli_error(capsys, ["drive", "--set", "base.port=/nonexistent", "--twist", "0.1", "0"],
              "--duration")


# --- the documented files are renderings of the schema ------------------------------------------


def test_shipped_default_config_is_the_rendered_schema() -> None:
    assert DEFAULT_CONFIG_PATH.read_text(encoding="utf-8") == render_config()


def test_shipped_default_calibration_is_the_rendered_schema() -> None:
    assert DEFAULT_CALIBRATION_PATH.read_text(encoding="utf-8") == render_calibration()


_KEY_LINE = re.compile(r"^(?P<indent> *)(?P<key>[a-z_0-9]+):(?P<value>.*)$")


@pytest.mark.parametrize(
    ("text", "cls"),
    [(render_config(), Config), (render_calibration(), Calibration)],
    ids=["config", "calibration"],
)
def test_every_leaf_key_is_documented_with_its_default(text: str, cls: type) -> None:
    lines = text.splitlines()
    seen: list[str] = []
    stack: list[tuple[int, str]] = []
    for i, line in enumerate(lines):
        m = _KEY_LINE.match(line)
        if not m:
            continue
        indent = len(m["indent"])
        while stack and stack[-1][0] >= indent:
            stack.pop()
        assert i > 0 and lines[i - 1].lstrip().startswith("#"), f"undocumented: {line!r}"
        if m["value"].strip():  # a leaf: its comment states the default
            assert "default:" in lines[i - 1], f"no default stated for {line!r}"
            seen.append(".".join([s for _, s in stack] + [m["key"]]))
        else:
            stack.append((indent, m["key"]))
    assert seen == leaf_paths(cls)


def test_config_show_prints_an_override(capsys) -> None:
    assert main(["config", "show", "--set", "base.port=/dev/ttyUSB9"]) == 0
    out, err = capsys.readouterr()
    assert "  port: /dev/ttyUSB9\n" in out
    assert f"# config file: {DEFAULT_CONFIG_PATH}" in out
    assert "error" not in err


def _non_default(cls: type, obj: Any) -> Any:
    """A copy of a schema instance with every leaf changed to another valid value."""
    hints = typing.get_type_hints(cls)
    changes: dict[str, Any] = {}
    for f in fields(cls):
        tp, value, meta = hints[f.name], getattr(obj, f.name), f.metadata
        if is_dataclass(tp):
            changes[f.name] = _non_default(tp, value)
        elif meta.get("choices") is not None:
            changes[f.name] = next(c for c in meta["choices"] if c != value)
        elif tp is bool:
            changes[f.name] = not value
        elif tp is str:
            changes[f.name] = value + "robot #1: 'x' yes"  # characters YAML must quote
        else:
            lo, hi = meta.get("min"), meta.get("max")
            lo = -10.0 if lo is None else lo
            hi = lo + 1000 if hi is None else hi
            pick = lo + (hi - lo) / 3.0
            if tp is int:
                changes[f.name] = int(pick)
            elif typing.get_origin(tp) is tuple:
                changes[f.name] = tuple(pick + 0.1 * k for k in range(len(value)))
            else:
                changes[f.name] = pick
    return dataclasses.replace(obj, **changes)


def test_round_trip_of_a_non_default_config(tmp_path) -> None:
    calibration = _non_default(Calibration, Calibration())
    cal_path = write(tmp_path / "cal.yaml", render_calibration(calibration))
    assert load_calibration(cal_path) == calibration

    config = dataclasses.replace(_non_default(Config, Config()), calibration_file="cal.yaml")
    defaults = Config()
    for f in fields(Config):
        assert getattr(config, f.name) != getattr(defaults, f.name)
    cfg_path = write(tmp_path / "robot.yaml", render_config(config))
    loaded = load_config(cfg_path)
    assert loaded.config == config
    assert loaded.calibration == calibration
    assert render_config(loaded.config) == render_config(config)
