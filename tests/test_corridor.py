"""Safe corridor: widths between walls, people at the sample time, caps, degenerate cases."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.planning.corridor import CorridorConfig, safe_corridor


def straight(length: float = 2.0, steps: int = 21) -> np.ndarray:
    x = np.linspace(0.0, length, steps)
    return np.stack([x, np.zeros(steps), np.zeros(steps)], axis=1)


def wall(y: float, x0: float = -1.0, x1: float = 3.0, step: float = 0.02) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, step)
    return np.stack([x, np.full_like(x, y)], axis=1)


def inside(poly: np.ndarray, pts: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Points inside a counter-clockwise convex polygon."""
    a, b = poly, np.roll(poly, -1, axis=0)
    e = b - a
    rel = pts[:, None, :] - a[None]
    cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]
    return np.all(cross >= -tol, axis=1)


def test_symmetric_walls_give_constant_half_width_minus_point_radius():
    cfg = CorridorConfig(samples=10, point_radius=0.05)
    pts = np.concatenate([wall(0.5), wall(-0.5)])
    c = safe_corridor(straight(), pts, None, None, cfg)
    np.testing.assert_allclose(c.left, 0.45, atol=1e-12)
    np.testing.assert_allclose(c.right, 0.45, atol=1e-12)
    assert c.samples.shape == (10, 3) and c.left.shape == (10,)
    np.testing.assert_allclose(c.samples[:, 0], np.linspace(0, 2, 10))


def test_asymmetric_walls():
    c = safe_corridor(straight(), np.concatenate([wall(0.3), wall(-0.8)]), None, None,
                      CorridorConfig())
    np.testing.assert_allclose(c.left, 0.3, atol=1e-12)
    np.testing.assert_allclose(c.right, 0.8, atol=1e-12)


def test_rotated_path_uses_its_normal():
    th = 0.7
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    p = straight()
    p[:, :2] = p[:, :2] @ rot.T
    p[:, 2] = th
    pts = np.concatenate([wall(0.4), wall(-0.6)]) @ rot.T
    c = safe_corridor(p, pts, None, None, CorridorConfig())
    np.testing.assert_allclose(c.left, 0.4, atol=1e-9)
    np.testing.assert_allclose(c.right, 0.6, atol=1e-9)


def test_person_at_the_sample_time_narrows_one_side():
    path = straight(2.0, 21)  # row i at x = 0.1 i
    steps = len(path)
    tp = np.zeros((1, steps, 2))
    tp[0, :, 0] = 1.0
    tp[0, :, 1] = 5.0  # far away ...
    row = 10  # ... except when the robot is at x = 1.0
    tp[0, row] = (1.0, 0.6)
    cfg = CorridorConfig(samples=21)
    c = safe_corridor(path, np.zeros((0, 2)), tp, np.array([0.25]), cfg)
    assert c.left[10] == np.float64(0.6 - 0.25) or abs(c.left[10] - 0.35) < 1e-12
    others = np.delete(np.arange(21), 10)
    np.testing.assert_allclose(c.left[others], cfg.max_width)
    np.testing.assert_allclose(c.right, cfg.max_width)
    # on the right side instead, and a disc across the sample closes both sides
    tp[0, row] = (1.0, -0.5)
    c = safe_corridor(path, np.zeros((0, 2)), tp, np.array([0.25]), cfg)
    assert abs(c.right[10] - 0.25) < 1e-12 and c.left[10] == cfg.max_width
    tp[0, row] = (1.0, 0.1)
    c = safe_corridor(path, np.zeros((0, 2)), tp, np.array([0.25]), cfg)
    assert c.left[10] == 0.0 and c.right[10] == 0.0


