"""DWA planner: identical choices with the per-sample reference, spatiotemporal checks, budget."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.config.settings import LimitsConfig
from runtime.planning.dwa import DWAConfig, plan, plan_coarse
from runtime.planning.dwa.window import prepare, rollout
from sim_stub.dwa_reference import plan_reference, random_world

LIM = LimitsConfig()
CFG = DWAConfig()
FOX = replace(CFG, weight_evasion=0.0)  # Fox et al.'s DWA: no evasion term
STEPS = 30
TIMES = (np.arange(STEPS) + 1) * 0.1


@pytest.mark.parametrize("cfg", [FOX, CFG], ids=["fox", "evasion"])
def test_vectorised_matches_reference_on_random_worlds(cfg):
    rng = np.random.default_rng(1)
    for _ in range(20):
        w = random_world(rng, STEPS, 100, 5, n_blobs=10)  # 10 static obstacles + 5 tracks
        a = plan_coarse(cfg, LIM, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"],
                        w["obs_radius"])
        b = plan_reference(cfg, LIM, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"],
                           w["obs_radius"])
        assert len(b.samples) == 400
        np.testing.assert_array_equal(a.samples[:400], b.samples)
        np.testing.assert_array_equal(a.admissible[:400], b.admissible)
        for k in ("heading", "clearance", "velocity", "density", "evasion"):  # float32 vs float64
            np.testing.assert_allclose(getattr(a, k)[:400], b.terms[k], atol=2e-5, rtol=0)
            np.testing.assert_allclose(a.raw[k][:400], b.raw[k], atol=1e-4, rtol=1e-5)
        if b.best_index >= 0:
            assert a.best_index == b.best_index
        else:
            assert not a.admissible_best and a.best == pytest.approx(b.best)


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_grid_clearance_is_a_tight_lower_bound(fx, fy):
    """Up to clearance_cap + r_eff (all the planner uses), the distance-transform grid's
    clearance is ≤ exact and within 2·cell·√2 of it, anywhere a rollout can be (fx, fy: the
    position as a fraction of the union of the step boxes)."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(-2.0, 2.0, (50, 2))
    prep = prepare(CFG, LIM, 0.3, 0.0, pts)
    cell = CFG.grid_cell_m
    lo, hi = prep.step_lo.min(0), prep.step_hi.max(0)
    px, py = lo + np.array([fx, fy]) * (hi - lo)
    ix, iy = prep.cell_index(px, py, cell)
    reach = CFG.clearance_cap_m + prep.r_eff
    grid_d = min(float(prep.dist_grid[ix, iy]), reach)
    exact = min(np.hypot(*(pts - [px, py]).T).min(), reach)
    assert grid_d <= exact + 1e-6  # float32 grid
    assert grid_d >= exact - 2 * cell * math.sqrt(2) - 1e-6


