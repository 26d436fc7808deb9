"""The training rewards (sim_stub.train.reward): the project's, unchanged, and the paper's
R_g + R_b + R_yaw, term by term, with their signs; the corridor's yaw error."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sim_stub.train.reward import RewardConfig, corridor_yaw_error, step_reward

PROJECT = RewardConfig()
PAPER = RewardConfig(kind="paper")


def _r(cfg: RewardConfig, progress_m: float = 0.0, dt_s: float = 0.1, outcome: str = "running",
       shield_changed: bool = False, yaw_error_rad: float = 0.0) -> float:
    return step_reward(cfg, progress_m=progress_m, dt_s=dt_s, outcome=outcome,
                       shield_changed=shield_changed, yaw_error_rad=yaw_error_rad)


@pytest.mark.parametrize("outcome", ["running", "success", "collision", "timeout"])
@pytest.mark.parametrize("changed", [False, True])
def test_project_reward_is_the_former_formula(outcome, changed):
    cfg = RewardConfig(progress_per_m=7.0, time_per_s=0.3, success=11.0, collision=13.0,
                       shield_change=0.2)
    progress, dt = 0.04, 0.1
    expected = 7.0 * progress - 0.3 * dt - (0.2 if changed else 0.0)
    expected += {"success": 11.0, "collision": -13.0}.get(outcome, 0.0)
    got = _r(cfg, progress, dt, outcome, changed, yaw_error_rad=2.0)  # the yaw does not count
    assert got == pytest.approx(expected, abs=1e-12)


def test_project_reward_signs():
    assert _r(PROJECT, progress_m=0.05) > 0 > _r(PROJECT, progress_m=-0.05)
    assert _r(PROJECT) == pytest.approx(-PROJECT.time_per_s * 0.1)  # standing still costs
    assert _r(PROJECT, shield_changed=True) < _r(PROJECT)
    assert _r(PROJECT, outcome="success") > PROJECT.success - 0.1
    assert _r(PROJECT, outcome="collision") < -PROJECT.collision


def test_paper_goal_term_approach_then_bonus():
    cfg = replace(PAPER, paper_approach_per_m=4.0, paper_goal=20.0)
    assert _r(cfg, progress_m=0.05) == pytest.approx(0.2)
    assert _r(cfg, progress_m=-0.05) == pytest.approx(-0.2)  # moving away is penalised
    assert _r(cfg, progress_m=0.05, outcome="success") == 20.0  # the bonus replaces approach
    assert _r(cfg, progress_m=0.05, dt_s=5.0, shield_changed=True) == pytest.approx(0.2)


def test_paper_collision_term():
    cfg = replace(PAPER, paper_collision=15.0, paper_approach_per_m=4.0)
    assert _r(cfg, progress_m=0.05, outcome="collision") == pytest.approx(0.2 - 15.0)
    assert _r(cfg, outcome="timeout") == 0.0  # other ends: no terminal term


@pytest.mark.parametrize("yaw", [0.3, -0.3, math.pi])
def test_paper_yaw_term_penalises_either_side(yaw):
    cfg = replace(PAPER, paper_yaw_per_rad=0.5)
    assert _r(cfg, yaw_error_rad=yaw) == pytest.approx(-0.5 * abs(yaw))
    assert _r(cfg, yaw_error_rad=0.0) == 0.0


def test_paper_terms_add_up():
    cfg = RewardConfig(kind="paper", paper_goal=10.0, paper_approach_per_m=10.0,
                       paper_collision=10.0, paper_yaw_per_rad=0.1)
    assert _r(cfg, 0.03, outcome="collision", yaw_error_rad=-0.4) == pytest.approx(
        0.3 - 10.0 - 0.04)
    assert _r(cfg, 0.03, outcome="success", yaw_error_rad=0.4) == pytest.approx(10.0 - 0.04)


def test_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="kind must be one of project, paper"):
        RewardConfig(kind="mine")


def _arc(v: float, omega: float, steps: int = 30, dt: float = 0.1) -> np.ndarray:
    """A DWA best path: the constant (v, ω) arc from the robot, (steps, 3) in base_link."""
    t = np.arange(1, steps + 1) * dt
    th = omega * t
    if omega == 0.0:
        return np.stack([v * t, 0.0 * t, th], axis=-1)
    return np.stack([v * np.sin(th) / omega, v * (1 - np.cos(th)) / omega, th], axis=-1)


def test_corridor_yaw_error_is_the_bearing_of_the_paths_end():
    assert corridor_yaw_error(_arc(0.5, 0.0)) == 0.0
    # an arc's chord bearing is half its heading change: ω·T/2, left positive
    assert corridor_yaw_error(_arc(0.5, 0.4)) == pytest.approx(0.4 * 3.0 / 2)
    assert corridor_yaw_error(_arc(0.5, -0.4)) == pytest.approx(-0.4 * 3.0 / 2)
    assert abs(corridor_yaw_error(_arc(-0.1, 0.0))) == pytest.approx(math.pi)  # behind


def test_corridor_yaw_error_of_a_path_that_stays_at_the_robot_is_zero():
    path = _arc(0.0, 1.0) * np.array([-0.0, -0.0, 1.0])  # signed zeros: atan2 would read ±π
    assert corridor_yaw_error(path) == 0.0