def test_track_grazing_the_band_uses_the_chord():
    path = straight(2.0, 21)
    tp = np.array([[[1.0 + 0.15, 0.6]]])  # static track (T, 1, 2), 0.15 m along the path
    cfg = CorridorConfig(samples=21, band=0.05)
    c = safe_corridor(path, np.zeros((0, 2)), tp, np.array([0.2]), cfg)
    # at sample x = 1.0: |c| = 0.15, strip edge 0.10 from the centre: e = sqrt(0.04 - 0.01)
    assert abs(c.left[10] - (0.6 - np.sqrt(0.03))) < 1e-12


def test_caps_when_all_free_and_far_points():
    cfg = CorridorConfig(max_width=1.5)
    c = safe_corridor(straight(), np.array([[1.0, 4.0], [1.0, -9.0], [50.0, 0.0]]), None, None, cfg)
    np.testing.assert_array_equal(c.left, 1.5)
    np.testing.assert_array_equal(c.right, 1.5)
    c = safe_corridor(straight(), np.concatenate([wall(2.5), wall(-1.6)]), None, None, cfg)
    np.testing.assert_array_equal(c.left, 1.5)
    np.testing.assert_array_equal(c.right, 1.5)


def test_zero_length_path_and_collinear_hull():
    path = np.tile([[0.5, -0.2, 0.3]], (7, 1))
    cfg = CorridorConfig(samples=5)
    c = safe_corridor(path, np.zeros((0, 2)), None, None, cfg)
    np.testing.assert_array_equal(c.samples, np.tile([[0.5, -0.2, 0.3]], (5, 1)))
    # all boundary points on one normal line: the hull is degenerate, the points are returned
    n = np.array([-np.sin(0.3), np.cos(0.3)])
    assert c.polygon.shape == (2, 2)
    np.testing.assert_allclose(c.polygon[0], np.array([0.5, -0.2]) + 1.5 * n)
    np.testing.assert_allclose(c.polygon[1], np.array([0.5, -0.2]) - 1.5 * n)
    # a straight path squeezed to width 0 everywhere: collinear points, returned as they are
    c = safe_corridor(straight(), np.array([[x, 0.0] for x in np.arange(-0.5, 2.6, 0.01)]),
                      None, None, CorridorConfig())
    np.testing.assert_array_equal(c.left, 0.0)
    assert np.allclose(c.polygon[:, 1], 0.0)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_polygon_contains_the_path_samples(seed: int):
    rng = np.random.default_rng(seed)
    steps = int(rng.integers(2, 30))
    v, w, dt = rng.uniform(0.05, 0.5), rng.uniform(-1.5, 1.5), 0.1
    th = w * dt * np.arange(steps)
    xy = np.concatenate([[[0, 0]], np.cumsum(v * dt * np.stack([np.cos(th[:-1]), np.sin(th[:-1])], 1), 0)])
    path = np.concatenate([xy, th[:, None]], axis=1)
    pts = rng.uniform(-2, 3, (int(rng.integers(0, 200)), 2))
    tracks = rng.uniform(-2, 3, (int(rng.integers(0, 4)), steps, 2))
    c = safe_corridor(path, pts, tracks, rng.uniform(0.1, 0.4, len(tracks)), CorridorConfig())
    assert np.all((c.left >= 0) & (c.left <= 1.5) & (c.right >= 0) & (c.right <= 1.5))
    if len(c.polygon) >= 3:
        assert inside(c.polygon, c.samples[:, :2], tol=1e-9).all()
    # every obstacle point is outside the open corridor segments (nothing within the strip)
    n = np.stack([-np.sin(c.samples[:, 2]), np.cos(c.samples[:, 2])], 1)
    t = np.stack([np.cos(c.samples[:, 2]), np.sin(c.samples[:, 2])], 1)
    for k in range(len(c.samples)):
        d = pts - c.samples[k, :2]
        a, cc = d @ n[k], np.abs(d @ t[k])
        strip = cc <= 0.05
        assert not np.any(strip & (a > 0) & (a < c.left[k] - 1e-12))
        assert not np.any(strip & (a < 0) & (-a < c.right[k] - 1e-12))
