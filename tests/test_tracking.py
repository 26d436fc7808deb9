"""Tracker: unit tests and a ground-truth run in scenario paper_d (render-free 2D ray casting)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from runtime.perception.clustering import Clusters, cluster_points
from runtime.perception.tracking import (
    Tracker,
    TrackerConfig,
    cv_matrices,
    cv_predict,
    position_update,
)
from runtime.planning.planning_step import predict_tracks_base
from sim_stub.orca import Circle, Polygon
from sim_stub.scenario import load_scenario
from sim_stub.world import World

FOV = math.radians(87.0)
MAX_RANGE = 4.0


# --- a render-free 2D "depth scan": nearest hit per bearing ray ----------------------------------


def scan(
    origin: np.ndarray,
    heading: float,
    circles: list[tuple[np.ndarray, float]],
    polygons: list[np.ndarray],
    rng: np.random.Generator,
    n_rays: int = 435,
    noise: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 2) where the rays of an 87° fan hit the nearest circle or polygon edge within
    MAX_RANGE (the visible side only, occlusion included), with isotropic Gaussian noise; and the
    index of the object each point came from (circles first, then polygons)."""
    ang = heading + np.linspace(-FOV / 2, FOV / 2, n_rays)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (R, 2)
    best = np.full(n_rays, np.inf)
    who = np.full(n_rays, -1)
    for k, (c, r) in enumerate(circles):
        oc = np.asarray(c) - origin
        b = d @ oc
        disc = b * b - (oc @ oc - r * r)
        th = b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc >= 0) & (th > 0) & (th < best)
        best[hit], who[hit] = th[hit], k
    for k, verts in enumerate(polygons):
        a = verts
        e = np.roll(verts, -1, axis=0) - a  # (E, 2)
        ao = a - origin  # (E, 2)
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (R, E)
        with np.errstate(divide="ignore", invalid="ignore"):
            th = (ao[None, :, 0] * e[None, :, 1] - ao[None, :, 1] * e[None, :, 0]) / denom
            u = (ao[None, :, 0] * d[:, None, 1] - ao[None, :, 1] * d[:, None, 0]) / denom
        ok = (np.abs(denom) > 1e-12) & (th > 0) & (u >= 0) & (u <= 1)
        th = np.where(ok, th, np.inf).min(axis=1)
        hit = th < best
        best[hit], who[hit] = th[hit], len(circles) + k
    sel = best <= MAX_RANGE
    pts = origin + d[sel] * best[sel, None]
    pts = pts + rng.normal(0.0, noise, pts.shape)
    return pts, who[sel]


# --- unit tests ------------------------------------------------------------------------------------


def arc_points(centre, radius, sensor, n=40, noise=0.0, rng=None):
    """Points on the half of a circle facing the sensor."""
    c = np.asarray(centre, float)
    towards = math.atan2(sensor[1] - c[1], sensor[0] - c[0])
    a = towards + np.linspace(-math.pi / 2 * 0.9, math.pi / 2 * 0.9, n)
    p = c + radius * np.stack([np.cos(a), np.sin(a)], axis=1)
    if noise and rng is not None:
        p = p + rng.normal(0, noise, p.shape)
    return p


def test_arc_centre_is_behind_the_visible_surface():
    sensor = np.zeros(2)
    pts = arc_points((2.0, 1.0), 0.3, sensor, noise=0.01, rng=np.random.default_rng(0))
    c = cluster_points(pts, TrackerConfig(), sensor)
    assert len(c) == 1
    assert np.hypot(*(c.centres[0] - [2.0, 1.0])) < 0.03
    centroid = pts.mean(axis=0)
    assert np.hypot(*(centroid - [2.0, 1.0])) > 0.1  # the plain centroid would be far off


