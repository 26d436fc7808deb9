"""Teleoperation job: a fixed twist for a duration, or a scripted list of twists.

Script time advances only in RUNNING cycles, so an outage (DEGRADED) pauses the script rather
than eating into it. After the last segment the job commands stop and waits until odometry says
the robot is still, so the final odometry includes the braking distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from runtime.config.schema import load_yaml_file
from runtime.errors import ConfigError
from runtime.types import STILL_M_S, STOP, Odometry, Prepared, Twist

STILL_OMEGA = 0.01  # rad/s
STILL_FOR_S = 0.3
SETTLE_TIMEOUT_S = 3.0


@dataclass(frozen=True)
class Segment:
    twist: Twist
    duration_s: float


def parse_script(path: Path) -> list[Segment]:
    """A YAML list of {v: m/s, omega: rad/s, duration: s}; errors name the file and entry."""
    data = load_yaml_file(path, "drive script")
    if not isinstance(data, list) or not data:
        raise ConfigError(f"{path}: a drive script is a non-empty list of {{v, omega, duration}}")
    segments = []
    for i, entry in enumerate(data):
        where = f"{path}: entry {i + 1}"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: expected a mapping with v, omega, duration")
        unknown = set(entry) - {"v", "omega", "duration"}
        if unknown:
            raise ConfigError(f"{where}: unknown key '{min(unknown)}'")
        values = {}
        for key, default in (("v", 0.0), ("omega", 0.0), ("duration", None)):
            value = entry.get(key, default)
            if value is None:
                raise ConfigError(f"{where}: key '{key}' is required")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"{where}: key '{key}': expected a finite number, got {value!r}")
            values[key] = float(value)
        if values["duration"] <= 0:
            raise ConfigError(f"{where}: key 'duration' must be positive, got {values['duration']}")
        segments.append(Segment(Twist(values["v"], values["omega"]), values["duration"]))
    return segments


class DriveJob:
    """Plays segments back to back on RUNNING time, then brakes and waits for standstill."""

    name = "drive"

    def __init__(self, segments: list[Segment], period_s: float) -> None:
        self._segments = segments
        self._half_period = 0.5 * period_s
        self._ends = [sum(s.duration_s for s in segments[: i + 1]) for i in range(len(segments))]
        self._elapsed = 0.0
        self._last_now: float | None = None
        self._settle_started: float | None = None
        self._still_since: float | None = None
        self._finished = False
        self.settled = False

    @property
    def finished(self) -> bool:
        return self._finished

    def step(self, now: float, odom: Odometry, world: object = None) -> Twist:
        """Target for this RUNNING cycle; time since the previous RUNNING cycle counts. The
        script ignores the world model.

        The command is held for one period, so a cycle belongs to the segment containing the
        middle of that period: each segment gets round(duration / period) cycles, not ±1.
        """
        if self._last_now is not None:
            self._elapsed += now - self._last_now
        self._last_now = now
        for segment, end in zip(self._segments, self._ends):
            if self._elapsed + self._half_period < end:
                return segment.twist
        self._settle(now, odom)
        return STOP

    def prepare(self, now: float, odom: Odometry, world: object = None) -> Prepared:
        return Prepared(self.step(now, odom))

    def decide(self, prepared: Prepared, action: object = None) -> Twist:
        """The script's twist for the cycle `prepare` saw."""
        return prepared.context

    def pause(self) -> None:
        """The loop left RUNNING: the next RUNNING cycle starts a new time base. The last RUNNING
        cycle's command was held for its period before the pause: that period counts."""
        if self._last_now is not None:
            self._elapsed += 2.0 * self._half_period
        self._last_now = None

    def _settle(self, now: float, odom: Odometry) -> None:
        if self._settle_started is None:
            self._settle_started = now
        still = abs(odom.v) < STILL_M_S and abs(odom.omega) < STILL_OMEGA
        self._still_since = (now if self._still_since is None else self._still_since) if still else None
        if self._still_since is not None and now - self._still_since >= STILL_FOR_S:
            self._finished = self.settled = True
        elif now - self._settle_started > SETTLE_TIMEOUT_S:
            self._finished = True

    def summary(self) -> dict[str, Any]:
        return {
            "segments": len(self._segments),
            "script_s": self._ends[-1] if self._ends else 0.0,
            "elapsed_s": round(self._elapsed, 4),
            "settled": self.settled,
        }


class HoldJob:
    """Keep the base stopped while the loop runs: bring-up mode for the service until a planner
    is configured (link, odometry, health, watchdog and systemd integration all live)."""

    name = "hold"
    finished = False

    def prepare(self, now: float, odom: Odometry, world: object = None) -> Prepared:
        return Prepared(STOP)

    def decide(self, prepared: Prepared, action: object = None) -> Twist:
        return STOP

    def pause(self) -> None:
        """Nothing to pause: holding has no time base."""

    def summary(self) -> dict[str, Any]:
        return {}
