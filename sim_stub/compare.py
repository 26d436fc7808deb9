"""Whether one planner beats another on the same episodes, or only drew luckier seeds.

`safemove eval` runs every planner on the same seeded episodes, so two results pair episode for
episode: only the episodes that one planner succeeded and the other did not say anything about
which is better. McNemar's exact test asks how likely a split of those discordant episodes at
least that uneven would be if neither planner were better; each success rate also gets its
95 % Wilson interval (sim_stub.binomial).

A result may be several files for one label (a policy scored on the test seeds and on the
validation seeds): their episodes are pooled, and no (scenario, seed) may appear twice.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.depth_source import D435_HFOV_DEG
from runtime.errors import UserError
from sim_stub.binomial import CONFIDENCE, mcnemar_exact_p, wilson_interval

# the settings that must agree for two results' episodes to be the same episodes
_CONDITIONS = ("fps", "noise", "crowd", "camera_hfov_deg")


@dataclass(frozen=True)
class Evaluation:
    """One planner's outcomes: success or not per (scenario, seed)."""

    label: str
    sources: tuple[Path, ...]
    conditions: dict[str, Any]
    success: dict[str, dict[int, bool]]


def _read(path: Path) -> tuple[dict[str, Any], list[tuple[str, int, bool]]]:
    """One `safemove eval --json` result: its conditions and (scenario, seed, success) rows."""
    try:
        result = json.loads(path.read_text())
    except OSError as exc:
        raise UserError(f"compare: {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"compare: {path}: not a `safemove eval --json` result ({exc})") from None
    if not isinstance(result, dict) or not isinstance(result.get("episodes"), list):
        raise UserError(f"compare: {path}: no 'episodes' list (not a `safemove eval --json`"
                        " result)")
    rows = []
    for i, ep in enumerate(result["episodes"]):
        try:
            scenario, seed, status = ep["scenario"], ep["seed"], ep["status"]
        except (KeyError, TypeError):
            raise UserError(f"compare: {path}: episodes[{i}] lacks 'scenario', 'seed' or"
                            " 'status'") from None
        if not isinstance(scenario, str) or isinstance(seed, bool) or not isinstance(seed, int):
            raise UserError(f"compare: {path}: episodes[{i}] has a bad scenario or seed")
        rows.append((scenario, seed, status == "success"))
    conditions = {k: result.get(k) for k in _CONDITIONS}
    if conditions["camera_hfov_deg"] is None:  # results from before --camera-hfov: the D435's
        conditions["camera_hfov_deg"] = D435_HFOV_DEG
    return conditions, rows


def _differ(a: dict[str, Any], b: dict[str, Any]) -> str:
    """The settings in which two results' conditions differ, as `key=a (b)`."""
    return ", ".join(f"{k}={a[k]} (against {b[k]})" for k in _CONDITIONS if a[k] != b[k])


def load_evaluation(label: str, paths: list[Path]) -> Evaluation:
    """The pooled episodes of `paths`, which must share their conditions and no episode."""
    conditions: dict[str, Any] | None = None
    success: dict[str, dict[int, bool]] = {}
    for path in paths:
        found, rows = _read(path)
        if conditions is not None and found != conditions:
            raise UserError(f"compare: {path}: ran with {_differ(found, conditions)} in"
                            f" {paths[0]}")
        conditions = found
        for scenario, seed, ok in rows:
            seeds = success.setdefault(scenario, {})
            if seed in seeds:
                raise UserError(f"compare: {path}: {scenario} seed {seed} appears twice in"
                                f" {label}")
            seeds[seed] = ok
    assert conditions is not None  # paths is never empty (the parser wants one)
    return Evaluation(label, tuple(paths), conditions, success)


def _seed_span(seeds: set[int]) -> str:
    return f"{len(seeds)} seeds ({min(seeds)}-{max(seeds)})" if seeds else "no seeds"


def compare(evaluations: list[Evaluation]) -> dict[str, Any]:
    """Per scenario of the first (the reference): every evaluation's success rate with its
    interval, and each other one against the reference, paired by seed."""
    reference, others = evaluations[0], evaluations[1:]
    for other in others:
        if other.conditions != reference.conditions:
            raise UserError(f"compare: {other.label} ran with"
                            f" {_differ(other.conditions, reference.conditions)} in"
                            f" {reference.label}: not the same episodes")
        for scenario, seeds in reference.success.items():
            theirs = set(other.success.get(scenario, {}))
            if theirs != set(seeds):
                raise UserError(f"compare: {other.label} has {_seed_span(theirs)} of"
                                f" {scenario}, {reference.label} {_seed_span(set(seeds))}:"
                                " compare results on the same episodes")
    scenarios: dict[str, Any] = {}
    for scenario, ref in reference.success.items():
        rates = {}
        for ev in evaluations:
            k, n = sum(ev.success[scenario].values()), len(ev.success[scenario])
            lo, hi = wilson_interval(k, n)
            rates[ev.label] = {"successes": k, "episodes": n, "success_rate": k / n,
                               "ci95": [lo, hi]}
        paired = {}
        for other in others:
            theirs = other.success[scenario]
            only_ref = sum(ref[s] and not theirs[s] for s in ref)
            only_other = sum(theirs[s] and not ref[s] for s in ref)
            paired[other.label] = {
                "difference": (sum(theirs.values()) - sum(ref.values())) / len(ref),
                "only_reference": only_ref, "only_this": only_other,
                "p_value": mcnemar_exact_p(only_ref, only_other)}
        scenarios[scenario] = {"rates": rates, "against_reference": paired}
    return {"reference": reference.label, "confidence": CONFIDENCE,
            "sources": {ev.label: [str(p) for p in ev.sources] for ev in evaluations},
            "scenarios": scenarios}


def table(result: dict[str, Any]) -> str:
    """The comparison as text: rates with intervals, then each against the reference."""
    ref = result["reference"]
    rows = [(f"{'scenario':<16}{'planner':<22}{'success':>8}{'95 % CI':>13}"
             f"{'vs ' + ref:>24}{'only ref/this':>15}{'p':>8}")]
    for scenario, s in result["scenarios"].items():
        for label, r in s["rates"].items():
            lo, hi = r["ci95"]
            vs, split, p = "", "", ""
            if label in s["against_reference"]:
                c = s["against_reference"][label]
                vs = f"{100 * c['difference']:+.1f} pts"
                split = f"{c['only_reference']}/{c['only_this']}"
                p = f"{c['p_value']:.3f}"
            ci = f"{100 * lo:.1f}-{100 * hi:.1f}%"
            rows.append(f"{scenario:<16}{label:<22}{100 * r['success_rate']:>7.1f}%{ci:>13}"
                        f"{vs:>24}{split:>15}{p:>8}")
    return "\n".join(rows)
