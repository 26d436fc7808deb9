"""The DWA's shared preparation, computed once per call: the dynamic window, the sample grid,
the rollouts, the static distance field and the density clusters (the reference implementation
uses the same)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from runtime.planning.dwa.config import DWAConfig
from runtime.safety.limits import LimitsConfig


@dataclass(frozen=True)
class WindowPreparation:
    window: tuple[float, float, float, float]  # v_lo, v_hi, w_lo, w_hi
    steps: int
    times: np.ndarray  # (steps,) t_k = (k+1)·dt
    r_eff: float
    coarse: np.ndarray  # (n_v·n_ω, 2) the coarse grid, v-major
    coarse_x: np.ndarray  # (steps, n_v·n_ω) float32 rollout of the coarse grid
    coarse_y: np.ndarray
    step_lo: np.ndarray  # (steps, 2) box holding step k of every window velocity's rollout
    step_hi: np.ndarray
    origin: tuple[float, float]  # base_link position of the grid's cell (0, 0) corner
    shape: tuple[int, int]  # grid cells along x, y
    dist_grid: np.ndarray | None  # (nx, ny) float32 conservative distance (m) to the nearest point
    clusters: np.ndarray  # (C, 2) static obstacles for density

    def cell_index(self, x: float, y: float, cell: float) -> tuple[int, int]:
        """The grid cell holding (x, y), clamped to the grid (the reference's per-point lookup)."""
        ix = min(max(int((x - self.origin[0]) / cell), 0), self.shape[0] - 1)
        iy = min(max(int((y - self.origin[1]) / cell), 0), self.shape[1] - 1)
        return ix, iy

    def box_distance(self, p: np.ndarray) -> np.ndarray:
        """Distance from points p (..., steps, 2) at each step to that step's rollout box."""
        gap = np.maximum(np.maximum(self.step_lo - p, p - self.step_hi), 0.0)
        return np.hypot(gap[..., 0], gap[..., 1])


def standing_reach(pos: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Tracks' centre distances (T, steps) below which a sample collides: `reach` (radius +
    r_eff), but for a track over the footprint at the first step with the robot standing where
    it is, no more than its distance to the standing robot at each step (module docs)."""
    stand = np.hypot(pos[..., 0], pos[..., 1])
    over = stand[:, :1] < reach[:, :1]
    return np.where(over, np.minimum(reach, stand), reach)


def dynamic_window(cfg: DWAConfig, lim: LimitsConfig, v0: float, w0: float
                   ) -> tuple[float, float, float, float]:
    """Velocities reachable within window_dt, intersected with the velocity box (never empty)."""
    dv_down = (lim.decel_max if v0 > 0 else lim.accel_max) * cfg.window_dt
    dv_up = (lim.accel_max if v0 >= 0 else lim.decel_max) * cfg.window_dt
    v_lo = min(max(v0 - dv_down, lim.v_min), lim.v_max)
    v_hi = min(max(v0 + dv_up, lim.v_min), lim.v_max)
    dw = lim.alpha_max * cfg.window_dt
    w_lo = min(max(w0 - dw, -lim.omega_max), lim.omega_max)
    w_hi = min(max(w0 + dw, -lim.omega_max), lim.omega_max)
    return v_lo, v_hi, w_lo, w_hi


def braking_sample(window: tuple[float, float, float, float]) -> tuple[float, float]:
    """The window's velocity closest to standstill (strongest braking the window allows)."""
    v_lo, v_hi, w_lo, w_hi = window
    return min(max(0.0, v_lo), v_hi), min(max(0.0, w_lo), w_hi)


def grid_spacing(cfg: DWAConfig, window: tuple[float, float, float, float]
                 ) -> tuple[float, float]:
    """Coarse-grid spacing (dv, dω); a single sample along an axis spans the whole window."""
    v_lo, v_hi, w_lo, w_hi = window
    return (v_hi - v_lo) / max(cfg.n_v - 1, 1), (w_hi - w_lo) / max(cfg.n_omega - 1, 1)


def grid_axes(cfg: DWAConfig, window: tuple[float, float, float, float]
              ) -> tuple[np.ndarray, np.ndarray]:
    """The coarse grid's v and ω values (the reference loops over the same)."""
    v_lo, v_hi, w_lo, w_hi = window
    return np.linspace(v_lo, v_hi, cfg.n_v), np.linspace(w_lo, w_hi, cfg.n_omega)


def coarse_samples(vs: np.ndarray, ws: np.ndarray) -> np.ndarray:
    """(n_v·n_ω, 2), v-major order (the reference loops in the same order)."""
    return np.column_stack([np.repeat(vs, len(ws)), np.tile(ws, len(vs))])


def unit_arcs(omegas: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position per unit speed after time t on an arc of rate ω: (sin ωt/ω, (1 − cos ωt)/ω),
    each (steps, n); the straight-line limit where |ω| < 1e-9."""
    th = times[:, None] * omegas
    straight = np.abs(omegas) < 1e-9
    inv = 1.0 / np.where(straight, 1.0, omegas)
    ux = np.where(straight, times[:, None], np.sin(th) * inv)
    uy = np.where(straight, 0.5 * times[:, None] ** 2 * omegas, (1.0 - np.cos(th)) * inv)
    return ux, uy


def rollout(samples: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact unicycle arcs: x, y, θ each (steps, K) (samples along the contiguous axis), in the
    dtype of `times`."""
    v = samples[:, 0].astype(times.dtype)
    w = samples[:, 1].astype(times.dtype)
    ux, uy = unit_arcs(w, times)
    return ux * v, uy * v, times[:, None] * w


def _coarse_rollout(vs: np.ndarray, ux: np.ndarray, uy: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The coarse grid's rollout, float32 (steps, n_v·n_ω), from the unit arcs of its ω values
    (steps, n_ω): the arcs depend on ω only and scale with v, so n_ω arcs are computed, not
    n_v·n_ω."""
    v = vs.astype(np.float32)[None, :, None]
    steps = len(ux)
    ux, uy = ux.astype(np.float32), uy.astype(np.float32)
    return ((ux[:, None, :] * v).reshape(steps, -1), (uy[:, None, :] * v).reshape(steps, -1))


def _step_boxes(cfg: DWAConfig, window: tuple[float, float, float, float], times: np.ndarray,
                ux: np.ndarray, uy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step, an axis-aligned box holding that step's point for EVERY velocity in the window:
    the coarse grid's box (x = v·ux(ω, t) is linear in v, so its extremes over v are at the
    window's ends) grown by how far a window velocity's point can be from the nearest coarse
    sample's (|∂p/∂v| ≤ t, |∂p/∂ω| ≤ |v|·t²/2), plus float32 rounding."""
    dv, dw = grid_spacing(cfg, window)
    grow = times * dv + max(abs(window[0]), abs(window[1])) * times**2 * 0.5 * dw + 1e-4
    ends = np.array([window[0], window[1]], dtype=np.float64)[:, None, None]
    px, py = ends * ux, ends * uy  # (2, steps, n_ω)
    lo = np.stack([px.min(axis=(0, 2)), py.min(axis=(0, 2))], -1) - grow[:, None]
    hi = np.stack([px.max(axis=(0, 2)), py.max(axis=(0, 2))], -1) + grow[:, None]
    return lo, hi


def _distance_grid(points: np.ndarray, lo: np.ndarray, shape: tuple[int, int], cell: float
                   ) -> np.ndarray | None:
    """Conservative distance (m) from each cell to the nearest point: the exact transform of the
    occupied cells minus cell·√2 (a point and a query may each sit anywhere in their cells)."""
    ij = np.floor((points - lo) / cell).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
    ij = ij[inside]
    if not len(ij):
        return None
    free = np.ones(shape, bool)
    free[ij[:, 0], ij[:, 1]] = False  # index [ix, iy]
    # scipy's exact transform, not cv2.distanceTransform: cv2's result depends on its buffers'
    # alignment, and a replay must reproduce every decision bit for bit
    edt = ndimage.distance_transform_edt(free).astype(np.float32)
    edt *= cell
    edt -= cell * math.sqrt(2.0)
    return edt


def _density_clusters(cfg: DWAConfig, points: np.ndarray, reach: float) -> np.ndarray:
    """Static points within reach + range, one obstacle per occupied density cell (at its
    points' mean), at most density_max_static of them, the nearest first kept."""
    near = (points * points).sum(axis=1) <= (reach + cfg.density_range_m + cfg.density_cell_m)**2
    p = points[near]
    if not len(p):
        return np.zeros((0, 2))
    cij = np.floor(p / cfg.density_cell_m).astype(np.int64)
    packed = (cij[:, 0] << 32) + (cij[:, 1] & 0xFFFFFFFF)
    _, inv, counts = np.unique(packed, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    clusters = np.stack([np.bincount(inv, p[:, 0], len(counts)),
                         np.bincount(inv, p[:, 1], len(counts))], axis=-1) / counts[:, None]
    if len(clusters) > cfg.density_max_static:
        r2 = (clusters * clusters).sum(axis=1)
        clusters = clusters[np.sort(np.argsort(r2, kind="stable")[: cfg.density_max_static])]
    return clusters


def prepare(cfg: DWAConfig, lim: LimitsConfig, v0: float, w0: float, points: np.ndarray
            ) -> WindowPreparation:
    window = dynamic_window(cfg, lim, v0, w0)
    steps = max(1, round(cfg.horizon_s / cfg.dt))
    times = (np.arange(steps) + 1) * cfg.dt
    r_eff = cfg.robot_radius_m + cfg.safety_margin_m
    cell = cfg.grid_cell_m
    vs, ws = grid_axes(cfg, window)
    ux, uy = unit_arcs(ws, times)
    cx, cy = _coarse_rollout(vs, ux, uy)
    step_lo, step_hi = _step_boxes(cfg, window, times, ux, uy)
    # every point within clearance_cap + r_eff of any rollout point falls inside the grid, so
    # the capped clearance never misses one
    margin = cfg.clearance_cap_m + r_eff + 2.0 * cell
    lo = step_lo.min(axis=0) - margin
    hi = step_hi.max(axis=0) + margin
    shape = (math.ceil((hi[0] - lo[0]) / cell), math.ceil((hi[1] - lo[1]) / cell))
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    dist_grid = _distance_grid(pts, lo, shape, cell) if len(pts) else None
    reach = max(abs(window[0]), abs(window[1])) * float(times[-1])
    clusters = _density_clusters(cfg, pts, reach) if len(pts) else np.zeros((0, 2))
    return WindowPreparation(window, steps, times, r_eff, coarse_samples(vs, ws), cx, cy, step_lo,
                    step_hi, (float(lo[0]), float(lo[1])), shape, dist_grid, clusters)
