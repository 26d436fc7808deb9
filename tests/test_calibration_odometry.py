"""Odometry calibration: the estimators on exact kinematics, and the guided runs through the
real base link against the emulator process with a known scale error, axle error and swapped
encoders; a run cut short leaves the calibration file untouched."""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

from calibration.odometry_fit import (
    EstimateError,
    RunTotals,
    SquareRun,
    encoder_mapping,
    m_per_tick,
    umbmark,
)
from calibration.odometry_runs import BaseRunner, OdometryPlan, RunConfig, calibrate_odometry
from drivers.spark.link import SparkBaseLink
from runtime.config.settings import load_calibration, load_config, render_calibration
from sim_stub.emulator_process import EmulatorProcess

NOMINAL_MPT = 0.00028885
NOMINAL_AXLE = 0.266


def _arc(pose, d_left, d_right, axle):
    x, y, th = pose
    ds, dth = (d_left + d_right) / 2, (d_right - d_left) / axle
    chord = ds * (math.sin(dth / 2) / (dth / 2) if abs(dth) > 1e-12 else 1.0)
    return x + chord * math.cos(th + dth / 2), y + chord * math.sin(th + dth / 2), th + dth


def _square_end(side, clockwise, k_left, k_right, axle_used, axle_true):
    """Where a robot ends that drives an odometry-perfect square with wheels k_left, k_right
    times their nominal size and a wheelbase axle_true where odometry assumes axle_used."""
    pose = (0.0, 0.0, 0.0)
    turn = (math.pi / 2) * (axle_used / 2) * (-1 if clockwise else 1)
    for _ in range(4):
        pose = _arc(pose, side * k_left, side * k_right, axle_true)
        pose = _arc(pose, -turn * k_left, turn * k_right, axle_true)
    return pose[:2]


@pytest.mark.parametrize(("k_left", "k_right", "axle_true"),
                         [(1.0, 1.0, 0.271), (0.998, 1.002, 0.266), (0.997, 1.001, 0.262)])
def test_umbmark_recovers_wheel_ratio_and_wheelbase(k_left, k_right, axle_true):
    runs = [SquareRun(1.0, cw, (0.0, 0.0), _square_end(1.0, cw, k_left, k_right, NOMINAL_AXLE,
                                                       axle_true)) for cw in (True, False)]
    result = umbmark(runs, NOMINAL_AXLE)
    assert result.ed == pytest.approx(k_right / k_left, abs=5e-4)
    assert result.eb * NOMINAL_AXLE == pytest.approx(axle_true, abs=3e-4)


def test_estimators_refuse_runs_that_did_something_else():
    with pytest.raises(EstimateError, match="one encoder forward and the other back"):
        encoder_mapping(RunTotals(300, 310, 0.5, 1.0))  # both forward: not a turn in place
    with pytest.raises(EstimateError, match="IMU yaw fell"):
        encoder_mapping(RunTotals(300, -300, -0.5, 1.0))
    assert encoder_mapping(RunTotals(300, -300, 0.5, 1.0)).left_encoder_offset == 14
    assert encoder_mapping(RunTotals(-300, 300, None, 1.0)).left_encoder_offset == 10
    with pytest.raises(EstimateError, match="did not drive straight"):
        m_per_tick(RunTotals(3000, 3500, 0.0, 3.0), 14, 1.0)
    with pytest.raises(EstimateError, match="positive number"):
        m_per_tick(RunTotals(3000, 3000, 0.0, 3.0), 14, -1.0)
    with pytest.raises(EstimateError, match="both directions"):
        umbmark([SquareRun(1.0, True, (0, 0), (0.01, 0.0))], NOMINAL_AXLE)


