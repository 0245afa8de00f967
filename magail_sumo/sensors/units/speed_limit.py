"""Speed limits along the route: the road's limit where the agent is and the lowest one ahead
(appended with ``ObservationConfig.speed_limit``).

``speed_limit`` (m/s) is the limit of the road at the agent's progress point on its reference
path; ``speed_limit_ahead`` (m/s) the lowest limit on the path within ``leader_range`` m ahead
and ``speed_limit_gap`` (m) how far ahead it begins (the limit here and 0 when none ahead is
lower), so a driver can slow down before a lower limit rather than at its sign. In a city the
limits are SUMO's lane speeds along the route (inside a junction the speed netconvert gives the
turn); in a recorded scene the recorded limit of the lane nearest each recorded position running
its way (WOMD stores one per lane, often none). 0 where the limit is unknown (no lane, none
recorded) and for an agent without a reference path (free steering).
"""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register

#: the highest limit reported (m/s)
MAX_LIMIT = 70.0


@register
class SpeedLimit(Sensor):
    """``speed_limit`` (m/s), ``speed_limit_ahead`` (m/s), ``speed_limit_gap`` (m) (module
    doc)."""

    name = "speed_limit"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["speed_limit", "speed_limit_ahead", "speed_limit_gap"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return (np.zeros(3, np.float32),
                np.array([MAX_LIMIT, MAX_LIMIT, config.leader_range], np.float32))

    def read(self, inp: SensorInput) -> np.ndarray:
        out = np.zeros((len(inp), 3), np.float32)
        path = inp.ego.path
        if path is None:
            return out
        rows = np.asarray(path.rows, np.int64)
        has = np.flatnonzero(rows >= 0)
        if has.size:
            here, low, gap = path.paths.limits_ahead(rows[has], np.asarray(path.at)[has],
                                                     self.config.leader_range)
            out[has, 0] = np.minimum(here, MAX_LIMIT)
            out[has, 1] = np.minimum(low, MAX_LIMIT)
            out[has, 2] = np.minimum(gap, self.config.leader_range)
        return out
