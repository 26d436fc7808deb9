"""Replay (runtime.process.replay) of flight recordings made by the real runtime driving the
simulated robot in real time: the same code reproduces every command bit for bit (the anytime
stages' budgets are replayed as they were spent), a changed stage is found, and a recording
whose command was altered at one cycle is reported at exactly that cycle."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from runtime.cli.main import main
from runtime.process.replay import replay

pytestmark = [pytest.mark.hil, pytest.mark.timeout(400)]


@pytest.fixture(scope="module", params=["dwa", "safemove"])
def recording(request, tmp_path_factory) -> Path:
    """A `safemove demo --record` run (the shipped policy for safemove), one file."""
    out_dir = tmp_path_factory.mktemp(f"rec-{request.param}")
    run = subprocess.run(
        [sys.executable, "-m", "runtime.cli.main", "demo", "--planner", request.param,
         "--record", str(out_dir),
         # a replay needs every cycle: a loaded machine must not drop one (a full queue's
         # drops are tests/test_recorder.py's)
         "--set", "recorder.queue_cycles=10000"],
        check=False, capture_output=True, text=True, timeout=360,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert run.returncode in (0, 1), run.stderr[-3000:]  # 1: the world said not success
    [path] = out_dir.glob("safemove-*.mcap")
    return path


def test_the_same_code_reproduces_every_command(recording):
    result = replay(recording)
    assert result["cycles"] > 200
    assert result["differing_commands"] == 0, result
    assert result["differing_shield_decisions"] == 0, result


def test_a_changed_dwa_weight_is_found(recording):
    result = replay(recording, overrides=["dwa.weight_heading=3.0"])
    assert result["differing_commands"] > 0, result
    first = result["first_divergence"]
    # up to the first divergence the decisions were the recorded ones
    assert replay(recording, limit=first["cycle"], overrides=["dwa.weight_heading=3.0"])[
        "differing_commands"] == 0


def altered(path: Path, out: Path, cycle: int) -> float:
    """A copy of the recording whose recorded command at `cycle` is off by 1 mm/s."""
    with path.open("rb") as f, out.open("wb") as g:
        reader = make_reader(f)
        summary = reader.get_summary()
        writer = Writer(g)
        writer.start(profile="", library="test")
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data)
                      for sid, s in summary.schemas.items()}
        channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding,
                                                    schema_ids[c.schema_id])
                       for cid, c in summary.channels.items()}
        for m in reader.iter_metadata():
            writer.add_metadata(m.name, m.metadata)
        n = 0
        changed = 0.0
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            data = message.data
            if channel.topic == "/cycle":
                if n == cycle:
                    c = json.loads(data)
                    c["command"]["v"] += 0.001
                    changed = c["command"]["v"]
                    data = json.dumps(c).encode()
                n += 1
            writer.add_message(channel_ids[message.channel_id], message.log_time, data,
                               message.publish_time)
        writer.finish()
    return changed


def test_a_recording_altered_at_one_cycle_is_reported_at_that_cycle(recording, tmp_path):
    changed = altered(recording, tmp_path / "altered.mcap", 150)
    result = replay(tmp_path / "altered.mcap")
    assert result["differing_commands"] == 1
    assert result["first_divergence"]["cycle"] == 150
    assert result["first_divergence"]["recorded"]["v"] == changed


def test_the_command_line(recording, tmp_path, capsys):
    assert main(["replay", str(recording), "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["differing_commands"] == 0
    assert main(["replay", str(recording), "--json", "--set", "dwa.weight_heading=3.0"]) == 1
    capsys.readouterr()
    bad = tmp_path / "not.mcap"
    bad.write_bytes(b"hello")
    assert main(["replay", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a readable MCAP file" in err[0], err


def test_a_recording_cut_short_replays_what_is_whole(recording, tmp_path):
    """A full disk or a power cut leaves a file without its index and footer."""
    cut = tmp_path / "cut.mcap"
    data = recording.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    whole, half = replay(recording), replay(cut)
    assert 0 < half["cycles"] < whole["cycles"]
    assert half["differing_commands"] == 0
