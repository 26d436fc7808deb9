"""`safemove eval --plots DIR`: each episode's true path in the world frame, drawn per scenario,
and the outcome rates; the JSON result stays as without pictures; a directory that cannot be
written or a missing matplotlib is one line and exit 2 before any episode runs."""

from __future__ import annotations

import json
import sys
from dataclasses import fields, replace

import numpy as np
import pytest
from rooms import write_room

import sim_stub.evaluate
from runtime.cli.main import main
from sim_stub.evaluate import EpisodeResult, EvalSettings, run_episode
from sim_stub.scenario import load_scenario
from sim_stub.world import World

pytestmark = pytest.mark.sim  # lock-stepped episodes (see tests/conftest.py)

SETTINGS = EvalSettings("dwa", None, ("loop.stats_interval_s=0",), None, 10.0, False)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def room(tmp_path):
    """A goal 0.85 m ahead of a start drawn in a 10 × 10 cm square (an episode of about 5 s of
    simulated time), a box turned 30°, a cylinder and a wall off the way."""
    return write_room(tmp_path, "plot_room", goal=(-0.6, 0.0), time_limit_s=8.0,
                      start=(-1.5, -1.4, -0.05, 0.05),
                      obstacles="\n  - {type: box, center: [1.0, 1.5], size: [0.8, 0.4],"
                                " yaw_deg: 30.0, height: 0.8}"
                                "\n  - {type: cylinder, center: [1.5, -1.5], radius: 0.3,"
                                " height: 1.0}"
                                "\n  - {type: wall, start: [-2.5, 2.5], end: [0.0, 2.5],"
                                " thickness: 0.15, height: 2.0}")


def _no_episodes(*args, **kwargs):
    raise AssertionError("an episode ran")


def test_trajectory_starts_at_the_start_and_changes_nothing(room):
    plain = run_episode(room, 2, SETTINGS)
    kept = run_episode(room, 2, replace(SETTINGS, trajectories=True))
    assert plain.trajectory is None
    traj = kept.trajectory
    assert traj is not None and traj.xy.dtype == np.float32
    # the same episode with or without its trajectory (job_p99_ms is wall time)
    same = [f.name for f in fields(EpisodeResult) if f.name not in ("trajectory", "job_p99_ms")]
    assert [getattr(kept, n) for n in same] == [getattr(plain, n) for n in same]
    assert kept.status == "success"
    # the start, once per control cycle, and where the world judged the episode over
    assert traj.xy.shape == (kept.cycles + 2, 2)
    start = World(load_scenario(room), seed=2).robot  # the world draws the start from the seed
    assert np.hypot(traj.xy[0, 0] - start.x, traj.xy[0, 1] - start.y) < 0.003
    assert -1.5 <= start.x <= -1.4 and -0.05 <= start.y <= 0.05
    end = traj.xy[-1].astype(float)
    assert np.hypot(*(end - traj.goal)) <= load_scenario(room).goal_tolerance_m
    assert traj.goal == (-0.6, 0.0) and traj.people_xy.shape == (0, 2)


def test_eval_plots_writes_pngs_and_keeps_the_json_as_it_was(room, tmp_path, capsys):
    from matplotlib.image import imread

    out = tmp_path / "pictures" / "new"  # created, parents too
    code = main(["eval", "--scenarios", room, "--episodes", "2", "--fps", "10", "--no-noise",
                 "--set", "loop.stats_interval_s=0", "--json", "--plots", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err[-2000:]
    result = json.loads(captured.out.strip().splitlines()[-1])
    expected_keys = [f.name for f in fields(EpisodeResult) if f.name != "trajectory"]
    assert len(result["episodes"]) == 2
    for episode in result["episodes"]:
        assert list(episode) == expected_keys  # no trajectory in the JSON
    pictures = [out / "plot_room_trajectories.png", out / "outcomes.png"]
    assert sorted(out.iterdir()) == sorted(pictures)  # no probe file left behind
    for path in pictures:
        assert f"eval: wrote {path}" in captured.err
        assert path.read_bytes()[:8] == PNG_SIGNATURE
        image = imread(path)
        assert image.shape[0] > 100 and image.shape[1] > 100
        assert path.stat().st_size < 500_000


def test_unwritable_plots_dir_is_one_line_and_exit_2_before_any_episode(room, tmp_path,
                                                                       capsys, monkeypatch):
    monkeypatch.setattr(sim_stub.evaluate, "run_episode", _no_episodes)
    a_file = tmp_path / "a_file"
    a_file.write_text("not a directory\n")
    code = main(["eval", "--scenarios", room, "--episodes", "1", "--plots",
                 str(a_file / "plots")])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    (line,) = captured.err.strip().splitlines()
    assert "--plots" in line and str(a_file / "plots") in line


def test_missing_matplotlib_is_one_line_naming_the_extra(room, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sim_stub.evaluate, "run_episode", _no_episodes)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` fails
    code = main(["eval", "--scenarios", room, "--episodes", "1", "--plots",
                 str(tmp_path / "plots")])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    (line,) = captured.err.strip().splitlines()
    assert "matplotlib" in line and "pip install 'safemove-rl[plots]'" in line
    assert not (tmp_path / "plots").exists()
