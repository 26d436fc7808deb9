"""Wheel odometry: integrate wheel increments into a pose (pure; no clock, no device).

Dead reckoning from the encoders alone. The EKF that fuses the gyro replaces the heading source
later; this stage is what that filter's wheel prediction is built on.
"""

from __future__ import annotations

import math

from runtime.geometry import wrap_angle
from runtime.types import Odometry, WheelIncrement


def advance(odom: Odometry, inc: WheelIncrement, axle_m: float) -> Odometry:
    """Integrate one increment with the midpoint heading (exact for constant curvature to 2nd order)."""
    ds = 0.5 * (inc.d_left + inc.d_right)
    dtheta = (inc.d_right - inc.d_left) / axle_m
    heading = odom.theta + 0.5 * dtheta
    v = ds / inc.dt if inc.dt > 0 else odom.v
    omega = dtheta / inc.dt if inc.dt > 0 else odom.omega
    return Odometry(
        t=inc.t,
        x=odom.x + ds * math.cos(heading),
        y=odom.y + ds * math.sin(heading),
        theta=wrap_angle(odom.theta + dtheta),
        v=v,
        omega=omega,
        distance=odom.distance + abs(ds),
    )
