"""Synthetic D435 depth: geometry against closed-form answers, range limits, noise model."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.depth_source import D435_848x480
from runtime.config.settings import CameraMount
from sim_stub.depth_render import Box, Cylinder, DepthRenderer, Scene, wall

K = D435_848x480
H = 0.643
LEVEL = CameraMount(translation_m=(0.0, 0.0, H), rpy_deg=(0.0, 0.0, 0.0))


def renderer(mount: CameraMount = LEVEL, **kw) -> DepthRenderer:
    return DepthRenderer(K, mount, **kw)


def test_d435_default_intrinsics() -> None:
    assert K.width == 848 and K.height == 480 and K.cx == 424 and K.cy == 240
    assert K.fx == pytest.approx(424 / np.tan(np.radians(43.5)))
    assert K.fx == K.fy and K.depth_unit_m == 0.001


def test_flat_floor_matches_closed_form() -> None:
    depth = renderer().render((0.0, 0.0, 0.0), Scene())
    for v in (300, 350, 420, 479):
        expected_m = H / ((v - K.cy) / K.fy)
        for u in (0, 200, 424, 847):
            assert abs(depth[v, u] * 1e-3 - expected_m) <= 0.001, (v, u)
    assert np.all(depth[: int(K.cy) + 1] == 0)  # at and above the horizon: nothing hit


def test_cylinder_straight_ahead() -> None:
    depth = renderer().render((0.0, 0.0, 0.0), Scene([Cylinder(2.0, 0.0, 0.3, 1.7)]))
    col = depth[60:400, int(K.cx)].astype(float) * 1e-3  # below row ~409 the floor is nearer
    assert np.all(np.abs(col - 1.70) <= 0.002)
    # pose moves the world: the same cylinder seen from a robot that stepped 0.5 m forward
    depth2 = renderer().render((0.5, 0.0, 0.0), Scene([Cylinder(2.0, 0.0, 0.3, 1.7)]))
    assert abs(depth2[240, 424] * 1e-3 - 1.20) <= 0.002
    # and turned 90 deg left: the cylinder at (0, 2) is straight ahead
    depth3 = renderer().render((0.0, 0.0, np.pi / 2), Scene([Cylinder(0.0, 2.0, 0.3, 1.7)]))
    assert abs(depth3[240, 424] * 1e-3 - 1.70) <= 0.002


def first_floor_row(z: np.ndarray, u: int) -> int:
    return int(np.argmax(np.isfinite(z[:, u])))


def test_pitch_and_roll_move_the_horizon() -> None:
    level = renderer().render_z((0.0, 0.0, 0.0), Scene()).copy()
    assert first_floor_row(level, 424) == int(K.cy) + 1
    pitched = renderer(CameraMount((0.0, 0.0, H), (0.0, 10.0, 0.0))).render_z((0, 0, 0), Scene())
    expected = K.cy - K.fy * np.tan(np.radians(10.0))  # pitch > 0 looks down: horizon moves up
    assert abs(first_floor_row(pitched, 424) - expected) <= 1.0
    rolled = renderer(CameraMount((0.0, 0.0, H), (10.0, 0.0, 0.0))).render_z((0, 0, 0), Scene())
    # roll > 0 raises the camera's left side: the horizon is lower on the left of the image
    assert first_floor_row(rolled, 50) > first_floor_row(rolled, 424) > first_floor_row(rolled, 800)


def test_range_limits_give_zero() -> None:
    r = renderer()
    z = r.render_z((0.0, 0.0, 0.0), Scene(boxes=[Box(0.2, 0.0, 0.1, 0.2, 0.0, 1.0)])).copy()
    depth = r.render((0.0, 0.0, 0.0), Scene(boxes=[Box(0.2, 0.0, 0.1, 0.2, 0.0, 1.0)]))
    near = z < 0.17
    far = np.isfinite(z) & (z > 10.0)
    assert near.sum() > 1000 and far.sum() > 1000
    assert np.all(depth[near] == 0) and np.all(depth[far] == 0)
    ok = (z >= 0.17) & (z <= 10.0)
    assert np.all(depth[ok] > 0)


def test_z_depth_not_ray_length() -> None:
    depth = renderer().render((0.0, 0.0, 0.0), Scene(boxes=[wall(3.0, -8.0, 3.0, 8.0, 0.1, 3.0)]))
    centre = depth[240, 424]
    assert abs(centre * 1e-3 - 2.95) <= 0.001
    for v, u in ((20, 20), (100, 800), (330, 40)):  # rows > ~337 see the floor first
        assert depth[v, u] == centre


def test_noise_seeded_and_grows_with_range() -> None:
    scene_near = Scene(boxes=[wall(2.0, -8.0, 2.0, 8.0, 0.0001, 3.0)], floor=False)
    scene_far = Scene(boxes=[wall(6.0, -20.0, 6.0, 20.0, 0.0001, 3.0)], floor=False)
    a = renderer(seed=7, edge_dropout_p=0.0).render((0, 0, 0), scene_near, noise=True)
    b = renderer(seed=7, edge_dropout_p=0.0).render((0, 0, 0), scene_near, noise=True)
    c = renderer(seed=8, edge_dropout_p=0.0).render((0, 0, 0), scene_near, noise=True)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    far = renderer(seed=7, edge_dropout_p=0.0).render((0, 0, 0), scene_far, noise=True)
    s_near = np.std(a[100:280].astype(float) - 2000.0)  # rows that see the wall (no floor)
    s_far = np.std(far[100:280].astype(float) - 6000.0)
    assert s_near == pytest.approx(0.001 * 2.0**2 * 1000, rel=0.1)
    assert s_far == pytest.approx(0.001 * 6.0**2 * 1000, rel=0.1)


def test_edge_dropout() -> None:
    scene = Scene([Cylinder(2.0, 0.0, 0.3, 1.7)], boxes=[wall(6.0, -8.0, 6.0, 8.0, 0.1, 3.0)])
    r = renderer(noise_k=0.0, edge_dropout_p=1.0)
    clean = r.render((0, 0, 0), scene)
    noisy = r.render((0, 0, 0), scene, noise=True)
    row = clean[200].astype(int)
    edges = np.flatnonzero(np.abs(np.diff(row)) > 250)
    assert len(edges) >= 2
    for e in edges:
        assert noisy[200, e] == 0 and noisy[200, e + 1] == 0
    assert noisy[200, 424] == clean[200, 424]


CLUTTER = Scene(
    [Cylinder(1.5, 0.4, 0.3, 1.7), Cylinder(3.0, -1.0, 0.25, 1.2), Cylinder(0.6, -0.5, 0.1, 0.8)],
    [Box(2.5, 1.2, 0.6, 0.4, 0.7, 0.8), wall(-1.0, 2.0, 6.0, 2.0), wall(6.0, -3.0, 6.0, 3.0)],
)
POSES = [(0.0, 0.0, 0.0), (0.4, -0.2, 0.3), (1.1, 0.5, -0.9), (-0.5, 0.0, 2.8)]
TILTED = CameraMount(translation_m=(0.1, 0.02, 0.2), rpy_deg=(0.5, 12.0, -1.0))


@pytest.mark.parametrize("d", [2, 4])
def test_decimated_render_is_the_full_render_subsampled(d: int) -> None:
    """Render what is read: pixel (i, j) of the decimated image is pixel (d·i, d·j) of the full
    one, bit for bit, and its intrinsics deproject it along the same ray."""
    full, dec = renderer(TILTED), renderer(TILTED, decimation=d)
    k = dec.intrinsics
    assert (k.width, k.height) == (848 // d, 480 // d)
    assert (k.fx * d, k.fy * d, k.cx * d, k.cy * d) == (K.fx, K.fy, K.cx, K.cy)
    for pose in POSES:
        want = full.render(pose, CLUTTER)[::d, ::d]
        got = dec.render(pose, CLUTTER)
        assert got.shape == want.shape and np.count_nonzero(want) > 1000
        assert np.array_equal(got, want), pose


def test_world_model_reads_the_same_points_from_a_decimated_render() -> None:
    """The pipeline's perception at decimation 1 on the decimated render gives the points it
    gives at decimation 4 on the full render: the simulator may render only what is read."""
    from dataclasses import replace

    from runtime.perception.depth_points import Perception, PerceptionConfig

    cfg = PerceptionConfig()
    assert cfg.decimation == 4
    full, dec = renderer(TILTED), renderer(TILTED, decimation=4)
    p_full = Perception(K, TILTED, cfg)
    p_dec = Perception(dec.intrinsics, TILTED, replace(cfg, decimation=1))
    seen = 0
    for pose in POSES:
        a = p_full.process(full.render(pose, CLUTTER))
        pa, sa = a.points.copy(), a.scan.copy()
        b = p_dec.process(dec.render(pose, CLUTTER))
        seen += len(pa)
        assert np.array_equal(pa, b.points) and np.array_equal(sa, b.scan), pose
    assert seen > 1000


def test_decimated_noise_is_the_same_model_per_pixel() -> None:
    """Same depth noise per kept pixel: the spread of (noisy - clean) on a wall at 3 m matches."""
    scene = Scene([], [wall(3.0, -5.0, 3.0, 5.0, height=3.0)], floor=False)
    spreads = []
    for d in (1, 4):
        r = renderer(decimation=d, edge_dropout_p=0.0, seed=2)
        clean = r.render((0.0, 0.0, 0.0), scene).astype(float)
        noisy = np.stack([r.render((0.0, 0.0, 0.0), scene, noise=True) for _ in range(4)])
        diff = (noisy - clean)[:, clean > 0] * 1e-3
        spreads.append(diff.std())
    assert spreads[0] == pytest.approx(0.001 * 9.0, rel=0.05)  # sigma = k z^2 at 3 m
    assert spreads[1] == pytest.approx(spreads[0], rel=0.1)


def test_decimation_outside_the_perception_choices_is_refused() -> None:
    with pytest.raises(ValueError, match="decimation"):
        renderer(decimation=3)
