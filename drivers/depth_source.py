"""The one interface every depth source implements (live D435, playback, simulator).

Depth stays in the sensor's integer units (Z16) here; `intrinsics.depth_unit_m` converts to
metres. Depth is Z along the optical axis (camera optical frame: z forward, x right, y down),
not ray length. `t` is host-monotonic seconds; in playback the recorded stamps are the clock.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Protocol, runtime_checkable

from runtime.types import DepthFrame, DepthIntrinsics

__all__ = [
    "D435_HFOV_DEG",
    "CountedDepthSource",
    "D435_848x480",
    "DepthFrame",
    "DepthIntrinsics",
    "DepthSource",
]

D435_HFOV_DEG = 87.0  # the D435's depth field of view, horizontal


def _d435_848x480() -> DepthIntrinsics:
    f = (848 / 2) / math.tan(math.radians(D435_HFOV_DEG) / 2)
    return DepthIntrinsics(width=848, height=480, fx=f, fy=f, cx=424.0, cy=240.0, depth_unit_m=0.001)


D435_848x480 = _d435_848x480()
"""Nominal D435 depth intrinsics at 848x480 (87 deg HFOV: fx = fy = 424 / tan(43.5 deg) = 446.8 px, 1 mm units)."""


@runtime_checkable
class DepthSource(Protocol):
    """A source of depth frames, polled from the control loop (never blocks for long)."""

    def start(self) -> None: ...

    def poll(self) -> DepthFrame | None:
        """The next frame if one is ready, else None at once."""
        ...

    def stop(self) -> None: ...

    @property
    def at_end(self) -> bool:
        """True only when a finished recording has delivered its last frame (never for a stall)."""
        ...


class CountedDepthSource(DepthSource, Protocol):
    """A live depth source (D435, simulator link): also counts its events for the run report."""

    counts: Counter[str]
    """Events by name (frames, stalls, restarts, reconnects, queue overflows, ...)."""
