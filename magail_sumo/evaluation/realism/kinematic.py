"""Kinematic features: speed, acceleration, yaw rate and yaw acceleration per step.

Central differences over the step axis (last axis), float32; the first and last steps are NaN
and NaN propagates.
"""

from __future__ import annotations

import numpy as np

from magail_sumo.sim.dynamics import wrap_angle


def central_diff(a: np.ndarray) -> np.ndarray:
    """``(a[t+1] - a[t-1]) / 2`` along the last axis, NaN at both ends."""
    out = np.full(a.shape, np.nan, a.dtype)
    out[..., 1:-1] = (a[..., 2:] - a[..., :-2]) / a.dtype.type(2)
    return out


def central_valid(valid: np.ndarray) -> np.ndarray:
    """``valid[t-1] & valid[t+1]`` along the last axis, False at both ends."""
    out = np.zeros_like(valid)
    out[..., 1:-1] = valid[..., :-2] & valid[..., 2:]
    return out


def linear_speed(x: np.ndarray, y: np.ndarray, z: np.ndarray, dt: float) -> np.ndarray:
    """Speed magnitude (m/s) from central differences of the 3-D position."""
    dx, dy, dz = central_diff(x), central_diff(y), central_diff(z)
    return np.sqrt(dx * dx + dy * dy + dz * dz) / x.dtype.type(dt)


def kinematic_features(x: np.ndarray, y: np.ndarray, z: np.ndarray, heading: np.ndarray,
                       dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Linear speed (m/s), linear acceleration (m/s², rate of change of the speed magnitude),
    angular speed (rad/s) and angular acceleration (rad/s²), each shaped like ``x``.

    Heading differences are wrapped into [-pi, pi) before dividing by the step time.
    """
    f = x.dtype.type
    speed = linear_speed(x, y, z, dt)
    accel = central_diff(speed) / f(dt)
    dh = wrap_angle(central_diff(heading) * f(2)) / f(2)
    d2h = wrap_angle(central_diff(dh) * f(2)) / f(2)
    return speed, accel, dh / f(dt), d2h / f(dt * dt)