def test_grid_covers_every_window_rollout_within_the_clearance_cap():
    """Any velocity in the window, at any step, lies in its step box, and the grid reaches
    clearance_cap + r_eff beyond every box (so no point that matters is left off the grid)."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        v0, w0 = rng.uniform(0.0, 0.5), rng.uniform(-1.0, 1.0)
        prep = prepare(CFG, LIM, v0, w0, np.zeros((0, 2)))
        v_lo, v_hi, w_lo, w_hi = prep.window
        s = np.stack([rng.uniform(v_lo, v_hi, 500), rng.uniform(w_lo, w_hi, 500)], -1)
        x, y, _ = rollout(s, prep.times)
        p = np.stack([x, y], -1)  # (steps, K, 2)
        assert (p >= prep.step_lo[:, None] - 1e-9).all() and (p <= prep.step_hi[:, None] + 1e-9).all()
        reach = CFG.clearance_cap_m + prep.r_eff
        assert (prep.step_lo.min(0) - reach >= prep.origin).all()
        far = np.array(prep.origin) + np.array(prep.shape) * CFG.grid_cell_m
        assert (prep.step_hi.max(0) + reach <= far).all()


def _crossing(y0: float, vy: float, x_cross: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """One person walking along +y through x = x_cross; at time t at (x_cross, y0 + vy t)."""
    pos = np.stack([np.full(STEPS, x_cross), y0 + vy * TIMES], -1)[None]
    return pos, np.full((1, STEPS), 0.25)


def _straight_index(res) -> int:
    return int(np.argmin(np.abs(res.samples[:400, 1]) + 10 * np.abs(res.samples[:400, 0] - 0.3)))


def test_crossing_obstacle_penalised_by_time_not_by_current_position():
    cfg = replace(CFG, weight_heading=1.0, weight_velocity=0.0, weight_density=0.0)
    goal = np.array([3.0, 0.0])
    # going straight at 0.3 m/s reaches x = 0.6 at t = 2 s; the person is 2 m to the side now
    # and on the path at t = 2 s
    pos, rad = _crossing(-2.0, 1.0)
    live = plan_coarse(cfg, LIM, 0.3, 0.0, goal, np.zeros((0, 2)), pos, rad)
    frozen = plan_coarse(cfg, LIM, 0.3, 0.0, goal, np.zeros((0, 2)),
                         np.repeat(pos[:, :1], STEPS, 1), rad)
    i = _straight_index(live)
    assert live.raw["clearance"][i] == 0.0  # collides at t ≈ 2 s
    assert frozen.raw["clearance"][i] == CFG.clearance_cap_m  # a frozen check sees nothing
    # the person has already crossed before the robot gets there: no penalty
    gone_pos, gone_rad = _crossing(-0.2, 2.0)  # on the path at t = 0.1 s, 3.8 m away by t = 2
    gone = plan_coarse(cfg, LIM, 0.3, 0.0, goal, np.zeros((0, 2)), gone_pos, gone_rad)
    assert gone.raw["clearance"][i] > 0.0
    assert gone.admissible[i]


def test_imminent_crossing_makes_sample_inadmissible():
    # the person reaches the robot's path point at t = 0.1 s: cannot stop in time at 0.3 m/s
    pos = np.stack([0.3 * TIMES, np.where(TIMES < 0.15, 0.0, 3.0)], -1)  # gone after 0.1 s
    res = plan_coarse(CFG, LIM, 0.3, 0.0, np.array([3.0, 0.0]), np.zeros((0, 2)),
                      pos[None], np.full((1, STEPS), 0.1))
    i = _straight_index(res)
    assert not res.admissible[i]
    frozen = plan_coarse(CFG, LIM, 0.3, 0.0, np.array([3.0, 0.0]), np.zeros((0, 2)),
                         np.repeat(pos[None, -1:], STEPS, 1), np.full((1, STEPS), 0.1))
    assert frozen.admissible[i]


def test_everything_blocked_returns_braking_sample():
    ring = 0.25 * np.stack([np.cos(np.linspace(0, 2 * np.pi, 200)),
                            np.sin(np.linspace(0, 2 * np.pi, 200))], -1)
    res = plan(CFG, LIM, 0.3, 0.5, np.array([3.0, 0.0]), ring)
    assert not res.admissible_best
    assert not res.admissible.any()
    v_lo = 0.3 - LIM.decel_max * CFG.window_dt
    assert res.best == pytest.approx((v_lo, 0.5 - LIM.alpha_max * CFG.window_dt))
    assert res.best_path.shape == (STEPS, 3)


def _drive_past_walker(cfg: DWAConfig, walker_v: float) -> float:
    """Closed loop at the control rate: the robot drives at 0.3 m/s toward a goal 6 m ahead; a
    person 4 m ahead (5 cm to the left) walks at `walker_v` m/s along −x and does not give way
    (0 m/s: stands there). Each cycle DWA plans on the person's constant-velocity prediction and
    its best command is held for one cycle. Returns the closest centre distance in 6 s."""
    x = y = th = 0.0
    v, w = 0.3, 0.0
    closest = math.inf
    for i in range(120):
        t = i * CFG.window_dt
        px, py = 4.0 - walker_v * t, 0.05
        c, s = math.cos(th), math.sin(th)
        rel = np.array([c * (px - x) + s * (py - y), -s * (px - x) + c * (py - y)])
        vel = np.array([-c * walker_v, s * walker_v])
        pos = (rel + vel * TIMES[:, None])[None]
        gx, gy = 6.0 - x, -y
        goal = np.array([c * gx + s * gy, -s * gx + c * gy])
        res = plan(cfg, LIM, v, w, goal, np.zeros((0, 2)), pos, (0.3 + 0.05 * TIMES)[None])
        v, w = res.best
        x, y, th = x + v * math.cos(th) * CFG.window_dt, y + v * math.sin(th) * CFG.window_dt, \
            th + w * CFG.window_dt
        closest = min(closest, math.hypot(px - x, py - y))
    return closest


def test_evasion_steps_off_the_line_of_a_person_walking_at_the_robot():
    """Fox et al.'s DWA brakes before a person walking head-on and stands in their way (a
    sample that can stop before the collision is admissible, and every sample's clearance is
    0): the person walks into it. With the evasion term the robot turns off the person's line
    cycle by cycle and lets them pass, at any weight from 1 (braking or backing off only puts
    the meeting past the horizon, and the term looks past it); a person standing in the way is
    not a walker, and the term changes nothing there."""
    contact = 0.3 + CFG.robot_radius_m
    for speed in (0.5, 0.8):
        assert _drive_past_walker(FOX, speed) < contact
        for weight in (1.0, 3.0, 6.0):
            evade = replace(CFG, weight_evasion=weight)
            assert _drive_past_walker(evade, speed) > contact + CFG.safety_margin_m
    assert _drive_past_walker(CFG, 0.0) == _drive_past_walker(FOX, 0.0)


def _beside(y: float, growth: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A person standing at (0, y), radius 0.3 m (+ growth·t, the prediction's uncertainty):
    over the footprint for |y| < 0.53 m."""
    return np.tile([0.0, y], (1, STEPS, 1)), (0.3 + growth * TIMES)[None]


