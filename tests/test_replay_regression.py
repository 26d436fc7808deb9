"""The regression test for changes to any stage: flight recordings made from the simulator,
shipped in tests/data/flight/, replayed through today's pipeline must reproduce every command
and every shield decision bit for bit.

- `eval_paper_b_seed2_{dwa,safemove}.mcap`: lock-stepped episodes (`safemove eval --planner
  dwa|safemove --scenarios paper_b --episodes 1 --seed 2 --no-noise --record DIR --set
  recorder.full_depth_every=1000`); the safemove one with the shipped policy;
- `demo_paper_a_dwa_realtime.mcap`: `safemove demo --planner dwa --record DIR`, the real-time
  runtime against the simulated robot, whose DWA and shield budgets ran on the clock.

When this test fails, a change altered what the robot decides (`safemove replay LOG` shows the
first cycle that differs and both commands). If the change is meant to, record the files again
with the commands above (the replay of a fresh recording by the same code is exact) and say so
in the commit.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from runtime.process.replay import replay

LOGS = sorted((Path(__file__).parent / "data" / "flight").glob("*.mcap"))


def test_the_shipped_logs_are_there():
    assert len(LOGS) == 3


@pytest.mark.parametrize("log", LOGS, ids=[p.stem for p in LOGS])
def test_a_shipped_recording_replays_bit_for_bit(log):
    result = replay(log)
    assert result["cycles"] > 100
    assert result["differing_commands"] == 0, result
    assert result["differing_shield_decisions"] == 0, result
