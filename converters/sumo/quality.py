"""Quality figures of a converted scene (definitions in conversion.json / issue 3).

* on_network_rate: share of valid states of moving vehicles lying within half the lane width
  + 0.5 m of a lane (junction-internal lanes included) whose direction is within 45° of the
  vehicle heading.
* route_rate: share of moving vehicles whose route is connected and covers >= 90 % of their
  valid states (same test, restricted to the route's lanes and the internal lanes between).
* signal_fidelity / sumo_baseline: from one SUMO run of the scenario (see :func:`run_baseline`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.scene import ObjectType, Scene
from magail_sumo.sim.session import SessionConfig, SumoSession

from .lanes import LaneSegments, on_lanes
from .routes import PARKED_MOVE, VehicleRoute, moved_distance, route_covers
from .signals import CHAR_CLASS, STATE_CLASS, SignalPrograms

COVERAGE = 0.9  #: share of its states a route must cover (route_rate)


def moving_vehicles(scene: Scene) -> np.ndarray:
    """Indices of vehicle tracks that move more than :data:`PARKED_MOVE` m."""
    return np.flatnonzero((scene.tracks.type == ObjectType.VEHICLE)
                          & (moved_distance(scene) > PARKED_MOVE))


def on_network_rate(scene: Scene, seg: LaneSegments, off: np.ndarray | None = None) -> float | None:
    """See module docstring; None when there are no moving vehicles.

    ``off`` (N, T) bool marks states to count as off the network whatever ``seg`` says (the
    states carried by synthesised lanes, for the map-only figure).
    """
    tr = scene.tracks
    idx = moving_vehicles(scene)
    v = tr.valid[idx]
    if not v.any():
        return None
    xy = np.stack([tr.x[idx][v], tr.y[idx][v]], axis=1)
    on = on_lanes(seg, xy, tr.heading[idx][v].astype(np.float64))
    if off is not None:
        on &= ~off[idx][v]
    return float(on.mean())


def route_rate(scene: Scene, seg: LaneSegments, routes: list[VehicleRoute], net) -> float | None:
    """See module docstring; None when there are no moving vehicles."""
    moving = moving_vehicles(scene)
    if not len(moving):
        return None
    by_track = {r.track: r for r in routes}
    good = 0
    for n in moving.tolist():
        r = by_track.get(n)
        if r is not None and r.connected and route_covers(scene, seg, r, net) >= COVERAGE:
            good += 1
    return good / len(moving)


@dataclass
class Baseline:
    """Outcome of one SUMO run of the scenario."""

    ade: float | None  # m, mean over valid states while simulated
    fde: float | None  # m, mean over vehicles at their last valid simulated step
    collisions: int
    teleports: int
    signal_fidelity: float | None


def run_baseline(scene: Scene, cfg: str, routes: list[VehicleRoute],
                 programs: SignalPrograms | None) -> Baseline:
    """Run ``sumo -c cfg`` (a :class:`~magail_sumo.sim.session.SumoSession` with the config's
    own step length, seed and teleport time) for the scene's duration; compare with the log.

    Positions: SUMO reports the front bumper; the box centre is half a length behind it.
    Timing: a vehicle departing at ``k * dt`` is placed during the step from ``k * dt``, so
    after ``k + 1`` steps the simulation shows log step ``k`` (the signal programs hold their
    first state one extra step to match).
    """
    tr = scene.tracks
    steps = scene.num_steps
    known = {r.id: r for r in routes if not r.parked}
    sim_xy = {vid: np.full((steps, 2), np.nan) for vid in known}
    has_signals = bool(scene.signals.known().any())
    hits = total = 0
    collisions = teleports = 0
    config = SessionConfig(step_length=None, seed=None, time_to_teleport=None, subscribe=False)
    with SumoSession(cfg, config=config) as session:
        ls = session.api
        for k in range(steps):  # after k + 1 steps SUMO shows the state of log step k
            session.step()
            collisions += ls.simulation.getCollidingVehiclesNumber()
            teleports += ls.simulation.getStartingTeleportNumber()
            for vid in ls.vehicle.getIDList():
                if vid in sim_xy:
                    x, y = ls.vehicle.getPosition(vid)
                    ang = np.radians(90.0 - ls.vehicle.getAngle(vid))
                    half = known[vid].length / 2
                    sim_xy[vid][k] = (x - half * np.cos(ang), y - half * np.sin(ang))
            if has_signals:
                tls_state = {t: ls.trafficlight.getRedYellowGreenState(t)
                             for t in (programs.states if programs else ())}
                rec = scene.signals.at_step(k)
                for lane, st in zip(rec.lane.tolist(), rec.state.tolist()):
                    if st == 0:
                        continue
                    total += 1
                    links = programs.lane_links.get(lane, []) if programs else []
                    if links and all(CHAR_CLASS.get(tls_state[t][i]) == STATE_CLASS[st]
                                     for t, i in links):
                        hits += 1
    errs, finals = [], []
    for vid, r in known.items():
        n = r.track
        sim = sim_xy[vid]
        ok = tr.valid[n] & ~np.isnan(sim[:, 0])
        if not ok.any():
            continue
        e = np.hypot(sim[ok, 0] - tr.x[n, ok], sim[ok, 1] - tr.y[n, ok])
        errs.append(e)
        last = np.flatnonzero(ok)[-1]  # last valid step the vehicle is still simulated
        finals.append(float(np.hypot(sim[last, 0] - tr.x[n, last], sim[last, 1] - tr.y[n, last])))
    ade = float(np.concatenate(errs).mean()) if errs else None
    fde = float(np.mean(finals)) if finals else None
    fid = hits / total if total else None
    return Baseline(ade, fde, collisions, teleports, fid)