def test_a_person_already_over_the_footprint_only_forbids_coming_closer():
    """A person standing 0.45 m to the left overlaps the footprint by 8 cm. Driving on toward
    the goal or turning away stays admissible; turning into them comes closer at once and is
    not. Without the overlap rule every moving sample collided at the first step and was
    inadmissible: the robot froze beside them."""
    goal = np.array([3.0, 0.0])
    pos, rad = _beside(0.45, growth=0.1)  # the disc grows faster than driving on gains
    on = plan_coarse(CFG, LIM, 0.2, 0.0, goal, np.zeros((0, 2)), pos, rad)
    assert on.admissible_best and on.best[0] > 0.1
    ref = plan_reference(CFG, LIM, 0.2, 0.0, goal, np.zeros((0, 2)), pos, rad)
    np.testing.assert_array_equal(on.admissible[:400], ref.admissible)
    pos, rad = _beside(0.45)
    on = plan_coarse(CFG, LIM, 0.2, 0.0, goal, np.zeros((0, 2)), pos, rad)
    assert on.admissible_best and on.best[0] > 0.1
    away = plan_coarse(CFG, LIM, 0.2, -1.0, goal, np.zeros((0, 2)), pos, rad)
    assert away.admissible.all()
    into = plan_coarse(CFG, LIM, 0.2, 1.0, goal, np.zeros((0, 2)), pos, rad)
    assert not into.admissible.any()
    for w0, res in ((0.0, on), (-1.0, away), (1.0, into)):
        ref = plan_reference(CFG, LIM, 0.2, w0, goal, np.zeros((0, 2)), pos, rad)
        np.testing.assert_array_equal(res.admissible[:400], ref.admissible)


