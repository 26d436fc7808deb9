"""Safety shield: certify the planner's command, or replace it (pure: no clock, no I/O).

The certificate (runtime.safety.certificate) says whether a command keeps the robot clear;
`shield` passes a certified command UNCHANGED; otherwise it substitutes the certified DWA
candidate nearest in normalised (v, ω) (ties: lowest cost); otherwise the command's turn in
place (v = 0, its ω) if that is certified; otherwise it brakes: its command is STOP, which the
limits stage (applied last, rate-limited from the last command sent) turns into braking at
decel_max and alpha_max from what the base was told, the braking the certificate models. Not
from odometry's speed: it lags the commands by a feedback period or two, so a brake computed
from it asks for little or no braking on every other cycle (or for speeding up toward the
lagging reading) and the robot brakes at about half the modelled rate. The braked decision's
certificate is that of braking from `state` as the certificate's own model has it.
Every intervention carries a reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from runtime.budget import TimeBudget
from runtime.safety.certificate import (
    Certificate,
    ShieldConfig,
    ShieldWorld,
    brake_command,
    braking_rollout,
    certify,
    certify_batch,
    world_arrays,
)
from runtime.safety.limits import LimitsConfig
from runtime.types import STOP, Twist

# Candidates are certified in chunks, nearest first, each CHUNK_GROWTH times the one before: a
# chunk's cost grows far slower than its size (most is numpy's per-call overhead, and a candidate that
# fails the people test skips the others), the search stops at the first chunk with a
# certified candidate, and the time budget is checked between chunks.
CHUNK = 8  # the first chunk
CHUNK_COST = 3.0  # its time in single certificates (measured 2-3), until one is timed
CHUNK_GROWTH = 4  # each chunk this many times the last one's size; its time is estimated alike


@dataclass(frozen=True)
class ShieldDecision:
    command: Twist
    kind: str  # "passed" | "replaced" (a DWA candidate) | "turned" (in place) | "braked"
    reason: str | None
    certificate: Certificate

    @property
    def intervened(self) -> bool:
        return self.kind != "passed"


def shield(cmd: Twist, state: Twist, candidates: np.ndarray, costs: np.ndarray | None,
           world: ShieldWorld, limits: LimitsConfig, cfg: ShieldConfig, *,
           deadline: float = math.inf, now: Callable[[], float] | None = None,
           budget: TimeBudget | None = None) -> ShieldDecision:
    """Certify `cmd`; pass it unchanged if certified, else the nearest certified candidate
    (candidates (K, 2) of (v, ω), costs (K,) for ties), else brake. Candidates are certified
    in chunks of CHUNK, CHUNK_GROWTH·CHUNK, …; with a clock `now`, the search stops when the
    next chunk (CHUNK_GROWTH times the last one's time; before one is timed, CHUNK_COST times the
    command's certificate) and the winner's certificate would end past `deadline` (braking needs no
    search, so the answer is always in time).
    `budget`: in place of one on `deadline` and `now` (a replay's recorded budget)."""
    wa = world_arrays(world)
    braking = braking_rollout(state, cfg, limits)
    if budget is None:
        budget = TimeBudget(deadline, now)
    cert = certify(cmd, state, world, cfg, limits, wa, braking)
    if cert.ok:
        return ShieldDecision(cmd, "passed", None, cert)
    cand = np.asarray(candidates, dtype=float).reshape(-1, 2)
    out_of_time = False
    if len(cand) and cfg.max_candidates > 0 and cmd.is_finite():
        sv = max(limits.v_max - limits.v_min, 1e-9)
        sw = max(2 * limits.omega_max, 1e-9)
        d = ((cand[:, 0] - cmd.v) / sv) ** 2 + ((cand[:, 1] - cmd.omega) / sw) ** 2
        cost = (np.zeros(len(cand)) if costs is None
                else np.nan_to_num(np.asarray(costs, dtype=float), nan=np.inf))
        order = np.lexsort((cost, d))[: cfg.max_candidates]
        single = budget.lap()  # the command's certificate
        expected = CHUNK_COST * single  # the next chunk's time, until one has been timed
        start, size = 0, CHUNK
        while start < len(order):
            if start:  # as long as the last chunk took, for each of its sizes in this one
                expected = CHUNK_GROWTH * budget.lap()
            if not budget.allows(expected + single):  # the chunk, then the winner's certificate
                out_of_time = True
                break
            chunk = order[start:start + size]
            start, size = start + size, CHUNK_GROWTH * size
            ok = certify_batch(cand[chunk], state, world, cfg, limits, wa, braking)
            if ok.any():
                i = int(chunk[np.argmax(ok)])
                tw = Twist(float(cand[i, 0]), float(cand[i, 1]))
                ci = certify(tw, state, world, cfg, limits, wa, braking)
                return ShieldDecision(tw, "replaced",
                                      f"replaced by candidate {i}: {cert.reason}", ci)
    why = "out of time for candidates" if out_of_time else "no certified candidate"
    if cmd.is_finite() and cmd.omega != 0.0:
        # the planner's turn without its translation: where every candidate drives on into
        # something (the nearest max_candidates are alike), turning is often still free
        turn = Twist(0.0, cmd.omega)
        ct = certify(turn, state, world, cfg, limits, wa, braking)
        if ct.ok:
            return ShieldDecision(turn, "turned", f"turning in place, {why}: {cert.reason}", ct)
    cb = certify(brake_command(state, cfg, limits), state, world, cfg, limits, wa, braking)
    return ShieldDecision(STOP, "braked", f"braking, {why}: {cert.reason}", cb)
