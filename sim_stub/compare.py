"""Whether one planner beats another, or only drew luckier episodes or a luckier training seed.

`safemove eval` runs every planner on the same seeded episodes, so two results of one run each
pair episode for episode: only the episodes that one planner succeeded in and the other did not
say which is better. McNemar's exact test asks how likely a split of those discordant episodes
at least that uneven would be if neither were better; each rate gets its 95 % Wilson interval
(sim_stub.binomial).

A trained policy is also one draw of its training seed, which moves the rates as much as the
episodes do. Given several training runs of each (every run scored on the same episodes), the
comparison is between runs: each run's rate is one sample, the rate's interval is
Student's t over the runs, and two planners differ by Welch's t-test. Episodes of one run may
come from several files (the test and the validation seeds), pooled; no (scenario, seed) may
appear twice in one run. Eval's what-ifs of sensing (`--camera-hfov`, `--surround-people`)
change what the robot knows, not the episodes, so planners may differ in them (what the sensing
buys, paired by episode).

Success is the default outcome; the others count collisions, and, since a policy's decisions
can only avoid people it saw coming, collisions with a person who had been in the camera's view
for at least `seen_s`, a second unless told (`seen-collision`), apart from the rest
(`unseen-collision`: out of view, just entered it, or a fixed obstacle).
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import ttest_1samp, ttest_ind

from drivers.depth_source import D435_HFOV_DEG
from runtime.errors import UserError
from sim_stub.binomial import CONFIDENCE, mcnemar_exact_p, wilson_interval

# the settings that must agree between planners: the crowd makes the world, the frame rate and
# noise the sensor model every planner is scored under
_EPISODE_CONDITIONS = ("fps", "noise", "crowd")
# eval's what-ifs of sensing (a wider camera, people seen all around): the same episodes (the
# world and the renderer's noise draw from their own seeded streams), the robot knowing more.
# Planners may differ in them (what the sensing buys, paired by episode); one planner's pooled
# files may not
_SENSING = ("camera_hfov_deg", "surround_people")
_CONDITIONS = _EPISODE_CONDITIONS + _SENSING

OUTCOMES = ("success", "collision", "seen-collision", "unseen-collision")


@dataclass(frozen=True)
class Outcome:
    """What an episode counts as. `seen_s`: how long a person must have been in the camera's
    view for a collision with them to count as seen coming."""

    name: str = "success"
    seen_s: float = 1.0

    def __post_init__(self) -> None:
        if self.name not in OUTCOMES:
            raise ValueError(f"outcome {self.name!r}: one of {OUTCOMES}")

    def __str__(self) -> str:
        return self.name if "seen" not in self.name else f"{self.name} ({self.seen_s:g} s)"

    def of(self, ep: dict[str, Any]) -> bool | None:
        """Whether the episode ended in this outcome; None when the result cannot tell (no
        number in `contact_in_view_s`: a result from before it was recorded)."""
        if self.name == "success":
            return ep["status"] == "success"
        if ep["status"] != "collision":
            return False
        if self.name == "collision":
            return True
        if "contact_in_view_s" not in ep:
            return None
        in_view = ep["contact_in_view_s"]
        if in_view is None:  # a fixed obstacle
            seen = False
        elif (seconds := _finite(in_view)) is not None:
            seen = seconds >= self.seen_s
        else:
            return None
        return seen == (self.name == "seen-collision")


@dataclass(frozen=True)
class Run:
    """One policy's (one training run's) outcomes: the outcome or not per (scenario, seed)."""

    sources: tuple[Path, ...]
    outcome: dict[str, dict[int, bool]]

    def rate(self, scenario: str) -> float:
        outcomes = self.outcome[scenario]
        return sum(outcomes.values()) / len(outcomes)


@dataclass(frozen=True)
class Evaluation:
    """One planner: its training runs (one for DWA or a single policy)."""

    label: str
    conditions: dict[str, Any]
    runs: tuple[Run, ...]
    outcome: Outcome = Outcome()


def _read(path: Path, outcome: Outcome) -> tuple[dict[str, Any], list[tuple[str, int, bool]]]:
    """One `safemove eval --json` result: its conditions and (scenario, seed, outcome) rows."""
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
            scenario, seed, has = ep["scenario"], ep["seed"], outcome.of(ep)
        except (KeyError, TypeError):
            raise UserError(f"compare: {path}: episodes[{i}] lacks 'scenario', 'seed' or"
                            " 'status'") from None
        if not isinstance(scenario, str) or isinstance(seed, bool) or not isinstance(seed, int):
            raise UserError(f"compare: {path}: episodes[{i}] has a bad scenario or seed")
        if has is None:
            raise UserError(f"compare: {path}: episodes[{i}] ({scenario} seed {seed}) has no"
                            f" number in 'contact_in_view_s', which --outcome {outcome.name}"
                            " needs (results from before it was recorded lack it: evaluate"
                            " again)")
        rows.append((scenario, seed, has))
    if not rows:
        raise UserError(f"compare: {path}: no episodes")
    conditions = {k: result.get(k) for k in _CONDITIONS}
    if conditions["camera_hfov_deg"] is None:  # results from before --camera-hfov: the D435's
        conditions["camera_hfov_deg"] = D435_HFOV_DEG
    if conditions["surround_people"] is None:  # from before --surround-people: the camera only
        conditions["surround_people"] = False
    return conditions, rows


def _differ(a: dict[str, Any], b: dict[str, Any],
            keys: tuple[str, ...] = _CONDITIONS) -> str:
    """The settings among `keys` in which two results' conditions differ, as `key=a (against
    b)`."""
    return ", ".join(f"{k}={a[k]} (against {b[k]})" for k in keys if a[k] != b[k])


def load_evaluation(label: str, runs: list[list[Path]],
                    outcome: Outcome = Outcome()) -> Evaluation:
    """`runs`: each run's files, whose episodes pool; every file under one label must have run
    under the same conditions."""
    first: tuple[Path, dict[str, Any]] | None = None
    loaded = []
    for paths in runs:
        found_outcomes: dict[str, dict[int, bool]] = {}
        for path in paths:
            found, rows = _read(path, outcome)
            if first is None:
                first = (path, found)
            elif found != first[1]:
                raise UserError(f"compare: {path}: ran with {_differ(found, first[1])} in"
                                f" {first[0]}")
            for scenario, seed, ok in rows:
                seeds = found_outcomes.setdefault(scenario, {})
                if seed in seeds:
                    raise UserError(f"compare: {path}: {scenario} seed {seed} appears twice in"
                                    f" one run of {label}")
                seeds[seed] = ok
        loaded.append(Run(tuple(paths), found_outcomes))
    assert first is not None  # the parser wants at least one file
    return Evaluation(label, first[1], tuple(loaded), outcome)


def _seed_span(seeds: set[int]) -> str:
    return f"{len(seeds)} seeds ({min(seeds)}-{max(seeds)})" if seeds else "no seeds"


def _check_same_episodes(reference: Evaluation, others: list[Evaluation]) -> None:
    for other in others:
        if differ := _differ(other.conditions, reference.conditions, _EPISODE_CONDITIONS):
            raise UserError(f"compare: {other.label} ran with {differ} in {reference.label}:"
                            " not the same episodes")
    expected = reference.runs[0].outcome
    for ev in [reference, *others]:
        for i, run in enumerate(ev.runs):
            name = ev.label if len(ev.runs) == 1 else f"{ev.label} run {i + 1}"
            if set(run.outcome) != set(expected):
                raise UserError(f"compare: {name} has scenarios {sorted(run.outcome)},"
                                f" {reference.label} {sorted(expected)}: compare results on"
                                " the same episodes")
            for scenario, seeds in expected.items():
                theirs = set(run.outcome[scenario])
                if theirs != set(seeds):
                    raise UserError(f"compare: {name} has {_seed_span(theirs)} of {scenario},"
                                    f" {reference.label} {_seed_span(set(seeds))}: compare"
                                    " results on the same episodes")


def _finite(x: Any) -> float | None:
    """x as a float, or None where it is no finite number (NaN, infinite, a bool, a string, or
    an integer beyond the float range, as a lying JSON file can hold)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    try:
        x = float(x)
    except OverflowError:
        return None
    return x if math.isfinite(x) else None


def _rates(ev: Evaluation, scenario: str) -> dict[str, Any]:
    """The outcome's rate over one run (Wilson interval) or the mean over runs (Student's t
    interval)."""
    rates = [run.rate(scenario) for run in ev.runs]
    if len(ev.runs) == 1:
        outcomes = ev.runs[0].outcome[scenario]
        lo, hi = wilson_interval(sum(outcomes.values()), len(outcomes))
        return {"runs": 1, "episodes": len(outcomes), "rate": rates[0],
                "ci95": [lo, hi], "interval": "wilson"}
    if np.ptp(rates) == 0.0:  # every run alike: no spread to scale t by
        lo = hi = rates[0]
    else:
        ci = ttest_1samp(rates, 0.0).confidence_interval(CONFIDENCE)
        lo, hi = max(0.0, float(ci.low)), min(1.0, float(ci.high))
    return {"runs": len(rates), "episodes": len(ev.runs[0].outcome[scenario]),
            "run_rates": rates, "rate": float(np.mean(rates)), "ci95": [lo, hi],
            "interval": "student t over runs"}


def _paired(reference: Run, other: Run, scenario: str) -> dict[str, Any]:
    """One run each on the same episodes: McNemar's exact test."""
    ref, theirs = reference.outcome[scenario], other.outcome[scenario]
    only_ref = sum(ref[s] and not theirs[s] for s in ref)
    only_other = sum(theirs[s] and not ref[s] for s in ref)
    return {"test": "mcnemar exact", "difference": (only_other - only_ref) / len(ref),
            "only_reference": only_ref, "only_this": only_other,
            "p_value": mcnemar_exact_p(only_ref, only_other)}


def _between_runs(reference: Evaluation, other: Evaluation, scenario: str) -> dict[str, Any]:
    """Several runs each: Welch's t-test on the runs' rates."""
    ref = [run.rate(scenario) for run in reference.runs]
    theirs = [run.rate(scenario) for run in other.runs]
    difference = float(np.mean(theirs) - np.mean(ref))
    if np.ptp(ref) == 0.0 and np.ptp(theirs) == 0.0:  # no spread: no test
        p, lo, hi = (1.0 if difference == 0.0 else 0.0), difference, difference
    else:
        with warnings.catch_warnings():  # one side without spread: scipy warns, still answers
            warnings.simplefilter("ignore", RuntimeWarning)
            test = ttest_ind(theirs, ref, equal_var=False)
            ci = test.confidence_interval(CONFIDENCE)
        p, lo, hi = float(test.pvalue), float(ci.low), float(ci.high)
    return {"test": "welch t over runs", "difference": difference, "ci95": [_finite(lo),
            _finite(hi)], "p_value": _finite(p)}


def compare(evaluations: list[Evaluation]) -> dict[str, Any]:
    """Per scenario of the reference (the first): every planner's rate of the outcome with its
    interval, and each other one against the reference."""
    reference, others = evaluations[0], evaluations[1:]
    assert all(ev.outcome == reference.outcome for ev in others)  # one --outcome for all
    _check_same_episodes(reference, others)
    for other in others:
        if (len(other.runs) == 1) != (len(reference.runs) == 1):
            raise UserError(f"compare: {reference.label} has {len(reference.runs)} run(s),"
                            f" {other.label} {len(other.runs)}: give one run each (paired by"
                            " episode) or two or more each (compared between runs)")
    scenarios: dict[str, Any] = {}
    for scenario in reference.runs[0].outcome:
        scenarios[scenario] = {
            "rates": {ev.label: _rates(ev, scenario) for ev in evaluations},
            "against_reference": {
                other.label: (_paired(reference.runs[0], other.runs[0], scenario)
                              if len(other.runs) == 1 else
                              _between_runs(reference, other, scenario))
                for other in others}}
    return {"outcome": str(reference.outcome), "reference": reference.label,
            "confidence": CONFIDENCE,
            "sources": {ev.label: [[str(p) for p in run.sources] for run in ev.runs]
                        for ev in evaluations},
            "sensing": {ev.label: {k: ev.conditions[k] for k in _SENSING} for ev in evaluations},
            "scenarios": scenarios}


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def table(result: dict[str, Any]) -> str:
    """The comparison as text: rates with intervals, then each against the reference (paired:
    the episodes only the reference / only this one ended in the outcome; between runs: the
    difference's interval)."""
    ref = result["reference"]
    rows = [f"outcome: {result['outcome']}"]
    for label, s in result["sensing"].items():
        seen = ([f"a {s['camera_hfov_deg']:g} deg camera"]
                if s["camera_hfov_deg"] != D435_HFOV_DEG else [])
        seen += ["every person around (--surround-people)"] if s["surround_people"] else []
        if seen:
            rows.append(f"{label} sees {' and '.join(seen)}")
    rows.append(f"{'scenario':<16}{'planner':<22}{'runs':>5}{'rate':>9}{'95 % CI':>14}"
                f"{'vs ' + ref:>22}{'only ref/this or CI':>22}{'p':>8}")
    for scenario, s in result["scenarios"].items():
        for label, r in s["rates"].items():
            vs, detail, p = "", "", ""
            if label in s["against_reference"]:
                c = s["against_reference"][label]
                vs = f"{100 * c['difference']:+.1f} pts"
                detail = (f"{c['only_reference']}/{c['only_this']}" if "only_this" in c
                          else f"{_pct(c['ci95'][0])} to {_pct(c['ci95'][1])} pts")
                p = "-" if c["p_value"] is None else f"{c['p_value']:.3f}"
            ci = f"{_pct(r['ci95'][0])}-{_pct(r['ci95'][1])}%"
            rows.append(f"{scenario:<16}{label:<22}{r['runs']:>5}{_pct(r['rate']):>8}%"
                        f"{ci:>14}{vs:>22}{detail:>22}{p:>8}")
    return "\n".join(rows)
