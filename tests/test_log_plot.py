"""`safemove plot LOG.mcap -o OUT.png` (sim_stub.log_plot): a recording of lock-stepped DWA
cycles in paper_a, written by the flight recorder, drawn into a PNG whose summary counts the
recorded cycles; a file that is missing, not an MCAP file or not a SafeMove recording, and an
output that cannot be written, are one line and exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from flight_records import episode_records, wait_written
from mcap.writer import Writer

from runtime.cli.main import main
from runtime.config.settings import RecorderConfig, load_config
from runtime.process.recorder import Recorder

pytest.importorskip("matplotlib")

pytestmark = [pytest.mark.sim, pytest.mark.timeout(180)]

CYCLES = 100


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, int]:
    """One MCAP file of `CYCLES` lock-stepped cycles, and how many cycles it holds."""
    directory = tmp_path_factory.mktemp("rec")
    loaded = load_config(None, [])
    rec = Recorder(directory, RecorderConfig(), loaded.calibration.camera,
                   loaded.config.perception.decimation, {"job": "dwa"})
    rec.start()
    for i, r in enumerate(episode_records(CYCLES)):
        rec.offer(r)
        wait_written(rec, i + 1)  # as at 20 Hz: the writer keeps up between cycles
    rec.stop()
    assert rec.stopped_reason is None and rec.counts["dropped"] == 0
    [path] = directory.glob("safemove-*.mcap")
    return path, rec.counts["cycles"]


def test_a_recording_is_drawn_with_its_summary(recording, tmp_path, capsys):
    from matplotlib.image import imread

    log, cycles = recording
    png = tmp_path / "run.png"
    assert main(["plot", str(log), "-o", str(png), "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1  # --json: the summary alone
    result = json.loads(out[-1])
    assert result["cycles"] == cycles == CYCLES
    assert result["job"] == "dwa" and result["plot"] == str(png)
    assert result["duration_s"] == pytest.approx((CYCLES - 1) / 20.0, abs=0.1)
    assert result["distance_m"] > 0.0 and result["obstacle_points"] > 0
    assert len(result["goals"]) == 1
    assert all(k != "passed" and n > 0 for k, n in result["interventions"].items())
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(png)
    assert image.shape[0] > 300 and image.shape[1] > 300
    assert np.ptp(image[..., :3]) > 0.5  # something was drawn


def test_figures_then_the_json_line(recording, tmp_path, capsys):
    log, _cycles = recording
    assert main(["plot", str(log), "-o", str(tmp_path / "run.png")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert any(line.startswith("cycles: ") for line in lines[:-1])
    assert json.loads(lines[-1])["cycles"] == CYCLES


def _error(argv: list[str], capsys) -> str:
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("safemove: error: "), captured.err
    return err[0]


def test_a_missing_file_is_one_line(tmp_path, capsys):
    line = _error(["plot", str(tmp_path / "nope.mcap"), "-o", str(tmp_path / "a.png")], capsys)
    assert "nope.mcap" in line and "cannot open" in line
    assert not (tmp_path / "a.png").exists()


def test_a_file_that_is_not_mcap_is_one_line(tmp_path, capsys):
    bad = tmp_path / "notes.mcap"
    bad.write_text("these are not the bytes of an MCAP file\n" * 20)
    line = _error(["plot", str(bad), "-o", str(tmp_path / "a.png")], capsys)
    assert "not a readable MCAP file" in line


def test_an_mcap_file_without_safemove_metadata_is_one_line(tmp_path, capsys):
    other = tmp_path / "other.mcap"
    with other.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="test")
        writer.finish()
    line = _error(["plot", str(other), "-o", str(tmp_path / "a.png")], capsys)
    assert "not a SafeMove flight recording" in line


def test_an_output_that_cannot_be_written_is_one_line(recording, tmp_path, capsys):
    log, _cycles = recording
    line = _error(["plot", str(log), "-o", str(tmp_path / "missing" / "run.png")], capsys)
    assert "cannot write" in line
    line = _error(["plot", str(log), "-o", str(tmp_path)], capsys)
    assert "is a directory" in line


def test_without_matplotlib_the_extra_is_named(recording, tmp_path, capsys, monkeypatch):
    import sys

    log, _cycles = recording
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib: ImportError
    line = _error(["plot", str(log), "-o", str(tmp_path / "run.png")], capsys)
    assert "pip install 'safemove-rl[plots]'" in line
