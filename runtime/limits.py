"""Velocity and acceleration limits, applied last, just before the base driver (pure)."""

from __future__ import annotations

from runtime.config import LimitsConfig
from runtime.types import Twist


def _step_towards(current: float, target: float, up: float, down: float) -> float:
    """Move `current` toward `target`, by at most `up` when speeding up and `down` when slowing."""
    speeding_up = abs(target) > abs(current) and (current == 0.0 or (target > 0) == (current > 0))
    limit = up if speeding_up else down
    return current + max(-limit, min(limit, target - current))


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
    if abs(v) < 1e-9:
        v = 0.0
    if abs(omega) < 1e-9:
        omega = 0.0
    return Twist(v, omega)