def test_a_wall_already_over_the_footprint_only_forbids_coming_closer():
    wall = np.stack([np.linspace(-1.0, 2.0, 301), np.full(301, 0.2)], -1)  # 0.2 m to the left
    goal = np.array([3.0, 0.0])
    on = plan_coarse(CFG, LIM, 0.2, 0.0, goal, wall)
    v, w = on.samples[:400, 0], on.samples[:400, 1]
    assert on.admissible_best and on.best[0] > 0.1
    assert on.admissible[(v == v.max()) & (w <= 0.0)].all()  # along it or away
    into = plan_coarse(CFG, LIM, 0.2, 1.0, goal, wall)
    assert (into.raw["clearance"] == 0).all()  # every arc into it comes closer
    for w0, res in ((0.0, on), (1.0, into)):
        ref = plan_reference(CFG, LIM, 0.2, w0, goal, wall)
        np.testing.assert_array_equal(res.admissible[:400], ref.admissible)


class FakeClock:
    def __init__(self, tick: float):
        self.t, self.tick, self.reads = 0.0, tick, 0

    def __call__(self) -> float:
        self.reads += 1
        self.t += self.tick
        return self.t


def test_refinement_stops_at_deadline_and_first_coarse_block_always_completes():
    rng = np.random.default_rng(3)
    w = random_world(rng, STEPS, 100, 5)
    args = (CFG, LIM, 0.2, 0.1, np.array([3.0, 1.0]), w["points"], w["obs_pos"],
            w["obs_radius"])
    # deadline already past: one interleaved block of the coarse grid, spanning the window
    cfg = replace(CFG, block_samples=100)
    r0 = plan(cfg, *args[1:], deadline=-1.0, now=FakeClock(0.001))
    assert r0.evaluated == 100 and r0.refine_rounds == 0 and r0.budget_cut
    full = plan_coarse(CFG, *args[1:])
    assert r0.samples[:, 0].min() == full.samples[:, 0].min()
    assert r0.samples[:, 0].max() == full.samples[:, 0].max()
    span = np.ptp(full.samples[:, 1])
    assert np.ptp(r0.samples[:, 1]) >= 0.75 * span  # a sparser grid over the same window
    # each clock read advances 1 ms: rounds end by the deadline, clock checked every round
    clock = FakeClock(0.001)
    many = replace(CFG, refine_max_rounds=8)
    r1 = plan(many, *args[1:], deadline=0.016, now=clock)
    assert 0 < r1.refine_rounds < many.refine_max_rounds and r1.budget_cut
    assert clock.t <= 0.016 + 0.001
    # no clock: a pure evaluation-count budget
    r2 = plan(*args)
    assert r2.refine_rounds == CFG.refine_max_rounds and not r2.budget_cut
    assert r2.evaluated == 400 + CFG.refine_max_rounds * (CFG.refine_n**2 - 1)
    assert r2.total[r2.best_index] >= r2.total[r2.admissible].max() - 1e-12


def test_best_path_matches_best_sample():
    rng = np.random.default_rng(4)
    w = random_world(rng, STEPS, 50, 3)
    r = plan(CFG, LIM, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"], w["obs_radius"])
    v, om = r.best
    x, y, th = r.best_path[-1]
    assert th == pytest.approx(om * 3.0)
    assert math.hypot(x, y) <= abs(v) * 3.0 + 1e-9


def test_same_world_gives_the_same_plan_bit_for_bit():
    """A replay must reproduce every decision: no result may depend on where numpy or a
    library happened to place its buffers (cv2's distance transform and magnitude did)."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        w = random_world(rng, STEPS, int(rng.integers(1, 200)), int(rng.integers(0, 8)))
        args = (CFG, LIM, w["v0"], w["w0"], w["goal"], w["points"], w["obs_pos"],
                w["obs_radius"])
        first = plan(*args)
        for _ in range(3):
            shifted = [np.empty(int(rng.integers(1, 4096)), np.uint8) for _ in range(4)]
            again = plan(*args)
            assert again.best == first.best and again.best_index == first.best_index
            for k in ("samples", "total", "admissible"):
                np.testing.assert_array_equal(getattr(again, k), getattr(first, k))
            for k in first.raw:
                np.testing.assert_array_equal(again.raw[k], first.raw[k])
            del shifted
