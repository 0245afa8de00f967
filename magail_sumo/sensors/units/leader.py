"""Leader: the nearest road user ahead in the agent's path, its gap and closing speed
(appended with ``ObservationConfig.leader``).

Ego frame as everywhere (+x along the agent's heading, +y to its left). A road user is in the
agent's path when its box centre is ahead (``x > 0``) and the two boxes overlap sideways
(``|y| < (w_agent + w_other)/2``); of those within ``leader_range`` m, the leader is the one
with the smallest gap ``x − (l_agent + l_other)/2`` (m, centre distance less the half
lengths: bumper to bumper for aligned boxes; negative when they overlap). Its closing speed is
the agent's speed less the leader's speed along the agent's heading (m/s; > 0: the gap
shrinks). Without a leader: gap ``leader_range``, closing speed 0. Road users of unknown speed
(``Boxes.speed`` None) count as still. One numba kernel over the agent × road-user pairs (in a
batched env only the agent's own world's road users and the shared ones).
"""

from __future__ import annotations

import numba
import numpy as np

from ..base import Boxes, Sensor, SensorInput, register
from ..worlds import BoxGroups


@register
class Leader(Sensor):
    """``leader_gap`` (m), ``leader_closing`` (m/s) (module doc)."""

    name = "leader"

    @classmethod
    def names(cls, config) -> list[str]:
        return [f"{cls.name}_gap", f"{cls.name}_closing"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([-np.inf, -np.inf], np.float32),
                np.array([config.leader_range, np.inf], np.float32))

    def read(self, inp: SensorInput) -> np.ndarray:
        rng = float(self.config.leader_range)
        out = np.zeros((len(inp), 2), np.float32)
        out[:, 0] = rng
        gap, along, found = self.find(inp, rng)
        out[found, 0] = gap[found]
        out[found, 1] = inp.ego.speed[found] - along[found]
        return out

    def find(self, inp: SensorInput, rng: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A,) gap (m), the leader's speed along the agent's heading (m/s) and whether the
        agent has one within ``rng`` m (:func:`nearest_ahead`)."""
        return nearest_ahead(inp.boxes, inp.index, inp.x, inp.y, inp.yaw, rng)


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
    if a == 0 or n <= 1:
        return np.full(a, np.inf), np.zeros(a), np.zeros(a, bool)
    f = lambda v: np.ascontiguousarray(v, np.float64)  # noqa: E731
    # a batched env: each agent against its world's boxes and the shared ones
    g = b.groups if b.groups is not None else BoxGroups.single(n)
    world, offsets, rows = g.world, g.offsets, g.rows
    speed = np.zeros(n) if b.speed is None else f(b.speed)
    return _nearest_ahead(f(b.x), f(b.y), f(b.yaw), f(b.length), f(b.width), speed,
                          np.ascontiguousarray(index, np.int64), f(x), f(y), f(yaw),
                          float(rng), bool(oriented), world, offsets, rows)


@numba.njit(cache=True)
def _nearest_ahead(bx, by, byaw, blen, bwid, bspeed, index, x, y, yaw, rng, oriented, world,
                   offsets, rows):
    """:func:`nearest_ahead` over the agents' own world's boxes and the shared ones
    (:class:`~magail_sumo.sensors.worlds.BoxGroups` buckets); ties go to the lowest row."""
    a = index.shape[0]
    gap_out, along_out = np.full(a, np.inf), np.zeros(a)
    found = np.zeros(a, np.bool_)
    shared = offsets.shape[0] - 2
    for i in range(a):
        me = index[i]
        c, s = np.cos(yaw[i]), np.sin(yaw[i])
        best, bj = np.inf, -1
        for bucket in (world[me], shared):
            for m in range(offsets[bucket], offsets[bucket + 1]):
                j = rows[m]
                if j == me:
                    continue
                dx, dy = bx[j] - x[i], by[j] - y[i]
                ex = c * dx + s * dy
                if not ex > 0.0:
                    continue
                ey = -s * dx + c * dy
                if oriented:
                    d = byaw[j] - yaw[i]
                    cd, sd = abs(np.cos(d)), abs(np.sin(d))
                    ext_along = cd * blen[j] + sd * bwid[j]
                    ext_across = sd * blen[j] + cd * bwid[j]
                else:
                    ext_along, ext_across = blen[j], bwid[j]
                gap = ex - 0.5 * (ext_along + blen[me])
                if abs(ey) < 0.5 * (ext_across + bwid[me]) and gap < rng and \
                        (gap < best or (gap == best and j < bj)):
                    best, bj = gap, j
        if bj >= 0:
            found[i] = True
            gap_out[i] = best
            along_out[i] = bspeed[bj] * np.cos(byaw[bj] - yaw[i])
    return gap_out, along_out, found
