"""Dynamic-window local planner with the SafeMove-RL cost, vectorised and anytime.

Frame and time: everything is in base_link at the current time (robot at the origin, heading 0).
Rollout step k (k = 0..steps-1) is the pose at t_k = (k+1)·dt under constant (v, ω) (exact
unicycle arc). Dynamic obstacles come as positions predicted at the SAME times: (T, steps, 2)
centres and (T, steps) radii that already include the growing uncertainty (the loop builds them
with `Tracker.predict_positions(t_now + dt, dt, steps)` transformed into base_link, radius =
track radius + n·std).

Cost (maximised): G = α·heading + β·clearance + γ·velocity − δ·density, each term min–max
normalised to [0, 1] over the evaluated sample set (σ in the paper; a constant term normalises to
0). Raw terms of one sample:
- heading   = π − |angle from the final heading to the goal seen from the final position| ∈ [0, π]
- clearance = clip(min over steps of the gap, 0, clearance_cap); gap = distance to the nearest
  static point − R, and to each track's centre at the same step − its radius − R, with
  R = robot_radius + safety_margin (so gap < 0 is a collision)
- velocity  = v
- density   = N_obs / max(avg_distance, density_min_avg_m): N_obs = obstacles whose closest
  approach to the trajectory is ≤ density_range_m, avg_distance = mean over those obstacles and
  all steps of the centre distance. Obstacles for density: each track (at its step-k position)
  and the static points clustered on a density_cell_m grid (one obstacle per occupied cell, at
  its points' mean; cells out of reach + range are dropped).
Admissible (Fox et al.): the sample can stop before its first colliding step:
v² ≤ 2·decel_max·s_free, s_free = |v|·(time of the last step before the first collision).
A collision later than that only lowers the clearance term.

Static clearance comes from a distance transform of an occupancy grid (grid_cell_m) built once
per call; the looked-up distance is reduced by cell·√2, so it is a lower bound on the exact
distance and at most 2·cell·√2 below it (tested).

Budget (the stage is pure, no clock reads of its own): the caller passes an absolute `deadline`
and the clock `now` it is measured on (the loop: `deadline=time.monotonic() + cfg.budget_s,
now=time.monotonic`; tests: a fake clock). The coarse grid is always evaluated; then refinement
rounds (a finer n×n grid around the current best, half the spacing each round) run while
`now() + estimated round time <= deadline`, up to refine_max_rounds. With `now=None` the rounds
are bounded only by refine_max_rounds (a pure evaluation-count budget). If no sample is
admissible the result is the strongest braking sample in the window with admissible_best False.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from runtime.limits import LimitsConfig
from runtime.schema import setting


@dataclass(frozen=True)
class DWAConfig:
    horizon_s: float = setting(3.0, "rollout horizon of each sample", "s", min=0.1, max=10.0)
    dt: float = setting(0.1, "rollout step (obstacle predictions use the same steps)", "s",
                        min=0.01, max=1.0)
    window_dt: float = setting(0.05, "dynamic window: reachable velocities within this time"
                               " (the control period)", "s", min=0.001, max=2.0)
    n_v: int = setting(20, "coarse grid: linear velocity samples", min=1, max=200)
    n_omega: int = setting(20, "coarse grid: angular velocity samples", min=1, max=200)
    refine_n: int = setting(5, "refinement: n×n samples around the best per round (odd)",
                            min=3, max=15)
    refine_max_rounds: int = setting(8, "refinement: most rounds per call", min=0, max=50)
    weight_heading: float = setting(1.0, "α: weight of the heading term", min=0.0)
    weight_clearance: float = setting(1.0, "β: weight of the clearance term", min=0.0)
    weight_velocity: float = setting(0.5, "γ: weight of the velocity term", min=0.0)
    weight_density: float = setting(0.5, "δ: weight of the density penalty", min=0.0)
    density_range_m: float = setting(1.0, "an obstacle counts for density within this distance"
                                     " of the trajectory", "m", min=0.0, max=10.0)
    density_cell_m: float = setting(0.5, "static points are clustered into obstacles on this grid"
                                    " for the density term", "m", min=0.05, max=5.0)
    density_max_static: int = setting(16, "at most this many static clusters (the nearest to the"
                                      " robot) count for density (bounds the cost)", min=0)
    density_min_avg_m: float = setting(0.1, "floor of the average distance in density", "m",
                                       min=0.001, max=5.0)
    robot_radius_m: float = setting(0.18, "robot footprint radius", "m", min=0.0, max=2.0)
    safety_margin_m: float = setting(0.05, "extra clearance kept from every obstacle", "m",
                                     min=0.0, max=2.0)
    clearance_cap_m: float = setting(1.0, "clearance term saturates here", "m", min=0.01,
                                     max=5.0)
    grid_cell_m: float = setting(0.03, "cell of the static distance-transform grid", "m",
                                 min=0.005, max=0.2)
    budget_s: float = setting(0.004, "stage budget: refinement stops by this time", "s",
                              min=0.0, max=1.0)
    chunk_elems: int = setting(200_000, "samples×steps×obstacles per vectorised chunk (bounds"
                               " temporaries)", min=1000)


@dataclass(frozen=True)
class DWAResult:
    samples: np.ndarray  # (K, 2) [v, ω] in evaluation order (coarse first)
    heading: np.ndarray  # (K,) normalised terms, [0, 1]
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
    half: float  # grid half size; origin of the grid at (-half, -half)
    n_cells: int
    dist_grid: np.ndarray | None  # (n, n) float64 conservative distance (m) to the nearest point
    clusters: np.ndarray  # (C, 2) static obstacles for density


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


def coarse_samples(cfg: DWAConfig, window: tuple[float, float, float, float]) -> np.ndarray:
    """(n_v·n_ω, 2), v-major order (the reference loops in the same order)."""
    v_lo, v_hi, w_lo, w_hi = window
    vs = np.linspace(v_lo, v_hi, cfg.n_v)
    ws = np.linspace(w_lo, w_hi, cfg.n_omega)
    return np.stack(np.meshgrid(vs, ws, indexing="ij"), axis=-1).reshape(-1, 2)


def prepare(cfg: DWAConfig, lim: LimitsConfig, v0: float, w0: float, points: np.ndarray
            ) -> Prepared:
    window = dynamic_window(cfg, lim, v0, w0)
    steps = max(1, round(cfg.horizon_s / cfg.dt))
    times = (np.arange(steps) + 1) * cfg.dt
    r_eff = cfg.robot_radius_m + cfg.safety_margin_m
    reach = max(abs(window[0]), abs(window[1])) * float(times[-1])
    cell = cfg.grid_cell_m
    half = reach + cfg.clearance_cap_m + r_eff + 2.0 * cell
    n = math.ceil(2.0 * half / cell)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    dist_grid = None
    if len(pts):
        ij = np.floor((pts + half) / cell).astype(np.int64)
        inside = (ij >= 0).all(1) & (ij < n).all(1)
        ij = ij[inside]
        if len(ij):
            occ = np.full((n, n), 255, np.uint8)
            occ[ij[:, 0], ij[:, 1]] = 0  # index [ix, iy]
            edt = cv2.distanceTransform(occ, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            dist_grid = edt.astype(np.float64) * cell - cell * math.sqrt(2.0)
    # density obstacles: static points clustered on a coarse grid, within reach + range
    clusters = np.zeros((0, 2))
    if len(pts):
        near = np.hypot(pts[:, 0], pts[:, 1]) <= reach + cfg.density_range_m + cfg.density_cell_m
        p = pts[near]
        if len(p):
            cij = np.floor(p / cfg.density_cell_m).astype(np.int64)
            packed = (cij[:, 0] << 32) + (cij[:, 1] & 0xFFFFFFFF)
            _, inv, counts = np.unique(packed, return_inverse=True, return_counts=True)
            sums = np.zeros((len(counts), 2))
            np.add.at(sums, inv.ravel(), p)
            clusters = sums / counts[:, None]
            if len(clusters) > cfg.density_max_static:
                r2 = (clusters * clusters).sum(axis=1)
                keep = np.sort(np.argsort(r2, kind="stable")[: cfg.density_max_static])
                clusters = clusters[keep]
    return Prepared(window, steps, times, r_eff, half, n, dist_grid, clusters)


# --- vectorised evaluation -----------------------------------------------------------------------


def rollout(samples: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact unicycle arcs: x, y, θ each (steps, K) (samples along the contiguous axis)."""
    v = samples[:, 0]
    w = samples[:, 1]
    t = times[:, None]
    th = t * w
    straight = np.abs(w) < 1e-9
    ws = np.where(straight, 1.0, w)
    r = v / ws
    x = np.where(straight, t * v, r * np.sin(th))
    y = np.where(straight, 0.5 * (t * t) * (v * w), r * (1.0 - np.cos(th)))
    return x, y, th


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


