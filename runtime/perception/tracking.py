"""Obstacle tracker: one frame's clusters (runtime.perception.clustering) → tracks with
velocity.

Pure stage: no clock, no I/O. Time is passed in (`update(..., t)`), the tracker keeps its own
state between calls (like the odometry filter).

Per frame (`update`: clustering first, whose settings are in this config section too)
1. Per-track constant-velocity Kalman filter (x = [x, y, vx, vy]), Q from the
   white-acceleration model for this frame's dt, all tracks predicted and updated at once as
   stacked numpy arrays (the equations of filterpy's `KalmanFilter`, Joseph-form update; one
   filterpy object per track cost tens of microseconds each in Python overhead, most of the
   tracker's time with twenty people).
2. Gated assignment: Mahalanobis d² = yᵀ S⁻¹ y with S = H P Hᵀ + R_j (R_j per cluster: a partly
   hidden cluster's is inflated, see clustering), plus a plausibility gate (the cluster may be no farther from the track's last hit than
   `max_speed_m_s` × time since + 3σ); gated pairs get a large finite cost (never NaN/inf),
   cost = d² + ln det S otherwise, `linear_sum_assignment` on the rectangular matrix, and gated
   pairs are dropped afterwards. Velocities above `max_speed_m_s` are clamped after update.
3. Births from unassigned clusters (tentative; confirmed after `birth_hits` hits; a tentative
   track dies at its first miss), deaths after `death_misses` consecutive misses or
   `death_unseen_s` without a hit. A confirmed track predicted (partly) outside the field of
   view is not missed — not seeing it there is no evidence it is gone — and coasts on its
   prediction (`coasting`) until `coast_out_of_view_s` after its last hit, so the planner keeps
   avoiding a person who walked out of the 87° view; past `death_unseen_s` it is no longer
   matched to clusters (a returning person starts a new track).
4. Stationarity: a track whose velocity is not significantly different from zero
   (vᵀ P_vv⁻¹ v < `stationary_chi2`, or |v| < `stationary_speed_m_s`) reports velocity 0 and is
   predicted as standing still, so static clutter gets no phantom velocity. The filter state
   keeps its estimate, so a person starting to walk is reported moving as soon as the test says
   so (a few frames).

Ideas follow the usual SORT-style tracker (GPL-3 code not used).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from runtime.config.schema import setting
from runtime.perception.clustering import Clusters, cluster_points

GATED_COST = 1.0e6  # finite stand-in for "not allowed"; pairs with it are dropped after solving


@dataclass(frozen=True)
class TrackerConfig:
    cluster_distance_m: float = setting(
        0.15,
        "points closer than this belong to the same cluster (grid-approximated, see docs)",
        "m",
        min=0.01,
        max=1.0,
    )
    min_cluster_points: int = setting(
        3, "clusters with fewer points are noise and ignored", min=1, max=10000
    )
    max_cluster_size_m: float = setting(
        1.0,
        "clusters wider than this (bounding-box diagonal) are static structure, e.g. walls,"
        " and are not tracked",
        "m",
        min=0.1,
        max=20.0,
    )
    person_radius_m: float = setting(
        0.3,
        "radius prior for centring one-sided arcs: a cluster is modelled as a disc of"
        " max(half its width, this) behind its visible surface",
        "m",
        min=0.0,
        max=2.0,
    )
    gate_chi2: float = setting(
        9.21,
        "association gate on the Mahalanobis distance squared (chi-square, 2 dof:"
        " 5.99 = 95 %, 9.21 = 99 %)",
        min=0.1,
        max=100.0,
    )
    accel_noise_m_s2: float = setting(
        1.0,
        "process noise: standard deviation of the white acceleration of a tracked object",
        "m/s^2",
        min=0.0,
        min_exclusive=True,
        max=50.0,
    )
    measurement_noise_m: float = setting(
        0.05, "standard deviation of a cluster centre measurement", "m", min=0.001, max=2.0
    )
    initial_speed_sigma_m_s: float = setting(
        1.0,
        "standard deviation of the velocity of a newborn track (its velocity starts at 0)",
        "m/s",
        min=0.01,
        max=10.0,
    )
    birth_hits: int = setting(
        3, "a tentative track is confirmed after this many hits", min=1, max=100
    )
    death_misses: int = setting(
        15,
        "a confirmed track is deleted after this many consecutive frames without a hit"
        " (a tentative one at its first miss)",
        min=1,
        max=1000,
    )
    death_unseen_s: float = setting(
        1.0,
        "a track is deleted after this long without a hit, whatever the frame count",
        "s",
        min=0.0,
        min_exclusive=True,
        max=60.0,
    )
    coast_out_of_view_s: float = setting(
        3.0,
        "a confirmed track predicted outside the field of view is not missed (it cannot be"
        " seen): it coasts on its prediction, with growing uncertainty, until this long after"
        " its last hit (with the sensor pose and heading given); past death_unseen_s it is no"
        " longer matched to clusters, only predicted",
        "s",
        min=0.0,
        max=60.0,
    )
    max_speed_m_s: float = setting(
        2.0,
        "plausible top speed of a tracked object; faster velocity estimates are clamped",
        "m/s",
        min=0.1,
        max=20.0,
    )
    stationary_chi2: float = setting(
        5.99,
        "a track whose velocity v has vᵀ P_vv⁻¹ v below this (chi-square, 2 dof) is reported"
        " as standing still (velocity 0)",
        min=0.0,
        max=100.0,
    )
    stationary_speed_m_s: float = setting(
        0.05,
        "a track slower than this is always reported as standing still",
        "m/s",
        min=0.0,
        max=1.0,
    )
    field_of_view_deg: float = setting(
        87.0,
        "horizontal field of view of the points fed in (when the sensor pose is given): a"
        " cluster touching its edge is cut off; 360 = points from all around (no edges)",
        "deg",
        min=1.0,
        max=360.0,
    )
    occlusion_margin_deg: float = setting(
        1.5,
        "a cluster whose angular edge lies this close to the field-of-view edge, or to the edge"
        " of a nearer cluster, is partly hidden: its centre gets a large uncertainty and it"
        " cannot start a track",
        "deg",
        min=0.0,
        max=20.0,
    )
    radius_smoothing: float = setting(
        0.3,
        "weight of a new measurement in the track's radius (exponential smoothing)",
        min=0.0,
        min_exclusive=True,
        max=1.0,
    )


@dataclass(frozen=True)
class Track:
    """A tracked object at a time. velocity is 0 when the stationarity test says so."""

    id: int
    position: np.ndarray  # (2,) m, odom
    velocity: np.ndarray  # (2,) m/s, odom
    radius: float  # m
    covariance: np.ndarray  # (4, 4) over [x, y, vx, vy]
    age: float  # s since birth
    hits: int
    confirmed: bool
    misses: int = 0  # consecutive frames without a hit
    stationary: bool = False
    coasting: bool = False  # unseen and predicted outside the field of view (not a miss)


# --- tracking --------------------------------------------------------------------------------------


def cv_matrices(dt: float, accel_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity F and white-acceleration Q for a step dt (per axis: q·[[dt⁴/4, dt³/2],
    [dt³/2, dt²]], i.e. the piecewise-constant white acceleration model)."""
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    q2 = accel_sigma * accel_sigma
    a, b, c = 0.25 * dt**4 * q2, 0.5 * dt**3 * q2, dt * dt * q2
    q = np.array([[a, 0.0, b, 0.0], [0.0, a, 0.0, b], [b, 0.0, c, 0.0], [0.0, b, 0.0, c]])
    return f, q


