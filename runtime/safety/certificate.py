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
  (c) unseen space: while the robot translates (v != 0), its LEAD POINTS must lie inside the
      current footprint disc (|p| <= R + unseen_tolerance) or in SEEN space: inside the camera's
      bearing span, in a bin that is not `unknown`, and nearer than that bin's scan return
      (beyond a return is shadow). The lead points lie on `lead_rays` rays at angles within
      ±lead_half_angle of the direction of travel (heading, or heading+π when reversing), from
      the footprint boundary (R) out to R + untracked_approach·(t + points_age), `lead_depths`
      of them on each, from t = latency on (before, the boundary only): a person may stand
      just out of sight and walk in, like an untracked point in (a), so the robot may not turn
      or drive at speed onto space it has not seen that such a person could reach before it
      stops (lead_depths = 1: the boundary only).
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

`certify_batch` decides many commands in one pass, their trajectories padded to one sample grid;
`certify` is the same computation for one command, explained, so the two always agree.
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
    lead_depths: int = setting(
        3, "points along each lead ray checked against unseen space, from the footprint out to"
        " untracked_approach_m_s × time (1 = the footprint only: a person walking out of unseen"
        " space is not reckoned with)", min=1, max=16)
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
        " so it stands before such a person can reach it, and likewise from unseen space on"
        " its lead rays (0 = off); the fastest walker the"
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


