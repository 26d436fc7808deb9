"""What the control cycle hands to the flight recorder (runtime.process.recorder)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from runtime.types import DecisionTrace, DepthFrame, WheelIncrement


@dataclass(frozen=True)
class CycleRecord:
    """References the control cycle hands to the recorder: nothing is copied in the cycle, and
    nothing here is changed after it (fresh arrays each cycle; the observation is a copy)."""

    t: float
    state: str
    increments: tuple[WheelIncrement, ...]
    frames: tuple[DepthFrame, ...]
    perceived: DepthFrame | None  # the frame the world model read this cycle, if any
    feedback_t: float | None
    result: Any  # runtime.pipeline.CycleResult
    trace: DecisionTrace | None
    commands: tuple[dict[str, Any], ...] = field(default_factory=tuple)
    control_t: float | None = None  # when the commands and the hold time were applied
    # the first cycle only: the control socket's passes during start-up (INIT) from the first
    # that applied a command, each {"t", "hold", "commands"}, which a replay applies before it
    startup_control: tuple[dict[str, Any], ...] = field(default_factory=tuple)