def test_clustering_separates_objects_and_drops_walls_and_noise():
    sensor = np.zeros(2)
    a = arc_points((2.0, 0.0), 0.3, sensor)
    b = arc_points((2.0, 1.2), 0.3, sensor)
    wall = np.stack([np.full(200, 3.5), np.linspace(-2, 2, 200)], axis=1)
    noise = np.array([[1.0, -1.0], [1.0, -1.02]])
    c = cluster_points(np.vstack([a, b, wall, noise]), TrackerConfig(), sensor)
    assert len(c) == 2
    assert c.n_structure == 1
    assert sorted(np.round(c.centres[:, 1], 1).tolist()) == [0.0, 1.2]
    # NaN rows are ignored, empty input is fine
    assert len(cluster_points(np.full((5, 2), np.nan), TrackerConfig(), sensor)) == 0
    assert len(cluster_points(np.zeros((0, 2)), TrackerConfig(), sensor)) == 0


def point_clusters(*centres) -> Clusters:
    c = np.asarray(centres, float).reshape(-1, 2)
    k = len(c)
    return Clusters(c, np.full(k, 0.3), np.full(k, 20), np.full(k, 0.6))


def test_constant_velocity_target_velocity_converges():
    rng = np.random.default_rng(1)
    tr = Tracker(TrackerConfig(measurement_noise_m=0.02))
    v = np.array([0.8, -0.3])
    errs = []
    for k in range(60):
        t = k / 15
        z = np.array([1.0, 2.0]) + v * t + rng.normal(0, 0.02, 2)
        tracks = tr.update(point_clusters(z), t)
        assert len(tracks) == 1
        errs.append(np.hypot(*(tracks[0].velocity - v)))
    assert tracks[0].confirmed and tracks[0].id == 1
    assert np.mean(errs[-15:]) < 0.1
    assert errs[0] > 0.8  # born with velocity 0
    vel_sd = np.sqrt(np.trace(tracks[0].covariance[2:, 2:]))
    assert vel_sd < 0.3 * TrackerConfig().initial_speed_sigma_m_s
    # the planner's prediction (base_link at the odom origin) moves it along, std growing
    pos, std, _ = predict_tracks_base(tracks, (0.0, 0.0, 0.0), 0.0, 0.5, 2)
    assert pos.shape == (1, 3, 2) and np.all(np.diff(std[0]) > 0)
    np.testing.assert_allclose(pos[0, 2], tracks[0].position + tracks[0].velocity, atol=1e-9)


def test_crossing_targets_keep_their_ids_through_a_merged_blob():
    """Two targets cross at right angles and are seen as one blob (at their midpoint) for
    ~0.9 s: neither track takes the blob (gated), both coast and are picked up again. The blob
    itself becomes a short-lived third track which may briefly claim one target (a fragment,
    reported); the two targets are never swapped and end with their original IDs."""
    rng = np.random.default_rng(2)
    tr = Tracker()
    ids_a, ids_b = set(), set()
    for k in range(75):  # 5 s, they cross at t = 2.5 s, 1 m/s each at right angles
        t = k / 15
        a = np.array([-2.5 + t, 0.0]) + rng.normal(0, 0.01, 2)
        b = np.array([0.0, -2.5 + t]) + rng.normal(0, 0.01, 2)
        if np.hypot(*(a - b)) < 0.6:  # merged into one blob while touching: one measurement
            tracks = tr.update(point_clusters(0.5 * (a + b)), t)
        else:
            tracks = tr.update(point_clusters(a, b), t)
        for x in tracks:
            if x.confirmed and x.misses == 0:
                if np.hypot(*(x.position - a)) < 0.3:
                    ids_a.add(x.id)
                elif np.hypot(*(x.position - b)) < 0.3:
                    ids_b.add(x.id)
    final = {x.id for x in tracks if x.confirmed and x.misses == 0}
    print(f"crossing through a blob: ids on a {sorted(ids_a)}, on b {sorted(ids_b)}")
    assert 1 in ids_a and 2 in ids_b and 2 not in ids_a and 1 not in ids_b
    assert final == {1, 2}


