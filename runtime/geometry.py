"""Frame conventions shared by the renderer (sim_stub) and perception (runtime): one definition.

REP 103: base_link x forward, y left, z up; the camera optical frame has z forward, x right,
y down. A mount's roll, pitch, yaw are ROS fixed-axis angles of camera_link in base_link.
"""

from __future__ import annotations

import math

import numpy as np

# camera_link ← optical: optical z is link x, optical x is −link y, optical y is −link z
R_LINK_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ROS fixed-axis RPY: R = Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def base_to_odom(points: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """(N, 2) points from base_link into odom, for a robot at pose (x, y, θ) in odom."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    out = np.empty_like(points)
    out[:, 0] = x + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = y + s * points[:, 0] + c * points[:, 1]
    return out


def thin_points(points: np.ndarray, cell_m: float) -> np.ndarray:
    """One point per cell of a `cell_m` grid: a depth image stacks hundreds of points on each
    bit of floor-plan, and clustering cost grows with points, not with obstacles. A scatter into
    a dense grid over the points' bounding box (no sort): the last point written to a cell wins."""
    if len(points) == 0:
        return points
    ij = np.floor((points - points.min(axis=0)) / cell_m).astype(np.intp)
    flat = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    owner = np.full(int(flat.max()) + 1, -1, dtype=np.intp)
    owner[flat] = np.arange(len(points))
    return points[owner[owner >= 0]]
