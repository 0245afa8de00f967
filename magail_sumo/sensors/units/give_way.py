"""Give way: the next road user the agent must give way to at a junction ahead (appended with
``ObservationConfig.give_way``).

``give_way_gap`` (m): the distance along the agent's route to the point where its path through
the junction meets that road user's (the conflict's entry), capped at :data:`GIVE_WAY_RANGE`;
``give_way_time`` (s): the time that road user needs to reach the conflict at its current
speed, capped at :data:`GIVE_WAY_HORIZON` (0 when it is in the conflict already). Of the
road users the agent must respond to (SUMO's junction model: the foe has the right of way, or
neither has), the one that reaches its conflict first; none (the caps) when there is none
within range or the agent has the way, nor for an agent within :data:`COMMITTED` m of the
conflict (it clears it). Only a SUMO run has a junction model
(``traci.vehicle.getJunctionFoes``: the city env passes these values); a recorded scene with
log background reads none.
"""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register

#: the farthest conflict reported (m); also what reads when none is ahead
GIVE_WAY_RANGE = 50.0
#: the longest time reported (s); also what reads when none is ahead
GIVE_WAY_HORIZON = 10.0
#: an agent this close to a conflict's entry (m) is committed: it clears the conflict rather
#: than stopping inside it with its nose in the other road user's lane (which then waits for
#: it as it waits for that road user)
COMMITTED = 1.0


@register
class GiveWay(Sensor):
    """``give_way_gap`` (m), ``give_way_time`` (s) (module doc)."""

    name = "give_way"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["give_way_gap", "give_way_time"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return (np.zeros(2, np.float32),
                np.array([GIVE_WAY_RANGE, GIVE_WAY_HORIZON], np.float32))

    def read(self, inp: SensorInput) -> np.ndarray:
        gap, time = inp.give_way[:, 0], inp.give_way[:, 1]
        none = ~(gap < GIVE_WAY_RANGE)
        return np.stack([np.where(none, GIVE_WAY_RANGE, np.clip(gap, 0.0, GIVE_WAY_RANGE)),
                         np.where(none, GIVE_WAY_HORIZON, np.clip(time, 0.0, GIVE_WAY_HORIZON))],
                        axis=1)
