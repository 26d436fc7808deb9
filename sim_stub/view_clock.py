"""How long each person has been inside the camera's horizontal view, from ground truth.

A collision with a person is judged not at fault when they walked into the robot, but whether
the robot could have seen them coming is a different question, and the answer says what
would help: better decisions (they were in view for seconds) or more sensing (they came from
outside the camera's view). The view here is the horizontal wedge of the camera at its mount,
out to the perception's range: a person counts as in view when any part of their disc is
inside it. Occlusion by other bodies is not considered (an upper bound on what was seen).
"""

from __future__ import annotations

import math

import numpy as np

from runtime.geometry import into_frame


class ViewClock:
    """Per person, the time since they last entered the view (NaN while outside it)."""

    def __init__(self, camera_xy: tuple[float, float], hfov_deg: float, range_m: float,
                 people: int) -> None:
        self._cam = np.asarray(camera_xy, dtype=float)
        self._half = math.radians(hfov_deg) / 2.0
        self._range = range_m
        self._since = np.full(people, np.nan)

    def in_view(self, robot_pose: tuple[float, float, float], positions: np.ndarray,
                radii: np.ndarray) -> np.ndarray:
        """Whether any part of each person's disc is inside the camera's wedge (N,)."""
        x, y, th = robot_pose
        bx, by = into_frame(positions[:, 0] - x, positions[:, 1] - y, th)
        bx, by = bx - self._cam[0], by - self._cam[1]
        dist = np.hypot(bx, by)
        # the disc's angular half-width seen from the camera (the whole circle when inside it)
        spread = np.arcsin(np.clip(radii / np.maximum(dist, 1e-9), 0.0, 1.0))
        return (np.abs(np.arctan2(by, bx)) - spread < self._half) & (dist - radii <= self._range)

    def update(self, t: float, robot_pose: tuple[float, float, float], positions: np.ndarray,
               radii: np.ndarray) -> None:
        seen = self.in_view(robot_pose, positions, radii)
        entered = seen & np.isnan(self._since)
        self._since[entered] = t
        self._since[~seen] = np.nan

    def seen_for(self, person: int, t: float) -> float:
        """Seconds person has been in view without a break at time t; 0 when out of view."""
        since = self._since[person]
        return 0.0 if math.isnan(since) else t - float(since)
