"""The DWA stage's settings and result (runtime.planning.dwa has the model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from runtime.config.schema import derived, setting


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
    refine_max_rounds: int = setting(
        3, "refinement: most rounds per call (round r samples at 2^-(r+1) of the coarse"
        " spacing; the shipped window after 3 rounds is finer than the base's 1 mm/s wheel"
        " command)", min=0, max=50)
    weight_heading: float = setting(1.0, "α: weight of the heading term", min=0.0)
    weight_clearance: float = setting(1.0, "β: weight of the clearance term", min=0.0)
    weight_velocity: float = setting(2.0, "γ: weight of the velocity term", min=0.0)
    weight_density: float = setting(0.2, "δ: weight of the density penalty", min=0.0)
    weight_evasion: float = setting(
        3.0, "ε: weight of the evasion penalty, how deep a walking person's predicted disc"
        " overlaps the sample's rollout, or the robot standing at its end while they walk on"
        " for another horizon (0: off, Fox et al.'s DWA)", min=0.0)
    evasion_cap_m: float = setting(1.0, "σ of the evasion term: the overlap depth that counts as"
                                   " 1 (deeper overlaps count as this)", "m", min=0.01, max=5.0)
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
    evasion: np.ndarray
    total: np.ndarray  # (K,) G, maximised
    admissible: np.ndarray  # (K,) bool
    raw: dict[str, np.ndarray]  # un-normalised terms (heading, clearance, velocity, density, evasion)
    best_index: int
    best: tuple[float, float]
    best_path: np.ndarray  # (steps, 3) x, y, θ
    admissible_best: bool
    evaluated: int
    refine_rounds: int
    budget_cut: bool
