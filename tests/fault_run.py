"""Shared by the fault-injection HIL tests: drive the simulated robot through a fault and read
what happened from the runtime's report and the base's ground truth.

Figures, all from the moment the fault began (host monotonic time, one clock for every process
on this machine): the loop's first DEGRADED transition, the base's first zero wheel command, the
first ground-truth standstill, and the distance the base travelled until then. A row per fault
goes into the table that `pytest -m faults` prints at the end (conftest.py)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sim_stub.emulator_process import EmulatorProcess

STILL_M_S = 0.005
SCENARIOS = Path(__file__).resolve().parent.parent / "sim_stub" / "scenarios"


def empty_room(directory: Path) -> Path:
    """paper_a's room with nobody in it: `drive` does not avoid people, and one who walks into
    the robot blinds the camera (DEGRADED, rightly), which is not what these tests are about."""
    scenario = directory / "paper_a_empty.yaml"
    scenario.write_text((SCENARIOS / "paper_a.yaml").read_text().replace("count: 8", "count: 0"))
    return scenario


@dataclass
class Sample:
    t: float
    v: float
    distance: float


@dataclass
class FaultFigures:
    degraded_s: float = math.nan
    zero_command_s: float = math.nan
    standstill_s: float = math.nan
    distance_m: float = math.nan

    def cells(self) -> list[str]:
        def f(x: float, unit: str) -> str:
            return "-" if math.isnan(x) else f"{x:.3f} {unit}"
        return [f(self.degraded_s, "s"), f(self.zero_command_s, "s"), f(self.standstill_s, "s"),
                f(self.distance_m, "m")]


def wait_moving(base: EmulatorProcess, v: float, timeout_s: float = 30.0) -> Sample:
    """Poll ground truth until the base moves at `v` or more."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = sample(base)
        if s.v >= v:
            return s
        time.sleep(0.05)
    raise AssertionError(f"the base never reached {v} m/s within {timeout_s} s")


def sample(base: EmulatorProcess) -> Sample:
    truth = base.truth()
    return Sample(time.monotonic(), float(truth["v"]), float(truth["distance"]))


def watch(base: EmulatorProcess, seconds: float) -> list[Sample]:
    """Ground truth at ~20 Hz for `seconds`."""
    out: list[Sample] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out.append(sample(base))
        time.sleep(0.05)
    return out


def figures(t0: float, start: Sample, samples: list[Sample], report: dict[str, Any],
            history: list[dict[str, Any]]) -> FaultFigures:
    """The fault's figures from t0 (when it began) to the last sample; NaN where it did not
    happen."""
    fig = FaultFigures()
    degraded = [tr["t"] for tr in report["transitions"] if tr["to"] == "DEGRADED" and tr["t"] >= t0]
    if degraded:
        fig.degraded_s = degraded[0] - t0
    end = samples[-1].t if samples else t0  # the fault's window, not the run's own end
    zero = [e["t"] for e in history if e.get("event") == "command" and t0 <= e["t"] <= end
            and e["left"] == 0 and e["right"] == 0]
    if zero:
        fig.zero_command_s = zero[0] - t0
    still = [s for s in samples if s.t >= t0 and abs(s.v) < STILL_M_S]
    if still:
        fig.standstill_s = still[0].t - t0
        fig.distance_m = still[0].distance - start.distance
    return fig
