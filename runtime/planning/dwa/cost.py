"""The DWA's cost terms, vectorised: raw terms for batches of samples against one prepared
world, their fixed scales and the total (runtime.planning.dwa has the formulas)."""

from __future__ import annotations

import math

import numpy as np

from runtime.geometry import wrap_angles
from runtime.planning.dwa.config import DWAConfig
from runtime.planning.dwa.window import WindowPreparation, rollout, standing_reach
from runtime.safety.limits import LimitsConfig


class Evaluator:
    """Raw terms for batches of samples against one prepared world.

    float32 in the hot part (millimetres at tens of metres; half the memory traffic of
    float64). Obstacles that cannot matter are dropped up front, exactly: one farther than
    density_range from every step's rollout box never counts for density, and a track whose gap
    to that box stays above clearance_cap never changes the capped clearance or admissibility.
    The rest are processed in groups sized so that a group's (group, steps, samples) distances
    stay in cache (cfg.chunk_elems)."""

    def __init__(self, cfg: DWAConfig, lim: LimitsConfig, prep: WindowPreparation, goal: np.ndarray,
                 obs_pos: np.ndarray, obs_radius: np.ndarray):
        self.cfg, self.lim, self.prep = cfg, lim, prep
        self.goal = np.asarray(goal, dtype=np.float64)
        self.times = prep.times.astype(np.float32)
        steps = prep.steps
        pos = np.asarray(obs_pos, dtype=np.float64).reshape(-1, steps, 2)
        reach_r = np.asarray(obs_radius, dtype=np.float64).reshape(-1, steps) + prep.r_eff
        far = prep.box_distance(pos)
        keep = (far <= np.maximum(cfg.density_range_m, reach_r + cfg.clearance_cap_m)).any(1)
        pos, reach_r = pos[keep], reach_r[keep]
        # a walking person's predicted centre moves over the horizon; a standing one's does not
        self.walking = np.any(np.abs(pos[:, -1] - pos[:, 0]) > 1e-9, axis=1).astype(bool)
        reach_r = standing_reach(pos, reach_r)
        walk = pos[self.walking]
        # where each walker is at the horizon, its velocity there and its reach (evasion's
        # after-horizon check)
        self.walk_end = walk[:, -1]
        self.walk_vel = (walk[:, -1] - walk[:, max(steps - 2, 0)]) / cfg.dt
        self.walk_reach = reach_r[self.walking][:, -1]
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

    def _after_horizon_gap(self, xf: np.ndarray, yf: np.ndarray) -> np.ndarray:
        """(K,) the closest any walker comes, walking on for another horizon, to the robot
        standing where each rollout ends, less its reach: a sample that only puts the meeting
        past the horizon (braking, backing off) is not an escape."""
        p, u = self.walk_end[:, None, :], self.walk_vel[:, None, :]  # (W, 1, 2)
        rx, ry = xf[None, :] - p[..., 0], yf[None, :] - p[..., 1]  # (W, K)
        uu = np.maximum((u ** 2).sum(-1), 1e-12)
        s = np.clip((rx * u[..., 0] + ry * u[..., 1]) / uu, 0.0, self.cfg.horizon_s)
        d = np.hypot(rx - s * u[..., 0], ry - s * u[..., 1]) - self.walk_reach[:, None]
        return d.min(axis=0).astype(np.float32)

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
        # the deepest overlap of a walking person's predicted disc with the rollout (≤ 0)
        walk_gap = np.zeros(k_n, np.float32)
        evade = self.cfg.weight_evasion > 0.0
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
                # plain IEEE operations: cv2.magnitude's result depends on the buffer's
                # alignment, and a replay must reproduce every decision bit for bit
                np.multiply(d, d, out=d)
                np.multiply(dy, dy, out=dy)
                d += dy
                np.sqrt(d, out=d)
                np.min(d, axis=1, out=closest[a:b])
                np.sum(d, axis=1, out=dist_sum[a:b])
                if a < n_t:
                    d -= self.reach_r[a:b]
                    np.minimum(gap, d.min(axis=0), out=gap)
                    walking = self.walking[a:b]
                    if evade and walking.any():
                        np.minimum(walk_gap, d[walking].min(axis=(0, 1)), out=walk_gap)
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
        if evade and len(self.walk_end):
            np.minimum(walk_gap, self._after_horizon_gap(x[-1], y[-1]), out=walk_gap)
        evasion = np.maximum(walk_gap, -cfg.evasion_cap_m).astype(np.float64)
        return {"heading": heading, "clearance": clearance.astype(np.float64),
                "velocity": v.copy(), "density": density, "evasion": evasion,
                "admissible": admissible}


def term_scales(cfg: DWAConfig, lim: LimitsConfig) -> dict[str, float]:
    """σ: the fixed scale of each cost term (its value at "1")."""
    return {"heading": math.pi, "clearance": cfg.clearance_cap_m,
            "velocity": max(lim.v_max, -lim.v_min, 1e-9), "density": cfg.density_scale,
            "evasion": cfg.evasion_cap_m}


def score_terms(cfg: DWAConfig, lim: LimitsConfig, raw: dict[str, np.ndarray]
           ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    n = {k: raw[k] / sigma for k, sigma in term_scales(cfg, lim).items()}
    total = (cfg.weight_heading * n["heading"] + cfg.weight_clearance * n["clearance"]
             + cfg.weight_velocity * n["velocity"] - cfg.weight_density * n["density"]
             + cfg.weight_evasion * n["evasion"])
    return n, total


def best_admissible(total: np.ndarray, admissible: np.ndarray) -> int:
    if not admissible.any():
        return -1
    return int(np.argmax(np.where(admissible, total, -np.inf)))