def test_passing_targets_keep_their_ids_through_occlusion():
    """Two people pass each other in parallel lanes 0.8 m apart, seen from the side by the scan,
    so the near one hides the far one for a while; points → clusters → tracks."""
    rng = np.random.default_rng(5)
    tr = Tracker()
    sensor = np.array([0.0, -3.0])
    ids = {0: set(), 1: set()}
    for k in range(90):  # 6 s at 15 Hz; they meet at t = 3 s
        t = k / 15
        a = np.array([-3.0 + t, -0.4])
        b = np.array([3.0 - t, 0.4])
        pts, _ = scan(sensor, math.pi / 2, [(a, 0.3), (b, 0.3)], [], rng)
        for x in tr.update(pts, t, sensor):
            if x.confirmed and x.misses == 0:
                for n, p in enumerate((a, b)):
                    if np.hypot(*(x.position - p)) < 0.3:
                        ids[n].add(x.id)
    assert len(ids[0]) == 1 and len(ids[1]) == 1 and ids[0] != ids[1]


def test_gated_outlier_does_not_hijack_a_track():
    tr = Tracker()
    for k in range(30):
        tracks = tr.update(point_clusters((1.0 + 0.5 * k / 15, 0.0)), k / 15)
    before = tracks[0]
    t = 30 / 15
    tracks = tr.update(point_clusters((before.position[0] + 1.5, 1.0)), t)  # far off: gated
    first = next(x for x in tracks if x.id == before.id)
    assert first.misses == 1
    assert np.hypot(*(first.position - (before.position + before.velocity / 15))) < 0.05
    assert np.all(tr.last_costs == tr.last_costs)  # no NaN
    newborn = [x for x in tracks if x.id != before.id]
    assert len(newborn) == 1 and not newborn[0].confirmed


def test_births_need_n_hits_and_deaths_after_m_misses():
    cfg = TrackerConfig(birth_hits=4, death_misses=3, death_unseen_s=10.0)
    tr = Tracker(cfg)
    for k in range(4):
        tracks = tr.update(point_clusters((2.0, 0.0)), k * 0.1)
        assert tracks[0].confirmed == (k == 3)
        assert tracks[0].hits == k + 1
    for m in range(1, 4):
        tracks = tr.update(Clusters.empty(), 0.3 + m * 0.1)
        assert len(tracks) == (1 if m < 3 else 0)
    # a tentative track dies at its first miss
    tr.update(point_clusters((5.0, 5.0)), 1.0)
    assert tr.update(Clusters.empty(), 1.1) == []
    # death by time unseen, even at a low frame rate
    tr = Tracker(TrackerConfig(birth_hits=1, death_misses=100, death_unseen_s=0.5))
    tr.update(point_clusters((2.0, 0.0)), 0.0)
    assert len(tr.update(Clusters.empty(), 0.4)) == 1
    assert tr.update(Clusters.empty(), 0.6) == []


def test_a_track_that_left_the_view_coasts_instead_of_dying():
    """Not seeing a person outside the field of view is no evidence that they are gone: the
    track coasts on its prediction until coast_out_of_view_s; in view, unseen, it dies at
    death_unseen_s."""
    cfg = TrackerConfig(birth_hits=1, death_misses=100, death_unseen_s=0.5,
                        coast_out_of_view_s=2.0)
    looking_at = np.array([0.0, 0.0, 0.0])  # the track at (2, 0) is dead ahead
    looking_away = np.array([0.0, 0.0, math.pi])
    for sensor, alive_at_1s in ((looking_at, False), (looking_away, True)):
        tr = Tracker(cfg)
        tr.update(point_clusters((2.0, 0.0)), 0.0, sensor_pose=looking_at)
        assert (len(tr.update(Clusters.empty(), 1.0, sensor_pose=sensor)) == 1) == alive_at_1s
    coasting = tr.update(Clusters.empty(), 1.9, sensor_pose=looking_away)[0]
    assert coasting.coasting and coasting.misses == 0
    assert tr.update(Clusters.empty(), 2.1, sensor_pose=looking_away) == []
    # half out of the view (its disc crosses the edge) counts as out of view
    tr = Tracker(cfg)
    edge = math.radians(87.0 / 2)
    tr.update(point_clusters((2.0 * math.cos(edge), 2.0 * math.sin(edge))), 0.0)
    assert len(tr.update(Clusters.empty(), 1.0, sensor_pose=looking_at)) == 1


