"""systemd/: the unit (systemd-analyze verify + security), the udev rule and install.sh."""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SYSTEMD_DIR = REPO / "systemd"
UNIT = SYSTEMD_DIR / "safemove.service"
RULES = SYSTEMD_DIR / "99-spark-base.rules"
INSTALL = SYSTEMD_DIR / "install.sh"
EXEC_BINARY = "/opt/safemove/.venv/bin/safemove"

# `systemd-analyze security --offline=true` exposure (0-10 as printed) measured for
# safemove.service with systemd 252: 1.2. The threshold is that number: removing any single one of
# ProtectSystem, ProtectHome, PrivateTmp, NoNewPrivileges, CapabilityBoundingSet, User,
# SystemCallFilter, SystemCallArchitectures, RestrictAddressFamilies, RestrictNamespaces,
# IPAddressDeny, ProtectKernelTunables, ProtectProc or DevicePolicy raises it to 1.3-3.2, so a
# weakened unit fails here. The remaining exposure is by design: device access (DeviceAllow,
# PrivateDevices=no), AF_UNIX + AF_NETLINK, no PrivateNetwork/PrivateUsers (udev events and
# device groups), no MemoryDenyWriteExecute (see the unit's comments). Other systemd versions
# weigh settings differently: re-measure there rather than loosen blindly.
MAX_EXPOSURE = 1.2

SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd_analyze = pytest.mark.skipif(
    SYSTEMD_ANALYZE is None, reason="systemd-analyze is not installed (package systemd)"
)


