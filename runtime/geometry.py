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

