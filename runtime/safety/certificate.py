"""The shield's certificate: does a command keep the robot clear of everything it knows (pure).

Motion model of a certificate (all in base_link at the time of the world data, t = 0):
  phase 0  [0, latency)                    the robot keeps its current twist `state` (the command
                                           the base is executing until the new one arrives);
  phase 1  [latency, latency + period)     it moves at `u` = apply_limits(cmd, state, period,
                                           limits) (the command as the limits stage, applied
                                           last, will pass it; cfg.model_limits=False: cmd as is);
  phase 2  braking                         v falls to 0 at `limits.decel_max`, ω to 0 at
                                           `limits.alpha_max`, both at once, until both are 0.
The horizon ends when the robot stands still. Unicycle kinematics, integrated with `substeps`
midpoint sub-steps per check step `check_dt`; the footprint is a disc of radius
`robot_radius + margin` (R) around base_link.

Obstacle model (what must stay clear, exactly):
  (a) static points: every point p of `points` must stay at distance >= R from the centre;
      while the robot closes on p (its speed toward p > 0.01 m/s) with p within
      ±approach_half_angle of the direction of travel, at distance >= R + untracked_approach·
      (t + points_age) (p may be a person the tracker has not confirmed, walking in: the robot
      must stand still before they could reach it, or it would have driven into them; they
      have been walking since the depth frame was taken, `points_age` ago).
  (b) tracks: track i's predicted centre moves piecewise linearly through `track_positions[i, k]`
      at times k·track_dt (beyond the last given time it continues with its last segment's
      velocity), its std likewise. A person may stop at any moment (one walking away can turn
      round or stand still), so at time t the centre may be anywhere on the segment from where
      it is now (k = 0) to where it is predicted at t (exact for the constant-velocity
      predictions the planner makes); the robot must stay at distance >= R + radius_i +
      k_sigma·std_i(t) from that whole segment. A person walking away from the robot therefore
      buys it no room: it keeps its distance from where they are now.
  (c) unseen space: while the robot translates (v != 0), its LEAD POINTS — the footprint boundary
      points at angles within ±lead_half_angle of the direction of travel (heading, or heading+π
      when reversing), `lead_rays` of them — must lie inside the current footprint disc
      (|p| <= R + unseen_tolerance) or in SEEN space: inside the camera's bearing span, in a bin
      that is not `unknown`, and nearer than that bin's scan return (beyond a return is shadow).
      Reversing with cfg.reverse_into_unseen=True skips (c) for v < 0 (trusts obstacle memory).
      Pure rotation in place (v == 0) sweeps only the current disc and is never unseen.
      The flanks of the moving disc outside the lead arc are left to obstacle memory (a), which
      remembers what left the 87° view: the camera cannot see them at all.
  (d) blind zone (closer than the camera's minimum range, `blind_range[b]` in base_link):
      an UNKNOWN bin (perception's missing-floor test flags a bin when something closer than the
      minimum range blanks the floor) is occupied over its whole wedge by (c). In a KNOWN bin,
      with cfg.blind_zone == "memory" (default) the blind zone is occupied only where obstacle
      memory holds points (a) — the floor behind it was seen this frame; with "occupied" a lead
      point in a known bin's blind zone (beyond the current disc) is occupied too (strict; it
      forbids all forward motion when blind_range > R + unseen_tolerance).
An obstacle that violates (a) or (b) even if the robot brakes now (a point inside the
footprint; a track whose inflated disc is over it, or reaches it by walking in or by its std
growing) makes every command fail the rule as stated, rotation in place included, and would
freeze the robot where it stands. For such an obstacle the rule becomes: at each time the
command must not bring it any closer than the BRAKING PATH does (the shield's own fallback,
`brake_command` from `state`, rolled out the same way; it stands where it stops), less the
two rollouts' integration mismatch (two sub-steps of the robot's own motion), wherever that
path's gap is below the slack plus that tolerance; elsewhere the rule as stated holds (the two
meet continuously). With the slack as tolerance, a fast track widened it to millimetres and
the robot could creep on at 2 cm/s into a person walking at it. Turning in place and moving away pass; approaching
does not; the robot never makes such a contact worse than braking would, and may step aside.
Compared with the gap at t = 0 instead, a person walking in or one whose std grew failed every
command, and so did every command while odometry's wheel quantisation reported a creep of
7 mm/s during a turn in place: the robot froze beside a person until they left, and in the
simulator they waited for each other.
Discretisation is made conservative: the check at sample times uses slacks (half the distance the
centre / a track / the clearance can change between samples for (a)/(b); a full step of lead-point
motion, as a dilation of bearing and range, for (c)/(d)), so a continuous-time violation of the
model is always caught at the neighbouring sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from runtime.config.schema import derived, setting
from runtime.geometry import bin_layout
from runtime.safety.limits import LimitsConfig, apply_limits
from runtime.types import STILL_M_S, Twist


@dataclass(frozen=True)
class ShieldConfig:
    """Shield settings. Braking rates are not repeated here: the guaranteed deceleration is
    `limits.decel_max` and the angular braking rate `limits.alpha_max` (LimitsConfig)."""

    robot_radius: float = derived(0.17, "radius of the robot's footprint disc",
                                  "robot.radius_m", "m")
    margin: float = setting(0.05, "clearance added to the footprint radius", "m", min=0.0, max=1.0)
    latency: float = setting(0.05, "sensing-to-actuation delay; the current twist is kept that long",
                             "s", min=0.0, max=1.0)
    period: float = derived(0.05, "control period; the new command is held that long before"
                            " braking", "loop.control_hz", "s")
    check_dt: float = setting(0.01, "time between checked samples of the trajectory", "s",
                              min=0.0, max=0.2, min_exclusive=True)
    substeps: int = setting(4, "integration sub-steps per check step", min=1, max=64)
    k_sigma: float = setting(2.0, "tracks are inflated by this many position standard deviations",
                             min=0.0, max=10.0)
    lead_half_angle_deg: float = setting(
        30.0, "half-angle of the footprint's lead arc checked against unseen space", "deg",
        min=0.0, max=90.0)
    lead_rays: int = setting(5, "points on the lead arc checked against unseen space", min=1, max=64)
    unseen_tolerance: float = setting(
        0.005, "a lead point this close outside the current disc still counts as inside", "m",
        min=0.0, max=0.1)
    blind_zone: str = setting(
        "memory", "known bins' space closer than the camera's minimum range: 'memory' = occupied"
        " only where obstacle memory has points; 'occupied' = always occupied",
        choices=("memory", "occupied"))
    reverse_into_unseen: bool = setting(
        False, "certify reversing into space the camera cannot see (trusting obstacle memory)")
    model_limits: bool = setting(
        True, "certify the command as the limits stage will pass it (rate-limited from state)")
    max_candidates: int = setting(64, "most DWA candidates certified per cycle before braking",
                                  min=0, max=100000)
    candidate_budget_s: float = setting(
        0.002, "time the search for a certified replacement may take before the shield brakes"
        " instead", "s", min=0.0, max=0.05)
    untracked_approach_m_s: float = setting(
        1.0, "a remembered point may be a person not (yet) tracked, e.g. one entering from the"
        " side, cut by the view's edge: while the robot closes on a point within"
        " ±approach_half_angle_deg of its heading, it keeps this speed × time as extra distance,"
        " so it stands before such a person can reach it (0 = off); the fastest walker the"
        " robot meets (the simulated crowds walk 0.5-1.0 m/s)", "m/s", min=0.0, max=3.0)
    approach_half_angle_deg: float = setting(
        45.0, "the front, around the direction of travel, where untracked_approach_m_s applies",
        "deg", min=0.0, max=90.0)

    @property
    def footprint(self) -> float:
        return self.robot_radius + self.margin


@dataclass(frozen=True)
class ShieldWorld:
    """The world as the shield sees it, all in base_link at t = 0 (the data's time).

    Tracks: predicted centres at times k·track_dt, k = 0..S-1 from now, in base_link
    (planning_step.predict_tracks_base), their position std, radii and ids (for the reason).
    Scan: bins right to left (perception conventions); `blind_range` None = no blind zone data
    (treated as 0, i.e. only unknown bins are blind).
    """

    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    track_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 1, 2)))
    track_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 1)))
    track_radii: np.ndarray = field(default_factory=lambda: np.zeros(0))
    track_dt: float = 0.1
    bin_angles: np.ndarray = field(default_factory=lambda: np.zeros(0))
    unknown: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    scan: np.ndarray = field(default_factory=lambda: np.zeros(0))
    blind_range: np.ndarray | None = None
    track_ids: tuple[int, ...] | None = None
    points_age: float = 0.0  # s since the depth frame the points were last seen in


@dataclass(frozen=True)
class Certificate:
    ok: bool
    reason: str | None
    min_clearance: float  # smallest margin over (a) and (b), m (inf when nothing to clear)
    time_of_min: float  # s, when it occurs


def _brake(x: float, rate: float, t: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.maximum(abs(x) - rate * t, 0.0)


def rollout(cmd: Twist, state: Twist, cfg: ShieldConfig, limits: LimitsConfig
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Twist]:
    """The certificate's trajectory: times (N,), poses (N, 3), v (N,), ω (N,), and the twist u
    held in phase 1. Samples every check_dt (plus the exact end time)."""
    u = apply_limits(cmd, state, cfg.period, limits) if cfg.model_limits else cmd
    t1 = cfg.latency + cfg.period
    t_stop = t1 + max(abs(u.v) / limits.decel_max, abs(u.omega) / limits.alpha_max)
    n = max(math.ceil(t_stop / cfg.check_dt - 1e-9), 1)
    h = t_stop / n if t_stop > 0 else cfg.check_dt
    m = cfg.substeps
    tf = np.arange(n * m + 1) * (h / m)
    tm = tf[:-1] + 0.5 * (h / m)  # midpoints of sub-steps

    def twist_at(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = np.where(t < cfg.latency, state.v, u.v)
        w = np.where(t < cfg.latency, state.omega, u.omega)
        tb = t - t1
        brake = tb >= 0
        v = np.where(brake, _brake(u.v, limits.decel_max, np.maximum(tb, 0)), v)
        w = np.where(brake, _brake(u.omega, limits.alpha_max, np.maximum(tb, 0)), w)
        return v, w

    vm, wm = twist_at(tm)
    ds = h / m
    th = np.concatenate(([0.0], np.cumsum(wm * ds)))
    thm = 0.5 * (th[:-1] + th[1:])
    x = np.concatenate(([0.0], np.cumsum(vm * np.cos(thm) * ds)))
    y = np.concatenate(([0.0], np.cumsum(vm * np.sin(thm) * ds)))
    idx = np.arange(0, n * m + 1, m)
    ts = tf[idx]
    vs, ws = twist_at(ts)
    # the sampled velocity at phase boundaries: use the larger magnitude of either side
    return ts, np.stack([x[idx], y[idx], th[idx]], axis=1), vs, ws, u


@dataclass(frozen=True)
class WorldArrays:
    """A ShieldWorld as float arrays plus what every certificate against it reuses (computed
    once per shield call, not once per candidate)."""

    points: np.ndarray  # (M, 2)
    tracks: np.ndarray  # (T, S, 2)
    std: np.ndarray  # (T, S)
    radii: np.ndarray  # (T, 1)
    track_speed: float  # largest track speed, m/s (for the between-sample slack)
    std_rate: float  # largest std growth, m/s
    bins_lo: float  # left edge of bin 0, rad
    bin_width: float  # rad
    unknown: np.ndarray  # (B,) bool
    scan: np.ndarray  # (B,)
    blind: np.ndarray  # (B,)


def world_arrays(world: ShieldWorld) -> WorldArrays:
    P = np.asarray(world.track_positions, dtype=float)
    S = np.asarray(world.track_std, dtype=float)
    nt, ns = P.shape[0], P.shape[1]
    speed = srate = 0.0
    if nt and ns > 1:
        speed = float(np.max(np.linalg.norm(np.diff(P, axis=1), axis=2))) / world.track_dt
        srate = float(np.max(np.abs(np.diff(S, axis=1)))) / world.track_dt
    nb = len(world.bin_angles)
    lo, w = bin_layout(np.asarray(world.bin_angles, dtype=float)) if nb else (0.0, 0.0)
    blind = (np.zeros(nb) if world.blind_range is None
             else np.broadcast_to(np.asarray(world.blind_range, dtype=float), (nb,)))
    return WorldArrays(
        points=np.asarray(world.points, dtype=float).reshape(-1, 2), tracks=P, std=S,
        radii=np.asarray(world.track_radii, dtype=float).reshape(nt, 1), track_speed=speed,
        std_rate=srate, bins_lo=lo, bin_width=w, unknown=np.asarray(world.unknown, dtype=bool),
        scan=np.asarray(world.scan, dtype=float), blind=blind)


def _track_at(wa: WorldArrays, track_dt: float, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Track centres (T, N, 2) and std (T, N) at times ts, piecewise linear with linear
    extrapolation."""
    P, S = wa.tracks, wa.std
    ns = P.shape[1]
    if ns == 1:
        return np.repeat(P, len(ts), axis=1), np.repeat(S, len(ts), axis=1)
    f = ts / track_dt
    k = np.clip(np.floor(f).astype(int), 0, ns - 2)
    a = (f - k)[None, :]
    pos = P[:, k] + a[..., None] * (P[:, k + 1] - P[:, k])
    std = S[:, k] + a * (S[:, k + 1] - S[:, k])
    return pos, np.maximum(std, 0.0)


def _swept_distance(c: np.ndarray, p0: np.ndarray, pt: np.ndarray) -> np.ndarray:
    """(T, N) distance from the robot's centre c (N, 2) to the segment from where each track is
    now, p0 (T, 1, 2), to where it is predicted at that time, pt (T, N, 2): a person may stop
    anywhere along the way, so the robot may not bank on them walking on out of its path."""
    seg = pt - p0
    rel = c[None, :, :] - p0
    along = np.einsum("tnk,tnk->tn", rel, seg) / np.maximum(np.einsum("tnk,tnk->tn", seg, seg),
                                                           1e-18)
    np.clip(along, 0.0, 1.0, out=along)
    d = rel - along[..., None] * seg
    return np.hypot(d[..., 0], d[..., 1])


_OUTSIDE, _UNKNOWN, _SHADOW, _BLIND = 1, 2, 3, 4


def _approach_margin(cfg: ShieldConfig, c: np.ndarray, heading: np.ndarray, vs: np.ndarray,
                     ts: np.ndarray, q: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(N, Q) extra distance for untracked points (module docs (a)): untracked_approach·t where
    the robot closes on the point within the front half-angle, else 0. `ts`: times since the
    points were seen (the depth frame's age included: a person walks on while it is read)."""
    rel_x = q[None, :, 0] - c[:, None, 0]
    rel_y = q[None, :, 1] - c[:, None, 1]
    along = (rel_x * np.cos(heading)[:, None] + rel_y * np.sin(heading)[:, None]) / np.maximum(
        d, 1e-9)  # cos of the point's bearing from the heading
    closing = vs[:, None] * along > STILL_M_S  # the robot's speed toward the point
    front = np.abs(along) >= math.cos(math.radians(cfg.approach_half_angle_deg))
    return np.where(closing & front, cfg.untracked_approach_m_s * ts[:, None], 0.0)


def _unseen(wa: WorldArrays, cfg: ShieldConfig, pts: np.ndarray, slack: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """For lead points (L, 2): why each is in unseen space (0 = it is not; _OUTSIDE, _UNKNOWN,
    _SHADOW, _BLIND) and the offending bin (-1 = outside view). Dilated by `slack` in range and
    bearing."""
    nb = len(wa.scan)
    kind = np.zeros(len(pts), dtype=np.int8)
    where = np.full(len(pts), -1)
    if nb == 0:
        kind[:] = _OUTSIDE
        return kind, where
    r = np.hypot(pts[:, 0], pts[:, 1])
    lo, w = wa.bins_lo, wa.bin_width
    phi = np.arctan2(pts[:, 1], pts[:, 0])
    delta = np.arcsin(np.clip(slack / np.maximum(r, 1e-12), 0.0, 1.0))
    delta = np.where(r <= slack, math.pi, delta)
    k0 = np.floor((phi - delta - lo) / w).astype(int)
    k1 = np.floor((phi + delta - lo) / w).astype(int)
    outside = (k0 < 0) | (k1 >= nb)
    kind[outside] = _OUTSIDE
    span = int(np.max(k1 - k0)) if len(pts) else 0
    for j in range(span + 1):
        k = k0 + j
        valid = (~outside) & (k <= k1) & (kind == 0)
        kc = np.clip(k, 0, nb - 1)
        tests = [(_UNKNOWN, wa.unknown[kc]), (_SHADOW, r + slack >= wa.scan[kc])]
        if cfg.blind_zone == "occupied":
            tests.append((_BLIND, r - slack < wa.blind[kc]))
        for code, hit in tests:
            hit = valid & hit & (kind == 0)
            kind[hit] = code
            where[hit] = kc[hit]
    return kind, where


def certify(cmd: Twist, state: Twist, world: ShieldWorld, cfg: ShieldConfig,
            limits: LimitsConfig | None = None, arrays: WorldArrays | None = None,
            braking: tuple[np.ndarray, np.ndarray] | None = None) -> Certificate:
    """Does `cmd`, held as described in the module docs, keep the footprint clear of the
    obstacle model until the robot stands still? (`arrays`: `world_arrays(world)`, `braking`:
    `braking_rollout(state, …)`, when certifying many commands against one world and state.)"""
    limits = limits if limits is not None else LimitsConfig()
    if not (cmd.is_finite() and state.is_finite()):
        return Certificate(False, "non-finite command or state", -math.inf, 0.0)
    wa = arrays if arrays is not None else world_arrays(world)
    ts, pose, vs, _ws, u = rollout(cmd, state, cfg, limits)
    R = cfg.footprint
    c = pose[:, :2]
    h = float(ts[1] - ts[0]) if len(ts) > 1 else cfg.check_dt
    vmax = max(abs(state.v), abs(u.v))
    wmax = max(abs(state.omega), abs(u.omega))
    slack_c = 0.5 * vmax * h + 1e-9
    best = (math.inf, 0.0)
    failures: list[tuple[float, str]] = []
    ref = c
    if len(wa.points) or len(wa.tracks):
        rt, rxy = braking if braking is not None else braking_rollout(state, cfg, limits)
        ref = np.stack([np.interp(ts, rt, rxy[:, 0]), np.interp(ts, rt, rxy[:, 1])], axis=1)
    # the two paths' sub-steps fall differently on the phase boundaries: up to one sub-step's
    # motion each (a tolerance of the robot's own speed only: a fast track must not widen it,
    # or the robot may creep on into a person walking at it)
    tol_ref = 2.0 * vmax * h / cfg.substeps + 1e-9

    # (a) static points: bounding-box prefilter, then all distances
    pts = wa.points
    if len(pts):
        age = max(world.points_age, 0.0)
        reach = R + slack_c + cfg.untracked_approach_m_s * (float(ts[-1]) + age)
        lo_b = c.min(axis=0) - reach
        hi_b = c.max(axis=0) + reach
        near = np.all((pts >= lo_b) & (pts <= hi_b), axis=1)
        q = pts[near]
        if len(q):
            d = np.sqrt(((c[:, None, :] - q[None, :, :]) ** 2).sum(axis=2))  # (N, Q)
            # where braking would bring a point over the footprint, the command may bring it no
            # closer than braking would (see module docs)
            ref_gap = np.sqrt(((ref[:, None, :] - q[None, :, :]) ** 2).sum(axis=2)) - R
            floor = np.minimum(ref_gap - slack_c - tol_ref, 0.0)
            outside = d[0] >= R
            approach = (np.where(outside[None, :],
                                 _approach_margin(cfg, c, pose[:, 2], vs, ts + age, q, d), 0.0)
                        if cfg.untracked_approach_m_s > 0.0 else np.zeros_like(d))
            marg = d - R - slack_c - floor - approach
            i, j = np.unravel_index(int(np.argmin(marg)), marg.shape)
            margin = float(marg[i, j])
            best = min(best, (margin, float(ts[i])))
            if margin < 0:
                ibad = int(np.argmax((marg < 0).any(axis=1)))
                tbad = float(ts[ibad])
                jbad = int(np.argmax(marg[ibad] < 0))
                p = q[jbad]
                what = ("drive at (it may be a person walking in)" if approach[ibad, jbad] > 0
                        else f"come within {R:.2f} m of" if floor[ibad, jbad] == 0.0
                        else "come closer than braking to")
                failures.append((tbad, (f"cmd would {what} the obstacle point "
                                       f"({p[0]:.2f}, {p[1]:.2f}) at t={tbad:.2f} s")))

    # (b) tracks
    nt = len(wa.tracks)
    if nt:
        tp, ts_std = _track_at(wa, world.track_dt, ts)
        slack_t = 0.5 * (vmax + wa.track_speed + cfg.k_sigma * wa.std_rate) * h + 1e-9
        p0 = wa.tracks[:, :1, :]  # where each track is now
        gap = _swept_distance(c, p0, tp) - (R + wa.radii + cfg.k_sigma * ts_std)  # (T, N)
        # where a track would overlap the footprint of the robot braking now, it may come no
        # closer than that (see module docs)
        braking_gap = _swept_distance(ref, p0, tp) - (R + wa.radii + cfg.k_sigma * ts_std)
        floor = np.minimum(braking_gap - slack_t - tol_ref, 0.0)
        marg = gap - slack_t - floor
        a, k = np.unravel_index(int(np.argmin(marg)), marg.shape)
        best = min(best, (float(marg[a, k]), float(ts[k])))
        if marg[a, k] < 0:
            hit = marg < 0
            first = np.where(hit.any(axis=1), np.argmax(hit, axis=1), len(ts))
            abad = int(np.argmin(first))
            tbad = float(ts[first[abad]])
            tid = world.track_ids[abad] if world.track_ids is not None else abad
            failures.append((tbad, f"cmd would reach track {tid} at t={tbad:.2f} s"))

    # (c)/(d) unseen space at the lead arc
    moving = vs != 0.0
    if cfg.reverse_into_unseen:
        moving &= vs > 0.0
    if moving.any():
        beta = math.radians(cfg.lead_half_angle_deg)
        offs = np.linspace(-beta, beta, cfg.lead_rays) if cfg.lead_rays > 1 else np.zeros(1)
        kk = np.nonzero(moving)[0]
        heading = pose[kk, 2] + np.where(vs[kk] < 0, math.pi, 0.0)
        ang = heading[:, None] + offs[None, :]
        lead = c[kk, None, :] + R * np.stack([np.cos(ang), np.sin(ang)], axis=2)
        lead = lead.reshape(-1, 2)
        slack_u = (vmax + R * wmax) * h + 1e-9
        outside_disc = np.hypot(lead[:, 0], lead[:, 1]) > R + cfg.unseen_tolerance - slack_u
        kind, where = _unseen(wa, cfg, lead, slack_u)
        bad = (kind != 0) & outside_disc
        if bad.any():
            f = int(np.argmax(bad))
            tbad = float(ts[kk[f // len(offs)]])
            b = int(where[f])
            what = {_OUTSIDE: "space outside the camera's view",
                    _UNKNOWN: f"unseen space in bin {b}",
                    _SHADOW: f"space behind the scan return in bin {b}",
                    _BLIND: f"the camera's blind zone in bin {b}"}[int(kind[f])]
            failures.append((tbad, f"cmd would enter {what} at t={tbad:.2f} s"))

    if failures:
        failures.sort(key=lambda x: x[0])
        return Certificate(False, failures[0][1], best[0], best[1])
    return Certificate(True, None, best[0], best[1])


def braking_rollout(state: Twist, cfg: ShieldConfig, limits: LimitsConfig
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) and positions (N, 2) of the robot if the shield brakes now (its fallback);
    it stands where it stops."""
    rt, rpose, *_ = rollout(brake_command(state, cfg, limits), state, cfg, limits)
    return rt, rpose[:, :2]


def brake_command(state: Twist, cfg: ShieldConfig, limits: LimitsConfig) -> Twist:
    """Maximum braking for one period: v toward 0 by decel_max·period, ω by alpha_max·period."""
    dv = limits.decel_max * cfg.period
    dw = limits.alpha_max * cfg.period
    v = math.copysign(max(abs(state.v) - dv, 0.0), state.v) if math.isfinite(state.v) else 0.0
    w = (math.copysign(max(abs(state.omega) - dw, 0.0), state.omega)
         if math.isfinite(state.omega) else 0.0)
    return Twist(v if v != 0.0 else 0.0, w if w != 0.0 else 0.0)
