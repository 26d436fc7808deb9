"""The long-run and start-up tools: their arithmetic, and one line when the runtime refuses."""

from __future__ import annotations

import pytest

from runtime.cli.main import main
from sim_stub.soak import last_line, slope_mb_per_h


def test_rss_slope_is_fitted_after_the_warm_up_only():
    warm = [(t, 100.0 + 0.01 * t) for t in range(0, 300, 30)]  # 36 MB/h while warming up
    flat = [(t, 110.0 + (0.5 if t % 60 else 0.0)) for t in range(300, 3600, 30)]
    assert slope_mb_per_h(warm + flat, warmup_s=300) == pytest.approx(0.0, abs=0.1)
    assert slope_mb_per_h(warm + flat, warmup_s=0) > 1.0
    assert slope_mb_per_h(warm[:2], warmup_s=0) is None


def test_last_line_is_what_the_runtime_said_without_its_prefix():
    err = "INFO x\nsafemove: error: /m.onnx: model file not found\n"
    assert last_line(err) == "/m.onnx: model file not found"
    assert last_line("") == "no output"


@pytest.mark.hil
def test_bench_startup_with_a_missing_model_is_one_line(capsys):
    assert main(["bench", "startup", "--runs", "1", "--model", "/nonexistent/actor.onnx"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == ("safemove: error: bench startup: the runtime exited before READY:"
                       " /nonexistent/actor.onnx: model file not found")


def test_soak_refuses_an_actor_for_the_dwa_planner_before_anything_starts(capsys):
    assert main(["soak", "paper_b", "--planner", "dwa", "--variant", "drl"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["safemove: error: soak: --variant is for --planner safemove, not dwa"]


def test_bench_startup_refuses_an_actor_for_the_dwa_planner(capsys):
    assert main(["bench", "startup", "--planner", "dwa", "--model", "actor.onnx"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["safemove: error: bench startup: --model is for --planner safemove, not dwa"]
