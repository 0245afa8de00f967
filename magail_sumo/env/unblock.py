"""Junctions that agents and SUMO's drivers block for each other: SUMO stops giving way to
standing agents.

SUMO's junction model makes a vehicle wait for every foe that approaches or stands on a
conflicting junction lane. An agent is not driven by SUMO: it stops when a road user stands in
its path (:mod:`magail_sumo.sensors.units.path_leader`). At a junction the two can wait for each
other for ever: a SUMO car turning left waits inside the junction for the agent coming the other
way, the agent stops because the waiting car's corner reaches into its lane (SUMO's drivers pass
such a corner, they have no boxes), and the agents queued behind it are foes of the SUMO car
too. On the real cologne8 city one such pair held a main road for the rest of a 10-min window.

The release: a SUMO-driven vehicle that has waited (SUMO's waiting time, speed < 0.1 m/s) at
least ``after_s`` seconds standing in the path of an agent (:data:`RANGE` m away at most) that
has stood as long on a junction's internal lane, the agent not being in the vehicle's own path
(its SUMO route's lanes; then SUMO's junction model, not the agent's box, holds it), stops
giving way to the standing agents among its junction foes (SUMO's ``junctionModel.ignoreIDs``
vehicle parameter, the ids added to those it already ignores), so it clears the junction and
the agents find their path free. It ignores no moving agent (a foe must have stood
:data:`FOE_STOOD` s). SUMO's own ``--ignore-junction-blocker`` does the like for every vehicle
after a time; tried with 10 and 30 s it also let SUMO's drivers move into agents waiting for a
gap (collisions and agents leaving the road rose on cologne8), so the release is kept to
vehicles that wait for an agent waiting for them. A weakness measured on Wildau: a released
driver's box sweeps wider than its lane as it turns, and the agent starts as soon as the
driver leaves its path; two such drivers ran into their agents in one 2-min window
(``docs/results/city.md``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

#: metres between a standing agent and the SUMO-driven vehicles considered for release
RANGE = 15.0
#: m/s below which a vehicle stands (SUMO's own waiting threshold)
STAND_SPEED = 0.1
#: metres ahead of a SUMO-driven vehicle its junction foes are read over
FOE_RANGE = 50.0
#: seconds a foe agent must have stood to be ignored
FOE_STOOD = 1.0
#: SUMO's vehicle parameter of foes its junction model ignores (space-separated ids)
IGNORE_PARAM = "junctionModel.ignoreIDs"


def release(api, ids, x, y, speed, edges, agents: Sequence[str], agent_x: np.ndarray,
            agent_y: np.ndarray, agent_stood: np.ndarray, after_s: float,
            blocks: Callable[[int, int], bool]) -> int:
    """Let SUMO-driven vehicles stop giving way to standing agents (module doc); the number of
    vehicles released.

    :param api: the running simulation's ``libsumo`` module.
    :param ids, x, y, speed, edges: every SUMO vehicle now (ids; box centres, m; m/s; road
        ids, internal lanes' edges start with ``:``).
    :param agents: the live agents' ids.
    :param agent_x, agent_y, agent_stood: the same agents' box centres (m) and how long (s)
        each has stood, in ``agents``' order.
    :param blocks: ``blocks(i, j)``: SUMO vehicle ``j`` (index of ``ids``) stands in agent
        ``i``'s path (position in ``agents``).
    """
    stuck = agent_stood >= after_s
    if not stuck.any():
        return 0
    edge = dict(zip(ids, edges))
    stood = dict(zip(agents, np.asarray(agent_stood, np.float64).tolist()))
    sx, sy = np.asarray(x, np.float64), np.asarray(y, np.float64)
    standing = np.asarray(speed, np.float64) < STAND_SPEED
    released = 0
    for i in np.flatnonzero(stuck):  # a few agents at most: the stuck ones on a junction
        if not edge.get(agents[i], "").startswith(":"):
            continue
        near = standing & (np.hypot(sx - agent_x[i], sy - agent_y[i]) < RANGE)
        for j in np.flatnonzero(near):
            vid = ids[j]
            if vid in stood or not blocks(int(i), int(j)) or \
                    api.vehicle.getWaitingTime(vid) < after_s:
                continue
            foes = [f[0] for f in api.vehicle.getJunctionFoes(vid, FOE_RANGE)
                    if f[7] and stood.get(f[0], 0.0) >= FOE_STOOD]
            have = api.vehicle.getParameter(vid, IGNORE_PARAM).split()
            new = [f for f in dict.fromkeys(foes) if f not in have]
            if new:
                api.vehicle.setParameter(vid, IGNORE_PARAM, " ".join(have + new))
                released += 1
    return released
