"""Velocity and acceleration limits, applied last, just before the base driver (pure)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from runtime.config.schema import setting
from runtime.types import Twist


@dataclass(frozen=True)
class LimitsConfig:
    v_max: float = setting(0.3, "maximum forward speed", "m/s", min=0.0, max=0.5)
    v_min: float = setting(
        -0.1, "minimum (most negative) speed; the camera cannot see behind", "m/s", min=-0.5, max=0.0
    )
    omega_max: float = setting(1.0, "maximum turn rate magnitude", "rad/s", min=0.0, max=4.0)
    accel_max: float = setting(
        0.5, "maximum linear acceleration", "m/s^2", min=0.0, max=5.0, min_exclusive=True
    )
    decel_max: float = setting(
        1.0,
        "braking deceleration the base guarantees; used for stops and braking",
        "m/s^2",
        min=0.0,
        max=5.0,
        min_exclusive=True,
    )
    alpha_max: float = setting(
        2.0, "maximum angular acceleration", "rad/s^2", min=0.0, max=20.0, min_exclusive=True
    )


def _step_towards(current: float, target: float, up: float, down: float) -> float:
    """Move `current` toward `target` in one step: by at most `down` while slowing toward zero
    and `up` while speeding up. A step that crosses zero spends the part of the step left after
    reaching zero speeding up, so reversing never accelerates at the braking rate."""
    if target == current:
        return target
    slowing = current != 0.0 and (target == 0.0 or (target > 0) != (current > 0) or abs(target) < abs(current))
    if not slowing:
        return current + math.copysign(min(up, abs(target - current)), target - current)
    if abs(target) < abs(current) and (target > 0) == (current > 0) and target != 0.0:
        return current - math.copysign(min(down, abs(current - target)), current)
    if abs(current) > down:
        return current - math.copysign(down, current)
    left_of_step = 1.0 - abs(current) / down
    return math.copysign(min(abs(target), up * left_of_step), target) if target != 0.0 else 0.0


def apply_limits(target: Twist, previous: Twist, dt: float, limits: LimitsConfig) -> Twist:
    """Clamp the target to the velocity box, then rate-limit it relative to the last command.

    Slowing down uses the braking deceleration, speeding up the (smaller) acceleration limit,
    so a brake request is never softened by the comfort limit.
    """
    v = min(limits.v_max, max(limits.v_min, target.v))
    omega = min(limits.omega_max, max(-limits.omega_max, target.omega))
    v = _step_towards(previous.v, v, limits.accel_max * dt, limits.decel_max * dt)
    alpha = limits.alpha_max * dt
    omega = _step_towards(previous.omega, omega, alpha, alpha)
    # float rounding in the rate step must not leave the box
    v = min(limits.v_max, max(limits.v_min, v))
    omega = min(limits.omega_max, max(-limits.omega_max, omega))
    if abs(v) < 1e-9:
        v = 0.0
    if abs(omega) < 1e-9:
        omega = 0.0
    return Twist(v, omega)

