"""Kinematic bicycle model for controlled vehicles, forward and inverse, over arrays of vehicles.

State per vehicle (scene frame): box-centre position ``x, y`` (m), ``yaw`` (rad, CCW from +x),
signed ``speed`` (m/s along the heading; negative = reversing). Action per vehicle:
``accel`` (m/s²) and ``steer`` (front-wheel angle, rad, positive = left). With wheelbase ``L``
the path curvature is ``k = tan(steer) / L``. One step of ``dt`` seconds first updates the speed,
then moves the vehicle the signed distance ``s = speed'·dt`` along an arc of curvature ``k``
(semi-implicit Euler; the chord of the arc points along the mid-step heading):

    speed' = speed + accel·dt,  s = speed'·dt,
    x' = x + s·cos(yaw + k·s/2),  y' = y + s·sin(yaw + k·s/2),  yaw' = yaw + k·s

Semi-implicit integration keeps the inverse well-posed: the speed after a step is the step's
displacement over ``dt``, so noise in recorded positions does not pile up in the speed. Limits (:class:`BicycleLimits`) clip
every action; the normalised action in [-1, 1]² maps linearly onto them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Wheelbase as a share of the box length when none is given (a 4.8 m car: 2.9 m).
WHEELBASE_RATIO = 0.6


@dataclass(frozen=True)
class BicycleLimits:
    """Action and state limits.

    :param max_accel: largest acceleration (m/s²).
    :param max_brake: largest deceleration (m/s², positive number).
    :param max_steer: largest front-wheel angle (rad).
    :param max_speed: forward speed cap (m/s).
    :param max_reverse_speed: reverse speed cap (m/s, positive number).
    :param max_offset: largest lateral offset from the reference path (m) in the
        ``accel_offset`` layout (:mod:`magail_sumo.sim.tracking`).
    :param max_steer_rate: largest change of the front-wheel angle per second (rad/s; 0: no
        limit): a step's steering is clipped to ``prev ± max_steer_rate·dt`` around the
        previous step's (:func:`limit_steer_rate`), a steering actuator's rate limit.
    """

    max_accel: float = 6.0
    max_brake: float = 10.0
    max_steer: float = 0.7
    max_speed: float = 40.0
    max_reverse_speed: float = 5.0
    max_offset: float = 1.5
    max_steer_rate: float = 0.0


@dataclass(frozen=True)
class VehicleState:
    """Kinematic state of V vehicles as (V,) float64 arrays (see module doc for frames)."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray


