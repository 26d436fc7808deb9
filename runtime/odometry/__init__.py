"""Wheel increments to pose: the EKF, dead reckoning, the pose history."""