# ----------------------------------------------------------------------------- helpers
def parse_unit(text: str) -> dict[str, list[tuple[str, str]]]:
    """Unit file -> {section: [(key, value), ...]} (no line continuations are used)."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = line[1:-1]
            sections.setdefault(current, [])
            continue
        assert current is not None, f"key outside a section: {raw!r}"
        key, sep, value = line.partition("=")
        assert sep, f"not KEY=VALUE: {raw!r}"
        sections[current].append((key.strip(), value.strip()))
    return sections


def values(sections, section: str, key: str) -> list[str]:
    return [v for k, v in sections.get(section, []) if k == key]


def one(sections, section: str, key: str) -> str:
    found = values(sections, section, key)
    assert len(found) == 1, f"[{section}] {key}= expected once, found {found}"
    return found[0]


def unit_with_existing_binary(tmp_path: Path) -> Path:
    """Copy of the unit whose ExecStart binary exists (verify fails on a missing one)."""
    fake = tmp_path / "bin" / "safemove"
    fake.parent.mkdir()
    fake.write_text("#!/bin/sh\nexit 0\n")
    fake.chmod(0o755)
    text = UNIT.read_text()
    assert text.count(f"ExecStart={EXEC_BINARY} ") == 1
    unit = tmp_path / "safemove.service"
    unit.write_text(text.replace(f"ExecStart={EXEC_BINARY} ", f"ExecStart={fake} "))
    return unit


def run(cmd, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=60, **kw)


# ----------------------------------------------------------------------------- unit content
def test_unit_settings():
    s = parse_unit(UNIT.read_text())
    svc = "Service"
    assert one(s, svc, "Type") == "notify"
    assert one(s, svc, "NotifyAccess") == "main"
    assert one(s, svc, "WatchdogSec") == "2s"
    assert one(s, svc, "ExecStart") == f"{EXEC_BINARY} run --config /etc/safemove/config.yaml"
    assert one(s, svc, "Restart") == "on-failure"
    assert one(s, svc, "RestartSec") == "2s"
    assert one(s, svc, "RestartPreventExitStatus") == "2"
    assert one(s, svc, "TimeoutStopSec") == "5s"
    assert one(s, svc, "KillSignal") == "SIGTERM"
    assert one(s, svc, "User") == "safemove"
    assert one(s, svc, "Group") == "safemove"
    assert one(s, svc, "SupplementaryGroups").split() == ["dialout", "video", "plugdev"]
    assert one(s, svc, "StateDirectory") == "safemove"
    assert one(s, svc, "LogsDirectory") == "safemove"
    # the control socket: in the runtime directory, reachable by the service's group only
    assert one(s, svc, "RuntimeDirectory") == "safemove"
    assert one(s, svc, "RuntimeDirectoryMode") == "0750"
    assert one(s, svc, "IPAddressDeny") == "any"
    assert one(s, svc, "Environment") == "PYTHONUNBUFFERED=1"
    assert one(s, svc, "DevicePolicy") == "closed"
    assert one(s, svc, "PrivateDevices") == "no"
    assert sorted(values(s, svc, "DeviceAllow")) == [
        "char-ttyUSB rw",
        "char-usb_device rw",
        "char-video4linux rw",
    ]
    assert set(one(s, svc, "RestrictAddressFamilies").split()) == {"AF_UNIX", "AF_NETLINK"}
    for key in (
        "NoNewPrivileges",
        "ProtectHome",
        "PrivateTmp",
        "ProtectKernelTunables",
        "ProtectKernelModules",
        "ProtectKernelLogs",
        "ProtectControlGroups",
        "RestrictNamespaces",
        "LockPersonality",
    ):
        assert one(s, svc, key) == "yes", key
    assert one(s, svc, "ProtectSystem") == "strict"
    assert one(s, svc, "SystemCallArchitectures") == "native"
    # Inherited SCHED_FIFO starves the camera: real-time only together with ResetOnFork.
    if values(s, svc, "CPUSchedulingPolicy") not in ([], ["other"]):
        assert one(s, svc, "CPUSchedulingResetOnFork") == "yes"

    unit = "Unit"
    assert one(s, unit, "Wants") == "dev-sparkBase.device"
    assert one(s, unit, "After") == "dev-sparkBase.device"
    assert not values(s, unit, "BindsTo"), "BindsTo would stop the runtime when the port vanishes"
    assert not values(s, unit, "Requires")
    assert values(s, unit, "StartLimitIntervalSec") and values(s, unit, "StartLimitBurst")
    assert one(s, "Install", "WantedBy") == "multi-user.target"


# ----------------------------------------------------------------------------- systemd-analyze
@needs_systemd_analyze
def test_systemd_analyze_verify_prints_nothing_about_the_unit(tmp_path):
    unit = unit_with_existing_binary(tmp_path)
    help_text = run([SYSTEMD_ANALYZE, "--help"]).stdout
    # Without --recursive-errors=no, verify exits 0 even on warnings (field notes); with it
    # (systemd >= 250) a warning about the unit makes it exit 1. The output check below holds
    # either way.
    flags = ["--recursive-errors=no"] if "--recursive-errors" in help_text else []
    res = run([SYSTEMD_ANALYZE, "verify", *flags, str(unit)], cwd=tmp_path)
    output = res.stdout + res.stderr
    about_unit = [line for line in output.splitlines() if str(unit) in line or "safemove" in line]
    assert about_unit == [], "systemd-analyze verify warned:\n" + output
    assert res.returncode == 0, output


@needs_systemd_analyze
def test_systemd_analyze_verify_catches_a_bad_key(tmp_path):
    """The check above would see a warning: prove it on a deliberately broken copy."""
    unit = unit_with_existing_binary(tmp_path)
    unit.write_text(unit.read_text().replace("[Service]\n", "[Service]\nWatchdogSecs=2s\n"))
    res = run([SYSTEMD_ANALYZE, "verify", str(unit)], cwd=tmp_path)
    assert "WatchdogSecs" in res.stdout + res.stderr


@needs_systemd_analyze
def test_systemd_analyze_security_exposure(tmp_path):
    unit = unit_with_existing_binary(tmp_path)
    res = run(
        [
            SYSTEMD_ANALYZE,
            "security",
            "--offline=true",
            # --threshold is on a 0-100 scale: 1.2 printed = 12.
            f"--threshold={round(MAX_EXPOSURE * 10)}",
            "--no-pager",
            str(unit),
        ],
        cwd=tmp_path,
    )
    output = res.stdout + res.stderr
    m = re.search(r"Overall exposure level for safemove\.service:\s*([0-9.]+)", output)
    assert m, output
    exposure = float(m.group(1))
    assert exposure <= MAX_EXPOSURE, output
    assert res.returncode == 0, output


# ----------------------------------------------------------------------------- udev rule
RULE_TOKEN = re.compile(r'([A-Z_]+(?:\{[^}]*\})?)\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"')


def parse_rules(text: str) -> list[list[tuple[str, str, str]]]:
    rules = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        assert not line.endswith("\\"), "no continuation lines expected"
        tokens = RULE_TOKEN.findall(line)
        rebuilt = ", ".join(f'{k}{op}"{v}"' for k, op, v in tokens)
        assert rebuilt == line, f"unparsed text in rule: {line!r}"
        rules.append(tokens)
    return rules


def test_udev_rule_for_the_base_and_camera():
    rules = parse_rules(RULES.read_text())
    base = [r for r in rules if ("ATTRS{idVendor}", "==", "1a86") in r]
    assert len(base) == 1
    [base] = base
    assert ("SUBSYSTEM", "==", "tty") in base
    assert ("ATTRS{idProduct}", "==", "7523") in base
    assert ("SYMLINK", "+=", "sparkBase") in base
    assert ("TAG", "+=", "systemd") in base
    assert ("GROUP", "=", "dialout") in base
    assert ("MODE", "=", "0660") in base

    cam_usb = [
        r
        for r in rules
        if ("SUBSYSTEM", "==", "usb") in r
        and any(k in ("ATTR{idVendor}", "ATTRS{idVendor}") and v == "8086" for k, _, v in r)
    ]
    assert len(cam_usb) == 1
    [cam] = cam_usb
    assert any(k.endswith("{idProduct}") and op == "==" and v == "0b07" for k, op, v in cam)
    assert ("GROUP", "=", "video") in cam
    assert ("MODE", "=", "0660") in cam


def test_udev_rule_file_name_sorts_late():
    # Rules run in lexical order; ours must come after the distribution's 50-udev-default.rules.
    assert RULES.name > "50-udev-default.rules"


# ----------------------------------------------------------------------------- install.sh
def test_install_sh_syntax_and_mode():
    assert run(["bash", "-n", str(INSTALL)]).returncode == 0
    assert INSTALL.stat().st_mode & stat.S_IXUSR, "install.sh must be executable"
    assert "set -euo pipefail" in INSTALL.read_text()


def make_source(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    (src / "systemd").mkdir(parents=True)
    (src / "runtime" / "config").mkdir(parents=True)
    (src / "calibration").mkdir()
    (src / "pyproject.toml").write_text('[project]\nname = "safemove-rl"\n')
    shutil.copy(UNIT, src / "systemd" / UNIT.name)
    shutil.copy(RULES, src / "systemd" / RULES.name)
    (src / "runtime" / "config" / "default_config.yaml").write_text("control_hz: 20\n")
    (src / "runtime" / "pipeline.py").write_text("# code\n")
    (src / "calibration" / "spark_default.yaml").write_text("camera_height_m: 0.3\n")
    # Things that must not be copied to /opt/safemove.
    (src / ".venv" / "bin").mkdir(parents=True)
    (src / ".git").mkdir()
    (src / "runtime" / "__pycache__").mkdir()
    (src / "runtime" / "__pycache__" / "loop.cpython-311.pyc").write_bytes(b"x")
    return src


def fake_tools(tmp_path: Path) -> tuple[dict[str, str], Path]:
    """PATH with stand-ins for the root-only tools that record any call to them."""
    bin_dir = tmp_path / "fakebin"
    bin_dir.mkdir()
    marker = tmp_path / "called.txt"
    for tool in ("useradd", "usermod", "groupadd", "systemctl", "udevadm", "runuser", "pip"):
        p = bin_dir / tool
        p.write_text(f'#!/bin/sh\necho "{tool} $*" >> "{marker}"\n')
        p.chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}:{os.environ.get('PATH', '/usr/bin:/bin')}")
    return env, marker


def install(src: Path, prefix: Path, env) -> subprocess.CompletedProcess:
    return run(["bash", str(INSTALL), "--source", str(src), "--prefix", str(prefix)], env=env)


def test_install_sh_prefix_layout(tmp_path):
    src = make_source(tmp_path)
    prefix = tmp_path / "stage"
    env, marker = fake_tools(tmp_path)
    res = install(src, prefix, env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert not marker.exists(), "--prefix must not run root tools:\n" + marker.read_text()

    app = prefix / "opt/safemove"
    assert (app / "pyproject.toml").is_file()
    assert (app / "runtime/pipeline.py").is_file()
    assert (app / "systemd/safemove.service").is_file()
    for excluded in (".venv", ".git", "runtime/__pycache__"):
        assert not (app / excluded).exists(), excluded
    assert (prefix / "etc/systemd/system/safemove.service").read_text() == UNIT.read_text()
    assert (prefix / "etc/udev/rules.d/99-spark-base.rules").read_text() == RULES.read_text()
    assert (prefix / "etc/safemove/config.yaml").read_text() == "control_hz: 20\n"
    assert (prefix / "etc/safemove/calibration.yaml").read_text() == "camera_height_m: 0.3\n"

    would = [ln for ln in res.stdout.splitlines() if ln.startswith("would run:")]
    joined = "\n".join(would)
    assert "useradd --system" in joined and "dialout,video,plugdev" in joined
    assert "/opt/safemove/.venv/bin/python -m pip install --upgrade /opt/safemove" in joined
    assert "[dev]" not in joined
    assert "udevadm control --reload" in joined
    assert "udevadm trigger" in joined
    assert "systemctl daemon-reload" in joined
    check = next(i for i, ln in enumerate(would) if "config show" in ln)
    enable = next(i for i, ln in enumerate(would) if "systemctl enable safemove.service" in ln)
    assert "--config /etc/safemove/config.yaml" in would[check]
    assert check < enable, "the config must be validated before the service is enabled"


def test_install_sh_keeps_existing_config_and_calibration(tmp_path):
    src = make_source(tmp_path)
    prefix = tmp_path / "stage"
    env, _ = fake_tools(tmp_path)
    etc = prefix / "etc/safemove"
    etc.mkdir(parents=True)
    (etc / "config.yaml").write_text("control_hz: 15  # tuned on this robot\n")
    (etc / "calibration.yaml").write_text("camera_height_m: 0.312  # measured\n")
    res = install(src, prefix, env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (etc / "config.yaml").read_text() == "control_hz: 15  # tuned on this robot\n"
    assert (etc / "calibration.yaml").read_text() == "camera_height_m: 0.312  # measured\n"
    assert f"kept existing {etc / 'calibration.yaml'}" in res.stdout

    # A second install (upgrade) removes modules deleted from the source.
    (src / "runtime" / "pipeline.py").unlink()
    res = install(src, prefix, env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert not (prefix / "opt/safemove/runtime/pipeline.py").exists()


def test_install_sh_stage_inside_source_does_not_copy_itself(tmp_path):
    src = make_source(tmp_path)
    env, _ = fake_tools(tmp_path)
    res = install(src, src / "stage", env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (src / "stage/opt/safemove/pyproject.toml").is_file()
    assert not (src / "stage/opt/safemove/stage").exists()


def test_install_sh_errors_are_one_line(tmp_path):
    src = make_source(tmp_path)
    (src / "calibration" / "spark_default.yaml").unlink()
    env, _ = fake_tools(tmp_path)
    res = install(src, tmp_path / "stage", env)
    assert res.returncode == 1
    assert res.stderr.count("\n") == 1
    assert "calibration/spark_default.yaml" in res.stderr and "error" in res.stderr

    res = run(["bash", str(INSTALL), "--bogus"], env=env)
    assert res.returncode == 2
    assert "--bogus" in res.stderr and res.stderr.count("\n") == 1

    res = run(["bash", str(INSTALL), "--help"], env=env)
    assert res.returncode == 0
    assert "--prefix" in res.stdout and "--source" in res.stdout


def test_install_sh_points_a_fresh_config_at_the_installed_calibration(tmp_path):
    src = make_source(tmp_path)
    (src / "runtime" / "config" / "default_config.yaml").write_text(
        "# comment\ncalibration_file: ''\nloop:\n  control_hz: 20.0\n"
    )
    env, _ = fake_tools(tmp_path)
    res = install(src, tmp_path / "stage", env)
    assert res.returncode == 0, res.stdout + res.stderr
    text = (tmp_path / "stage/etc/safemove/config.yaml").read_text()
    lines = text.splitlines()
    assert lines[0] == "# comment"
    assert lines[1].startswith("calibration_file: calibration.yaml  #")
    assert lines[2:] == ["loop:", "  control_hz: 20.0"]
