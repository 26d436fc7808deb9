"""Textbook per-sample DWA of the same cost and admissibility as runtime.planning.dwa (coarse grid only).

Used only by the benchmark and the identical-choice test. Written in the style of the common
textbook implementation (PythonRobotics' dynamic_window_approach): for v, for ω, a trajectory
loop, an obstacle loop per trajectory point. It shares runtime.planning.dwa's map preparation
(`prepare`: the dynamic window, the static distance-transform grid, the static clusters for
density), so its static clearance has the same quantisation; everything per sample is computed
here in plain Python. The trajectory is integrated step by step on exact arcs (not Euler), so it
is the same motion model as the vectorised closed form up to rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.planning.dwa import DWAConfig
from runtime.planning.dwa.cost import term_scales
from runtime.planning.dwa.window import braking_sample, grid_axes, prepare
from runtime.safety.limits import LimitsConfig


@dataclass(frozen=True)
class ReferenceResult:
    samples: np.ndarray
    terms: dict[str, np.ndarray]  # normalised heading, clearance, velocity, density
    raw: dict[str, np.ndarray]
    total: np.ndarray
    admissible: np.ndarray
    best_index: int
    best: tuple[float, float]


def _trajectory(v: float, w: float, dt: float, steps: int) -> list[tuple[float, float, float]]:
    x = y = th = 0.0
    out = []
    for _ in range(steps):
        th_new = th + w * dt
        if abs(w) < 1e-9:
            x += v * dt * math.cos(th)
            y += v * dt * math.sin(th)
        else:
            x += v / w * (math.sin(th_new) - math.sin(th))
            y += v / w * (math.cos(th) - math.cos(th_new))
        th = th_new
        out.append((x, y, th))
    return out


def plan_reference(cfg: DWAConfig, lim: LimitsConfig, v0: float, omega0: float, goal,
                   points, obs_pos=None, obs_radius=None) -> ReferenceResult:
    prep = prepare(cfg, lim, v0, omega0, points)
    steps = prep.steps
    obs = [] if obs_pos is None else np.asarray(obs_pos, float).reshape(-1, steps, 2).tolist()
    rad = [] if obs_radius is None else np.asarray(obs_radius, float).reshape(-1, steps).tolist()
    clusters = prep.clusters.tolist()
    grid = None if prep.dist_grid is None else prep.dist_grid.tolist()
    gx, gy = float(goal[0]), float(goal[1])
    # gaps count from an obstacle's overlap where the robot stands (runtime.planning.dwa's module docs)
    over = [math.hypot(*obs[j][0]) < rad[j][0] + prep.r_eff for j in range(len(obs))]
    walking = [any(abs(obs[j][k][i] - obs[j][0][i]) > 1e-9 for k in range(steps) for i in (0, 1))
               for j in range(len(obs))]
    static_floor = 0.0
    if grid is not None:
        ix, iy = prep.cell_index(0.0, 0.0, cfg.grid_cell_m)
        static_floor = min(grid[ix][iy] - prep.r_eff, 0.0)
    vs, ws = (axis.tolist() for axis in grid_axes(cfg, prep.window))

    samples: list[tuple[float, float]] = []
    raws: dict[str, list[float]] = {"heading": [], "clearance": [], "velocity": [], "density": [],
                                    "evasion": []}
    admissible: list[bool] = []
    for v in vs:
        for w in ws:
            traj = _trajectory(v, w, cfg.dt, steps)
            min_gap = math.inf
            walk_gap = 0.0
            first_coll = -1
            n_obs = len(obs) + len(clusters)
            closest = [math.inf] * n_obs
            dist_sum = [0.0] * n_obs
            for k, (x, y, _) in enumerate(traj):
                gap_k = math.inf
                if grid is not None:
                    ix, iy = prep.cell_index(x, y, cfg.grid_cell_m)
                    gap_k = grid[ix][iy] - prep.r_eff - static_floor
                for j in range(len(obs)):
                    ox, oy = obs[j][k]
                    d = math.sqrt((x - ox) ** 2 + (y - oy) ** 2)
                    reach = rad[j][k] + prep.r_eff
                    if over[j]:  # no closer than to the robot standing still
                        reach = min(reach, math.hypot(ox, oy))
                    gap_k = min(gap_k, d - reach)
                    if walking[j]:
                        walk_gap = min(walk_gap, d - reach)
                    closest[j] = min(closest[j], d)
                    dist_sum[j] += d
                for c, (ox, oy) in enumerate(clusters):
                    j = len(obs) + c
                    d = math.sqrt((x - ox) ** 2 + (y - oy) ** 2)
                    closest[j] = min(closest[j], d)
                    dist_sum[j] += d
                if gap_k < 0.0 and first_coll < 0:
                    first_coll = k
                min_gap = min(min_gap, gap_k)
            x, y, th = traj[-1]
            ang = math.atan2(gy - y, gx - x) - th
            ang = (ang + math.pi) % (2.0 * math.pi) - math.pi
            heading = math.pi - abs(ang)
            clearance = min(max(min_gap, 0.0), cfg.clearance_cap_m)
            count, mean_sum = 0.0, 0.0
            for j in range(len(closest)):
                soft = 1.0 - closest[j] / cfg.density_range_m if cfg.density_range_m > 0 else 0.0
                if soft > 0.0:
                    count += soft
                    mean_sum += soft * dist_sum[j] / steps
            density = count / max(mean_sum / count, cfg.density_min_avg_m) if count else 0.0
            if first_coll < 0:
                ok = True
            else:
                s_free = abs(v) * first_coll * cfg.dt
                ok = v * v <= 2.0 * lim.decel_max * s_free
            samples.append((v, w))
            raws["heading"].append(heading)
            raws["clearance"].append(clearance)
            raws["velocity"].append(v)
            raws["density"].append(density)
            if cfg.weight_evasion:
                walk_gap = min(walk_gap, _after_horizon_gap(cfg, traj[-1], obs, rad, walking, over,
                                                            prep.r_eff, steps))
            raws["evasion"].append(max(walk_gap, -cfg.evasion_cap_m) if cfg.weight_evasion else 0.0)
            admissible.append(ok)

    scales = term_scales(cfg, lim)
    terms = {k: [a / scales[k] for a in vals] for k, vals in raws.items()}
    total, best, best_total = [], -1, -math.inf
    for i in range(len(samples)):
        g = (cfg.weight_heading * terms["heading"][i] + cfg.weight_clearance * terms["clearance"][i]
             + cfg.weight_velocity * terms["velocity"][i] - cfg.weight_density * terms["density"][i]
             + cfg.weight_evasion * terms["evasion"][i])
        total.append(g)
        if admissible[i] and g > best_total:
            best, best_total = i, g
    best_vw = samples[best] if best >= 0 else braking_sample(prep.window)
    return ReferenceResult(
        samples=np.array(samples), terms={k: np.array(a) for k, a in terms.items()},
        raw={k: np.array(a) for k, a in raws.items()}, total=np.array(total),
        admissible=np.array(admissible), best_index=best, best=best_vw,
    )


def _after_horizon_gap(cfg: DWAConfig, end: tuple[float, float, float], obs: list, rad: list,
                       walking: list[bool], over: list[bool], r_eff: float, steps: int) -> float:
    """The closest a walker, walking on for another horizon from its last predicted step, comes
    to the robot standing at the rollout's end, less its reach at that step."""
    gap = math.inf
    for j in range(len(obs)):
        if not walking[j]:
            continue
        (px, py), (qx, qy) = obs[j][-1], obs[j][max(steps - 2, 0)]
        ux, uy = (px - qx) / cfg.dt, (py - qy) / cfg.dt
        rx, ry = end[0] - px, end[1] - py
        s = min(max((rx * ux + ry * uy) / max(ux * ux + uy * uy, 1e-12), 0.0), cfg.horizon_s)
        reach = rad[j][-1] + r_eff
        if over[j]:
            reach = min(reach, math.hypot(px, py))
        gap = min(gap, math.hypot(rx - s * ux, ry - s * uy) - reach)
    return gap


