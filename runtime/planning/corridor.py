"""Safe corridor along the best DWA path (the paper's Ω; pure: no clock, no I/O).

K samples are taken at equal arc length along the path (steps, 3) of (x, y, θ) in base_link
(first and last row included). At each sample s with heading θ (interpolated from the path) the
normal line Φ runs along n = (-sin θ, cos θ) (left positive). The free width on each side is the
distance from s along ±n to the nearest obstacle boundary, capped at `max_width`:

- an obstacle is a disc (centre q, radius r): static points with r = `point_radius`, tracks with
  their radius (+ `track_inflation`) at the time the robot reaches the sample;
- the normal line is a strip of half-width `band` (so sparse points are not missed); with
  a = (q - s)·n (along the normal) and c = (q - s)·t (along the path), the disc meets the strip
  iff |c| <= r + band, and then its extent along the normal is a ± e with
  e = sqrt(r² - max(|c| - band, 0)²);
- left  = min over meeting discs with a + e >= 0 of max(a - e, 0);
  right = min over meeting discs with a - e <= 0 of max(-a - e, 0)
  (a disc straddling or touching the sample, or a point on it, closes both sides: width 0).
So two walls of points at ±w/2 from a straight path give left = right = w/2 - point_radius.

Track positions are given per path row (T, steps, 2) (or (T, 1, 2) for static tracks); the time
the robot reaches sample k is taken as the first path row whose arc length is >= the sample's.
The polygon Ω is the convex hull (counter-clockwise vertices) of the 2K boundary points
s ± width·n; if they are degenerate (fewer than 3 distinct or collinear) Ω is the distinct
boundary points themselves. A path of zero length gives K copies of its start.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from runtime.config.schema import setting


@dataclass(frozen=True)
class CorridorConfig:
    samples: int = setting(10, "sample points K along the path (normal lines)", min=1, max=1000)
    max_width: float = setting(1.5, "free width per side is capped at this", "m", min=0.0, max=20.0)
    band: float = setting(0.05, "half-width of the strip around each normal line", "m",
                          min=0.0, max=1.0)
    point_radius: float = setting(0.0, "radius given to each static obstacle point", "m",
                                  min=0.0, max=1.0)
    track_inflation: float = setting(0.0, "added to each track's radius", "m", min=0.0, max=2.0)


@dataclass(frozen=True)
class Corridor:
    left: np.ndarray  # (K,) free width to the left of each sample, m
    right: np.ndarray  # (K,) free width to the right, m
    samples: np.ndarray  # (K, 3) x, y, θ of the samples
    polygon: np.ndarray  # (P, 2) Ω's vertices, counter-clockwise


def _sample_path(path: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """K samples at equal arc length (K, 3) and the path row index reached at each (K,)."""
    xy = path[:, :2]
    seg = np.hypot(*np.diff(xy, axis=0).T) if len(path) > 1 else np.zeros(0)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    length = float(s[-1])
    if length <= 1e-12:
        return np.repeat(path[:1], k, axis=0), np.zeros(k, dtype=int)
    target = np.linspace(0.0, length, k)
    x = np.interp(target, s, xy[:, 0])
    y = np.interp(target, s, xy[:, 1])
    # heading: interpolate the unwrapped θ over arc length (rows at the same arc length keep the
    # first one's heading, as np.interp does with repeated abscissae)
    th = np.interp(target, s, np.unwrap(path[:, 2]))
    row = np.minimum(np.searchsorted(s, target - 1e-12, side="left"), len(path) - 1)
    return np.stack([x, y, th], axis=1), row


def _widths(samples: np.ndarray, centres: np.ndarray, radii: np.ndarray, band: float,
            cap: float) -> tuple[np.ndarray, np.ndarray]:
    """Left/right free width per sample (K,) for discs with centres (N, 2) (the same for every
    sample) or (K, N, 2) (per sample), radii (N,) or (K, N). Only the few discs that meet a
    strip get the extent computation."""
    k = len(samples)
    left = np.full(k, cap)
    right = np.full(k, cap)
    if centres.shape[-2] == 0:
        return left, right
    th = samples[:, 2]
    t = np.stack([np.cos(th), np.sin(th)], axis=1)  # (K, 2)
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    s_t = (samples[:, :2] * t).sum(axis=1)
    s_n = (samples[:, :2] * n).sum(axis=1)
    if centres.ndim == 2:  # (q − s)·t for all pairs as one (K, 2) × (2, N) product
        along = t @ centres.T - s_t[:, None]
    else:
        along = np.einsum("knd,kd->kn", centres, t) - s_t[:, None]
    c = np.abs(along)
    r = np.broadcast_to(radii, c.shape)
    kk, nn = np.nonzero(c <= r + band)
    if not len(kk):
        return left, right
    q = centres[nn] if centres.ndim == 2 else centres[kk, nn]
    a = (q * n[kk]).sum(axis=1) - s_n[kk]
    rm = r[kk, nn]
    e = np.sqrt(np.maximum(rm**2 - np.maximum(c[kk, nn] - band, 0.0) ** 2, 0.0))
    np.minimum.at(left, kk, np.where(a + e >= 0, np.maximum(a - e, 0.0), np.inf))
    np.minimum.at(right, kk, np.where(a - e <= 0, np.maximum(-a - e, 0.0), np.inf))
    return left, right


def safe_corridor(path: np.ndarray, points: np.ndarray, track_positions: np.ndarray | None,
                  track_radii: np.ndarray | None, cfg: CorridorConfig) -> Corridor:
    """The safe corridor along `path` (steps, 3) given static points (M, 2) and tracks'
    predicted centres (T, steps | 1, 2) with radii (T,), all in base_link."""
    path = np.asarray(path, dtype=float).reshape(-1, 3)
    if len(path) == 0:
        raise ValueError("safe_corridor needs a path with at least one row")
    samples, row = _sample_path(path, cfg.samples)
    cap = cfg.max_width
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    # static points: only those that can reach a strip of any sample within the cap
    if len(pts):
        lo = samples[:, :2].min(axis=0) - cap - cfg.band - cfg.point_radius
        hi = samples[:, :2].max(axis=0) + cap + cfg.band + cfg.point_radius
        pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    left, right = _widths(samples, pts, np.full(len(pts), cfg.point_radius), cfg.band, cap)
    if track_positions is not None and len(track_positions):
        tp = np.asarray(track_positions, dtype=float)
        tp = tp[:, np.minimum(row, tp.shape[1] - 1)]  # (T, K, 2)
        tr = np.asarray(track_radii, dtype=float).reshape(-1) + cfg.track_inflation
        lt, rt = _widths(samples, tp.transpose(1, 0, 2), tr[None, :], cfg.band, cap)
        left, right = np.minimum(left, lt), np.minimum(right, rt)
    n = np.stack([-np.sin(samples[:, 2]), np.cos(samples[:, 2])], axis=1)
    bl = samples[:, :2] + left[:, None] * n
    br = samples[:, :2] - right[:, None] * n
    boundary = np.concatenate([bl, br[::-1]])
    return Corridor(left, right, samples, _hull(boundary))


def _hull(pts: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (OpenCV's, y up); the distinct points if degenerate."""
    idx = cv2.convexHull(pts.astype(np.float32), clockwise=False, returnPoints=False)
    hull = pts[idx.ravel()] if idx is not None else pts[:0]  # None: OpenCV found no hull
    if len(hull) >= 3:
        x, y = hull[:, 0], hull[:, 1]
        if 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) > 1e-12:
            return hull
    _, first = np.unique(np.round(pts, 12), axis=0, return_index=True)
    return pts[np.sort(first)]
