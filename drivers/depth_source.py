"""The one interface every depth source implements (live D435, playback, simulator).

Depth stays in the sensor's integer units (Z16) here; `intrinsics.depth_unit_m` converts to
metres. Depth is Z along the optical axis (camera optical frame: z forward, x right, y down),
not ray length. `t` is host-monotonic seconds; in playback the recorded stamps are the clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class DepthIntrinsics:
    """Pinhole intrinsics of a depth stream (D435 depth has zero distortion)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_unit_m: float = 0.001


def _d435_848x480() -> DepthIntrinsics:
    f = (848 / 2) / math.tan(math.radians(87.0) / 2)
    return DepthIntrinsics(width=848, height=480, fx=f, fy=f, cx=424.0, cy=240.0, depth_unit_m=0.001)


D435_848x480 = _d435_848x480()
"""Nominal D435 depth intrinsics at 848x480 (~87 deg HFOV, fx = fy ~ 424.7 px, 1 mm units)."""


@dataclass
class DepthFrame:
    """One depth image, owned by us (copied out of any SDK buffer)."""

    depth: np.ndarray  # uint16, shape (height, width), Z16 in intrinsics.depth_unit_m
    t: float  # seconds (host monotonic; in playback the recorded timestamps)
    frame_number: int
    intrinsics: DepthIntrinsics

    def depth_m(self) -> np.ndarray:
        """Depth in metres as float32 (0 stays 0 = invalid)."""
        return self.depth.astype(np.float32) * np.float32(self.intrinsics.depth_unit_m)


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
