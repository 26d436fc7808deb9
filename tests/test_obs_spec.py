"""The observation contract: block order, sizes, normalisation, JSON, validation, presets."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.policy.obs_spec import (
    PRESETS,
    ActionSpec,
    CorridorBlock,
    DWABlock,
    GoalBlock,
    ObservationBuilder,
    ObsSpec,
    ScanBlock,
    SpecError,
    VelocityBlock,
    load_spec,
)

ACTION = ActionSpec(v_min=0.0, v_max=0.4, omega_max=2.0)


def world(scan, unknown=None, span_deg=87.0):
    scan = np.asarray(scan, dtype=np.float32)
    n = len(scan)
    half = math.radians(span_deg) / 2
    angles = -half + (np.arange(n) + 0.5) * (2 * half / n)
    unk = np.zeros(n, bool) if unknown is None else np.asarray(unknown, bool)
    return SimpleNamespace(scan=scan, unknown=unk, bin_angles=angles.astype(np.float32))


def dwa_result(steps=30, best=(0.2, -0.5), best_index=1):
    t = (np.arange(steps) + 1) * 0.1
    path = np.stack([0.3 * t, 0.1 * t, np.zeros(steps)], axis=1)
    terms = {k: np.array([0.0, v, 1.0]) for k, v in
             (("heading", 0.9), ("clearance", 0.4), ("velocity", 0.5), ("density", 0.1))}
    return SimpleNamespace(best=best, best_path=path, best_index=best_index, **terms)


def test_presets_are_the_papers_three_variants_with_pinned_sizes_and_order():
    assert [b.kind for b in PRESETS["drl"].blocks] == ["goal", "velocity", "scan"]
    assert [b.kind for b in PRESETS["drl_dwa"].blocks] == ["goal", "velocity", "scan", "dwa"]
    assert [b.kind for b in PRESETS["safemove"].blocks] == [
        "goal", "velocity", "scan", "dwa", "corridor"]
    assert {k: s.size for k, s in PRESETS.items()} == {"drl": 25, "drl_dwa": 41, "safemove": 61}
    assert PRESETS["safemove"].layout() == [("goal", 0, 3), ("velocity", 3, 5), ("scan", 5, 25),
                                            ("dwa", 25, 41), ("corridor", 41, 61)]
    names = PRESETS["safemove"].names()
    assert names[:5] == ["goal.distance", "goal.sin_bearing", "goal.cos_bearing", "velocity.v",
                         "velocity.omega"]
    assert names[25:29] == ["dwa.best_v", "dwa.best_omega", "dwa.path[0].x", "dwa.path[0].y"]
    assert names[37:41] == ["dwa.heading", "dwa.clearance", "dwa.velocity", "dwa.density"]
    assert names[41] == "corridor.left[0]" and names[51] == "corridor.right[0]"


def test_goal_and_velocity_blocks():
    spec = ObsSpec("t", (GoalBlock(distance_max_m=5.0), VelocityBlock()), ACTION)
    b = ObservationBuilder(spec)
    obs = b.build(np.array([0.0, 2.0]), 0.1, -1.0)  # goal 2 m to the left
    np.testing.assert_allclose(obs, [0.4, 1.0, 0.0, -0.5, -0.5], atol=1e-7)
    obs = b.build(np.array([-30.0, 0.0]), 0.4, 3.0)  # far behind; speeds at/over the box
    np.testing.assert_allclose(obs, [1.0, 0.0, -1.0, 1.0, 1.0], atol=1e-7)
    obs = b.build(np.array([0.0, 0.0]), -0.2, 0.0)  # at the goal; reversing below v_min
    np.testing.assert_allclose(obs, [0.0, 0.0, 1.0, -1.0, 0.0], atol=1e-7)
    assert obs.dtype == np.float32 and obs is b.vector  # preallocated, reused


def test_scan_block_resamples_min_range_right_to_left_unknown_is_near():
    spec = ObsSpec("t", (ScanBlock(bins=3, span_deg=87.0, range_max_m=4.0),), ACTION)
    b = ObservationBuilder(spec)
    # 6 perception bins (right to left) → 3: min over the two in each
    obs = b.build(np.zeros(2), 0, 0, world([1.0, 3.0, np.inf, np.inf, 8.0, 2.0]))
    np.testing.assert_allclose(obs, [0.25, 1.0, 0.5])
    unknown = [False, False, False, True, False, False]
    obs = b.build(np.zeros(2), 0, 0, world([np.inf, np.inf, np.inf, np.inf, np.nan, np.inf],
                                           unknown))
    np.testing.assert_allclose(obs, [1.0, 0.0, 0.0])  # unknown and NaN: occupied, never free


def test_scan_bins_the_camera_does_not_cover_are_unseen_not_free():
    spec = ObsSpec("t", (ScanBlock(bins=4, span_deg=180.0),), ACTION)
    obs = ObservationBuilder(spec).build(np.zeros(2), 0, 0, world([np.inf] * 10, span_deg=87.0))
    np.testing.assert_allclose(obs, [0.0, 1.0, 1.0, 0.0])


def test_dwa_block_best_path_points_and_terms():
    spec = ObsSpec("t", (DWABlock(path_points=3, path_scale_m=0.9),), ACTION)
    obs = ObservationBuilder(spec).build(np.zeros(2), 0, 0, dwa=dwa_result())
    # path rows 9, 19, 29 (t = 1, 2, 3 s): (0.3t, 0.1t) / 0.9, x clipped to 1
    expected = [0.0, -0.25, 0.3 / 0.9, 0.1 / 0.9, 0.6 / 0.9, 0.2 / 0.9, 1.0, 0.3 / 0.9,
                0.9, 0.4, 0.5, 0.1]
    np.testing.assert_allclose(obs, expected, atol=1e-6)


def test_corridor_block_left_then_right_normalised():
    spec = ObsSpec("t", (CorridorBlock(samples=3, width_max_m=2.0),), ACTION)
    cor = SimpleNamespace(left=np.array([0.5, 1.0, 5.0]), right=np.array([0.0, 2.0, 0.25]))
    obs = ObservationBuilder(spec).build(np.zeros(2), 0, 0, corridor=cor)
    np.testing.assert_allclose(obs, [0.25, 0.5, 1.0, 0.0, 1.0, 0.125])
    with pytest.raises(ValueError, match="3 samples"):
        ObservationBuilder(spec).build(np.zeros(2), 0, 0, corridor=SimpleNamespace(
            left=np.zeros(4), right=np.zeros(4)))


def test_built_observations_stay_inside_the_specs_bounds():
    spec = PRESETS["safemove"]
    rng = np.random.default_rng(1)
    b = ObservationBuilder(spec)
    lo, hi = spec.bounds()
    for _ in range(50):
        scan = rng.uniform(0, 12, 90).astype(np.float32)
        scan[rng.random(90) < 0.2] = np.inf
        w = world(scan, rng.random(90) < 0.1)
        cor = SimpleNamespace(left=rng.uniform(0, 3, 10), right=rng.uniform(0, 3, 10))
        d = dwa_result(best=(rng.uniform(-1, 1), rng.uniform(-3, 3)))
        obs = b.build(rng.uniform(-20, 20, 2), rng.uniform(-1, 1), rng.uniform(-3, 3), w, d, cor)
        assert np.all(obs >= lo) and np.all(obs <= hi)


def tw(action: ActionSpec, a0: float, a1: float) -> tuple[float, float]:
    t = action.to_twist(np.array([a0, a1], dtype=np.float32))
    return t.v, t.omega


def test_action_mapping():
    a = ActionSpec(v_min=-0.1, v_max=0.3, omega_max=1.5)
    assert tw(a, -1.0, -1.0) == pytest.approx((-0.1, -1.5))
    assert tw(a, 1.0, 1.0) == pytest.approx((0.3, 1.5))
    assert tw(a, 0.0, 0.5) == pytest.approx((0.1, 0.75))
    assert tw(a, 7.0, -9.0) == pytest.approx((0.3, -1.5))  # clipped first
    sb3 = ActionSpec(v_min=0.0, v_max=0.3, omega_max=1.0, output_low=(0.0, -1.0),
                     output_high=(0.3, 1.0))  # an SB3 model that outputs physical units
    assert tw(sb3, 0.2, -0.4) == pytest.approx((0.2, -0.4))
    assert a.normalise(0.1, 0.75) == pytest.approx((0.0, 0.5))


def test_json_round_trip_and_versioned():
    for spec in PRESETS.values():
        data = json.loads(spec.to_json())
        assert data["spec_version"] == 1
        assert ObsSpec.from_json(spec.to_json(), "x") == spec
    # a custom order and sizes, as for an actor trained elsewhere (scan first)
    custom = {"spec_version": 1, "name": "td3_nav", "blocks": [
        {"type": "scan", "bins": 20, "span_deg": 180}, {"type": "goal"}, {"type": "velocity"}],
        "action": {"v_min": 0.0, "v_max": 0.5, "omega_max": 1.0}}
    spec = ObsSpec.from_dict(custom, "x")
    assert spec.size == 25 and spec.layout()[0] == ("scan", 0, 20)


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d.update(spec_version=2), "key 'spec_version': this runtime reads version 1, got 2"),
    (lambda d: d.pop("spec_version"), "key 'spec_version': expected an integer"),
    (lambda d: d["blocks"][2].update(bins=0), "key 'blocks[2].bins': must be at least 1, got 0"),
    (lambda d: d["blocks"][2].update(binz=3), "unknown key 'blocks[2].binz' (did you mean"),
    (lambda d: d["blocks"][1].update(type="lidar"), "key 'blocks[1].type': must be one of"),
    (lambda d: d["blocks"].append({"type": "goal"}), "key 'blocks[5].type': block 'goal' appears"),
    (lambda d: d["action"].update(v_max=-0.2), "key 'action.v_max': must be greater than"),
    (lambda d: d["action"].update(omega_max=float("nan")), "key 'action.omega_max': must be finite"),
    (lambda d: d.update(extra=1), "unknown key 'extra'"),
    (lambda d: d.update(blocks=[]), "key 'blocks': expected a non-empty list"),
])
def test_invalid_specs_are_refused_naming_the_key(mutate, message):
    data = PRESETS["safemove"].to_dict()
    mutate(data)
    with pytest.raises(SpecError) as err:
        ObsSpec.from_dict(data, "spec.json")
    assert str(err.value).startswith("spec.json: ") and message in str(err.value)


def test_load_spec_by_preset_or_file(tmp_path):
    assert load_spec("drl") is PRESETS["drl"]
    path = tmp_path / "s.json"
    path.write_text(PRESETS["drl_dwa"].to_json())
    assert load_spec(str(path)) == PRESETS["drl_dwa"]
    with pytest.raises(SpecError, match="not a preset"):
        load_spec("safemoov")
    with pytest.raises(SpecError, match="spec file not found"):
        load_spec(str(tmp_path / "missing.json"))
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(SpecError, match="bad.json: not valid JSON"):
        load_spec(str(tmp_path / "bad.json"))