def random_world(rng: np.random.Generator, steps: int, n_points: int, n_tracks: int,
                 n_blobs: int = 10, dt: float = 0.1) -> dict:
    """A random planning problem in base_link: static points in `n_blobs` tight blobs centred in
    distinct density cells 0.7–2.2 m away (so, with the default density_cell_m, one density
    obstacle each), tracks starting 1–3 m away walking at up to ~1 m/s with a radius growing with
    time, a goal ahead, a current twist inside the velocity box."""
    cell = 0.5
    cand = [(i, j) for i in range(-5, 6) for j in range(-5, 6)
            if 0.7 <= math.hypot((i + 0.5) * cell, (j + 0.5) * cell) <= 2.2]
    pick = rng.choice(len(cand), size=min(n_blobs, len(cand)), replace=False)
    centres = (np.array([cand[p] for p in pick], dtype=float) + 0.5) * cell
    pts = centres[rng.integers(0, len(centres), n_points)] + rng.uniform(-0.1, 0.1, (n_points, 2))
    t = (np.arange(steps) + 1) * dt
    ang = rng.uniform(-math.pi, math.pi, n_tracks)
    p0 = rng.uniform(1.0, 3.0, (n_tracks, 1)) * np.stack([np.cos(ang), np.sin(ang)], -1)
    vel = rng.normal(0, 0.5, (n_tracks, 2))
    pos = p0[:, None, :] + vel[:, None, :] * t[None, :, None]
    rad = rng.uniform(0.2, 0.3, (n_tracks, 1)) + 0.05 * t[None, :]
    goal = rng.uniform([1.0, -3.0], [5.0, 3.0])
    return {"v0": float(rng.uniform(0.0, 0.3)), "w0": float(rng.uniform(-0.8, 0.8)),
            "goal": goal, "points": pts, "obs_pos": pos, "obs_radius": rad}