def turning_radius(length: np.ndarray | float, limits: BicycleLimits) -> np.ndarray:
    """Radius (m) of the tightest circle a vehicle of box ``length`` (m) can drive: the
    bicycle model at full steering, ``wheelbase / tan(max_steer)`` (wheelbase
    :data:`WHEELBASE_RATIO` of the length; a 5 m car at 0.7 rad: 3.6 m)."""
    return WHEELBASE_RATIO * np.asarray(length, np.float64) / np.tan(limits.max_steer)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi) (floor modulo; a float32 array stays float32)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def clip_action(accel: np.ndarray, steer: np.ndarray, limits: BicycleLimits
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip to the limits; NaN becomes 0. Returns (accel, steer, clipped mask)."""
    # (np.where / np.minimum / np.maximum: the values of np.nan_to_num and np.clip, without
    # their per-call overhead, most of this function's time for a few agents)
    ok_a, ok_d = np.isfinite(accel), np.isfinite(steer)
    a = np.where(ok_a, np.asarray(accel, np.float64), 0.0)
    d = np.where(ok_d, np.asarray(steer, np.float64), 0.0)
    a_c = np.minimum(np.maximum(a, -limits.max_brake), limits.max_accel)
    d_c = np.minimum(np.maximum(d, -limits.max_steer), limits.max_steer)
    return a_c, d_c, ~ok_a | ~ok_d | (a_c != a) | (d_c != d)


def limit_steer_rate(steer: np.ndarray, prev: np.ndarray, limits: BicycleLimits, dt: float
                     ) -> np.ndarray:
    """Front-wheel angles ``steer`` (rad) within ``max_steer_rate·dt`` of the previous step's
    ``prev`` (rad), unchanged when ``limits.max_steer_rate`` is 0 (no limit)."""
    if limits.max_steer_rate <= 0:
        return steer
    step = limits.max_steer_rate * dt
    return np.clip(steer, prev - step, prev + step)


#: Layouts of the two entries of a normalised action: ours, the seed's (steering first), and
#: route-relative control (acceleration, lateral offset from the reference path:
#: :mod:`magail_sumo.sim.tracking`).
ACTION_LAYOUTS: tuple[str, ...] = ("accel_steer", "steer_throttle", "accel_offset")
#: components of one agent's normalised action in every layout (the two controls)
ACTION_SIZE = 2


def denormalise(action: np.ndarray, limits: BicycleLimits, layout: str = "accel_steer"
                ) -> tuple[np.ndarray, np.ndarray]:
    """Map a (V, 2) action in [-1, 1]² onto physical units: (accel m/s², steer rad), or in the
    ``accel_offset`` layout (accel m/s², lateral offset m, left positive).

    ``layout="accel_steer"``: (accel, steer); ``"steer_throttle"`` (the seed's): (steer,
    throttle/brake); ``"accel_offset"``: (accel, offset), offset scaling ``max_offset``.
    Positive accel in [0, 1] scales ``max_accel``; negative scales ``max_brake``.
    """
    act = np.asarray(action, np.float64)
    if layout == "steer_throttle":
        act = act[:, ::-1]
    elif layout not in ACTION_LAYOUTS:
        raise ValueError(f"action layout must be one of {ACTION_LAYOUTS}, got {layout!r}")
    u = np.clip(act[:, 0], -1.0, 1.0)
    accel = np.where(u >= 0, u * limits.max_accel, u * limits.max_brake)
    scale = limits.max_offset if layout == "accel_offset" else limits.max_steer
    return accel, np.clip(act[:, 1], -1.0, 1.0) * scale


def normalise(accel: np.ndarray, steer: np.ndarray, limits: BicycleLimits,
              layout: str = "accel_steer") -> np.ndarray:
    """Inverse of :func:`denormalise`: (V, 2) in [-1, 1]² in the given layout (``steer``: the
    lateral offset, m, in the ``accel_offset`` layout)."""
    a = np.asarray(accel, np.float64)
    u = np.where(a >= 0, a / limits.max_accel, a / limits.max_brake)
    scale = limits.max_offset if layout == "accel_offset" else limits.max_steer
    out = np.clip(np.stack([u, np.asarray(steer) / scale], axis=1), -1.0, 1.0)
    return out[:, ::-1].copy() if layout == "steer_throttle" else out


def relayout(action: np.ndarray, layout: str) -> np.ndarray:
    """(V, 2) normalised ``accel_steer`` actions in ``layout`` (a copy): ``steer_throttle``
    swaps the entries; ``accel_offset`` keeps the acceleration and sets the lateral offset to
    0 (recorded vehicles' actions: a recorded vehicle's reference path is its own recorded
    route, :mod:`magail_sumo.sim.tracking`)."""
    act = np.array(action, copy=True)
    if layout == "steer_throttle":
        return act[:, ::-1].copy()
    if layout == "accel_offset":
        act[:, 1] = 0.0
    elif layout != "accel_steer":
        raise ValueError(f"action layout must be one of {ACTION_LAYOUTS}, got {layout!r}")
    return act


def step(state: VehicleState, accel: np.ndarray, steer: np.ndarray, wheelbase: np.ndarray,
         dt: float, limits: BicycleLimits | None) -> VehicleState:
    """Advance every vehicle by one step.

    :param limits: actions and speed are clipped to these first; None replays the actions as
        given (expert log replay: recorded motion includes sensor noise no real car would need).
    """
    if limits is None:
        a, d = np.asarray(accel, np.float64), np.asarray(steer, np.float64)
        speed_next = state.speed + a * dt
    else:
        a, d, _ = clip_action(accel, steer, limits)
        speed_next = np.clip(state.speed + a * dt, -limits.max_reverse_speed, limits.max_speed)
    s = speed_next * dt
    k = np.tan(d) / wheelbase
    mid = state.yaw + 0.5 * k * s
    return VehicleState(state.x + s * np.cos(mid), state.y + s * np.sin(mid),
                        wrap_angle(state.yaw + k * s), speed_next)


def inverse(state: VehicleState, x_next: np.ndarray, y_next: np.ndarray, wheelbase: np.ndarray,
            dt: float, yaw_next: np.ndarray | None = None, heading_weight: float = 0.5,
            min_move: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """The action that moves each vehicle from ``state`` towards recorded targets.

    Position: the chord to the target fixes the signed distance ``s`` (negative when the target
    lies behind: reversing) and the acceleration, from ``s = (speed + accel·dt)·dt``.

    Curvature: without ``yaw_next``, the curvature makes the mid-step heading point along the
    chord, so :func:`step` without limits lands exactly on the target. A position-exact model
    has no control over the heading it ends with (it reflects about the chord every step and
    random-walks on noisy logs), so with ``yaw_next`` the curvature is the blend
    ``(1 - w)·k_chord + w·k_heading`` with ``w = heading_weight``, where ``k_heading`` turns the
    vehicle to ``yaw_next`` over the step: the heading error then decays (factor ``w - 1`` per
    step) while the position error stays a few centimetres (measured on the real scenes:
    < 0.07 m worst, heading p95 < 3 degrees at w = 0.5). Below ``min_move`` metres per step the
    chord is mostly position noise (a waiting car's box jitters by centimetres) and only the
    heading target steers.

    :returns: (accel m/s², steer rad), unclipped.
    """
    dx, dy = x_next - state.x, y_next - state.y
    dist = np.hypot(dx, dy)
    chord = np.arctan2(dy, dx)
    behind = np.cos(chord - state.yaw) < 0
    s = np.where(behind, -dist, dist)
    chord = np.where(behind, chord + np.pi, chord)
    moving = dist > 1e-6
    safe_s = np.where(moving, s, 1.0)
    k = np.where(moving, 2.0 * wrap_angle(chord - state.yaw) / safe_s, 0.0)
    if yaw_next is not None:
        k_yaw = np.where(moving, wrap_angle(yaw_next - state.yaw) / safe_s, 0.0)
        k = np.where(dist < min_move, k_yaw, (1.0 - heading_weight) * k + heading_weight * k_yaw)
    steer = np.arctan(k * wheelbase)
    accel = (s / dt - state.speed) / dt
    return accel, steer
