"""The settings a policy was trained with, against the settings it runs with.

A TD3 actor learns the closed loop it was trained in: DWA's weights make the `dwa` block of its
observation, perception and memory its scan, the shield and the limits what its actions become.
Run with other values, it meets inputs it never saw and nothing says so. Training records the
resolved values of those sections (`decision_settings`) in its summary, which a shipped actor
carries in its metadata (`safemove.training`), and `safemove run` and `safemove eval` log one
line per key whose running value differs (`trained_settings_report`). It is a warning, not a
refusal: a robot's own values (a wider footprint, a slower limit) may be what its owner wants.

Left out: what differs per machine or device and changes no decision (serial ports, the depth
device, health timeouts, the recorder, the control socket, onnxruntime's threads).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from runtime.config.schema import apply_override, build, to_plain
from runtime.config.settings import Config
from runtime.errors import ConfigError

log = logging.getLogger("safemove.policy")

SECTIONS = ("robot", "odometry", "perception", "memory", "tracking", "dwa", "shield", "recovery",
            "limits")
LOOP_KEYS = ("control_hz",)  # the period: DWA's window and the shield's reach follow it
RECORD_KEY = "decision_settings"  # in a training summary and `safemove.training`


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, dict):
        for key, sub in value.items():
            _flatten(f"{prefix}.{key}", sub, out)
    else:
        out[prefix] = value


def decision_settings(config: Config) -> dict[str, Any]:
    """The resolved values that shape the policy's closed loop, as `section.key` → plain value
    (lists for tuples), JSON-ready."""
    out: dict[str, Any] = {}
    for name in SECTIONS:
        _flatten(name, to_plain(getattr(config, name)), out)
    for key in LOOP_KEYS:
        out[f"loop.{key}"] = getattr(config.loop, key)
    return out


@dataclass(frozen=True)
class Difference:
    key: str
    trained: Any
    running: Any

    def as_dict(self) -> dict[str, Any]:
        return {"key": self.key, "trained": self.trained, "running": self.running}


@dataclass(frozen=True)
class TrainedSettingsReport:
    """What the comparison found: `basis` says what the trained values are taken from (None:
    nothing to compare with), `differences` the keys whose values differ, `unmatched` the keys
    only one side has (settings added or removed since the training)."""

    basis: str | None
    differences: tuple[Difference, ...] = ()
    unmatched: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return {"basis": self.basis, "differences": [d.as_dict() for d in self.differences],
                "unmatched": list(self.unmatched)}

    def log(self, model: str) -> None:
        """One line per differing key (WARNING), one for what could not be compared (INFO)."""
        if self.basis is None:
            log.info("%s: no record of the settings it was trained with; not compared", model)
            return
        for d in self.differences:
            log.warning("%s: trained with %s=%s, running with %s (%s)", model, d.key, d.trained,
                        d.running, self.basis)
        if self.unmatched:
            log.info("%s: %d setting(s) not in both its training record and this config: %s",
                     model, len(self.unmatched), ", ".join(self.unmatched))


def _trained_values(training: dict[str, Any] | None) -> tuple[dict[str, Any] | None, str | None]:
    """The trained values and where they come from: the record itself, or for a run recorded
    before it, today's defaults with the run's --set overrides (it ran on its commit's defaults,
    which today's equal unless a default changed since: the basis says so)."""
    if not training:
        return None, None
    record = training.get(RECORD_KEY)
    if isinstance(record, dict):
        return record, "its training record"
    settings = training.get("settings")
    if not isinstance(settings, dict) or settings.get("config") is not None:
        return None, None  # trained on a config file this machine cannot see
    overrides = settings.get("overrides") or []
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        return None, None
    data: dict[str, Any] = {}
    try:
        for assignment in overrides:
            apply_override(data, Config, assignment)
        config = build(Config, data, "the policy's training overrides")
    except ConfigError:
        return None, None
    basis = "its training predates the settings record: today's defaults"
    return decision_settings(config), basis + (" with " + ", ".join(overrides) if overrides else "")


def trained_settings_report(training: dict[str, Any] | None,
                            config: Config) -> TrainedSettingsReport:
    """Compare an actor's training record (`Policy.training`) with the running config."""
    trained, basis = _trained_values(training)
    if trained is None:
        return TrainedSettingsReport(None)
    running = decision_settings(config)
    differences = tuple(Difference(k, trained[k], running[k]) for k in running
                        if k in trained and trained[k] != running[k])
    unmatched = tuple(sorted(set(trained) ^ set(running)))
    return TrainedSettingsReport(basis, differences, unmatched)
