"""The shield's batched certificate decides exactly as the single-command one, and the shield,
which certifies its candidates in batches, decides exactly as it did one candidate at a time.

Seeded random worlds (deterministic): points (some over the footprint), tracks walking in or
standing, with growing std, scans with unknown and shadowed bins, a blind zone, old frames;
states and commands reversing, turning, standing; non-finite commands and candidates."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import replace

import numpy as np

from runtime.config.settings import LimitsConfig
from runtime.safety.certificate import (
    ShieldConfig,
    ShieldWorld,
    brake_command,
    certify,
    certify_batch,
)
from runtime.safety.shield import ShieldDecision, shield
from runtime.types import STOP, Twist

LIM = LimitsConfig()
NB = 64
EDGES = np.deg2rad(np.linspace(-43.5, 43.5, NB + 1))
ANG = 0.5 * (EDGES[:-1] + EDGES[1:])
CONFIGS = (
    ShieldConfig(),
    ShieldConfig(untracked_approach_m_s=0.0),
    ShieldConfig(reverse_into_unseen=True, blind_zone="occupied", lead_depths=1),
    ShieldConfig(model_limits=False, lead_rays=1, lead_depths=1),
    ShieldConfig(max_candidates=9, substeps=2, check_dt=0.013),
)

ONLY = (None, "points", "tracks", "scan")


def random_world(rng: np.random.Generator, only: str | None = None) -> ShieldWorld:
    """`only`: "points", "tracks" or "scan", the others empty or clear (so that one test
    decides more often)."""
    m = 0 if only in ("tracks", "scan") else int(rng.choice([5, 40, 150]))
    pts = rng.uniform([-1.2, -1.2], [1.6, 1.2], (m, 2))
    if m and rng.random() < 0.2:
        pts[0] = rng.uniform(-0.15, 0.15, 2)  # over the footprint: the braking floor applies
    nt = 0 if only in ("points", "scan") else int(rng.integers(1, 4))
    steps = int(rng.choice([1, 2, 12]))
    tk = np.arange(steps)[None, :, None] * 0.1
    p0 = rng.uniform([-0.8, -1.2], [1.5, 1.2], (nt, 1, 2))
    vel = rng.uniform(-1.5, 1.5, (nt, 1, 2)) * (rng.random((nt, 1, 1)) < 0.8)
    std = rng.uniform(0.0, 0.05, (nt, 1)) + rng.uniform(0.0, 0.2, (nt, 1)) * tk[..., 0]
    unknown = rng.random(NB) < rng.choice([0.0, 0.05, 0.3])
    scan = np.where(rng.random(NB) < 0.3, rng.uniform(0.2, 3.0, NB), np.inf)
    blind = None if rng.random() < 0.5 else rng.uniform(0.0, 0.35, NB)
    if only in ("points", "tracks"):
        unknown, scan, blind = np.zeros(NB, bool), np.full(NB, np.inf), None
    return ShieldWorld(points=pts, track_positions=p0 + vel * tk, track_std=std,
                       track_radii=rng.uniform(0.1, 0.35, nt), track_dt=0.1, bin_angles=ANG,
                       unknown=unknown, scan=scan, blind_range=blind,
                       track_ids=tuple(range(10, 10 + nt)) if rng.random() < 0.5 else None,
                       points_age=float(rng.choice([0.0, 0.1])))


def random_twist(rng: np.random.Generator) -> Twist:
    v = float(rng.choice([0.0, LIM.v_min, LIM.v_max, rng.uniform(LIM.v_min, LIM.v_max)]))
    w = float(rng.choice([0.0, rng.uniform(-LIM.omega_max, LIM.omega_max)]))
    return Twist(v, w)


def random_commands(rng: np.random.Generator, k: int, state: Twist) -> np.ndarray:
    cmds = np.stack([rng.uniform(LIM.v_min, LIM.v_max, k),
                     rng.uniform(-LIM.omega_max, LIM.omega_max, k)], 1)
    cmds[rng.random(k) < 0.2, 0] = 0.0  # turning in place, standing
    cmds[rng.random(k) < 0.1] = (state.v, state.omega)
    cmds[rng.random(k) < 0.05, int(rng.integers(0, 2))] = rng.choice([np.nan, np.inf])
    return cmds


def shield_one_by_one(cmd: Twist, state: Twist, candidates: np.ndarray, costs: np.ndarray | None,
                      world: ShieldWorld, limits: LimitsConfig, cfg: ShieldConfig
                      ) -> ShieldDecision:
    """The shield as it was, one `certify` per candidate in nearest-first order (no clock)."""
    cert = certify(cmd, state, world, cfg, limits)
    if cert.ok:
        return ShieldDecision(cmd, "passed", None, cert)
    if len(candidates) and cfg.max_candidates > 0 and cmd.is_finite():
        sv = max(limits.v_max - limits.v_min, 1e-9)
        sw = max(2 * limits.omega_max, 1e-9)
        d = ((candidates[:, 0] - cmd.v) / sv) ** 2 + ((candidates[:, 1] - cmd.omega) / sw) ** 2
        cost = np.zeros(len(candidates)) if costs is None else np.nan_to_num(costs, nan=np.inf)
        for i in np.lexsort((cost, d))[: cfg.max_candidates]:
            tw = Twist(float(candidates[i, 0]), float(candidates[i, 1]))
            ci = certify(tw, state, world, cfg, limits)
            if ci.ok:
                return ShieldDecision(tw, "replaced",
                                      f"replaced by candidate {int(i)}: {cert.reason}", ci)
    if cmd.is_finite() and cmd.omega != 0.0:
        turn = Twist(0.0, cmd.omega)
        ct = certify(turn, state, world, cfg, limits)
        if ct.ok:
            return ShieldDecision(turn, "turned",
                                  f"turning in place, no certified candidate: {cert.reason}", ct)
    return ShieldDecision(STOP, "braked", f"braking, no certified candidate: {cert.reason}",
                          certify(brake_command(state, cfg, limits), state, world, cfg, limits))


def test_batch_decisions_equal_single_certificates_on_random_worlds():
    rng = np.random.default_rng(20240514)
    reasons: list[str] = []
    for trial in range(300):
        world = random_world(rng, ONLY[trial // len(CONFIGS) % 4])
        cfg = CONFIGS[trial % len(CONFIGS)]
        state = random_twist(rng)
        cmds = random_commands(rng, int(rng.integers(1, 20)), state)
        ok = certify_batch(cmds, state, world, cfg, LIM)
        for c, got in zip(cmds, ok):
            cert = certify(Twist(float(c[0]), float(c[1])), state, world, cfg, LIM)
            assert got == cert.ok, (trial, c, cert.reason)
            reasons.append(cert.reason or "ok")
    # every test decided some commands, so the equality above is not vacuous
    assert reasons.count("ok") > 300
    for why in ("cmd would come within", "cmd would come closer than braking to",
                "cmd would drive at (it may be a person walking in)", "cmd would reach track",
                "cmd would enter space outside", "cmd would enter unseen space in bin",
                "cmd would enter space behind", "cmd would enter the camera's blind zone",
                "cmd would pass within a walker's reach of space outside",
                "cmd would pass within a walker's reach of unseen space in bin",
                "cmd would pass within a walker's reach of space behind",
                "non-finite command or state"):
        assert sum(r.startswith(why) for r in reasons) > 3, why


def test_batch_of_nothing_and_a_non_finite_state():
    world = random_world(np.random.default_rng(1), "points")
    assert certify_batch(np.zeros((0, 2)), Twist(), world, ShieldConfig(), LIM).shape == (0,)
    ok = certify_batch(np.zeros((3, 2)), Twist(math.nan, 0.0), world, ShieldConfig(), LIM)
    assert ok.tolist() == [False, False, False]


def test_shield_decides_as_the_one_by_one_search_on_random_worlds():
    rng = np.random.default_rng(7)
    kinds: Counter[str] = Counter()
    for trial in range(300):
        world = random_world(rng, ONLY[trial // len(CONFIGS) % 4])
        cfg = CONFIGS[trial % len(CONFIGS)]
        if trial % 7 == 0:
            cfg = replace(cfg, max_candidates=int(rng.choice([0, 1, 8, 17])))
        state = random_twist(rng)
        cmd = random_twist(rng) if rng.random() < 0.9 else Twist(math.nan, 0.3)
        k = int(rng.choice([0, 3, 30, 30]))
        cand = random_commands(rng, k, state)
        if k > 8 and cmd.is_finite():  # the nearest are much like the command: more chunks
            cand[: k // 2] = (cmd.v, cmd.omega) + rng.normal(0.0, 0.01, (k // 2, 2))
        costs = None if trial % 5 == 0 else np.where(rng.random(k) < 0.05, np.nan, rng.random(k))
        want = shield_one_by_one(cmd, state, cand, costs, world, LIM, cfg)
        got = shield(cmd, state, cand, costs, world, LIM, cfg)
        assert got == want, trial
        kinds[got.kind] += 1
    assert min(kinds[k] for k in ("passed", "replaced", "turned", "braked")) > 3, kinds


def test_a_spent_time_budget_stops_the_search_before_any_candidate():
    """With the deadline already past, no chunk may start: the shield brakes."""
    wall = ShieldWorld(points=np.stack([np.full(50, 0.24), np.linspace(-0.5, 0.5, 50)], 1),
                       bin_angles=ANG, unknown=np.zeros(NB, bool), scan=np.full(NB, np.inf))
    turn = np.array([[0.0, 0.5]])  # certified: the shield takes it when it has the time
    d = shield(Twist(0.1, 0.0), Twist(), turn, None, wall, LIM, ShieldConfig())
    assert d.kind == "replaced"
    clock = iter(range(100))
    d = shield(Twist(0.1, 0.0), Twist(), turn, None, wall, LIM, ShieldConfig(), deadline=0.0,
               now=lambda: float(next(clock)))
    assert d.kind == "braked" and "out of time for candidates" in (d.reason or "")