def _brake(x: np.ndarray, rate: float, t: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.maximum(np.abs(x) - rate * t, 0.0)


@dataclass(slots=True)  # not frozen: one per certificate, and frozen ones build slower
class Rollouts:
    """K certificate trajectories on one sample grid. Row k's samples are j <= n[k], every
    check step of its own length plus its exact end time; later ones pad the grid (the robot
    stands where it stopped)."""

    ts: np.ndarray  # (K, N) times
    pose: np.ndarray  # (K, N, 3)
    vs: np.ndarray  # (K, N)
    u: np.ndarray  # (K, 2) the twist held in phase 1
    n: np.ndarray  # (K,) last sample of each row
    h: np.ndarray  # (K,) time between the row's samples
    valid: np.ndarray  # (K, N) whether a sample belongs to its row's trajectory


def rollouts(cmds: np.ndarray, state: Twist, cfg: ShieldConfig, limits: LimitsConfig
             ) -> Rollouts:
    """The certificate's trajectories of K finite commands (K, 2) of (v, ω), all at once."""
    t1 = cfg.latency + cfg.period
    rows = []  # per command (they are few): u, the number of samples and their spacing
    for v, w in np.asarray(cmds, dtype=float).reshape(-1, 2).tolist():
        u = Twist(v, w)
        if cfg.model_limits:
            u = apply_limits(u, state, cfg.period, limits)
        t_stop = t1 + max(abs(u.v) / limits.decel_max, abs(u.omega) / limits.alpha_max)
        steps = max(math.ceil(t_stop / cfg.check_dt - 1e-9), 1)
        rows.append((u.v, u.omega, steps, t_stop / steps if t_stop > 0 else cfg.check_dt))
    table = np.array(rows, dtype=float).reshape(-1, 4)
    uv, uw, h = table[:, :1], table[:, 1:2], table[:, 3]
    n = table[:, 2].astype(int)
    m = cfg.substeps
    ds = (h / m)[:, None]
    tf = np.arange(int(n.max()) * m + 1)[None, :] * ds
    tm = tf[:, :-1] + 0.5 * ds  # midpoints of sub-steps

    def speed_at(t: np.ndarray, now: float, held: np.ndarray, rate: float) -> np.ndarray:
        """v or ω at times t: `now` until the latency, `held` from then, braking at `rate`
        from t1."""
        tb = t - t1
        return np.where(tb >= 0, _brake(held, rate, np.maximum(tb, 0)),
                        np.where(t < cfg.latency, now, held))

    vm = speed_at(tm, state.v, uv, limits.decel_max)
    wm = speed_at(tm, state.omega, uw, limits.alpha_max)
    x, y, th = np.zeros((3, *tf.shape))  # integrated from 0 at t = 0
    np.cumsum(wm * ds, axis=1, out=th[:, 1:])
    thm = 0.5 * (th[:, :-1] + th[:, 1:])
    np.cumsum(vm * np.cos(thm) * ds, axis=1, out=x[:, 1:])
    np.cumsum(vm * np.sin(thm) * ds, axis=1, out=y[:, 1:])
    ts = tf[:, ::m]
    vs = speed_at(ts, state.v, uv, limits.decel_max)
    pose = np.stack([x[:, ::m], y[:, ::m], th[:, ::m]], axis=2)
    return Rollouts(ts, pose, vs, table[:, :2], n, ts[:, 1] - ts[:, 0],
                    np.arange(ts.shape[1])[None, :] <= n[:, None])


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
    """Track centres (T, K, N, 2) and std (T, K, N) at times ts (K, N), piecewise linear with
    linear extrapolation."""
    P, S = wa.tracks, wa.std
    nt, ns = P.shape[0], P.shape[1]
    if ns == 1:
        return (np.broadcast_to(P[:, None, :, :], (nt, *ts.shape, 2)),
                np.broadcast_to(S[:, None, :], (nt, *ts.shape)))
    f = ts / track_dt
    k = np.clip(np.floor(f).astype(int), 0, ns - 2)
    a = (f - k)[None]
    pos = P[:, k] + a[..., None] * (P[:, k + 1] - P[:, k])
    std = S[:, k] + a * (S[:, k + 1] - S[:, k])
    return pos, np.maximum(std, 0.0)


def _swept_distance(c: np.ndarray, p0: np.ndarray, pt: np.ndarray) -> np.ndarray:
    """(T, K, N) distance from the robot's centre c (K, N, 2) to the segment from where each
    track is now, p0 (T, 1, 1, 2), to where it is predicted at that time, pt (T, K, N, 2): a
    person may stop anywhere along the way, so the robot may not bank on them walking on out of
    its path."""
    sx, sy = pt[..., 0] - p0[..., 0], pt[..., 1] - p0[..., 1]
    rx, ry = c[..., 0] - p0[..., 0], c[..., 1] - p0[..., 1]
    along = (rx * sx + ry * sy) / np.maximum(sx * sx + sy * sy, 1e-18)
    np.clip(along, 0.0, 1.0, out=along)
    return np.hypot(rx - along * sx, ry - along * sy)


_OUTSIDE, _UNKNOWN, _SHADOW, _BLIND = 1, 2, 3, 4


def _unseen(wa: WorldArrays, cfg: ShieldConfig, pts: np.ndarray, slack: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """For lead points (L, 2): why each is in unseen space (0 = it is not; _OUTSIDE, _UNKNOWN,
    _SHADOW, _BLIND) and the offending bin (-1 = outside view). Dilated by `slack` (L,) in range
    and bearing."""
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


@dataclass(slots=True)  # not frozen: one per certificate, and frozen ones build slower
class _Margins:
    """How K commands fare in each test, sample by sample (< 0: violated; +inf on the grid's
    padding): what `certify_batch` reduces to decisions and `certify` explains."""

    ts: np.ndarray  # (K, N) sample times
    point_cmd: np.ndarray  # (P,) the command of each (command, point near its path) pair
    point_xy: np.ndarray  # (P, 2) the point
    point_at: np.ndarray  # (E,) the entries of (P, N) (pair, sample) with margins below
    points: np.ndarray  # (E,) margins of (a)
    approach: np.ndarray  # (E,) the untracked-approach margin taken off them
    floor: np.ndarray  # (E,) the braking path's floor taken off them (0: the rule as stated)
    tracks: np.ndarray  # (T, K, N) margins of (b)
    lead_cmd: np.ndarray  # (M,) the command and sample of each translating sample's lead arc
    lead_sample: np.ndarray  # (M,)
    lead_kind: np.ndarray  # (M, L) why a lead point is unseen (0: seen, or inside the disc)
    lead_bin: np.ndarray  # (M, L) its bin (-1: outside the view)


def _point_margins(p: Rollouts, ref: np.ndarray, slack_c: np.ndarray, tol_ref: np.ndarray,
                   pts: np.ndarray, age: float, cfg: ShieldConfig, explain: bool
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                              np.ndarray]:
    """(a) as the _Margins fields from point_cmd to floor, for the (command, point) pairs
    inside each path's bounding box grown by the farthest a point can matter (outside it every
    margin is positive). `explain`: every entry; else only those that may be violated: the
    floor (<= 0) and the approach margin (<= untracked_approach·t) can only take off up to
    that bound from the margin without them (float rounding is monotonic), so an entry whose
    margin without them is at least the bound is not violated, and most entries skip the
    braking path and the bearing."""
    R = cfg.footprint
    speed = cfg.untracked_approach_m_s
    cx, cy = p.pose[..., 0], p.pose[..., 1]  # the padding repeats the last pose: no effect
    reach = (R + slack_c + speed * (p.ts[np.arange(len(p.n)), p.n] + age))[:, None]
    px, py = pts[None, :, 0], pts[None, :, 1]
    near = ((px >= cx.min(axis=1)[:, None] - reach) & (px <= cx.max(axis=1)[:, None] + reach)
            & (py >= cy.min(axis=1)[:, None] - reach) & (py <= cy.max(axis=1)[:, None] + reach))
    pk, pj = np.nonzero(near)
    if not len(pk):
        return pk, pts[pj], pk, np.zeros(0), np.zeros(0), np.zeros(0)
    qx, qy = pts[pj, :1], pts[pj, 1:]
    rx, ry = qx - cx[pk], qy - cy[pk]  # (P, N) the point relative to the centre
    d = np.sqrt(rx * rx + ry * ry)
    base = d - R - slack_c[pk, None]
    late = speed * (p.ts[pk] + age)  # the approach margin, where it applies
    outside = d[:, :1] >= R  # the point is outside the footprint now
    # at the entries: per_sample of a (K, N) array, per_entry of a (P, N) or (P, 1) one
    if explain:
        at = np.arange(d.size)
        k = pk[:, None]

        def per_sample(a: np.ndarray) -> np.ndarray:
            return a[pk]

        def per_entry(a: np.ndarray) -> np.ndarray:
            return a
    else:
        at = np.flatnonzero((base - late < 0) & p.valid[pk])
        i, j = np.divmod(at, d.shape[1])
        k = pk[i]
        kj = k * d.shape[1] + j

        def per_sample(a: np.ndarray) -> np.ndarray:
            return np.ravel(a).take(kj)

        def per_entry(a: np.ndarray) -> np.ndarray:
            return a.take(at) if a.shape[1] > 1 else a.take(i)  # (P, 1): one value a pair
    # where braking would bring a point over the footprint, the command may bring it no closer
    # than braking would (see module docs)
    fx, fy = per_sample(ref[..., 0]) - per_entry(qx), per_sample(ref[..., 1]) - per_entry(qy)
    floor = np.minimum(np.sqrt(fx * fx + fy * fy) - R - slack_c[k] - tol_ref[k], 0.0)
    if speed > 0.0:
        # closing on a point ahead (cos of its bearing from the heading) outside the footprint
        th = per_sample(p.pose[..., 2])
        along = ((per_entry(rx) * np.cos(th) + per_entry(ry) * np.sin(th))
                 / np.maximum(per_entry(d), 1e-9))
        closing = per_sample(p.vs) * along > STILL_M_S  # the robot's speed toward the point
        front = np.abs(along) >= math.cos(math.radians(cfg.approach_half_angle_deg))
        approach = np.where(closing & front & per_entry(outside), per_entry(late), 0.0)
    else:
        approach = np.zeros_like(floor)
    marg = np.where(per_sample(p.valid), per_entry(base) - floor - approach, np.inf)
    return pk, pts[pj], at, np.ravel(marg), np.ravel(approach), np.ravel(floor)


def _track_margins(p: Rollouts, ref: np.ndarray, vmax: np.ndarray, tol_ref: np.ndarray,
                   wa: WorldArrays, track_dt: float, cfg: ShieldConfig) -> np.ndarray:
    """(b) margins (T, K, N)."""
    c = p.pose[..., :2]
    tp, tstd = _track_at(wa, track_dt, p.ts)
    slack_t = (0.5 * (vmax + wa.track_speed + cfg.k_sigma * wa.std_rate) * p.h + 1e-9)[:, None]
    p0 = wa.tracks[:, None, :1, :]  # where each track is now
    reach = cfg.footprint + wa.radii[:, None] + cfg.k_sigma * tstd
    gap = _swept_distance(c, p0, tp) - reach
    # where a track would overlap the footprint of the robot braking now, it may come no closer
    # than that (see module docs)
    braking_gap = _swept_distance(ref, p0, tp) - reach
    floor = np.minimum(braking_gap - slack_t - tol_ref[:, None], 0.0)
    return np.where(p.valid, gap - slack_t - floor, np.inf)


def _lead_fractions(cfg: ShieldConfig) -> np.ndarray:
    """Where the lead points lie along a lead ray, as fractions of the walker's reach."""
    if cfg.lead_depths > 1 and cfg.untracked_approach_m_s > 0.0:
        return np.linspace(0.0, 1.0, cfg.lead_depths)
    return np.zeros(1)


def _lead_kinds(p: Rollouts, vmax: np.ndarray, wmax: np.ndarray, wa: WorldArrays, age: float,
                cfg: ShieldConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(c)/(d) at the lead rays of every translating sample: its command, sample, and each lead
    point's unseen kind and bin, as in _Margins."""
    moving = (p.vs != 0.0) & p.valid
    if cfg.reverse_into_unseen:
        moving &= p.vs > 0.0
    beta = math.radians(cfg.lead_half_angle_deg)
    offs = np.linspace(-beta, beta, cfg.lead_rays) if cfg.lead_rays > 1 else np.zeros(1)
    frac = _lead_fractions(cfg)
    at = np.flatnonzero(moving)
    kk, jj = np.divmod(at, moving.shape[1])
    if not len(at):
        L = len(offs) * len(frac)
        return kk, jj, np.zeros((0, L), np.int8), np.zeros((0, L), int)
    R = cfg.footprint
    pose = p.pose.reshape(-1, 3)[at]
    heading = pose[:, 2] + np.where(p.vs.ravel()[at] < 0, math.pi, 0.0)
    ang = heading[:, None] + offs[None, :]
    # each ray from the footprint out to where a person walking out of unseen space since the
    # depth frame was taken could be by now: (L,) = rays × depths, ray-major
    speed = cfg.untracked_approach_m_s
    # from when the command takes effect: the motion before (the latency) is no command's to
    # change, and checking it with the reach fails every command, braking too, when odometry
    # reads a standing robot creeping by a quantum backwards
    t = p.ts.ravel()[at]
    rate = np.where(t >= cfg.latency, speed, 0.0)
    radius = R + (rate * (t + age))[:, None] * frac[None, :]  # (M, D)
    direction = np.stack([np.cos(ang), np.sin(ang)], axis=2)  # (M, rays, 2)
    lead = pose[:, None, None, :2] + radius[:, None, :, None] * direction[:, :, None, :]
    lead = lead.reshape(-1, 2)
    # how far a lead point moves between samples: the centre, the turn at its radius, the reach
    slack_u = ((vmax[kk, None] + radius * wmax[kk, None] + rate[:, None] * frac[None, :])
               * p.h[kk, None] + 1e-9)
    slack_u = np.broadcast_to(slack_u[:, None, :], (len(kk), len(offs), len(frac))).ravel()
    outside_disc = np.hypot(lead[:, 0], lead[:, 1]) > R + cfg.unseen_tolerance - slack_u
    kind, where = _unseen(wa, cfg, lead, slack_u)
    kind[~outside_disc] = 0
    return kk, jj, kind.reshape(len(kk), -1), where.reshape(len(kk), -1)


@dataclass(slots=True)
class _Paths:
    """K commands' rollouts with what every test derives from them (per row, so a subset of
    rows is tested exactly as it would be among all of them)."""

    p: Rollouts
    ref: np.ndarray  # (K, N, 2) the braking path at the rows' sample times
    vmax: np.ndarray  # (K,) the largest |v| and |ω| of the row's phases
    wmax: np.ndarray
    slack_c: np.ndarray  # (K,) between-sample slack of the robot's own motion
    tol_ref: np.ndarray  # (K,) the two rollouts' integration mismatch

    def rows(self, keep: np.ndarray) -> _Paths:
        p = self.p
        return _Paths(Rollouts(p.ts[keep], p.pose[keep], p.vs[keep], p.u[keep], p.n[keep],
                               p.h[keep], p.valid[keep]), self.ref[keep], self.vmax[keep],
                      self.wmax[keep], self.slack_c[keep], self.tol_ref[keep])


def _paths(cmds: np.ndarray, state: Twist, wa: WorldArrays, cfg: ShieldConfig,
           limits: LimitsConfig, braking: tuple[np.ndarray, np.ndarray] | None) -> _Paths:
    p = rollouts(cmds, state, cfg, limits)
    vmax = np.maximum(abs(state.v), np.abs(p.u[:, 0]))
    wmax = np.maximum(abs(state.omega), np.abs(p.u[:, 1]))
    slack_c = 0.5 * vmax * p.h + 1e-9
    # the two paths' sub-steps fall differently on the phase boundaries: up to one sub-step's
    # motion each (a tolerance of the robot's own speed only: a fast track must not widen it,
    # or the robot may creep on into a person walking at it)
    tol_ref = 2.0 * vmax * p.h / cfg.substeps + 1e-9
    ref = p.pose[..., :2]
    if len(wa.points) or len(wa.tracks):
        rt, rxy = braking if braking is not None else braking_rollout(state, cfg, limits)
        ref = np.stack([np.interp(p.ts, rt, rxy[:, 0]), np.interp(p.ts, rt, rxy[:, 1])], axis=2)
    return _Paths(p, ref, vmax, wmax, slack_c, tol_ref)


def _margins(cmds: np.ndarray, state: Twist, world: ShieldWorld, wa: WorldArrays,
             cfg: ShieldConfig, limits: LimitsConfig,
             braking: tuple[np.ndarray, np.ndarray] | None) -> _Margins:
    """Every test's margins for finite commands (K, 2) from a finite state."""
    q = _paths(cmds, state, wa, cfg, limits, braking)
    p = q.p
    tracks = (_track_margins(p, q.ref, q.vmax, q.tol_ref, wa, world.track_dt, cfg)
              if len(wa.tracks) else np.zeros((0, *p.ts.shape)))
    return _Margins(p.ts, *_point_margins(p, q.ref, q.slack_c, q.tol_ref, wa.points,
                                          max(world.points_age, 0.0), cfg, explain=True),
                    tracks, *_lead_kinds(p, q.vmax, q.wmax, wa, max(world.points_age, 0.0), cfg))


def certify_batch(cmds: np.ndarray, state: Twist, world: ShieldWorld, cfg: ShieldConfig,
                  limits: LimitsConfig | None = None, arrays: WorldArrays | None = None,
                  braking: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """`certify(...).ok` of each of the commands (K, 2) of (v, ω), all in one pass: a
    certificate's cost is mostly numpy's per-call overhead, which the K commands share. A
    decision needs only the pairs of command and point that may be violated, and only the
    commands no earlier test failed: people (b) fail most candidates the shield searches
    when the planner's command failed, so they are tested first, then unseen space (c, d),
    then points (a)."""
    limits = limits if limits is not None else LimitsConfig()
    cmds = np.asarray(cmds, dtype=float).reshape(-1, 2)
    ok = np.all(np.isfinite(cmds), axis=1) & state.is_finite()
    if not ok.any():
        return ok
    wa = arrays if arrays is not None else world_arrays(world)
    q = _paths(cmds[ok], state, wa, cfg, limits, braking)
    alive = np.arange(len(q.vmax))  # rows of q no test has failed yet
    if len(wa.tracks):  # NaN counts as no violation, as argmin finds it in `certify`
        tracks = _track_margins(q.p, q.ref, q.vmax, q.tol_ref, wa, world.track_dt, cfg)
        alive = np.flatnonzero(~(tracks.min(axis=(0, 2)) < 0))
        q = q.rows(alive)
    if len(alive):
        lead_cmd, _, lead_kind, _ = _lead_kinds(q.p, q.vmax, q.wmax, wa,
                                                  max(world.points_age, 0.0), cfg)
        failed = np.zeros(len(alive), dtype=bool)
        failed[lead_cmd[(lead_kind != 0).any(axis=1)]] = True
        alive, q = alive[~failed], q.rows(~failed)
    if len(alive) and len(wa.points):
        mg_cmd, _, at, points, _, _ = _point_margins(
            q.p, q.ref, q.slack_c, q.tol_ref, wa.points, max(world.points_age, 0.0), cfg,
            explain=False)
        failed = np.zeros(len(alive), dtype=bool)
        failed[mg_cmd[at[points < 0] // q.p.ts.shape[1]]] = True
        alive = alive[~failed]
    passed = np.zeros(int(ok.sum()), dtype=bool)
    passed[alive] = True
    ok[ok] = passed
    return ok


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
    mg = _margins(np.array([[cmd.v, cmd.omega]], dtype=float), state, world, wa, cfg, limits,
                  braking)
    ts = mg.ts[0]
    R = cfg.footprint
    best = (math.inf, 0.0)
    failures: list[tuple[float, str]] = []

    if len(mg.point_cmd):
        # (N, Q): `explain` keeps every entry
        marg, approach, floor = (a.reshape(len(mg.point_cmd), -1).T
                                 for a in (mg.points, mg.approach, mg.floor))
        i, j = np.unravel_index(int(np.argmin(marg)), marg.shape)
        margin = float(marg[i, j])
        best = min(best, (margin, float(ts[i])))
        if margin < 0:
            ibad = int(np.argmax((marg < 0).any(axis=1)))
            tbad = float(ts[ibad])
            jbad = int(np.argmax(marg[ibad] < 0))
            p = mg.point_xy[jbad]
            what = ("drive at (it may be a person walking in)" if approach[ibad, jbad] > 0
                    else f"come within {R:.2f} m of" if floor[ibad, jbad] == 0.0
                    else "come closer than braking to")
            failures.append((tbad, (f"cmd would {what} the obstacle point "
                                   f"({p[0]:.2f}, {p[1]:.2f}) at t={tbad:.2f} s")))

    if mg.tracks.size:
        marg = mg.tracks[:, 0]  # (T, N)
        a, k = np.unravel_index(int(np.argmin(marg)), marg.shape)
        best = min(best, (float(marg[a, k]), float(ts[k])))
        if marg[a, k] < 0:
            hit = marg < 0
            first = np.where(hit.any(axis=1), np.argmax(hit, axis=1), len(ts))
            abad = int(np.argmin(first))
            tbad = float(ts[first[abad]])
            tid = world.track_ids[abad] if world.track_ids is not None else abad
            failures.append((tbad, f"cmd would reach track {tid} at t={tbad:.2f} s"))

    bad = (mg.lead_kind != 0).ravel()
    if bad.any():
        f = int(np.argmax(bad))
        tbad = float(ts[mg.lead_sample[f // mg.lead_kind.shape[1]]])
        b = int(mg.lead_bin.ravel()[f])
        reach = "pass within a walker's reach of" if f % len(_lead_fractions(cfg)) else "enter"
        what = {_OUTSIDE: "space outside the camera's view",
                _UNKNOWN: f"unseen space in bin {b}",
                _SHADOW: f"space behind the scan return in bin {b}",
                _BLIND: f"the camera's blind zone in bin {b}"}[int(mg.lead_kind.ravel()[f])]
        failures.append((tbad, f"cmd would {reach} {what} at t={tbad:.2f} s"))

    if failures:
        failures.sort(key=lambda x: x[0])
        return Certificate(False, failures[0][1], best[0], best[1])
    return Certificate(True, None, best[0], best[1])


def braking_rollout(state: Twist, cfg: ShieldConfig, limits: LimitsConfig
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Times (N,) and positions (N, 2) of the robot if the shield brakes now (its fallback);
    it stands where it stops."""
    br = brake_command(state, cfg, limits)
    p = rollouts(np.array([[br.v, br.omega]], dtype=float), state, cfg, limits)
    return p.ts[0], p.pose[0, :, :2]


def brake_command(state: Twist, cfg: ShieldConfig, limits: LimitsConfig) -> Twist:
    """Maximum braking for one period: v toward 0 by decel_max·period, ω by alpha_max·period."""
    dv = limits.decel_max * cfg.period
    dw = limits.alpha_max * cfg.period
    v = math.copysign(max(abs(state.v) - dv, 0.0), state.v) if math.isfinite(state.v) else 0.0
    w = (math.copysign(max(abs(state.omega) - dw, 0.0), state.omega)
         if math.isfinite(state.omega) else 0.0)
    return Twist(v if v != 0.0 else 0.0, w if w != 0.0 else 0.0)
