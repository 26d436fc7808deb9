"""The DWA's anytime search: the coarse grid in interleaved blocks, then refinement rounds
around the best sample, each only while the time budget allows (runtime.planning.dwa)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from runtime.budget import TimeBudget
from runtime.planning.dwa.config import DWAConfig, DWAResult
from runtime.planning.dwa.cost import Evaluator, best_admissible, score_terms
from runtime.planning.dwa.window import braking_sample, grid_spacing, prepare, unit_arcs
from runtime.safety.limits import LimitsConfig


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
    budget: TimeBudget | None = None,
) -> DWAResult:
    """One planning call (see the module docs for frames, cost, admissibility and budget).
    `budget`: in place of one on `deadline` and `now` (a replay's recorded budget)."""
    clock = budget if budget is not None else TimeBudget(deadline, now)
    prep = prepare(cfg, lim, v0, omega0, points)
    steps = prep.steps
    if obs_pos is None:
        obs_pos, obs_radius = np.zeros((0, steps, 2)), np.zeros((0, steps))
    elif obs_radius is None:
        raise ValueError("plan: obs_pos given without obs_radius")
    ev = Evaluator(cfg, lim, prep, goal, obs_pos, obs_radius)
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
    _, total = score_terms(cfg, lim, raw)
    best = best_admissible(total, raw["admissible"])
    rounds = 0
    v_lo, v_hi, w_lo, w_hi = prep.window
    dv, dw = grid_spacing(cfg, prep.window)
    grid = _refine_offsets(cfg.refine_n)
    found_samples, found = [samples], [raw]
    evaluated = len(samples)
    best_sample = samples[best] if best >= 0 else None
    best_total = float(total[best]) if best >= 0 else -math.inf
    # a round has no more samples than a coarse block: the slowest block bounds the first round
    while best_sample is not None and rounds < cfg.refine_max_rounds and (dv > 0 or dw > 0):
        if not clock.allows(slowest):
            break
        new = best_sample + grid * np.array([dv, dw]) * 0.5**rounds
        new[:, 0] = np.clip(new[:, 0], v_lo, v_hi)
        new[:, 1] = np.clip(new[:, 1], w_lo, w_hi)
        r = ev.evaluate(new)
        # the terms are per sample: scoring a round alone equals scoring it with all before it
        _, round_total = score_terms(cfg, lim, r)
        i = best_admissible(round_total, r["admissible"])
        if i >= 0 and round_total[i] > best_total:  # ties keep the earlier sample
            best, best_sample, best_total = evaluated + i, new[i], float(round_total[i])
        found_samples.append(new)
        found.append(r)
        evaluated += len(new)
        rounds += 1
        lap = clock.lap()
        slowest = lap if rounds == 1 else max(slowest, lap)
    if rounds:
        samples = np.concatenate(found_samples)
        raw = {k: np.concatenate([f[k] for f in found]) for k in raw}
    if best < 0:  # nothing admissible: brake
        brake = np.array([braking_sample(prep.window)])
        r = ev.evaluate(brake)
        samples = np.concatenate([samples, brake])
        raw = {k: np.concatenate([raw[k], r[k]]) for k in raw}
        best = len(samples) - 1
        evaluated += 1
    norm, total = score_terms(cfg, lim, raw)
    bv, bw = float(samples[best, 0]), float(samples[best, 1])
    ux, uy = unit_arcs(np.array([bw]), prep.times)
    bx, by, bth = ux[:, 0] * bv, uy[:, 0] * bv, prep.times * bw
    return DWAResult(
        samples=samples, heading=norm["heading"], clearance=norm["clearance"],
        velocity=norm["velocity"], density=norm["density"], evasion=norm["evasion"],
        total=total,
        admissible=raw["admissible"],
        raw={k: raw[k] for k in ("heading", "clearance", "velocity", "density", "evasion")},
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
