"""Obstacle points in odom → clusters with a centre, a radius and a measurement noise each
(the tracker's measurements). Pure: no clock, no I/O.

Steps
1. Clustering (`cluster_points`). Points (N, 2) are snapped to a grid of `cluster_distance_m / 4`
   cells (voxel down-sampling; one representative per occupied cell), the occupied cells are
   linked when their centres are within `cluster_distance_m` (single linkage, `scipy.cluster.
   hierarchy`, cut at that distance); each raw point inherits its cell's label.
   Approximation: because cell centres stand in for points, two points up to
   `cluster_distance_m + cell·√2` (≈ 1.35 × the setting) apart may be linked, and two points
   slightly closer than the setting may stay apart. Clusters with fewer than
   `min_cluster_points` raw points are noise; clusters whose extent (bounding-box diagonal in
   the sensor's ray frame) exceeds `max_cluster_size_m` are static structure (walls, shelves)
   and are not tracked.
2. Centre of a cluster (`_arc_centres`). A depth sensor sees only the near side of a person, so
   the centroid of the points lies ~0.6 r in front of the true centre. We fit a circle of known
   radius along the sensor ray instead: in the ray frame of the cluster (t along the ray from the
   sensor through the centroid, s across it) a circle of radius r centred at (D, s0) has its near
   surface at t = D − sqrt(r² − (s − s0)²), so every point gives one estimate
   D_i = t_i + sqrt(r² − (s_i − s0)²); D is their mean over the points with |s − s0| ≤ 0.9 r
   (grazing points are ill-conditioned). s0 is the middle of the cluster's width and
   r = max(half the width, `person_radius_m`). Closed form, vectorised over all clusters.
   Error: with 1 cm range noise and a full visible arc the centre is within ~1 cm for round
   objects; a partially occluded person (width < 2 r) still gets the person radius, so its
   centre error is roughly the error of the radius prior (a 0.25 m person modelled as 0.30 m
   sits 5 cm too deep). Non-round objects (boxes) get a consistent but not "true" centre, which
   moves when the viewpoint moves a lot; the reported disc (centre, r) always touches the seen
   surface from behind. Objects narrower than a person are modelled as person-sized discs
   behind their surface (conservative for the shield). Without a sensor position the plain
   centroid is used.
3. Partly hidden clusters. With the sensor pose given, a cluster is "truncated" when an angular
   edge lies within `occlusion_margin_deg` of the field-of-view edge or inside/beside the span
   of a cluster that is nearer there. A truncated cluster cannot start a track, is gated with the
   plain measurement noise (so it only feeds a track that already agrees with it) and updates
   with a noise inflated by its disc radius. A cluster narrower than its disc gets its noise
   inflated by the missing half-width in both gating and update.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.cluster.hierarchy import linkage

from runtime.geometry import wrap_angles


class ClusterSettings(Protocol):
    """The clustering settings (runtime.perception.tracking.TrackerConfig holds them)."""

    @property
    def cluster_distance_m(self) -> float: ...

    @property
    def min_cluster_points(self) -> int: ...

    @property
    def max_cluster_size_m(self) -> float: ...

    @property
    def person_radius_m(self) -> float: ...

    @property
    def measurement_noise_m(self) -> float: ...

    @property
    def occlusion_margin_deg(self) -> float: ...

    @property
    def field_of_view_deg(self) -> float: ...


@dataclass(frozen=True)
class Clusters:
    """One frame's clusters, odom frame. Only the trackable ones (not noise, not structure)."""

    centres: np.ndarray  # (K, 2) m, arc-corrected centres
    radii: np.ndarray  # (K,) m, disc radius used for the centre
    counts: np.ndarray  # (K,) raw points per cluster
    extents: np.ndarray  # (K,) m, bounding-box diagonal in the ray frame
    n_structure: int = 0  # clusters dropped as too large (static structure)
    noise: np.ndarray | None = None  # (K,) m, measurement std per centre; None = config value
    truncated: np.ndarray | None = None  # (K,) bool: partly hidden (no births); None = none
    gate_noise: np.ndarray | None = None  # (K,) m, std used for gating; None = `noise`

    def __len__(self) -> int:
        return len(self.centres)

    @staticmethod
    def empty() -> Clusters:
        z = np.zeros(0)
        return Clusters(np.zeros((0, 2)), z, np.zeros(0, dtype=int), z, 0)


