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

The jump: when the agent stands in the waiting vehicle's path too (the two boxes each in the
other's way: a SUMO car turning left out of a side road stood with its nose in the lane of an
agent on the main road, 2 m in front of it), no release can help, the vehicle would drive into
the agent. After :data:`JUMP_AFTER` times ``after_s`` of that (both standing), the SUMO-driven
vehicle jumps to the start of the lane after the junction on its route, as SUMO's own
teleport moves a jammed vehicle on along its route (SUMO's teleport is off in the env:
``SessionConfig.time_to_teleport``), if that lane has room for it. Counted apart
(``SumoCityEnv.jumped``). On cologne8 one such pair held a main road for 5 of 10 minutes.
A driver the release cannot free jumps the same way: SUMO holds it behind the car it merges
after onto the lane past the junction, and that car follows the agent that stands for the
driver. No junction foe is part of that circle, so there is nothing to ignore. On cologne8 a
car turning round inside a signal cluster held the straight approach for the rest of a 10-min
window, until this jump took its trips from 0.83 to 0.94 of SUMO's drivers'.
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
#: a pair blocking each other's paths jumps after this many times the release's wait
JUMP_AFTER = 3.0
#: ``blocks(i, j)`` answers: j not in agent i's path; j in it, held by SUMO's junction model
#: (the agent not in j's path: release); j in it and the agent in j's path (jump)
FREE, HELD, MUTUAL = 0, 1, 2
#: metres of free lane a jumping vehicle needs beyond its own length
JUMP_ROOM = 2.0


def release(api, ids, x, y, speed, edges, agents: Sequence[str], agent_x: np.ndarray,
            agent_y: np.ndarray, agent_stood: np.ndarray, after_s: float,
            blocks: Callable[[int, int], int]) -> tuple[int, int]:
    """Let SUMO-driven vehicles stop giving way to standing agents, or jump on when the two
    block each other's paths (module doc); the numbers of vehicles released and jumped.

    :param api: the running simulation's ``libsumo`` module.
    :param ids, x, y, speed, edges: every SUMO vehicle now (ids; box centres, m; m/s; road
        ids, internal lanes' edges start with ``:``).
    :param agents: the live agents' ids.
    :param agent_x, agent_y, agent_stood: the same agents' box centres (m) and how long (s)
        each has stood, in ``agents``' order.
    :param blocks: ``blocks(i, j)``: whether SUMO vehicle ``j`` (index of ``ids``) stands in
        agent ``i``'s path (position in ``agents``), and whether the agent stands in ``j``'s:
        :data:`FREE`, :data:`HELD` or :data:`MUTUAL`.
    """
    stuck = agent_stood >= after_s
    if not stuck.any():
        return 0, 0
    edge = dict(zip(ids, edges))
    stood = dict(zip(agents, np.asarray(agent_stood, np.float64).tolist()))
    sx, sy = np.asarray(x, np.float64), np.asarray(y, np.float64)
    standing = np.asarray(speed, np.float64) < STAND_SPEED
    released = jumped = 0
    for i in np.flatnonzero(stuck):  # a few agents at most: the stuck ones on a junction
        if not edge.get(agents[i], "").startswith(":"):
            continue
        near = standing & (np.hypot(sx - agent_x[i], sy - agent_y[i]) < RANGE)
        for j in np.flatnonzero(near):
            vid = ids[j]
            if vid in stood:
                continue
            waited = api.vehicle.getWaitingTime(vid)
            if waited < after_s:
                continue
            how = blocks(int(i), int(j))
            if how == MUTUAL:
                if _late(agent_stood[i], waited, after_s) and edge.get(vid, "").startswith(":"):
                    jumped += jump(api, vid)
                continue
            if how != HELD:
                continue
            foes = [f[0] for f in api.vehicle.getJunctionFoes(vid, FOE_RANGE)
                    if f[7] and stood.get(f[0], 0.0) >= FOE_STOOD]
            have = api.vehicle.getParameter(vid, IGNORE_PARAM).split()
            new = [f for f in dict.fromkeys(foes) if f not in have]
            if new:
                api.vehicle.setParameter(vid, IGNORE_PARAM, " ".join(have + new))
                released += 1
            elif _late(agent_stood[i], waited, after_s) and edge.get(vid, "").startswith(":"):
                # nothing left to release: what holds it is not a foe but the vehicle it
                # merges behind, itself behind the agent that waits for it
                jumped += jump(api, vid)
    return released, jumped


def _late(agent_stood: float, waited: float, after_s: float) -> bool:
    """Whether an agent and a SUMO-driven vehicle have both stood :data:`JUMP_AFTER` times
    the release's wait."""
    late = JUMP_AFTER * after_s
    return agent_stood >= late and waited >= late


def jump(api, vid: str) -> bool:
    """Move SUMO-driven vehicle ``vid``, standing on a junction's internal lane, to the start
    of the normal lane its internal lanes lead to (module doc), if that lane is free for its
    length plus :data:`JUMP_ROOM` m; whether it moved."""
    lane = api.vehicle.getLaneID(vid)
    for _ in range(4):  # a connection crosses its junction on at most a few internal lanes
        links = api.lane.getLinks(lane)
        if not links:
            return False
        lane = links[0][0]
        if not lane.startswith(":"):
            break
    else:
        return False
    need = api.vehicle.getLength(vid) + JUMP_ROOM
    for other in api.lane.getLastStepVehicleIDs(lane):
        if api.vehicle.getLanePosition(other) - api.vehicle.getLength(other) < need:
            return False
    try:
        api.vehicle.moveTo(vid, lane, 0.0)
    except Exception:  # the lane is not on its route after all: it waits on
        return False
    return True
