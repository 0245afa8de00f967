"""Constant velocity: the ``constvel`` trajectory model (a scene's recorded state at its current
step moved on at its velocity, and the fill-in for unknown steps of any other method) and
:class:`ConstantVelocityPolicy`, its env-driving form (zero action: speed and heading held).

Positions are box centres in the scene frame (m), headings rad CCW from +x, one column per
simulated step of :data:`~magail_sumo.scene.types.STEP_LENGTH` s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.scene.types import STEP_LENGTH
from magail_sumo.sim.dynamics import ACTION_SIZE


@dataclass
class Track:
    """Simulated states of A agents over T simulated steps, NaN where unknown (m, rad, m/s)."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray

    @classmethod
    def empty(cls, a: int, t: int) -> "Track":
        return cls(*(np.full((a, t), np.nan) for _ in range(4)))


def current_state(scene: Scene, ids: np.ndarray) -> tuple[np.ndarray, ...]:
    """(rows, x, y, z, heading, vx, vy) of the agents ``ids`` (track ids) at the scene's
    current step; ``rows`` index ``scene.tracks``."""
    tr = scene.tracks
    row_of = {int(i): k for k, i in enumerate(tr.id.tolist())}
    rows = np.array([row_of[int(i)] for i in ids], np.int64)
    c = scene.current_time_index
    return (rows, tr.x[rows, c], tr.y[rows, c], tr.z[rows, c],
            tr.heading[rows, c].astype(np.float64), tr.vx[rows, c].astype(np.float64),
            tr.vy[rows, c].astype(np.float64))


def fill_constant_velocity(scene: Scene, ids: np.ndarray, track: Track
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Complete ``track``: unknown steps continue the last known state at constant velocity
    (speed along the heading); before any known state, the recorded state at the current
    step (its velocity vector) is extrapolated. Returns (x, y, yaw), each (A, T)."""
    _, x0, y0, _, h0, vx0, vy0 = current_state(scene, ids)
    a, t = track.x.shape
    have = np.isfinite(track.x) & np.isfinite(track.y)
    steps = np.arange(t)
    last = np.maximum.accumulate(np.where(have, steps, -1), axis=1)  # (A, T)
    seen = last >= 0
    li = np.maximum(last, 0)
    take = lambda arr: np.take_along_axis(arr, li, 1)  # noqa: E731
    bx = np.where(seen, take(track.x), x0[:, None])
    by = np.where(seen, take(track.y), y0[:, None])
    byaw = np.where(seen, take(track.yaw), h0[:, None])
    sp = np.nan_to_num(take(track.speed))
    vx = np.where(seen, sp * np.cos(byaw), vx0[:, None])
    vy = np.where(seen, sp * np.sin(byaw), vy0[:, None])
    gap = (steps[None] - np.where(seen, last, -1)) * STEP_LENGTH  # s since the base state
    return bx + vx * gap, by + vy * gap, byaw


def constant_velocity(scene: Scene, ids: np.ndarray, n_steps: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, yaw) (A, ``n_steps``): recorded state at the current step moved at its velocity."""
    return fill_constant_velocity(scene, ids, Track.empty(len(ids), n_steps))


class ConstantVelocityPolicy:
    """Zero action for every agent: speed and heading held (the bicycle model's constant
    velocity, in any action layout). A policy factory: the spec
    ``magail_sumo.agents.constant_velocity:ConstantVelocityPolicy`` (the seed is unused)."""

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {n: np.zeros(ACTION_SIZE, np.float32) for n in observations}