def cv_predict(x: np.ndarray, p: np.ndarray, f: np.ndarray, q: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Every track's prediction at once: x (T, 4), P (T, 4, 4) → F x, F P Fᵀ + Q."""
    return x @ f.T, f @ p @ f.T + q


def position_update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r2: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """K tracks' Kalman update by position measurements z (K, 2) of variance r2 (K,) per axis
    (H = [I 0]), in Joseph form, P = (I - KH) P (I - KH)ᵀ + K R Kᵀ, which keeps P symmetric and
    positive where the short form loses it to rounding (filterpy's choice too)."""
    s = p[:, :2, :2] + r2[:, None, None] * np.eye(2)
    a, b, c = s[:, 0, 0], s[:, 0, 1], s[:, 1, 1]  # S is symmetric: its inverse in closed form
    det = a * c - b * b
    s_inv = np.stack([np.stack([c, -b], -1), np.stack([-b, a], -1)], -2) / det[:, None, None]
    k = p[:, :, :2] @ s_inv  # (K, 4, 2)
    x = x + (k @ (z - x[:, :2])[..., None])[..., 0]
    ikh = np.broadcast_to(np.eye(4), p.shape).copy()
    ikh[:, :, :2] -= k
    p = ikh @ p @ ikh.transpose(0, 2, 1) + r2[:, None, None] * (k @ k.transpose(0, 2, 1))
    return x, p


class _TrackState:
    __slots__ = ("born", "coasting", "confirmed", "hits", "id", "last_hit", "last_z", "misses", "p",
                 "radius", "x")

    def __init__(self, tid: int, x: np.ndarray, p: np.ndarray, radius: float, t: float) -> None:
        self.id = tid
        self.x = x  # (4,) [x, y, vx, vy]
        self.p = p  # (4, 4) its covariance
        self.radius = radius
        self.born = t
        self.last_hit = t
        self.last_z = np.array(x[:2], dtype=float)
        self.hits = 1
        self.misses = 0
        self.confirmed = False
        self.coasting = False


class Tracker:
    """Multi-object tracker (stateful, pure: time comes in with each call)."""

    def __init__(self, config: TrackerConfig = TrackerConfig()) -> None:
        self.config = config
        self._tracks: list[_TrackState] = []
        self._next_id = 1
        self._t: float | None = None
        self.last_costs: np.ndarray = np.zeros((0, 0))  # the last cost matrix (for tests/bench)

    # --- public --------------------------------------------------------------------------------

    def update(
        self,
        measurement: Clusters | np.ndarray,
        t: float,
        sensor_pose: np.ndarray | None = None,
    ) -> list[Track]:
        """One frame at time t: clusters (or raw points (N, 2) in odom, clustered here with the
        sensor pose (x, y[, heading]) for the arc fit and occlusion test) → all tracks
        (tentative ones have confirmed=False)."""
        if isinstance(measurement, Clusters):
            clusters = measurement
        else:
            clusters = cluster_points(measurement, self.config, sensor_pose)
        cfg = self.config
        if self._t is not None and t < self._t:
            raise ValueError(f"tracker time went backwards: {t} < {self._t}")
        dt = 0.0 if self._t is None else t - self._t
        self._t = t

        if dt > 0.0 and self._tracks:
            f, q = cv_matrices(dt, cfg.accel_noise_m_s2)
            xs, ps = cv_predict(np.array([tr.x for tr in self._tracks]),
                                np.array([tr.p for tr in self._tracks]), f, q)
            for tr, x, p in zip(self._tracks, xs, ps):
                tr.x, tr.p = x, p

        z = clusters.centres
        sig2 = (
            np.full(len(z), cfg.measurement_noise_m**2)
            if clusters.noise is None
            else np.asarray(clusters.noise, dtype=float) ** 2
        )
        gate2 = sig2 if clusters.gate_noise is None else np.asarray(clusters.gate_noise) ** 2
        rows, cols = self._associate(z, gate2, t)
        assigned_t = np.zeros(len(self._tracks), dtype=bool)
        assigned_c = np.zeros(len(z), dtype=bool)
        if len(rows):
            xs, ps = position_update(np.array([self._tracks[i].x for i in rows]),
                                     np.array([self._tracks[i].p for i in rows]), z[cols],
                                     sig2[cols])
            for i, x, p in zip(rows, xs, ps):
                self._tracks[i].x, self._tracks[i].p = x, p
                self._clamp_speed(x)
        for i, j in zip(rows, cols):
            tr = self._tracks[i]
            a = cfg.radius_smoothing
            tr.radius = (1.0 - a) * tr.radius + a * float(clusters.radii[j])
            tr.hits += 1
            tr.misses = 0
            tr.coasting = False
            tr.last_hit = t
            tr.last_z = z[j].copy()
            if tr.hits >= cfg.birth_hits:
                tr.confirmed = True
            assigned_t[i] = True
            assigned_c[j] = True

        survivors = []
        for i, tr in enumerate(self._tracks):
            if not assigned_t[i]:
                tr.coasting = tr.confirmed and self._out_of_view(tr, sensor_pose)
                if tr.coasting:
                    if t - tr.last_hit < cfg.coast_out_of_view_s:
                        survivors.append(tr)
                    continue
                tr.misses += 1
                if not tr.confirmed:
                    continue
                if tr.misses >= cfg.death_misses or t - tr.last_hit >= cfg.death_unseen_s:
                    continue
            survivors.append(tr)
        can_birth = ~assigned_c
        if clusters.truncated is not None:
            can_birth &= ~np.asarray(clusters.truncated, dtype=bool)
        for j in np.flatnonzero(can_birth):
            survivors.append(self._birth(z[j], float(clusters.radii[j]), t))
        self._tracks = survivors
        return [self._export(tr, tr.x, tr.p, t) for tr in self._tracks]

    def _out_of_view(self, tr: _TrackState, sensor_pose: np.ndarray | None) -> bool:
        """Is any part of the track's disc outside the sensor's horizontal field of view (so
        not seeing it is no evidence that it is gone)? Needs the pose with its heading."""
        half = 0.5 * math.radians(self.config.field_of_view_deg)
        if sensor_pose is None or len(sensor_pose) < 3 or half >= math.pi:
            return False
        dx = float(tr.x[0]) - float(sensor_pose[0])
        dy = float(tr.x[1]) - float(sensor_pose[1])
        d = math.hypot(dx, dy)
        if d <= tr.radius:
            return True  # the sensor is inside the disc: too close to be seen whole
        bearing = abs(math.remainder(math.atan2(dy, dx) - float(sensor_pose[2]), math.tau))
        return bearing + math.asin(min(1.0, tr.radius / d)) > half

    # --- internals -----------------------------------------------------------------------------

    def _associate(
        self, z: np.ndarray, sig2: np.ndarray, t: float
    ) -> tuple[np.ndarray, np.ndarray]:
        nt, nz = len(self._tracks), len(z)
        if nt == 0 or nz == 0:
            self.last_costs = np.zeros((nt, nz))
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
        xs = np.array([tr.x[:2] for tr in self._tracks])  # (T, 2)
        ps = np.array([tr.p[:2, :2] for tr in self._tracks])  # (T, 2, 2)
        # S = H P Hᵀ + R_j for every pair (T, Z); R_j = sig2_j I
        a = ps[:, 0, 0, None] + sig2[None, :]
        c = ps[:, 1, 1, None] + sig2[None, :]
        b = np.broadcast_to(ps[:, 0, 1, None], a.shape)
        det = np.maximum(a * c - b * b, 1e-12)
        y = z[None, :, :] - xs[:, None, :]  # (T, Z, 2)
        d2 = (c * y[..., 0] ** 2 - 2 * b * y[..., 0] * y[..., 1] + a * y[..., 1] ** 2) / det
        gated = ~(d2 <= self.config.gate_chi2)  # NaN-safe: NaN counts as gated
        # plausibility: no track may jump from where it was last seen faster than max_speed
        # (a coasting track's covariance grows enough to swallow a nearby static obstacle)
        last = np.array([tr.last_z for tr in self._tracks])
        since = np.array([t - tr.last_hit for tr in self._tracks])
        jump = np.hypot(*(z[None, :, :] - last[:, None, :]).transpose(2, 0, 1))
        reach = self.config.max_speed_m_s * since[:, None] + 3.0 * np.sqrt(
            sig2[None, :] + self.config.measurement_noise_m**2
        )
        gated |= ~(jump <= reach)
        # a track kept alive only by coasting out of view (unseen longer than death_unseen_s) is
        # a prediction for the planner, not a hypothesis to match: its covariance has grown
        # enough to claim a static obstacle's cluster; a returning person gets a new track
        gated[since > self.config.death_unseen_s] = True
        # cost: d² plus log det S (the negative log-likelihood, up to constants), so a track
        # with a tight covariance is preferred over a vague one at the same d²
        cost = d2 + np.log(det)
        cost = np.where(gated, GATED_COST, cost)
        self.last_costs = cost
        rows, cols = linear_sum_assignment(cost)
        ok = ~gated[rows, cols]
        return rows[ok], cols[ok]

    def _birth(self, z: np.ndarray, radius: float, t: float) -> _TrackState:
        cfg = self.config
        p = np.diag([cfg.measurement_noise_m**2] * 2 + [cfg.initial_speed_sigma_m_s**2] * 2)
        tr = _TrackState(self._next_id, np.array([z[0], z[1], 0.0, 0.0], dtype=float), p,
                         radius, t)
        if cfg.birth_hits <= 1:
            tr.confirmed = True
        self._next_id += 1
        return tr

    def _clamp_speed(self, x: np.ndarray) -> None:
        v = x[2:]
        speed = math.hypot(v[0], v[1])
        if speed > self.config.max_speed_m_s:
            x[2:] = v * (self.config.max_speed_m_s / speed)

    def _is_stationary(self, x: np.ndarray, p: np.ndarray) -> bool:
        vx, vy = float(x[2]), float(x[3])
        if math.hypot(vx, vy) < self.config.stationary_speed_m_s:
            return True
        a, b, c = p[2, 2], p[2, 3], p[3, 3]
        det = a * c - b * b
        if det <= 1e-18:
            return False
        d2 = (c * vx * vx - 2 * b * vx * vy + a * vy * vy) / det
        return bool(d2 < self.config.stationary_chi2)

    def _export(self, tr: _TrackState, x: np.ndarray, p: np.ndarray, t: float) -> Track:
        stationary = self._is_stationary(x, p)
        vel = np.zeros(2) if stationary else np.array(x[2:4], dtype=float)
        return Track(
            id=tr.id,
            position=np.array(x[:2], dtype=float),
            velocity=vel,
            radius=float(tr.radius),
            covariance=np.array(p, dtype=float),
            age=float(t - tr.born),
            hits=tr.hits,
            confirmed=tr.confirmed,
            misses=tr.misses,
            stationary=stationary,
            coasting=tr.coasting,
        )
