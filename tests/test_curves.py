"""`safemove curves [LABEL=]DIR ... -o OUT.png` (sim_stub.train.curves): training runs' monitors
drawn in one figure, with each run's last window in figures; a monitor that is missing or does
not parse, a bad summary, a label twice and an output that cannot be written are one line naming
the file (and line) and exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from runtime.cli.main import main

pytest.importorskip("matplotlib")

HEADER = '#{"t_start": 1796575745.1, "env_id": "None"}\n'


def _run(folder: Path, episodes: list[tuple[float, int, str]], demo_steps: int | None = None,
         finished: bool = True) -> Path:
    """A run directory: its monitor (return, length, outcome per episode) and, when finished,
    its summary (with the demonstrations' steps of a TD3+BC run)."""
    folder.mkdir()
    rows = "".join(f"{r},{n},{i * 0.5},{o}\n" for i, (r, n, o) in enumerate(episodes))
    (folder / "monitor.csv").write_text(HEADER + "r,l,t,outcome\n" + rows, encoding="utf-8")
    if finished:
        summary = {"recipe": "td3"} if demo_steps is None else {"recipe": "bc-td3",
                                                                "demo_steps": demo_steps}
        (folder / "summary.json").write_text(json.dumps(summary), encoding="utf-8")
    return folder


def _curves(capsys, *argv: str) -> tuple[int, dict, str]:
    code = main(["curves", *argv, "--json"])
    out, err = capsys.readouterr()
    return code, (json.loads(out.strip().splitlines()[-1]) if code == 0 else {}), err


def test_runs_are_drawn_with_their_last_window(tmp_path, capsys):
    a = _run(tmp_path / "a", [(1.0, 10, "collision")] * 2 + [(5.0, 20, "success")] * 3,
             demo_steps=30)
    b = _run(tmp_path / "b", [(2.0, 5, "timeout"), (4.0, 5, "success")], finished=False)
    png = tmp_path / "curves.png"
    code, result, err = _curves(capsys, str(a), f"seed 1={b}", "-o", str(png), "--window", "2")
    assert code == 0 and err == ""
    assert png.stat().st_size > 0 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert result["output"] == str(png) and result["window"] == 2
    assert result["runs"]["a"] == {"episodes": 5, "env_steps": 80, "success_pct_last": 100.0,
                                   "return_last": 5.0, "finished": True, "td3_from": 30}
    assert result["runs"]["seed 1"] == {"episodes": 2, "env_steps": 10, "success_pct_last": 50.0,
                                        "return_last": 3.0, "finished": False, "td3_from": None}


def test_a_run_shorter_than_the_window_has_no_last_window(tmp_path, capsys):
    a = _run(tmp_path / "a", [(1.0, 10, "success")])
    code, result, _ = _curves(capsys, str(a), "-o", str(tmp_path / "c.png"))
    assert code == 0
    assert result["runs"]["a"]["success_pct_last"] is None
    assert result["runs"]["a"]["return_last"] is None


def test_a_last_line_still_being_written_is_left_for_the_next_read(tmp_path, capsys):
    run = _run(tmp_path / "run", [(1.0, 10, "success"), (2.0, 20, "collision")], finished=False)
    with (run / "monitor.csv").open("a", encoding="utf-8") as f:
        f.write("3.5,3")  # a run still training, caught mid-line
    code, result, _ = _curves(capsys, str(run), "-o", str(tmp_path / "c.png"), "--window", "2")
    assert code == 0
    assert result["runs"]["run"]["episodes"] == 2 and result["runs"]["run"]["env_steps"] == 30


@pytest.mark.parametrize(("monitor", "expected"), [
    ("r,l,t,outcome\n1,10,0,success\n", "line 1: not a training monitor"),
    (HEADER + "r,t,outcome\n1,0,success\n", "line 2: no column l"),
    (HEADER + "r,l,t,outcome\n1,10,0,success\n1,0,0.5,success\n", "line 4: not an episode"),
    (HEADER + "r,l,t,outcome\nnan,10,0,success\n", "line 3: not an episode"),
    (HEADER + "r,l,t,outcome\n1,ten,0,success\n", "line 3: not an episode"),
    (HEADER + "r,l,t,outcome\n1,10,0,\n", "line 3: not an episode"),
    (HEADER + "r,l,t,outcome\n1,10\n", "line 3: not an episode"),
])
def test_a_monitor_that_does_not_parse_is_one_line_naming_file_and_line(
        tmp_path, capsys, monitor, expected):
    run = tmp_path / "run"
    run.mkdir()
    (run / "monitor.csv").write_text(monitor, encoding="utf-8")
    png = tmp_path / "c.png"
    code, _, err = _curves(capsys, str(run), "-o", str(png))
    assert code == 2 and not png.exists()
    [line] = err.strip().splitlines()
    assert f"{run / 'monitor.csv'}: {expected}" in line


def test_a_folder_without_a_monitor_or_with_a_bad_summary_is_one_line(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = _curves(capsys, str(empty), "-o", str(tmp_path / "c.png"))
    assert code == 2 and f"{empty / 'monitor.csv'}: file not found" in err
    code, _, err = _curves(capsys, str(tmp_path / "nothere"), "-o", str(tmp_path / "c.png"))
    assert code == 2 and "nothere: not a directory" in err
    run = _run(tmp_path / "run", [(1.0, 10, "success")], finished=False)
    (run / "summary.json").write_text("{", encoding="utf-8")
    code, _, err = _curves(capsys, str(run), "-o", str(tmp_path / "c.png"))
    assert code == 2 and f"{run / 'summary.json'}: not a readable JSON file" in err
    assert len(err.strip().splitlines()) == 1


def test_a_label_twice_and_an_unwritable_output_are_one_line(tmp_path, capsys):
    a = _run(tmp_path / "a", [(1.0, 10, "success")])
    code, _, err = _curves(capsys, f"x={a}", f"x={a}", "-o", str(tmp_path / "c.png"))
    assert code == 2 and "a label appears twice" in err
    code, _, err = _curves(capsys, str(a), "-o", str(tmp_path / "no" / "c.png"))
    assert code == 2 and "is not a directory" in err
    code, _, err = _curves(capsys, str(a), "-o", str(tmp_path))
    assert code == 2 and "is a directory, not a file" in err


def test_runs_with_different_demonstrations_get_no_takeover_line(tmp_path, capsys, monkeypatch):
    """The dashed "TD3 from here" line is drawn only where every run's TD3 started at the same
    step (a plain TD3 run has none)."""
    from sim_stub.train import curves

    drawn = {}
    monkeypatch.setattr(curves, "plot_curves",
                        lambda runs, out, window, td3_from=None: drawn.update(td3_from=td3_from))
    a = _run(tmp_path / "a", [(1.0, 10, "success")], demo_steps=30)
    b = _run(tmp_path / "b", [(1.0, 10, "success")], demo_steps=30)
    c = _run(tmp_path / "c", [(1.0, 10, "success")])
    assert _curves(capsys, str(a), str(b), "-o", str(tmp_path / "x.png"))[0] == 0
    assert drawn["td3_from"] == 30
    assert _curves(capsys, str(a), str(c), "-o", str(tmp_path / "x.png"))[0] == 0
    assert drawn["td3_from"] is None
