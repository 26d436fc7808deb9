"""Dynamic-window local planner with the SafeMove-RL cost, vectorised and anytime.

Frame and time: everything is in base_link at the current time (robot at the origin, heading 0).
Rollout step k (k = 0..steps-1) is the pose at t_k = (k+1)·dt under constant (v, ω) (exact
unicycle arc). Dynamic obstacles come as positions predicted at the SAME times: (T, steps, 2)
centres and (T, steps) radii that already include the growing uncertainty (the planning step
builds them with `planning_step.predict_tracks_base`: constant velocity, radius = track radius
+ min(k_sigma·std, cap)).

Cost (maximised): G = α·heading + β·clearance + γ·velocity − δ·density + ε·evasion, each term
divided by a fixed scale σ (`term_scales`: π, clearance_cap_m, the top speed, density_scale,
evasion_cap_m), so the weights mean the same in every window. Normalising over the evaluated
samples instead (min–max, or by the largest) stretches differences of millimetres across a
narrow dynamic window until they outvote everything: it kept the robot creeping at a few cm/s
toward anything within the clearance cap. Raw terms of one sample:
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
- evasion   = max(−evasion_cap, min over walking tracks of their gap) ≤ 0: how deep the predicted
  disc of a person walking (a track whose predicted centre moves) overlaps the rollout, or the
  robot standing at the rollout's end while the person walks on at the same velocity for another
  horizon (braking or backing off only puts the meeting past the horizon; it is no escape). On
  by default (ε = 3; 0 is Fox et al.'s DWA). Fox et al.'s admissibility counts a sample
  admissible when it can stop before its first collision, which a standing robot always can:
  standing in the path of a person who does not see it scores as well as stepping aside
  (clearance is 0 for both), and the robot stops before the person and is walked into. With
  this term the deeper overlap costs more, so the robot turns off the person's line cycle by
  cycle while the person is still seconds away (one cycle's window holds only a little turn).
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
exactly; the rest are processed in cache-sized groups (see `Evaluator`).

Budget (the stage is pure, no clock reads of its own): the caller passes an absolute `deadline`
and the clock `now` it is measured on (the loop: `deadline=time.monotonic() + cfg.budget_s,
now=time.monotonic`; tests: a fake clock). The coarse grid is evaluated in interleaved blocks of
block_samples (every prefix of blocks spans the whole window); the first block always runs, each
further block and each refinement round (a finer n×n grid around the current best, half the
spacing each round, up to refine_max_rounds) only while the slowest such step so far would end
by the deadline. With `now=None` only the counts bound the work (deterministic). If no sample is
admissible the result is the strongest braking sample in the window with admissible_best False.
"""

from runtime.planning.dwa.config import DWAConfig, DWAResult
from runtime.planning.dwa.search import plan, plan_coarse

__all__ = ["DWAConfig", "DWAResult", "plan", "plan_coarse"]
