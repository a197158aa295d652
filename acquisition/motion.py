"""Servo motion model for planning: how long a move takes.

Dynamixel X-series run a trapezoidal velocity profile in position mode (e-Manual, "Profile
Velocity(112)"/"Profile Acceleration(108)"): velocity unit 0.229 rev/min, acceleration unit
214.577 rev/min²; acceleration 0 means "infinite" (a step to the profile velocity). All axes of a
pose move together (sync write), so a move lasts as long as its slowest axis.
"""

from __future__ import annotations

import math

import numpy as np

from acquisition.config import AxisConfig

__all__ = ["axis_speed_rad_s", "axis_accel_rad_s2", "trapezoid_time_s", "move_time_s"]

RPM_PER_UNIT = 0.229
REV_PER_MIN2_PER_UNIT = 214.577


def axis_speed_rad_s(axis: AxisConfig) -> float:
    servo = axis.profile_velocity * RPM_PER_UNIT * 2.0 * math.pi / 60.0
    return servo / axis.gear_ratio


def axis_accel_rad_s2(axis: AxisConfig) -> float:
    if axis.profile_acceleration == 0:
        return math.inf
    servo = axis.profile_acceleration * REV_PER_MIN2_PER_UNIT * 2.0 * math.pi / 3600.0
    return servo / axis.gear_ratio


def trapezoid_time_s(distance: np.ndarray | float, v: float, a: float) -> np.ndarray:
    """Time to travel `distance` (rad) from rest to rest with max speed v and acceleration a.

    Triangle profile when the distance is too short to reach v (d < v²/a): t = 2√(d/a);
    otherwise t = d/v + v/a (accelerate v/a, cruise, decelerate v/a).
    """
    d = np.abs(np.asarray(distance, dtype=np.float64))
    if math.isinf(a):
        return d / v
    reach = v * v / a
    return np.where(d >= reach, d / v + v / a, 2.0 * np.sqrt(d / a))


def move_time_s(axes: dict[str, AxisConfig], start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Move time between axis vectors (…, n_axes) ordered like `axes`; the slowest axis wins.

    `trapezoid_time_s` for all axes at once (per-axis speed and acceleration as arrays): the
    planner calls this for every candidate leg of a large plan. With infinite acceleration the
    ramp v/a and the threshold v²/a are 0, so every leg cruises, as in `trapezoid_time_s`.
    """
    v = np.array([axis_speed_rad_s(ax) for ax in axes.values()])
    a = np.array([axis_accel_rad_s2(ax) for ax in axes.values()])
    d = np.abs(np.asarray(end, dtype=np.float64) - np.asarray(start, dtype=np.float64))
    t = np.where(d >= v * v / a, d / v + v / a, 2.0 * np.sqrt(d / a))
    return t.max(axis=-1)