class TruthOperator:
    """Stands in for the person with the tape measure: reads the emulator's ground truth."""

    def __init__(self, emu: EmulatorProcess) -> None:
        self.emu = emu
        self.start: dict = {}

    def prepare(self, instruction: str) -> None:
        self.start = self.emu.truth()

    def _moved(self) -> tuple[float, float, float]:
        now, a = self.emu.truth(), self.start
        dx, dy = now["x"] - a["x"], now["y"] - a["y"]
        c, s = math.cos(a["theta_unwrapped"]), math.sin(a["theta_unwrapped"])
        return c * dx + s * dy, -s * dx + c * dy, now["theta_unwrapped"] - a["theta_unwrapped"]

    def measured_length(self, odometry_m: float) -> float:
        return math.hypot(*self._moved()[:2])

    def measured_end(self, square: str) -> tuple[float, float]:
        return self._moved()[:2]

    def measured_turn_deg(self, commanded_deg: float) -> float:
        return math.degrees(self._moved()[2])


TRUE_MPT = NOMINAL_MPT * 1.03
TRUE_AXLE = NOMINAL_AXLE + 0.005


@pytest.mark.hil
@pytest.mark.parametrize("emulator", [["--m-per-tick", repr(TRUE_MPT), "--axle-m",
                                       repr(TRUE_AXLE), "--swap-encoders", "--max-accel", "3",
                                       "--gyro-bias", "0.01"]], indirect=True)
def test_guided_runs_recover_scale_axle_and_swap_on_the_emulator(emulator, tmp_path):
    from calibration.calibration_file import write_calibration

    loaded = load_config(None, [f"base.port={emulator.link}"])
    link = SparkBaseLink(loaded.config.base, loaded.calibration.odometry)
    link.open()
    fast = RunConfig(v_max=0.45, omega_max=3.0, accel=2.0, alpha=12.0, still_for_s=0.2)
    plan = OdometryPlan(length_m=0.6, turns=1, squares=1, side_m=0.25, still_s=0.5)
    try:
        result = calibrate_odometry(BaseRunner(link, loaded.calibration.odometry, fast),
                                    TruthOperator(emulator), loaded.calibration.odometry, plan)
    finally:
        link.close()
    odo = result.calibration
    assert odo.m_per_tick == pytest.approx(TRUE_MPT, rel=0.005)
    assert odo.axle_length_m == pytest.approx(TRUE_AXLE, abs=0.001)
    assert result.axle_turns_m == pytest.approx(TRUE_AXLE, abs=0.001)  # gyro bias cancelled
    assert odo.left_encoder_offset == 10 and result.summary()["encoders_swapped"]
    assert result.mapping.imu_agrees and result.umbmark is not None
    path = tmp_path / "cal.yaml"
    path.write_text(render_calibration(loaded.calibration), encoding="utf-8")
    _, changes = write_calibration(path, loaded.calibration.__class__(
        loaded.calibration.camera, odo), loaded.calibration)
    written = load_calibration(path).odometry
    assert written.left_encoder_offset == 10
    assert written.m_per_tick == pytest.approx(TRUE_MPT, rel=0.005)
    assert any(c.startswith("odometry.left_encoder_offset: 14 -> 10") for c in changes)


@pytest.mark.hil
def test_run_cut_short_by_stale_feedback_leaves_the_file(emulator, tmp_path):
    path = tmp_path / "cal.yaml"
    path.write_text(render_calibration(), encoding="utf-8")
    before = path.read_text()
    proc = subprocess.Popen(
        [sys.executable, "-m", "runtime.cli.main", "calibrate", "odometry",
         "--set", f"base.port={emulator.link}", "--set", f"calibration_file={path}"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        proc.stdin.write("\n" * 5)  # "ready" to every placement prompt
        proc.stdin.flush()
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:  # the first motion: the mapping turn has begun
            if emulator.wait_for("command", timeout_s=15.0)["left"] != 0:
                break
        emulator.send("drop", frames=150)  # the base goes silent for 3 s mid-run
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, err
    assert "base feedback is stale" in err and "Traceback" not in err
    assert path.read_text() == before and not list(Path(tmp_path).glob("*.bak"))
