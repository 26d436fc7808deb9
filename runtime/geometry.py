"""Frame conventions and the small geometry every stage shares: one definition each.

REP 103: base_link x forward, y left, z up; the camera optical frame has z forward, x right,
y down. A mount's roll, pitch, yaw are ROS fixed-axis angles of camera_link in base_link.
Planar poses are (x, y, θ) of base_link in odom.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np

A = TypeVar("A", float, np.ndarray)


def wrap_angle(a: float) -> float:
    """Wrap to [-π, π)."""
    wrapped = (a + math.pi) % (2.0 * math.pi) - math.pi
    return wrapped - 2.0 * math.pi if wrapped >= math.pi else wrapped


def wrap_angles(a: np.ndarray) -> np.ndarray:
    """Element-wise wrap to [-π, π] (the vectorised stages' form)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def bin_layout(bin_angles: np.ndarray) -> tuple[float, float]:
    """(lower edge of bin 0, bin width) of evenly spaced bearing-bin centres, right to left (a
    single bin spans the whole circle)."""
    if len(bin_angles) > 1:
        width = float(bin_angles[1] - bin_angles[0])
    else:
        width = 2.0 * math.pi
    return float(bin_angles[0]) - width / 2, width


def bin_index(bearing: np.ndarray, lo: float, width: float, bins: int) -> np.ndarray:
    """Bin index of each bearing (rad); -1 outside the span."""
    k = np.floor((np.asarray(bearing) - lo) / width).astype(np.intp)
    k[(k < 0) | (k >= bins)] = -1
    return k


def into_frame(dx: A, dy: A, theta: float) -> tuple[A, A]:
    """A vector (dx, dy) given in a parent frame, expressed in a child frame rotated by `theta`
    (e.g. odom → base_link: the offset from the robot, the robot's heading)."""
    c, s = math.cos(theta), math.sin(theta)
    return c * dx + s * dy, -s * dx + c * dy


def from_frame(x: float, y: float, theta: float, dx: A, dy: A) -> tuple[A, A]:
    """A point (dx, dy) given in a child frame whose pose in its parent is (x, y, theta),
    expressed in the parent (e.g. base_link → odom at the robot's pose): `into_frame` undone."""
    c, s = math.cos(theta), math.sin(theta)
    return x + c * dx - s * dy, y + s * dx + c * dy

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

