"""The calibration file writer (validated, atomic, backup, diff) and `safemove calibrate check`
(floor height/tilt, points below the floor, encoder mapping) against rendered truth and the
emulator."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_calibration_camera import clutter, write_recording

from calibration.calibration_file import write_calibration
from calibration.check import check_camera
from drivers.depth_source import D435_848x480
from runtime.cli.main import main
from runtime.config.calibration import Calibration, CameraMount, OdometryCalibration
from runtime.config.settings import load_calibration, render_calibration
from runtime.errors import ConfigError
from sim_stub.depth_render import DepthRenderer

TRUTH = CameraMount((0.09, 0.02, 0.45), (1.0, 8.0, 0.0))


@pytest.fixture(scope="module")
def depths() -> list[np.ndarray]:
    renderer = DepthRenderer(D435_848x480, TRUTH, seed=4)
    scene = clutter(np.random.default_rng(4))
    return [renderer.render((0.0, 0.0, 0.0), scene, noise=True) for _ in range(5)]


def test_write_keeps_a_backup_and_lists_the_changes(tmp_path):
    path = tmp_path / "cal.yaml"
    old = Calibration()
    path.write_text(render_calibration(old), encoding="utf-8")
    new = Calibration(TRUTH, OdometryCalibration(0.000297516123, 0.27112345, 10))
    backup, changes = write_calibration(path, new, old)
    assert backup is not None and backup.read_text() == render_calibration(old)
    loaded = load_calibration(path)
    assert loaded.odometry == OdometryCalibration(0.000297516, 0.2711, 10)  # rounded
    assert path.read_text() == render_calibration(loaded)  # the documented rendering
    assert changes == [
        "camera.translation_m: [0.094, 0.018, 0.643] -> [0.09, 0.02, 0.45]",
        "camera.rpy_deg: [0.0, 0.0, 0.0] -> [1.0, 8.0, 0.0]",
        "odometry.m_per_tick: 0.00028885 -> 0.000297516",
        "odometry.axle_length_m: 0.266 -> 0.2711",
        "odometry.left_encoder_offset: 14 -> 10",
    ]
    assert not list(tmp_path.glob(".cal.yaml.*.tmp"))


def test_an_estimate_out_of_range_is_refused_and_the_file_untouched(tmp_path):
    path = tmp_path / "cal.yaml"
    path.write_text(render_calibration(), encoding="utf-8")
    bad = Calibration(CameraMount((0.1, 0.0, 2.5), (0.0, 0.0, 0.0)))
    with pytest.raises(ConfigError, match=r"key 'camera.translation_m': must be at most 2.0"):
        write_calibration(path, bad, Calibration())
    assert path.read_text() == render_calibration() and not list(tmp_path.glob("*.bak"))


def test_check_passes_the_true_calibration_and_fails_a_wrong_one(depths):
    good = {i.name: i for i in check_camera(depths, D435_848x480, TRUTH)}
    assert all(i.ok for i in good.values()), [i.line() for i in good.values()]
    assert set(good) == {"floor_height", "floor_tilt", "below_floor"}
    pitched = CameraMount(TRUTH.translation_m, (1.0, 11.0, 0.0))  # 3 deg too much: the floor
    # then rises ahead of the robot, so the real floor lies under the calibrated one
    bad = {i.name: i for i in check_camera(depths, D435_848x480, pitched)}
    assert bad["floor_tilt"].ok is False and bad["below_floor"].ok is False
    assert bad["floor_height"].ok is True  # the height is right; the tilt is not


def test_check_command_on_a_recording(tmp_path, depths, capsys):
    rec = tmp_path / "check.db3"
    write_recording(rec, depths, None)
    cal = tmp_path / "cal.yaml"
    cal.write_text(render_calibration(Calibration(TRUTH)), encoding="utf-8")
    args = ["calibrate", "check", "--recording", str(rec), "--frames", "5", "--no-motion",
            "--set", f"calibration_file={cal}"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert out.count("PASS") == 3 and json.loads(out.splitlines()[-1])["ok"] is True
    cal.write_text(render_calibration(Calibration(CameraMount((0.09, 0.02, 0.50),
                                                              (1.0, 8.0, 0.0)))))
    assert main(args) == 1
    report = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert report["failed"] == ["floor_height"]  # 5 cm too high: the floor lies below z = 0


@pytest.mark.hil
@pytest.mark.parametrize("emulator", [["--swap-encoders"]], indirect=True)
def test_check_finds_swapped_encoders_on_the_emulator(emulator, safemove):
    proc = safemove(["calibrate", "check", "--set", f"base.port={emulator.link}"])
    assert proc.wait(timeout=20) == 1, proc.stderr
    report = proc.report()
    assert report["failed"] == ["encoder_mapping"]
    assert "set odometry.left_encoder_offset to 10" in report["items"][0]["detail"]