class _Evaluator:
    """Raw terms for batches of samples against one prepared world."""

    def __init__(self, cfg: DWAConfig, lim: LimitsConfig, prep: Prepared, goal: np.ndarray,
                 obs_pos: np.ndarray, obs_radius: np.ndarray):
        self.cfg, self.lim, self.prep = cfg, lim, prep
        self.goal = np.asarray(goal, dtype=np.float64)
        steps = prep.steps
        obs_pos = np.asarray(obs_pos, dtype=np.float64).reshape(-1, steps, 2)
        obs_radius = np.asarray(obs_radius, dtype=np.float64).reshape(-1, steps)
        self.n_tracks = len(obs_pos)
        c = prep.clusters
        # density/clearance obstacles (N, steps): tracks first, then static clusters (fixed)
        self.ox = np.concatenate([obs_pos[:, :, 0], np.repeat(c[:, 0:1], steps, 1)])[:, :, None]
        self.oy = np.concatenate([obs_pos[:, :, 1], np.repeat(c[:, 1:2], steps, 1)])[:, :, None]
        self.orad = obs_radius[:, :, None]  # (T, steps, 1)

    def evaluate(self, samples: np.ndarray) -> dict[str, np.ndarray]:
        cfg, prep = self.cfg, self.prep
        x, y, th = rollout(samples, prep.times)  # (S, K)
        k_n = len(samples)
        steps = prep.steps
        gx, gy = self.goal
        ang = np.arctan2(gy - y[-1], gx - x[-1]) - th[-1]
        heading = np.pi - np.abs(_wrap(ang))
        if prep.dist_grid is not None:  # static gap per step: one grid lookup per point
            n = prep.n_cells
            inv = 1.0 / cfg.grid_cell_m
            ix = ((x + prep.half) * inv).astype(np.intp)  # x + half > 0 inside the grid
            iy = ((y + prep.half) * inv).astype(np.intp)
            np.clip(ix, 0, n - 1, out=ix)
            np.clip(iy, 0, n - 1, out=iy)
            gap = prep.dist_grid[ix, iy]
            gap -= prep.r_eff
        else:
            gap = np.full(x.shape, np.inf)
        n_obs = self.ox.shape[0]
        nt = self.n_tracks
        density = np.zeros(k_n)
        if n_obs:
            chunk = max(1, cfg.chunk_elems // (steps * n_obs))
            rng = cfg.density_range_m
            for a in range(0, k_n, chunk):
                b = min(k_n, a + chunk)
                d = x[None, :, a:b] - self.ox  # (N, S, k)
                dy = y[None, :, a:b] - self.oy
                np.multiply(d, d, out=d)
                np.multiply(dy, dy, out=dy)
                np.add(d, dy, out=d)
                np.sqrt(d, out=d)
                if nt:
                    dyn = d[:nt] - self.orad
                    dmin = dyn.min(axis=0)
                    dmin -= prep.r_eff
                    np.minimum(gap[:, a:b], dmin, out=gap[:, a:b])
                within = d.min(axis=1) <= rng  # (N, k)
                cnt = within.sum(axis=0)
                sum_mean = (d.sum(axis=1) * within).sum(axis=0) / steps
                ok = cnt > 0
                avg = sum_mean / np.maximum(cnt, 1)
                density[a:b] = np.where(ok, cnt / np.maximum(avg, cfg.density_min_avg_m), 0.0)
        clearance = np.minimum(np.maximum(gap.min(axis=0), 0.0), cfg.clearance_cap_m)
        coll = gap < 0.0
        first = np.argmax(coll, axis=0)
        any_coll = coll[first, np.arange(k_n)]
        v = samples[:, 0]
        s_free = np.abs(v) * first * cfg.dt
        admissible = ~any_coll | (v * v <= 2.0 * self.lim.decel_max * s_free)
        return {"heading": heading, "clearance": clearance, "velocity": v.copy(),
                "density": density, "admissible": admissible}


def normalise(a: np.ndarray) -> np.ndarray:
    lo, hi = float(a.min()), float(a.max())
    if not hi > lo:
        return np.zeros_like(a)
    return (a - lo) / (hi - lo)


def _score(cfg: DWAConfig, raw: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    n = {k: normalise(raw[k]) for k in ("heading", "clearance", "velocity", "density")}
    total = (cfg.weight_heading * n["heading"] + cfg.weight_clearance * n["clearance"]
             + cfg.weight_velocity * n["velocity"] - cfg.weight_density * n["density"])
    return n, total


def _best(total: np.ndarray, admissible: np.ndarray) -> int:
    if not admissible.any():
        return -1
    return int(np.argmax(np.where(admissible, total, -np.inf)))


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
    prep = prepare(cfg, lim, v0, omega0, points)
    steps = prep.steps
    if obs_pos is None:
        obs_pos, obs_radius = np.zeros((0, steps, 2)), np.zeros((0, steps))
    ev = _Evaluator(cfg, lim, prep, goal, obs_pos, obs_radius)
    t_start = now() if now is not None else 0.0
    samples = coarse_samples(cfg, prep.window)
    raw = ev.evaluate(samples)
    n_c = len(samples)
    _, total = _score(cfg, raw)
    best = _best(total, raw["admissible"])
    rounds, cut = 0, False
    if now is not None:
        t_prev = now()
        est = (t_prev - t_start) * (cfg.refine_n**2 - 1) / n_c
    v_lo, v_hi, w_lo, w_hi = prep.window
    dv = (v_hi - v_lo) / max(cfg.n_v - 1, 1)
    dw = (w_hi - w_lo) / max(cfg.n_omega - 1, 1)
    offs = np.linspace(-1.0, 1.0, cfg.refine_n)
    grid = np.stack(np.meshgrid(offs, offs, indexing="ij"), -1).reshape(-1, 2)
    grid = grid[(grid != 0).any(axis=1)]
    while best >= 0 and rounds < cfg.refine_max_rounds and (dv > 0 or dw > 0):
        if now is not None and now() + est > deadline:
            cut = True
            break
        scale = 0.5**rounds
        centre = samples[best]
        new = centre + grid * np.array([dv * scale, dw * scale])
        new[:, 0] = np.clip(new[:, 0], v_lo, v_hi)
        new[:, 1] = np.clip(new[:, 1], w_lo, w_hi)
        r = ev.evaluate(new)
        samples = np.concatenate([samples, new])
        raw = {k: np.concatenate([raw[k], r[k]]) for k in raw}
        _, total = _score(cfg, raw)
        best = _best(total, raw["admissible"])
        rounds += 1
        if now is not None:
            t = now()
            est = max(est, t - t_prev)
            t_prev = t
    evaluated = len(samples)
    if best < 0:  # nothing admissible: brake
        brake = np.array([braking_sample(prep.window)])
        r = ev.evaluate(brake)
        samples = np.concatenate([samples, brake])
        raw = {k: np.concatenate([raw[k], r[k]]) for k in raw}
        best = len(samples) - 1
        evaluated += 1
    norm, total = _score(cfg, raw)
    bx, by, bth = (a[:, 0] for a in rollout(samples[best:best + 1], prep.times))
    return DWAResult(
        samples=samples, heading=norm["heading"], clearance=norm["clearance"],
        velocity=norm["velocity"], density=norm["density"], total=total,
        admissible=raw["admissible"],
        raw={k: raw[k] for k in ("heading", "clearance", "velocity", "density")},
        best_index=best, best=(float(samples[best, 0]), float(samples[best, 1])),
        best_path=np.stack([bx, by, bth], axis=-1),
        admissible_best=bool(raw["admissible"][best]), evaluated=evaluated,
        refine_rounds=rounds, budget_cut=cut,
    )


def plan_coarse(cfg: DWAConfig, lim: LimitsConfig, v0: float, omega0: float, goal: np.ndarray,
                points: np.ndarray, obs_pos: np.ndarray | None = None,
                obs_radius: np.ndarray | None = None) -> DWAResult:
    """The coarse grid only (no refinement): what the reference implementation computes."""
    from dataclasses import replace

    return plan(replace(cfg, refine_max_rounds=0), lim, v0, omega0, goal, points, obs_pos,
                obs_radius)


# --- benchmark helpers ---------------------------------------------------------------------------
