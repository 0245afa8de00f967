"""Leader: the nearest road user ahead in the agent's path, its gap and closing speed
(appended with ``ObservationConfig.leader``).

Ego frame as everywhere (+x along the agent's heading, +y to its left). A road user is in the
agent's path when its box centre is ahead (``x > 0``) and the two boxes overlap sideways
(``|y| < (w_agent + w_other)/2``); of those within ``leader_range`` m, the leader is the one
with the smallest gap ``x − (l_agent + l_other)/2`` (m, centre distance less the half
lengths: bumper to bumper for aligned boxes; negative when they overlap). Its closing speed is
the agent's speed less the leader's speed along the agent's heading (m/s; > 0: the gap
shrinks). Without a leader: gap ``leader_range``, closing speed 0. Road users of unknown speed
(``Boxes.speed`` None) count as still. Vectorised over the (A, N) agent × road-user pairs.
"""

from __future__ import annotations

import numpy as np

from ..base import Boxes, Sensor, SensorInput, register


@register
class Leader(Sensor):
    """``leader_gap`` (m), ``leader_closing`` (m/s) (module doc)."""

    name = "leader"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["leader_gap", "leader_closing"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([-np.inf, -np.inf], np.float32),
                np.array([config.leader_range, np.inf], np.float32))

    def read(self, inp: SensorInput) -> np.ndarray:
        rng = float(self.config.leader_range)
        out = np.zeros((len(inp), 2), np.float32)
        out[:, 0] = rng
        gap, along, found = nearest_ahead(inp.boxes, inp.index, inp.x, inp.y, inp.yaw, rng)
        out[found, 0] = gap[found]
        out[found, 1] = inp.ego.speed[found] - along[found]
        return out


def nearest_ahead(b: Boxes, index: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                  rng: float, oriented: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each agent's leader among boxes ``b`` (module doc): (A,) gap (m; ``inf`` without one),
    the leader's speed along the agent's heading (m/s; 0 without one) and whether it has one.

    :param index: (A,) the agents' own rows of ``b`` (never their own leader).
    :param x, y, yaw: (A,) the agents' poses (scene frame). :param rng: farthest gap (m).
    :param oriented: take the other box's extents along the agent's axes from its heading
        (half extents ``|cos d|·l/2 + |sin d|·w/2`` along and ``|sin d|·l/2 + |cos d|·w/2``
        across, ``d`` the heading difference), so a crossing vehicle blocks the path with its
        length (the gap guard); False: its length along and its width across, as the leader
        sensor reads it.
    """
    n, a = len(b), len(index)
    gap_out, along_out = np.full(a, np.inf), np.zeros(a)
    if a == 0 or n <= 1:
        return gap_out, along_out, np.zeros(a, bool)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    dx = b.x[None, :] - x[:, None]
    dy = b.y[None, :] - y[:, None]
    ex, ey = c * dx + s * dy, -s * dx + c * dy
    if oriented:
        d = np.asarray(b.yaw, np.float64)[None, :] - yaw[:, None]
        cd, sd = np.abs(np.cos(d)), np.abs(np.sin(d))
        ext_along = cd * b.length[None, :] + sd * b.width[None, :]
        ext_across = sd * b.length[None, :] + cd * b.width[None, :]
    else:
        ext_along, ext_across = b.length[None, :], b.width[None, :]
    gap = ex - 0.5 * (ext_along + b.length[index][:, None])
    ahead = (ex > 0) & (np.abs(ey) < 0.5 * (ext_across + b.width[index][:, None])) & (gap < rng)
    ahead[np.arange(a), index] = False
    gap = np.where(ahead, gap, np.inf)
    j = np.argmin(gap, axis=1)
    best = gap[np.arange(a), j]
    found = np.isfinite(best)
    speed = np.zeros(n) if b.speed is None else np.asarray(b.speed, np.float64)
    along = speed[j] * np.cos(np.asarray(b.yaw, np.float64)[j] - yaw)
    gap_out[found], along_out[found] = best[found], along[found]
    return gap_out, along_out, found
