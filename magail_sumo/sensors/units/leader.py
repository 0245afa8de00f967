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

from ..base import Sensor, SensorInput, register


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
        b, rng = inp.boxes, float(self.config.leader_range)
        n, a = len(b), len(inp)
        out = np.zeros((a, 2), np.float32)
        out[:, 0] = rng
        if a == 0 or n <= 1:
            return out
        c, s = np.cos(inp.yaw)[:, None], np.sin(inp.yaw)[:, None]
        dx = b.x[None, :] - inp.x[:, None]
        dy = b.y[None, :] - inp.y[:, None]
        ex, ey = c * dx + s * dy, -s * dx + c * dy
        idx = inp.index
        gap = ex - 0.5 * (b.length[None, :] + b.length[idx][:, None])
        ahead = (ex > 0) & (np.abs(ey) < 0.5 * (b.width[None, :] + b.width[idx][:, None])) & \
            (gap < rng)
        ahead[np.arange(a), idx] = False
        gap = np.where(ahead, gap, np.inf)
        j = np.argmin(gap, axis=1)
        found = np.isfinite(gap[np.arange(a), j])
        speed = np.zeros(n) if b.speed is None else np.asarray(b.speed, np.float64)
        along = speed[j] * np.cos(np.asarray(b.yaw, np.float64)[j] - inp.yaw)
        out[found, 0] = gap[np.arange(a), j][found]
        out[found, 1] = (inp.ego.speed[found] - along[found])
        return out