def test_costs_never_nan_and_time_cannot_go_back():
    tr = Tracker(TrackerConfig(birth_hits=1))
    tr.update(point_clusters((0.0, 0.0), (1e6, 1e6)), 0.0)
    tr.update(point_clusters((0.1, 0.0), (-1e6, 3.0), (0.0, 0.0)), 0.1)
    assert np.all(np.isfinite(tr.last_costs)) and tr.last_costs.shape == (2, 3)
    with pytest.raises(ValueError):
        tr.update(Clusters.empty(), 0.05)


def test_static_clutter_has_no_velocity():
    rng = np.random.default_rng(3)
    tr = Tracker()
    sensor = np.zeros(2)
    for k in range(150):
        pts = np.vstack(
            [
                arc_points((2.0, 0.5), 0.4, sensor, n=30, noise=0.01, rng=rng),
                # a box whose visible part flickers (occlusion): centre estimate jitters
                np.stack([np.full(20, 3.0), np.linspace(-1.0, -0.4 - 0.2 * (k % 3), 20)], 1),
            ]
        )
        tracks = tr.update(pts, k / 15, sensor)
    assert len(tracks) == 2
    for x in tracks:
        assert x.confirmed and np.hypot(*x.velocity) <= 0.05


# --- ground truth run in paper_d ------------------------------------------------------------------


def run_paper_d(seconds: float = 60.0, hz: float = 15.0, omega: float = 0.1):
    scen = load_scenario("paper_d")
    world = World(scen)
    rng = np.random.default_rng(7)
    tracker = Tracker()
    static_circles = [
        (np.asarray(s.center), s.radius) for s in world.shapes if isinstance(s, Circle)
    ]
    static_polys = [s.vertices for s in world.shapes if isinstance(s, Polygon)]
    static_centres = [c for c, _ in static_circles] + [v.mean(axis=0) for v in static_polys]
    n_agents = len(world.crowd)
    dt = 1.0 / hz
    pos_err, vel_err, speed_err, static_speed = [], [], [], []
    last_id = {}
    switches = 0
    theta = world.robot.theta
    for k in range(int(seconds * hz)):
        theta = math.atan2(math.sin(theta + omega * dt), math.cos(theta + omega * dt))
        world.follow_robot(dt, world.robot.x, world.robot.y, theta, 0.0, omega)
        snap = world.snapshot()
        origin = snap.robot_pose[:2]
        circles = [(p, r) for p, r in zip(snap.agent_positions, snap.agent_radii)]
        pts, who = scan(origin, theta, circles + static_circles, static_polys, rng)
        # tracks coasting outside the view are predictions, not estimates of what is seen
        tracks = [x for x in tracker.update(pts, snap.t, np.array([*origin, theta]))
                  if x.confirmed and not x.coasting]
        if not tracks:
            continue
        counts = np.bincount(who[who >= 0], minlength=n_agents + len(static_centres))
        # ground-truth objects in view (>= 3 scan points): agents, then static obstacles; one
        # joint Hungarian matching on centre distance <= 0.5 m
        in_view = np.flatnonzero(counts >= 3)
        if len(in_view) == 0:
            continue
        gt = np.vstack([snap.agent_positions, np.array(static_centres)])[in_view]
        tp = np.array([x.position for x in tracks])
        dist = np.hypot(*(tp[:, None, :] - gt[None, :, :]).T).T
        rows, cols = linear_sum_assignment(np.where(dist <= 0.5, dist, 1e6))
        for i, j in zip(rows, cols):
            if dist[i, j] > 0.5:
                continue
            a = int(in_view[j])
            if a >= n_agents:
                static_speed.append(np.hypot(*tracks[i].velocity))
                continue
            pos_err.append(dist[i, j])
            vel_err.append(np.hypot(*(tracks[i].velocity - snap.agent_velocities[a])))
            speed_err.append(
                abs(np.hypot(*tracks[i].velocity) - np.hypot(*snap.agent_velocities[a]))
            )
            if a in last_id and last_id[a] != tracks[i].id:
                switches += 1
            last_id[a] = tracks[i].id
    return {
        "pos_err": np.array(pos_err),
        "vel_err": np.array(vel_err),
        "speed_err": np.array(speed_err),
        "static_speed": np.array(static_speed),
        "switches_per_min": switches / (seconds / 60.0),
        "switches": switches,
    }