def _label_points(points: np.ndarray, distance: float) -> tuple[np.ndarray, int]:
    """Connected components of points (grid down-sampled, see module docs): single linkage cut
    at `distance` is exactly the components of the "closer than distance" graph, and for the
    tens of cells a frame has it is cheaper than building a sparse graph."""
    cell = distance / 4.0
    ij = np.floor(points / cell).astype(np.int64)
    # one int64 per cell (row-wise np.unique is several times slower than a 1-D one)
    packed = (ij[:, 0] << 32) + (ij[:, 1] & 0xFFFFFFFF)
    uniq, first, inverse = np.unique(packed, return_index=True, return_inverse=True)
    m = len(uniq)
    if m < 2:
        return inverse, m
    cell_labels, count = _cut_single_linkage((ij[first] + 0.5) * cell, distance)
    return cell_labels[inverse], count


def _cut_single_linkage(centres: np.ndarray, distance: float) -> tuple[np.ndarray, int]:
    """Flat clusters of single linkage cut at `distance`. Its merge heights never decrease, so
    the merges at or below the cut are the first k rows; each point's cluster is its highest
    ancestor among them (scipy's fcluster does the same after validation that costs more than
    the linkage itself at this size)."""
    n = len(centres)
    merges = linkage(centres, method="single")
    k = int(np.searchsorted(merges[:, 2], distance, side="right"))
    parent = np.full(2 * n - 1, -1, dtype=np.intp)
    children = merges[:k, :2].astype(np.intp)
    parent[children[:, 0]] = n + np.arange(k)
    parent[children[:, 1]] = n + np.arange(k)
    root = np.arange(n)
    while True:
        up = parent[root]
        climbing = up >= 0
        if not climbing.any():
            break
        root[climbing] = up[climbing]
    _, labels = np.unique(root, return_inverse=True)
    return labels, int(labels.max()) + 1


