"""The observation contract's ranges: every feature the builder produces lies inside
`spec.bounds()` (the training Box and the export's parity sampling assume it), on simulated runs
of every preset and on inputs built to leave the range; NaN stays NaN (the job brakes on it)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.policy.obs_spec import (
    PRESETS,
    ActionSpec,
    DWABlock,
    ObservationBuilder,
    ObsSpec,
    ScanBlock,
)
from sim_stub.recorded_observations import recorded_observations

ACTION = ActionSpec(v_min=0.0, v_max=0.4, omega_max=2.0)
TERMS = ("heading", "clearance", "velocity", "density")


def dwa_result(terms: dict[str, float], steps: int = 30) -> SimpleNamespace:
    """A DWA result (duck-typed like runtime.planning.dwa.DWAResult) whose best sample (index 1) has
    the given normalised cost terms."""
    t = (np.arange(steps) + 1) * 0.1
    path = np.stack([0.3 * t, 0.1 * t, np.zeros(steps)], axis=1)
    arrays = {k: np.array([0.5, terms[k], 0.5]) for k in TERMS}
    return SimpleNamespace(best=(0.2, -0.5), best_path=path, best_index=1, **arrays)


def out_of_bounds(spec: ObsSpec, obs: np.ndarray) -> list[str]:
    """'name: min..max' of each feature with a value outside its declared range."""
    lo, hi = spec.bounds()
    bad = (obs < lo) | (obs > hi)
    return [f"{name}: {obs[:, j].min():.4g}..{obs[:, j].max():.4g}"
            for j, name in enumerate(spec.names()) if bad[:, j].any()]


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_simulated_runs_stay_inside_the_declared_bounds(name):
    spec = PRESETS[name]
    obs = recorded_observations(spec, 300, seed=0)
    assert obs.shape == (300, spec.size)
    assert np.isfinite(obs).all()
    assert out_of_bounds(spec, obs) == []


def test_dwa_cost_terms_above_their_scale_are_clipped_to_one():
    spec = ObsSpec("t", (DWABlock(path_points=3),), ACTION)
    b = ObservationBuilder(spec)
    # density near a crowd reaches several times its scale; the others are at or over 1
    obs = b.build(np.zeros(2), 0, 0, dwa=dwa_result(
        {"heading": 1.0 + 1e-6, "clearance": 1.0, "velocity": 1.7, "density": 2.23}))
    np.testing.assert_array_equal(obs[-4:], [1.0, 1.0, 1.0, 1.0])
    assert out_of_bounds(spec, obs[None]) == []
    # a reversing sample's velocity term (v < 0) is below the declared range
    obs = b.build(np.zeros(2), 0, 0, dwa=dwa_result(
        {"heading": 0.25, "clearance": 0.5, "velocity": -0.5, "density": 0.0}))
    np.testing.assert_array_equal(obs[-4:], [0.25, 0.5, 0.0, 0.0])


def test_a_nan_dwa_term_stays_nan():
    spec = ObsSpec("t", (DWABlock(path_points=3),), ACTION)
    obs = ObservationBuilder(spec).build(np.zeros(2), 0, 0, dwa=dwa_result(
        {"heading": 0.5, "clearance": math.nan, "velocity": 0.5, "density": 3.0}))
    terms = obs[-4:]
    assert terms[0] == pytest.approx(0.5) and math.isnan(terms[1])
    assert terms[2] == pytest.approx(0.5) and terms[3] == 1.0


def test_nan_goal_and_speed_stay_nan():
    spec = PRESETS["drl_dwa"]
    scan = np.full(90, np.inf, dtype=np.float32)
    half = math.radians(87.0) / 2
    angles = (-half + (np.arange(90) + 0.5) * (2 * half / 90)).astype(np.float32)
    world = SimpleNamespace(scan=scan, unknown=np.zeros(90, bool), bin_angles=angles)
    obs = ObservationBuilder(spec).build(np.array([math.nan, 1.0]), math.nan, 0.0, world,
                                         dwa_result(dict.fromkeys(TERMS, 0.5)))
    names = spec.names()
    for feature in ("goal.distance", "goal.sin_bearing", "goal.cos_bearing", "velocity.v"):
        assert math.isnan(obs[names.index(feature)]), feature
    assert not np.isnan(obs[names.index("velocity.omega"):]).any()


@pytest.mark.parametrize("range_max_m", [1.7, 4.0])
def test_free_scan_bins_are_at_most_one_and_negative_ranges_at_least_zero(range_max_m):
    # 1.7 m: range_max · (1 / range_max) rounds above 1 in float32
    spec = ObsSpec("t", (ScanBlock(bins=3, span_deg=87.0, range_max_m=range_max_m),), ACTION)
    half = math.radians(87.0) / 2
    angles = (-half + (np.arange(6) + 0.5) * (2 * half / 6)).astype(np.float32)
    scan = np.array([np.inf, range_max_m, -0.2, 1.0, 1.0, 50.0], dtype=np.float32)
    world = SimpleNamespace(scan=scan, unknown=np.zeros(6, bool), bin_angles=angles)
    obs = ObservationBuilder(spec).build(np.zeros(2), 0, 0, world)
    assert obs[0] == 1.0 and obs[1] == 0.0
    assert obs[2] == pytest.approx(1.0 / range_max_m)
    assert out_of_bounds(spec, obs[None]) == []
