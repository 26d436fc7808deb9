"""Dynamic-window local planner with the SafeMove-RL cost, vectorised and anytime.

Frame and time: everything is in base_link at the current time (robot at the origin, heading 0).
Rollout step k (k = 0..steps-1) is the pose at t_k = (k+1)·dt under constant (v, ω) (exact
unicycle arc). Dynamic obstacles come as positions predicted at the SAME times: (T, steps, 2)
centres and (T, steps) radii that already include the growing uncertainty (the planning step
builds them with `planning_step.predict_tracks_base`: constant velocity, radius = track radius
+ min(k_sigma·std, cap)).

Cost (maximised): G = α·heading + β·clearance + γ·velocity − δ·density, each term divided by a
fixed scale σ (`term_scales`: π, clearance_cap_m, the top speed, density_scale), so the weights
mean the same in every window. Normalising over the evaluated samples instead (min–max, or by
the largest) stretches differences of millimetres across a narrow dynamic window until they
outvote everything: it kept the robot creeping at a few cm/s toward anything within the
clearance cap. Raw terms of one sample:
- heading   = π − |angle from the final heading to the goal seen from the final position| ∈ [0, π]
- clearance = clip(min over steps of the gap, 0, clearance_cap); gap = distance to the nearest
  static point − R, and to each track's centre at the same step − its radius − R, with
  R = robot_radius + safety_margin (so gap < 0 is a collision)
- velocity  = v
- density   = N_obs / max(avg_distance, density_min_avg_m): N_obs = obstacles near the
  trajectory, counted softly: one whose closest approach is c counts w = max(0, 1 − c/range)
  (range = density_range_m); avg_distance = the w-weighted mean over obstacles of their mean
  centre distance over all steps. (A hard count jumps by one where an obstacle enters the
  range; with a narrow window that step outweighed the velocity term and parked the robot at
  the range's edge.) Obstacles for density: each track (at its step-k position) and the static
  points clustered on a density_cell_m grid (one obstacle per occupied cell, at its points'
  mean; cells out of reach + range are dropped).
Admissible (Fox et al.): the sample can stop before its first colliding step:
v² ≤ 2·decel_max·s_free, s_free = |v|·(time of the last step before the first collision).
A collision later than that only lowers the clearance term.
An obstacle that already overlaps the footprint with the robot standing where it is (a person
who stepped up beside it, a wall the robot was pushed near) would make every moving sample
collide at once and freeze the robot beside it, moving away included; as in the shield, it
collides only where a sample brings it closer than it comes to the robot standing still: a
track over the footprint at the first step, where its centre is nearer the standing robot than
its reach (its disc grows, or it walks in); the static distance field, below its value at the
robot (the field holds the nearest point only, so while the robot overlaps one point the others
get the same allowance; the shield checks points one by one).

Static clearance comes from a distance transform of an occupancy grid (grid_cell_m) built once
per call over the region the window's rollouts can reach plus the clearance reach; the
looked-up distance is reduced by cell·√2, so up to clearance_cap + R it is a lower bound on the
exact distance and at most 2·cell·√2 below it (tested).

Speed: float32 in the hot part; obstacles that cannot matter (farther than the density range,
and for tracks also than the clearance reach, from every step's rollout box) are dropped
exactly; the rest are processed in cache-sized groups (see `_Evaluator`).

Budget (the stage is pure, no clock reads of its own): the caller passes an absolute `deadline`
and the clock `now` it is measured on (the loop: `deadline=time.monotonic() + cfg.budget_s,
now=time.monotonic`; tests: a fake clock). The coarse grid is evaluated in interleaved blocks of
block_samples (every prefix of blocks spans the whole window); the first block always runs, each
further block and each refinement round (a finer n×n grid around the current best, half the
spacing each round, up to refine_max_rounds) only while the slowest such step so far would end
by the deadline. With `now=None` only the counts bound the work (deterministic). If no sample is
admissible the result is the strongest braking sample in the window with admissible_best False.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from runtime.budget import TimeBudget
from runtime.config.schema import derived, setting
from runtime.geometry import wrap_angles
from runtime.safety.limits import LimitsConfig


@dataclass(frozen=True)
class DWAConfig:
    horizon_s: float = setting(3.0, "rollout horizon of each sample", "s", min=0.1, max=10.0)
    dt: float = setting(0.1, "rollout step (obstacle predictions use the same steps)", "s",
                        min=0.01, max=1.0)
    window_dt: float = derived(0.05, "dynamic window: reachable velocities within this time",
                               "loop.control_hz", "s")
    n_v: int = setting(20, "coarse grid: linear velocity samples", min=1, max=200)
    n_omega: int = setting(20, "coarse grid: angular velocity samples", min=1, max=200)
    refine_n: int = setting(5, "refinement: n×n samples around the best per round (odd)",
                            min=3, max=15)
    refine_max_rounds: int = setting(8, "refinement: most rounds per call", min=0, max=50)
    weight_heading: float = setting(1.0, "α: weight of the heading term", min=0.0)
    weight_clearance: float = setting(1.0, "β: weight of the clearance term", min=0.0)
    weight_velocity: float = setting(2.0, "γ: weight of the velocity term", min=0.0)
    weight_density: float = setting(0.2, "δ: weight of the density penalty", min=0.0)
    density_range_m: float = setting(1.0, "an obstacle counts for density within this distance"
                                     " (fully at 0, fading linearly to 0 at this distance)"
                                     " of the trajectory", "m", min=0.0, max=10.0)
    density_cell_m: float = setting(0.5, "static points are clustered into obstacles on this grid"
                                    " for the density term", "m", min=0.05, max=5.0)
    density_scale: float = setting(4.0, "σ of the density term: the density that counts as 1"
                                   " (e.g. two obstacles at an average 0.5 m)", "1/m",
                                   min=0.001, max=1000.0)
    density_max_static: int = setting(16, "at most this many static clusters (the nearest to the"
                                      " robot) count for density (bounds the cost)", min=0)
    density_min_avg_m: float = setting(0.1, "floor of the average distance in density", "m",
                                       min=0.001, max=5.0)
    robot_radius_m: float = derived(0.17, "robot footprint radius", "robot.radius_m", "m")
    safety_margin_m: float = setting(0.05, "extra clearance kept from every obstacle", "m",
                                     min=0.0, max=2.0)
    track_k_sigma: float = setting(2.0, "a track's predicted disc grows by this many standard"
                                   " deviations of its predicted position", min=0.0, max=10.0)
    track_inflation_cap_m: float = setting(
        0.5, "at most this much is added to a track's radius for prediction uncertainty (the"
        " shield keeps its own, uncapped, over its short horizon)", "m", min=0.0, max=10.0)
    clearance_cap_m: float = setting(0.5, "clearance term saturates here", "m", min=0.01,
                                     max=5.0)
    grid_cell_m: float = setting(0.03, "cell of the static distance-transform grid", "m",
                                 min=0.005, max=0.2)
    budget_s: float = setting(0.004, "stage budget: refinement stops by this time", "s",
                              min=0.0, max=1.0)
    block_samples: int = setting(400, "the coarse grid is evaluated in interleaved blocks of this"
                                 " many samples; the deadline is checked between blocks", min=1)
    chunk_elems: int = setting(100_000, "obstacles×steps×samples per vectorised group (keeps each"
                               " group's float32 distances in cache)", min=1000)


@dataclass(frozen=True)
class DWAResult:
    samples: np.ndarray  # (K, 2) [v, ω] in evaluation order (coarse first)
    heading: np.ndarray  # (K,) terms divided by their scale σ (term_scales)
    clearance: np.ndarray
    velocity: np.ndarray
    density: np.ndarray
    total: np.ndarray  # (K,) G, maximised
    admissible: np.ndarray  # (K,) bool
    raw: dict[str, np.ndarray]  # un-normalised terms (heading, clearance, velocity, density)
    best_index: int
    best: tuple[float, float]
    best_path: np.ndarray  # (steps, 3) x, y, θ
    admissible_best: bool
    evaluated: int
    refine_rounds: int
    budget_cut: bool


# --- shared preparation (the "map"; the reference implementation uses the same) -----------------


@dataclass(frozen=True)
class Prepared:
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


def _unit_arcs(omegas: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    ux, uy = _unit_arcs(w, times)
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
    occ = np.full(shape, 255, np.uint8)
    occ[ij[:, 0], ij[:, 1]] = 0  # index [ix, iy]
    # float32 already (no copy): asarray only gives the type checker the dtype cv2's stub lacks
    edt = np.asarray(cv2.distanceTransform(occ, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), np.float32)
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
            ) -> Prepared:
    window = dynamic_window(cfg, lim, v0, w0)
    steps = max(1, round(cfg.horizon_s / cfg.dt))
    times = (np.arange(steps) + 1) * cfg.dt
    r_eff = cfg.robot_radius_m + cfg.safety_margin_m
    cell = cfg.grid_cell_m
    vs, ws = grid_axes(cfg, window)
    ux, uy = _unit_arcs(ws, times)
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
    return Prepared(window, steps, times, r_eff, coarse_samples(vs, ws), cx, cy, step_lo,
                    step_hi, (float(lo[0]), float(lo[1])), shape, dist_grid, clusters)


# --- vectorised evaluation -----------------------------------------------------------------------


class _Evaluator:
    """Raw terms for batches of samples against one prepared world.

    float32 in the hot part (millimetres at tens of metres; half the memory traffic of
    float64). Obstacles that cannot matter are dropped up front, exactly: one farther than
    density_range from every step's rollout box never counts for density, and a track whose gap
    to that box stays above clearance_cap never changes the capped clearance or admissibility.
    The rest are processed in groups sized so that a group's (group, steps, samples) distances
    stay in cache (cfg.chunk_elems)."""

    def __init__(self, cfg: DWAConfig, lim: LimitsConfig, prep: Prepared, goal: np.ndarray,
                 obs_pos: np.ndarray, obs_radius: np.ndarray):
        self.cfg, self.lim, self.prep = cfg, lim, prep
        self.goal = np.asarray(goal, dtype=np.float64)
        self.times = prep.times.astype(np.float32)
        steps = prep.steps
        self.ones = np.ones(steps, np.float32)
        pos = np.asarray(obs_pos, dtype=np.float64).reshape(-1, steps, 2)
        reach_r = np.asarray(obs_radius, dtype=np.float64).reshape(-1, steps) + prep.r_eff
        far = prep.box_distance(pos)
        keep = (far <= np.maximum(cfg.density_range_m, reach_r + cfg.clearance_cap_m)).any(1)
        pos, reach_r = pos[keep], reach_r[keep]
        reach_r = standing_reach(pos, reach_r)
        pos, reach_r = pos.astype(np.float32), reach_r.astype(np.float32)
        c = prep.clusters
        if len(c):
            c = c[(prep.box_distance(c[:, None, :]) <= cfg.density_range_m).any(axis=1)]
        c = c.astype(np.float32)
        # (N, steps, 1) obstacle centres: tracks first, then static clusters; reach_r (T, steps, 1)
        # is the centre distance below which a track blocks the step
        self.ox = np.concatenate([pos[:, :, 0], np.repeat(c[:, 0:1], steps, 1)])[:, :, None]
        self.oy = np.concatenate([pos[:, :, 1], np.repeat(c[:, 1:2], steps, 1)])[:, :, None]
        self.reach_r = reach_r[:, :, None]
        if prep.dist_grid is not None:
            self.grid_flat = prep.dist_grid.ravel() - np.float32(prep.r_eff)
            # a point already over the footprint where the robot stands: gaps count from that
            # overlap (module docs)
            ix, iy = prep.cell_index(0.0, 0.0, cfg.grid_cell_m)
            self.grid_flat -= min(self.grid_flat[ix * prep.shape[1] + iy], np.float32(0.0))

    def _static_gap(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Gap to the static points per rollout point: one flat grid lookup each."""
        prep = self.prep
        if prep.dist_grid is None:
            return np.full(x.shape, np.inf, np.float32)
        ny = prep.shape[1]
        inv = np.float32(1.0 / self.cfg.grid_cell_m)
        # every window rollout lies in its step box and the grid reaches beyond every box
        # (prepare), so the indices are in range; mode="clip" only guards the memory access
        ix = ((x - np.float32(prep.origin[0])) * inv).astype(np.int32)
        iy = ((y - np.float32(prep.origin[1])) * inv).astype(np.int32)
        ix *= ny
        ix += iy
        return self.grid_flat.take(ix, mode="clip")

    def evaluate(self, samples: np.ndarray, x: np.ndarray | None = None,
                 y: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Raw terms of `samples`; x, y: their rollout when already known (the coarse grid)."""
        cfg, prep = self.cfg, self.prep
        if x is None or y is None:
            x, y, _ = rollout(samples, self.times)  # (steps, K) float32
        k_n = len(samples)
        steps = prep.steps
        v = samples[:, 0]
        ang = (np.arctan2(self.goal[1] - y[-1].astype(np.float64),
                          self.goal[0] - x[-1].astype(np.float64))
               - samples[:, 1] * prep.times[-1])
        heading = np.pi - np.abs(wrap_angles(ang))
        gap = self._static_gap(x, y)
        n_obs, n_t = len(self.ox), len(self.reach_r)
        density = np.zeros(k_n)
        if n_obs:
            closest = np.empty((n_obs, k_n), np.float32)
            dist_sum = np.empty((n_obs, k_n), np.float32)
            group = max(1, min(n_obs, cfg.chunk_elems // (steps * k_n)))
            d_buf = np.empty((group, steps, k_n), np.float32)
            dy_buf = np.empty_like(d_buf)
            groups = [(a, min(a + group, n_t)) for a in range(0, n_t, group)]
            groups += [(a, min(a + group, n_obs)) for a in range(n_t, n_obs, group)]
            for a, b in groups:  # a group never mixes tracks and static clusters
                d, dy = d_buf[: b - a], dy_buf[: b - a]
                np.subtract(x, self.ox[a:b], out=d)
                np.subtract(y, self.oy[a:b], out=dy)
                flat = d.reshape(-1, k_n)
                cv2.magnitude(flat, dy.reshape(-1, k_n), flat)
                np.min(d, axis=1, out=closest[a:b])
                np.matmul(self.ones, d, out=dist_sum[a:b])  # sum over steps (BLAS)
                if a < n_t:
                    d -= self.reach_r[a:b]
                    np.minimum(gap, d.min(axis=0), out=gap)
            # soft count: an obstacle whose closest approach is c counts 1 − c/range
            rng = max(cfg.density_range_m, 1e-9)
            weight = np.maximum(1.0 - closest / np.float32(rng), 0.0, dtype=np.float32)
            count = weight.sum(axis=0, dtype=np.float64)
            avg = ((weight * dist_sum).sum(axis=0, dtype=np.float64)
                   / (steps * np.maximum(count, 1e-12)))
            density = np.where(count > 0, count / np.maximum(avg, cfg.density_min_avg_m), 0.0)
        clearance = np.minimum(np.maximum(gap.min(axis=0), 0.0), cfg.clearance_cap_m)
        coll = gap < 0.0
        first = np.argmax(coll, axis=0)
        any_coll = coll[first, np.arange(k_n)]
        s_free = np.abs(v) * first * cfg.dt
        admissible = ~any_coll | (v * v <= 2.0 * self.lim.decel_max * s_free)
        return {"heading": heading, "clearance": clearance.astype(np.float64),
                "velocity": v.copy(), "density": density, "admissible": admissible}


def term_scales(cfg: DWAConfig, lim: LimitsConfig) -> dict[str, float]:
    """σ: the fixed scale of each cost term (its value at "1")."""
    return {"heading": math.pi, "clearance": cfg.clearance_cap_m,
            "velocity": max(lim.v_max, -lim.v_min, 1e-9), "density": cfg.density_scale}


def _score(cfg: DWAConfig, lim: LimitsConfig, raw: dict[str, np.ndarray]
           ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    n = {k: raw[k] / sigma for k, sigma in term_scales(cfg, lim).items()}
    total = (cfg.weight_heading * n["heading"] + cfg.weight_clearance * n["clearance"]
             + cfg.weight_velocity * n["velocity"] - cfg.weight_density * n["density"])
    return n, total


def _best(total: np.ndarray, admissible: np.ndarray) -> int:
    if not admissible.any():
        return -1
    return int(np.argmax(np.where(admissible, total, -np.inf)))


@functools.lru_cache(maxsize=8)
def _refine_offsets(n: int) -> np.ndarray:
    """The n×n refinement grid in units of the current spacing, without its centre."""
    offs = np.linspace(-1.0, 1.0, n)
    grid = np.stack(np.meshgrid(offs, offs, indexing="ij"), -1).reshape(-1, 2)
    grid = grid[(grid != 0).any(axis=1)]
    grid.flags.writeable = False
    return grid


def interleaved_blocks(n: int, block: int) -> list[np.ndarray]:
    """Indices 0..n-1 in blocks of at most `block`; block b holds b, b + nb, b + 2·nb, … so
    every prefix of blocks spans the whole window (a cut-short coarse grid is a sparser grid)."""
    nb = max(1, math.ceil(n / block))
    return [np.arange(b, n, nb) for b in range(nb)]


def plan(
    cfg: DWAConfig,
    lim: LimitsConfig,
    v0: float,
    omega0: float,
    goal: np.ndarray,
    points: np.ndarray,
    obs_pos: np.ndarray | None = None,
    obs_radius: np.ndarray | None = None,
    *,
    deadline: float = math.inf,
    now: Callable[[], float] | None = None,
) -> DWAResult:
    """One planning call (see the module docs for frames, cost, admissibility and budget)."""
    clock = TimeBudget(deadline, now)
    prep = prepare(cfg, lim, v0, omega0, points)
    steps = prep.steps
    if obs_pos is None:
        obs_pos, obs_radius = np.zeros((0, steps, 2)), np.zeros((0, steps))
    elif obs_radius is None:
        raise ValueError("plan: obs_pos given without obs_radius")
    ev = _Evaluator(cfg, lim, prep, goal, obs_pos, obs_radius)
    coarse = prep.coarse
    blocks = interleaved_blocks(len(coarse), cfg.block_samples)
    parts: list[dict[str, np.ndarray]] = []
    slowest = 0.0
    for i, idx in enumerate(blocks):
        if i and not clock.allows(slowest):
            break
        if len(blocks) == 1:
            parts.append(ev.evaluate(coarse, prep.coarse_x, prep.coarse_y))
        else:
            parts.append(ev.evaluate(coarse[idx], prep.coarse_x[:, idx], prep.coarse_y[:, idx]))
        slowest = max(slowest, clock.lap())
    if len(blocks) == 1:
        samples, raw = coarse, parts[0]
    else:
        order = np.concatenate(blocks[: len(parts)])
        back = np.argsort(order, kind="stable")  # evaluated samples back into v-major order
        samples = coarse[order][back]
        raw = {k: np.concatenate([p[k] for p in parts])[back] for k in parts[0]}
    _, total = _score(cfg, lim, raw)
    best = _best(total, raw["admissible"])
    rounds = 0
    v_lo, v_hi, w_lo, w_hi = prep.window
    dv, dw = grid_spacing(cfg, prep.window)
    grid = _refine_offsets(cfg.refine_n)
    # a round has no more samples than a coarse block: the slowest block bounds the first round
    while best >= 0 and rounds < cfg.refine_max_rounds and (dv > 0 or dw > 0):
        if not clock.allows(slowest):
            break
        scale = 0.5**rounds
        new = samples[best] + grid * np.array([dv * scale, dw * scale])
        new[:, 0] = np.clip(new[:, 0], v_lo, v_hi)
        new[:, 1] = np.clip(new[:, 1], w_lo, w_hi)
        r = ev.evaluate(new)
        samples = np.concatenate([samples, new])
        raw = {k: np.concatenate([raw[k], r[k]]) for k in raw}
        _, total = _score(cfg, lim, raw)
        best = _best(total, raw["admissible"])
        rounds += 1
        lap = clock.lap()
        slowest = lap if rounds == 1 else max(slowest, lap)
    evaluated = len(samples)
    if best < 0:  # nothing admissible: brake
        brake = np.array([braking_sample(prep.window)])
        r = ev.evaluate(brake)
        samples = np.concatenate([samples, brake])
        raw = {k: np.concatenate([raw[k], r[k]]) for k in raw}
        best = len(samples) - 1
        evaluated += 1
    norm, total = _score(cfg, lim, raw)
    bv, bw = float(samples[best, 0]), float(samples[best, 1])
    ux, uy = _unit_arcs(np.array([bw]), prep.times)
    bx, by, bth = ux[:, 0] * bv, uy[:, 0] * bv, prep.times * bw
    return DWAResult(
        samples=samples, heading=norm["heading"], clearance=norm["clearance"],
        velocity=norm["velocity"], density=norm["density"], total=total,
        admissible=raw["admissible"],
        raw={k: raw[k] for k in ("heading", "clearance", "velocity", "density")},
        best_index=best, best=(float(samples[best, 0]), float(samples[best, 1])),
        best_path=np.stack([bx, by, bth], axis=-1),
        admissible_best=bool(raw["admissible"][best]), evaluated=evaluated,
        refine_rounds=rounds, budget_cut=clock.cut,
    )


def plan_coarse(cfg: DWAConfig, lim: LimitsConfig, v0: float, omega0: float, goal: np.ndarray,
                points: np.ndarray, obs_pos: np.ndarray | None = None,
                obs_radius: np.ndarray | None = None) -> DWAResult:
    """The coarse grid only (no refinement): what the reference implementation computes."""
    from dataclasses import replace

    return plan(replace(cfg, refine_max_rounds=0), lim, v0, omega0, goal, points, obs_pos,
                obs_radius)


# --- benchmark helpers ---------------------------------------------------------------------------