def test_paper_d_ground_truth(capsys):
    m = run_paper_d()
    with capsys.disabled():
        print(
            f"\npaper_d: {len(m['pos_err'])} matches; median position error"
            f" {np.median(m['pos_err']) * 100:.1f} cm, median velocity error"
            f" {np.median(m['vel_err']):.3f} m/s, median speed error"
            f" {np.median(m['speed_err']):.3f} m/s; ID switches {m['switches']}"
            f" ({m['switches_per_min']:.1f}/min); static speed max"
            f" {m['static_speed'].max() if len(m['static_speed']) else float('nan'):.3f} m/s"
            f" over {len(m['static_speed'])} frames"
        )
    assert len(m["pos_err"]) > 500
    assert np.median(m["pos_err"]) <= 0.10
    assert np.median(m["vel_err"]) <= 0.15
    assert len(m["static_speed"]) > 50
    assert np.all(m["static_speed"] <= 0.05)


def test_cv_matrices_shape():
    f, q = cv_matrices(0.1, 1.0)
    assert f.shape == q.shape == (4, 4)
    assert np.allclose(q, q.T) and np.all(np.linalg.eigvalsh(q) >= -1e-15)


def test_single_linkage_cut_matches_scipy_fcluster():
    from scipy.cluster.hierarchy import fcluster, linkage

    from runtime.perception.clustering import _cut_single_linkage

    rng = np.random.default_rng(7)
    for _ in range(50):
        centres = rng.uniform(-3, 3, size=(int(rng.integers(2, 80)), 2))
        ours, count = _cut_single_linkage(centres, 0.4)
        ref = fcluster(linkage(centres, method="single"), t=0.4, criterion="distance")
        # same partition (labels may be numbered differently)
        pairs = {(a, b) for a, b in zip(ours, ref)}
        assert len(pairs) == count == len(set(ref))


def test_stacked_kalman_steps_equal_filterpy_s_filter():
    """The tracker predicts and updates all tracks at once; each track's step must be the one
    filterpy's KalmanFilter takes (its predict, its Joseph-form update)."""
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(7)
    n = 6
    x = rng.normal(0.0, 2.0, (n, 4))
    a = rng.normal(0.0, 0.3, (n, 4, 4))
    p = a @ a.transpose(0, 2, 1) + 0.01 * np.eye(4)
    f, q = cv_matrices(0.067, 1.0)
    z = rng.normal(0.0, 2.0, (n, 2))
    r2 = rng.uniform(0.001, 0.05, n)
    xs, ps = cv_predict(x, p, f, q)
    xu, pu = position_update(xs, ps, z, r2)
    h = np.hstack([np.eye(2), np.zeros((2, 2))])
    for i in range(n):
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.x, kf.P, kf.F, kf.Q, kf.H = x[i].reshape(4, 1), p[i].copy(), f, q, h
        kf.predict()
        np.testing.assert_allclose(xs[i], kf.x[:, 0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ps[i], kf.P, rtol=1e-12, atol=1e-12)
        kf.update(z[i].reshape(2, 1), R=np.eye(2) * r2[i])
        np.testing.assert_allclose(xu[i], kf.x[:, 0], rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(pu[i], kf.P, rtol=1e-10, atol=1e-12)