def cluster_points(
    points: np.ndarray, config: ClusterSettings, sensor_pose: np.ndarray | None = None
) -> Clusters:
    """Cluster obstacle points (N, 2, odom) and estimate each cluster's centre and radius.

    sensor_pose: the sensor's (x, y) or (x, y, heading) in odom, for the one-sided-arc centre fit
    and the occlusion test (the heading adds the field-of-view edges); None = plain centroids.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        return Clusters.empty()
    labels, n = _label_points(pts, config.cluster_distance_m)
    counts = np.bincount(labels, minlength=n)
    keep = counts >= config.min_cluster_points
    if not np.any(keep):
        return Clusters.empty()
    # renumber the kept clusters 0..K-1 and drop the points of the others
    new_id = np.full(n, -1)
    new_id[keep] = np.arange(int(keep.sum()))
    lab = new_id[labels]
    sel = lab >= 0
    pts, lab = pts[sel], lab[sel]
    counts = counts[keep]
    k = len(counts)
    centroid = (
        np.stack([np.bincount(lab, pts[:, 0], k), np.bincount(lab, pts[:, 1], k)], axis=1)
        / counts[:, None]
    )

    sensor_xy = None if sensor_pose is None else np.asarray(sensor_pose, dtype=float).reshape(-1)
    if sensor_xy is None:
        ray = np.tile([1.0, 0.0], (k, 1))
        origin = np.zeros(2)
    else:
        origin = sensor_xy[:2]
        ray = centroid - origin
        norm = np.hypot(ray[:, 0], ray[:, 1])
        ray = np.where(norm[:, None] > 1e-9, ray / np.maximum(norm, 1e-9)[:, None], [1.0, 0.0])
    rel = pts - origin
    u = ray[lab]
    t_along = rel[:, 0] * u[:, 0] + rel[:, 1] * u[:, 1]
    s_across = -rel[:, 0] * u[:, 1] + rel[:, 1] * u[:, 0]

    order = np.argsort(lab, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    s_sorted, t_sorted = s_across[order], t_along[order]
    s_min = np.minimum.reduceat(s_sorted, starts)
    s_max = np.maximum.reduceat(s_sorted, starts)
    t_min = np.minimum.reduceat(t_sorted, starts)
    t_max = np.maximum.reduceat(t_sorted, starts)
    extents = np.hypot(s_max - s_min, t_max - t_min)

    if sensor_xy is None:
        centres = centroid
        radii = np.maximum(0.5 * extents, 1e-3)
        deficit = np.zeros(k)
    else:
        centres, radii = _arc_centres(
            lab, k, s_across, t_along, s_min, s_max, counts, ray, origin, config.person_radius_m
        )
        # a cluster narrower than its disc (partly occluded, or at the edge of the view) has its
        # centre known only to within the missing width: inflate its measurement noise by it
        deficit = np.maximum(radii - 0.5 * (s_max - s_min), 0.0)
    truncated = np.zeros(k, dtype=bool)
    if sensor_xy is not None:
        truncated = _hidden_edges(lab, order, starts, s_across, t_along, ray, sensor_xy, config)
    gate_noise = np.where(
        truncated, config.measurement_noise_m, np.sqrt(config.measurement_noise_m**2 + deficit**2)
    )
    # the centre of a cut-off cluster is known only to within its disc: it updates a track weakly,
    # and only a track whose prediction already agrees with it (gated with the plain noise above,
    # so a coasting track cannot be dragged onto a half-seen static obstacle)
    deficit = np.where(truncated, np.maximum(deficit, radii), deficit)
    noise = np.sqrt(config.measurement_noise_m**2 + deficit**2)

    small = extents <= config.max_cluster_size_m
    return Clusters(
        centres=centres[small],
        radii=radii[small],
        counts=counts[small],
        extents=extents[small],
        n_structure=int(k - small.sum()),
        noise=noise[small],
        truncated=truncated[small],
        gate_noise=gate_noise[small],
    )


def _hidden_edges(
    lab: np.ndarray,
    order: np.ndarray,
    starts: np.ndarray,
    s: np.ndarray,
    t: np.ndarray,
    ray: np.ndarray,
    sensor: np.ndarray,
    config: ClusterSettings,
) -> np.ndarray:
    """Clusters with an angular edge at the field-of-view edge or next to a nearer cluster's edge
    (a scan sees an occluder's edge right beside the edge of what it hides)."""
    k = len(ray)
    alpha = np.arctan2(s, t)  # bearing of each point relative to its cluster's ray
    rng = np.hypot(s, t)
    a_sorted = alpha[order]
    a_min = np.minimum.reduceat(a_sorted, starts)
    a_max = np.maximum.reduceat(a_sorted, starts)
    r_lo = np.zeros(k)
    r_hi = np.zeros(k)
    i_lo = np.flatnonzero(alpha == a_min[lab])
    i_hi = np.flatnonzero(alpha == a_max[lab])
    r_lo[lab[i_lo]] = rng[i_lo]
    r_hi[lab[i_hi]] = rng[i_hi]
    bearing = np.arctan2(ray[:, 1], ray[:, 0])
    lo, hi = bearing + a_min, bearing + a_max
    margin = math.radians(config.occlusion_margin_deg)
    out = np.zeros(k, dtype=bool)
    if len(sensor) >= 3 and config.field_of_view_deg < 360.0:
        half = 0.5 * math.radians(config.field_of_view_deg)
        out |= wrap_angles(lo - sensor[2]) <= -half + margin
        out |= wrap_angles(hi - sensor[2]) >= half - margin
    if k > 1:
        # i's low edge beside or inside the angular span of a cluster j that is nearer there
        # (edges of near objects jitter by degrees, so "inside" counts too), and the mirror case
        def inside(edge: np.ndarray) -> np.ndarray:
            return (wrap_angles(edge[:, None] - lo[None, :]) >= -margin) & (
                wrap_angles(edge[:, None] - hi[None, :]) <= margin
            )

        low_hidden = inside(lo) & (r_hi[None, :] < r_lo[:, None])
        high_hidden = inside(hi) & (r_lo[None, :] < r_hi[:, None])
        np.fill_diagonal(low_hidden, False)
        np.fill_diagonal(high_hidden, False)
        out |= low_hidden.any(axis=1) | high_hidden.any(axis=1)
    return out


def _arc_centres(
    lab: np.ndarray,
    k: int,
    s: np.ndarray,
    t: np.ndarray,
    s_min: np.ndarray,
    s_max: np.ndarray,
    counts: np.ndarray,
    ray: np.ndarray,
    origin: np.ndarray,
    prior_radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-radius circle fit along each cluster's ray (module docs, step 2)."""
    s0 = 0.5 * (s_min + s_max)
    r = np.maximum(0.5 * (s_max - s_min), prior_radius)
    r = np.maximum(r, 1e-3)
    ds = s - s0[lab]
    rl = r[lab]
    inner = np.abs(ds) <= 0.9 * rl
    d_i = t + np.sqrt(np.maximum(rl * rl - ds * ds, 0.0))
    w = inner.astype(float)
    wsum = np.bincount(lab, w, k)
    dsum = np.bincount(lab, w * d_i, k)
    dall = np.bincount(lab, d_i, k) / counts
    depth = np.where(wsum > 0, dsum / np.maximum(wsum, 1.0), dall)
    perp = np.stack([-ray[:, 1], ray[:, 0]], axis=1)
    centres = origin + ray * depth[:, None] + perp * s0[:, None]
    return centres, r
