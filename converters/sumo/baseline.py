"""SUMO's own car-following on a converted bundle: the one home of the SUMO car-following baseline.

SUMO's default car-following (Krauss) drives the bundle's routes in a
:class:`~magail_sumo.sim.session.SumoSession` of its ``.sumocfg`` (:func:`bundle_session`).
Two runs use it:

* the converter's quality run (:func:`run_baseline`): SUMO drives the whole converted scenario
  from its start, as ``sumo -c`` runs it (the configuration's own step length, seed and
  teleport time); ``conversion.json`` takes ``signal_fidelity`` and ``sumo_baseline`` (ADE,
  FDE, collisions, teleports against the log) from it;
* the evaluation method ``sumo`` (:func:`drive_from_current`, through
  ``magail_sumo.agents.sumo_baseline.sumo_rollout``): SUMO, seeded per rollout, drives the sim
  agents from the scene's current step on; the agents it does not drive move as the caller's
  model says (constant velocity) and are obstacles to SUMO's drivers.

Both read SUMO the same way: a vehicle departing at ``k * dt`` is placed during the step from
``k * dt``, so after ``k + 1`` steps the simulation shows log step ``k``; SUMO reports a
vehicle's front bumper and angle (:mod:`magail_sumo.sim.frames`), its box centre is half a
length behind.

The evaluation run in detail: route vehicles are placed at their recorded pose and speed at
the scene's current step, then released (parked vehicles, which SUMO holds on its own parking
position, keep their recorded pose); each vehicle gets a speed factor ~ N(1,
:data:`SPEED_FACTOR_SD`) (clipped to [0.8, 1.2]) drawn from the rollout seed, which also seeds
SUMO (driver imperfection ``sigma``), so rollouts differ. Every other agent (pedestrians,
objects SUMO does not carry, parked vehicles, route vehicles that depart later or whose
insertion SUMO refused) moves as the caller's model says and is an obstacle in SUMO
(:class:`~magail_sumo.sim.session.Obstacles`) that SUMO's drivers brake for; a route vehicle
departing later leaves its obstacle when SUMO inserts it. A route vehicle that reaches the last
edge of its route (its log ended there, or SUMO drove it faster than the human) keeps driving:
its route is extended, edge by edge, by the straightest connection from its lane
(:func:`_continue_routes`); at a dead end inside the mapped area (a driveway or parking aisle
without a lane) it stops at the lane's end, and only one that reaches the edge of the map leaves
SUMO and goes on at constant velocity as an obstacle. A route vehicle due at the current step or
whose insertion SUMO put off (no room at its departure) is inserted at its recorded pose at the
current step when its route passes within :data:`QUEUED_MATCH` m, else it is taken out of SUMO
and an obstacle.

SUMO (without its sublane model) drives every vehicle on its lane's centre line, so at the
handover a vehicle would jump sideways by its recorded offset from the centre (a cyclist at the
right of a wide lane up to 2 m, into the path of a car turning past it). The recorded offset
(:func:`lateral_offsets`, kept within the lane) is carried in the reported pose instead, fading
with time constant :data:`LATERAL_OFFSET_TAU`; SUMO drives as before. SUMO's sublane model
(``--lateral-resolution 0.8``), which would keep the offset in SUMO itself, scored worse on the
scene that showed it (2a1e44d405a6833f: meta-metric 0.424 against 0.476, scored-agent
collisions 0.22 against 0.25; with the carried offset 0.698 and 0.0).

SUMO is reached through the running session (its ``api``); one simulation per process
(libsumo), so callers run each rollout batch in a fresh worker process.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Collection

import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.scene.types import STEP_LENGTH
from magail_sumo.sim.boxes import signed_box_distance
from magail_sumo.sim.frames import centre_to_front, yaw_to_sumo_angle
from magail_sumo.sim.session import OBSTACLE_PREFIX, Obstacles, SessionConfig, SumoSession
from magail_sumo.sim.sumo_config import SumoInputs

from .bundle import SceneBundle
from .routes import VehicleRoute, parked_tracks
from .signals import CHAR_CLASS, STATE_CLASS, SignalPrograms

DT = STEP_LENGTH  #: s per step
SPEED_FACTOR_SD = 0.1
#: m, a route vehicle whose insertion SUMO put off is inserted at its recorded pose at the current
#: step when its route passes this close (else it is an obstacle)
QUEUED_MATCH = 5.0
#: s, time constant with which a vehicle's recorded lateral offset from its lane's centre line at
#: the current step fades in its reported pose (:func:`lateral_offsets`); None: kept for good.
#: Chosen on the tuning scenes (3 TFRecords + 2a1e44d405a6833f) among 0, 1, 3 and None: 1 and 3
#: alike (meta-metric 0.759), None 0.717 (a vehicle turning with its offset kept drifts off),
#: 0 0.703
LATERAL_OFFSET_TAU: float | None = 1.0


def bundle_session(sumocfg: str | Path, seed: int | None = None,
                   inputs: SumoInputs | None = None) -> SumoSession:
    """The SUMO run of a bundle's configuration (not started; use it as a context manager).

    ``seed`` None: as ``sumo -c sumocfg`` runs it, with the configuration's own step length,
    seed and teleport time, queried through the session's ``api`` only (no subscriptions; the
    quality run). Else SUMO seeded with ``seed`` at :data:`DT` s steps, no teleports, every
    vehicle subscribed (:meth:`~magail_sumo.sim.session.SumoSession.vehicles`; a rollout).
    ``inputs``: the configuration already read (a loaded bundle's
    :attr:`~.bundle.SceneBundle.inputs`).
    """
    if seed is None:
        config = SessionConfig(step_length=None, seed=None, time_to_teleport=None,
                               subscribe=False)
    else:
        config = SessionConfig(seed=seed)
    return SumoSession(None if inputs is not None else sumocfg, inputs=inputs, config=config)


# ------------------------------------------------------------------ the converter's quality run

#: signalled lanes whose states SUMO does not show as recorded listed in ``conversion.json``
#: (``quality.signal_misses``), worst first
SIGNAL_MISSES_KEPT = 20
#: the signal miss of a lane without a SUMO link (the converter names the cause from the map:
#: :func:`.signals.unmapped_reason`)
UNMAPPED = "not part of a traffic-light link"


@dataclass
class Baseline:
    """Outcome of one SUMO run of the scenario."""

    ade: float | None  # m, mean over valid states while simulated
    fde: float | None  # m, mean over vehicles at their last valid simulated step
    collisions: int
    teleports: int
    signal_fidelity: float | None
    #: the signalled lanes behind a signal fidelity below 1 (:func:`_signal_misses`)
    signal_misses: list[dict] = field(default_factory=list)
    #: SUMO-driven vehicles whose box overlaps the recorded box of a non-moving vehicle at some
    #: step (:func:`parked_overlaps`); None when the scene has none
    parked_overlaps: int | None = None


def parked_boxes(scene: Scene) -> tuple[np.ndarray, list[str]]:
    """Rows and SUMO ids (track ids) of the scene's parked vehicles and cyclists
    (:func:`~.routes.parked_tracks`): the boxes :func:`parked_overlaps` checks."""
    rows = parked_tracks(scene)
    return rows, [str(int(i)) for i in scene.tracks.id[rows]]


def parked_overlaps(api, scene: Scene, k: int, rows: np.ndarray, skip: set[str],
                    size: dict[str, tuple[float, float]]) -> set[tuple[str, int]]:
    """(SUMO vehicle, parked row) pairs whose boxes overlap after the step showing log step
    ``k``: every vehicle in SUMO but those in ``skip`` (the parked vehicles themselves) and
    obstacles, its box from SUMO's front-bumper pose, length and width (cached in ``size``);
    the parked boxes as recorded at ``k`` (rows valid at ``k``). Overlap: signed box distance
    below 0 (:func:`magail_sumo.sim.boxes.signed_box_distance`)."""
    tr = scene.tracks
    here = rows[tr.valid[rows, k]]
    ids = [v for v in api.vehicle.getIDList() if v not in skip
           and not v.startswith(OBSTACLE_PREFIX)]
    if not len(here) or not ids:
        return set()
    pose = np.array([(*api.vehicle.getPosition(v), api.vehicle.getAngle(v)) for v in ids])
    for v in ids:
        if v not in size:
            size[v] = (api.vehicle.getLength(v), api.vehicle.getWidth(v))
    length, width = np.array([size[v] for v in ids]).T
    yaw = np.radians(90.0 - pose[:, 2])
    cx = pose[:, 0] - length / 2 * np.cos(yaw)
    cy = pose[:, 1] - length / 2 * np.sin(yaw)
    px, py = tr.x[here, k].astype(np.float64), tr.y[here, k].astype(np.float64)
    pl, pw = tr.length[here, k].astype(np.float64), tr.width[here, k].astype(np.float64)
    # only pairs whose circumscribed circles meet can overlap
    reach = np.hypot(length, width)[:, None] / 2 + np.hypot(pl, pw)[None] / 2
    a, b = np.nonzero((cx[:, None] - px[None]) ** 2 + (cy[:, None] - py[None]) ** 2
                      < reach ** 2)
    if not len(a):
        return set()
    d = signed_box_distance(cx[a], cy[a], yaw[a], length[a], width[a], px[b], py[b],
                            tr.heading[here[b], k].astype(np.float64), pl[b], pw[b])
    return {(ids[i], int(here[j])) for i, j in zip(a[d < 0].tolist(), b[d < 0].tolist())}


def _signal_misses(counts: dict[int, list], programs: SignalPrograms | None) -> list[dict]:
    """The signalled lanes SUMO did not show as recorded at every step, worst first: ``{"lane":
    id, "agree": share of its recorded steps, "reason": ...}``; the reason is "not part of a
    traffic-light link" (the conversion found no SUMO link for it) or the first disagreement
    ("SUMO shows g where the log has stop, first at step 12")."""
    out = []
    for lane, (hits, total, first) in counts.items():
        if hits == total:
            continue
        if programs is None or not programs.lane_links.get(lane):
            reason = UNMAPPED
        else:
            k, sumo, rec = first
            reason = f"SUMO shows {sumo} where the log has {rec}, first at step {k}"
        out.append({"lane": int(lane), "agree": round(hits / total, 3), "reason": reason})
    out.sort(key=lambda m: (m["agree"], m["lane"]))
    return out[:SIGNAL_MISSES_KEPT]


def run_baseline(scene: Scene, cfg: str, routes: list[VehicleRoute],
                 programs: SignalPrograms | None) -> Baseline:
    """Run ``sumo -c cfg`` (:func:`bundle_session` without a seed) for the scenario's duration;
    compare with the log.

    Positions: SUMO reports the front bumper; the box centre is half a length behind it.
    Timing: a vehicle departing at ``k * dt`` is placed during the step from ``k * dt``, so
    after ``k + 1`` steps the simulation shows log step ``k`` (the signal programs hold their
    first state one extra step to match). Also counted: the SUMO-driven vehicles that ever
    overlap a recorded non-moving vehicle (:func:`parked_overlaps`), whether the bundle carries
    those vehicles or not.
    """
    tr = scene.tracks
    steps = scene.num_steps
    known = {r.id: r for r in routes if not r.parked}
    sim_xy = {vid: np.full((steps, 2), np.nan) for vid in known}
    has_signals = bool(scene.signals.known().any())
    hits = total = 0
    lanes: dict[int, list] = {}  # signalled lane -> [hits, total, first disagreement]
    collisions = teleports = 0
    parked_rows, parked_ids = parked_boxes(scene)
    skip, size, hit_pairs = set(parked_ids), {}, set()
    with bundle_session(cfg) as session:
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
            if len(parked_rows):
                hit_pairs |= parked_overlaps(ls, scene, k, parked_rows, skip, size)
            if has_signals:
                tls_state = {t: ls.trafficlight.getRedYellowGreenState(t)
                             for t in (programs.states if programs else ())}
                rec = scene.signals.at_step(k)
                for lane, st in zip(rec.lane.tolist(), rec.state.tolist()):
                    if st == 0:
                        continue
                    total += 1
                    count = lanes.setdefault(lane, [0, 0, None])
                    count[1] += 1
                    links = programs.lane_links.get(lane, []) if programs else []
                    shown = [tls_state[t][i] for t, i in links]
                    if links and all(CHAR_CLASS.get(c) == STATE_CLASS[st] for c in shown):
                        hits += 1
                        count[0] += 1
                    elif count[2] is None:
                        count[2] = (k, "".join(shown), STATE_CLASS[st])
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
    return Baseline(ade, fde, collisions, teleports, fid, _signal_misses(lanes, programs),
                    len({v for v, _ in hit_pairs}) if len(parked_rows) else None)


# ------------------------------------------------------------------ the evaluation method "sumo"

def _departures(routes: Path) -> dict[str, int]:
    """Departure step of every vehicle of a bundle's route file."""
    root = ET.parse(routes).getroot()
    return {v.get("id", ""): int(round(float(v.get("depart", "0")) / DT))
            for v in root.iter("vehicle")}


#: link directions (SUMO ``lane.getLinks``) in the order a continued route prefers them;
#: turnarounds ("t") are never taken
_CONTINUE_ORDER = {"s": 0, "R": 1, "L": 1, "r": 2, "l": 2}


#: m, a dead end (a lane without successor) has mapped road ahead when lane, road-line or
#: road-edge points lie between these distances ahead of the lane's end...
DEAD_END_AHEAD = (2.0, 30.0)
#: m, ...and within this distance to either side of its direction
DEAD_END_HALF_WIDTH = 8.0


def map_points(scene: Scene) -> np.ndarray:
    """(P, 2) points of every lane, road line and road edge of the scene's map (scene frame)."""
    m = scene.roadmap
    parts = [f.polyline[:, :2] for feats in (m.lanes, m.road_lines, m.road_edges) for f in feats]
    return np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 2))


def _mapped_ahead(shape: np.ndarray, points: np.ndarray) -> bool:
    """Whether ``points`` (P, 2) hold mapped road ahead of the end of a lane of centre line
    ``shape`` (K, 2): :data:`DEAD_END_AHEAD` along its last segment, within
    :data:`DEAD_END_HALF_WIDTH` to the side."""
    d = shape[-1] - shape[-2]
    n = float(np.hypot(*d))
    if n < 1e-6 or not len(points):
        return False
    ux, uy = d / n
    rx, ry = (points - shape[-1]).T
    ahead, side = rx * ux + ry * uy, np.abs(ry * ux - rx * uy)
    lo, hi = DEAD_END_AHEAD
    return bool(np.any((ahead > lo) & (ahead < hi) & (side < DEAD_END_HALF_WIDTH)))


#: m of lanes a continued route is extended by at a time (more than one step's drive: SUMO
#: would otherwise cross a short added edge and arrive within one step)
CONTINUE_AHEAD = 50.0


def _continue_routes(api, vehicles, ends: dict[str, str], keep: Collection[str] = (),
                     points: np.ndarray | None = None) -> None:
    """Extend the route of every vehicle now on the last edge of its route: edge after edge,
    the successor reached from the lane by the straightest link (:data:`_CONTINUE_ORDER`, then
    the shorter link), until :data:`CONTINUE_AHEAD` m are added or a dead end is reached.
    ``ends`` maps a vehicle to the last edge of its route (filled on first sight, updated when
    extended, "" once it ends for good); vehicles in ``keep`` (parked ones, held at their
    parking stop) keep their routes. ``api``: the running session's TraCI-style domains
    (:attr:`~magail_sumo.sim.session.SumoSession.api`).

    A lane without a successor (a turnaround aside) is a dead end: where the scene's map goes on
    ahead of it (``points``, :func:`map_points`; :func:`_mapped_ahead`) — the end of a driveway
    or parking aisle the map has no lane for — the vehicle stops at the lane's end and stays
    there (as the humans who drive there park); at the edge of the map it leaves SUMO at the
    lane's end."""
    for vid, edge in zip(vehicles.ids, vehicles.edge):
        if vid in keep:
            continue
        last = ends.get(vid)
        if last is None:
            last = ends[vid] = api.vehicle.getRoute(vid)[-1]
        if edge != last or not last:
            continue
        lane, added, chain, dead_end = api.vehicle.getLaneID(vid), 0.0, [edge], False
        while added < CONTINUE_AHEAD:
            links = [ln for ln in api.lane.getLinks(lane) if ln[6] in _CONTINUE_ORDER]
            if not links:
                dead_end = True  # ``lane`` (on ``chain[-1]``) goes nowhere
                break
            nxt = min(links, key=lambda ln: (_CONTINUE_ORDER[ln[6]], ln[7]))[0]
            if api.lane.getEdgeID(nxt) in chain:  # a loop
                break
            lane = nxt
            chain.append(api.lane.getEdgeID(lane))
            added += api.lane.getLength(lane)
        ends[vid] = chain[-1] if added >= CONTINUE_AHEAD else ""
        try:
            if len(chain) > 1:
                api.vehicle.setRoute(vid, chain)
            if dead_end and points is not None and _mapped_ahead(
                    np.asarray(api.lane.getShape(lane)), points):
                api.vehicle.setStop(vid, chain[-1], max(0.0, api.lane.getLength(lane) - 0.1),
                                   int(lane.rsplit("_", 1)[1]), duration=1e6)
        except Exception:  # SUMO refused (the class may not use the edge; too close to brake)
            ends[vid] = ""


def lateral_offsets(api, v, cols: dict[str, int], x0: np.ndarray, y0: np.ndarray,
                    width: np.ndarray) -> np.ndarray:
    """(A,) signed lateral offset (m, left of the direction of travel positive) of each recorded
    centre ``(x0, y0)[a]`` from the pose SUMO placed vehicle ``vid`` (``cols``: vehicle ->
    agent ``a``) at, for the vehicles of ``v`` (:meth:`~magail_sumo.sim.session.SumoSession.
    vehicles`, right after the placement), clipped so the box stays within its lane (``width``
    of each agent's box; the lane's width from ``api``).

    Without SUMO's sublane model every vehicle drives on its lane's centre line: a cyclist at
    the right of a 4.5 m lane is put up to 2 m aside, into the path of a car turning past it,
    and every vehicle jumps sideways at the handover. The offset is carried in the reported pose
    instead (:func:`drive_from_current`); SUMO's sublane model, which would carry it in SUMO,
    drove worse (module doc). ``api``: the running session's TraCI-style domains. Agents not
    placed (not in ``cols``, or off every lane) get 0."""
    out = np.zeros(len(x0))
    for i, vid in enumerate(v.ids):
        a = cols.get(vid)
        if a is None:
            continue
        try:
            half = 0.5 * float(api.lane.getWidth(api.vehicle.getLaneID(vid))) - 0.5 * width[a]
        except Exception:  # not on a lane
            continue
        lat = (-(x0[a] - v.x[i]) * np.sin(v.yaw[i]) + (y0[a] - v.y[i]) * np.cos(v.yaw[i]))
        half = max(half, 0.0)
        out[a] = np.clip(lat, -half, half)
    return out


def _drop(api, ids, routed: set[str]) -> None:
    """Take route vehicles that have not departed out of SUMO's insertion queue (``api``: the
    session's, as for :func:`_continue_routes`)."""
    for i in ids:
        if str(int(i)) in routed:
            try:
                api.vehicle.remove(str(int(i)))
            except Exception:  # never loaded or already gone
                pass


@dataclass(frozen=True)
class DriveSetup:
    """What :func:`drive` needs of a scene, its bundle and its agents whatever the seed (read
    once for all the rollouts of a batch; :func:`prepare_drive`)."""

    scene: Scene
    bundle: SceneBundle
    ids: np.ndarray  # (A,) track ids of the agents
    n_steps: int
    start: tuple[np.ndarray, ...]  # (rows, x, y, z, heading, vx, vy) at the current step
    future: tuple[np.ndarray, np.ndarray, np.ndarray]  # (x, y, yaw) of agents SUMO does not drive
    departs: dict[str, int]  # departure step of every route vehicle
    points: np.ndarray  # (P, 2) the map's points (:func:`map_points`)


def prepare_drive(scene: Scene, bundle_dir: Path, ids: np.ndarray, n_steps: int,
                  start: tuple[np.ndarray, ...],
                  future: tuple[np.ndarray, np.ndarray, np.ndarray]) -> DriveSetup:
    """The :class:`DriveSetup` of :func:`drive_from_current`'s arguments but the seed (the
    bundle read and checked, its departures, the map's points)."""
    bundle = SceneBundle.load(scene, bundle_dir)
    return DriveSetup(scene, bundle, ids, n_steps, start, future,
                      _departures(bundle.files.routes), map_points(scene))


def drive_from_current(scene: Scene, bundle_dir: Path, seed: int, ids: np.ndarray, n_steps: int,
                       start: tuple[np.ndarray, ...],
                       future: tuple[np.ndarray, np.ndarray, np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SUMO's car-following (module doc) drives the agents ``ids`` (track ids) over ``n_steps``
    steps after the scene's current step, in the bundle of ``bundle_dir``, seeded with
    ``seed``.

    :param start: ``(rows, x, y, z, heading, vx, vy)`` of the agents at the current step
        (``rows`` index ``scene.tracks``; box centres, scene frame).
    :param future: ``(x, y, yaw)``, each (A, ``n_steps``): how the agents SUMO does not drive
        move on (their obstacles' poses); an agent leaving SUMO goes on at constant velocity
        from its last state in SUMO.
    :returns: ``(x, y, yaw, speed)``, each (A, ``n_steps``): the states SUMO drove (the
        recorded lateral offset carried in x, y), NaN where SUMO did not drive the agent.
        Several seeds of one scene: :func:`prepare_drive` once, then :func:`drive` per seed
        (the same result).
    """
    return drive(prepare_drive(scene, bundle_dir, ids, n_steps, start, future), seed)


def drive(setup: DriveSetup, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`drive_from_current` of a prepared scene, seeded with ``seed``."""
    scene, bundle, ids, n_steps = setup.scene, setup.bundle, setup.ids, setup.n_steps
    col = {str(int(i)): k for k, i in enumerate(ids)}
    rows, x0, y0, _, h0, vx0, vy0 = setup.start
    length = scene.tracks.length[rows, scene.current_time_index].astype(np.float64)
    width = scene.tracks.width[rows, scene.current_time_index].astype(np.float64)
    cur = scene.current_time_index
    rng = np.random.default_rng(seed)
    tx, ty, tyaw, tspeed = (np.full((len(ids), n_steps), np.nan) for _ in range(4))
    held: list[str] = []
    routed = set(bundle.sumo_ids)
    departs = setup.departs
    due: set[str] = set()
    later: set[str] = set()
    gone: dict[int, int] = {}  # agent -> column of its last state before it left SUMO
    ends: dict[str, str] = {}  # driven vehicle -> last edge of its (continued) route
    points = setup.points
    obstacles: Obstacles | None = None
    obs = np.zeros(0, np.int64)
    offsets = np.zeros(len(ids))  # each agent's recorded lateral offset from its lane's centre
    ox, oy, oyaw = setup.future  # the future of every agent SUMO does not drive
    with bundle_session(bundle.sumocfg, seed, bundle.inputs) as sess:
        api = sess.api  # the running simulation's TraCI-style domains
        for k in range(cur + 1 + n_steps):  # after k + 1 steps SUMO shows log step k
            if k == cur:  # start the future from the recorded state: pose and speed
                present = set(api.vehicle.getIDList())
                # route vehicles whose insertion SUMO has put off (no room at their departure)
                # are inserted at their recorded pose on their route, when it is that close
                queued = {vid for vid in col if vid in routed and vid not in present
                          and vid not in bundle.parked and departs.get(vid, cur) <= cur}
                for vid in sorted(present | queued):
                    a = col.get(vid)
                    if a is None or vid in bundle.parked:
                        continue
                    fx, fy = centre_to_front(x0[a:a + 1], y0[a:a + 1], h0[a:a + 1],
                                             length[a:a + 1])
                    try:
                        api.vehicle.moveToXY(vid, "", -1, float(fx[0]), float(fy[0]),
                                            float(yaw_to_sumo_angle(h0[a:a + 1])[0]), 1,
                                            100.0 if vid in present else QUEUED_MATCH)
                        api.vehicle.setSpeed(vid, float(np.hypot(vx0[a], vy0[a])))
                        held.append(vid)
                        present.add(vid)
                    except Exception:  # off its route: SUMO keeps its own state
                        pass
                # every other agent becomes an obstacle SUMO's drivers see: pedestrians,
                # objects SUMO does not carry, parked vehicles (off the lanes in SUMO) and route
                # vehicles not in SUMO yet (those departing later drop theirs when they depart)
                due = {vid for vid in col if departs.get(vid, -1) == cur}  # inserted this step
                later = {vid for vid in col if departs.get(vid, -1) > cur}
                driven = (present | due) - bundle.parked
                obs = np.array([a for vid, a in col.items() if vid not in driven], np.int64)
                _drop(api, [ids[a] for a in obs], routed - present - later)
                obstacles = Obstacles(sess, [str(int(ids[a])) for a in obs], length[obs],
                                      width[obs], kinds=scene.tracks.type[rows[obs]])
            elif k == cur + 1 and obstacles is not None:  # insertions SUMO refused at the current step
                now = set(api.vehicle.getIDList())
                late = np.array([col[vid] for vid in sorted(due - now - bundle.parked)], np.int64)
                if len(late):
                    _drop(api, [ids[a] for a in late], routed - now)
                    obstacles.add([str(int(ids[a])) for a in late], length[late], width[late])
                    obs = np.r_[obs, late]
            if obstacles is not None and k >= cur:
                t = k - cur - 1  # column of log step k (-1: the current step)
                if t < 0:
                    obstacles.place(x0[obs], y0[obs], h0[obs])
                else:
                    px, py, pyaw = ox[obs, t], oy[obs, t], oyaw[obs, t]
                    for j in (np.flatnonzero(np.isin(obs, list(gone))).tolist() if gone
                              else ()):
                        a, t0 = int(obs[j]), gone[int(obs[j])]  # on from its last SUMO state
                        d = tspeed[a, t0] * (t - t0) * DT
                        px[j] = tx[a, t0] + d * np.cos(tyaw[a, t0])
                        py[j] = ty[a, t0] + d * np.sin(tyaw[a, t0])
                        pyaw[j] = tyaw[a, t0]
                    obstacles.place(px, py, pyaw)
            if k == cur + 1:
                for vid in held:
                    try:
                        api.vehicle.setSpeed(vid, -1.0)
                    except Exception:
                        pass
            departed, arrived = sess.step()
            if k == cur:
                offsets = lateral_offsets(api, sess.vehicles(), {vid: col[vid] for vid in held},
                                          x0, y0, width)
            if obstacles is not None and later.intersection(departed):
                obstacles.retire(later.intersection(departed))
            # an agent leaving SUMO (its route ends) goes on at constant velocity: an obstacle
            left = [col[vid] for vid in arrived if vid in col and vid not in bundle.parked]
            if obstacles is not None and k > cur + 1 and left:
                t0 = k - cur - 2  # column of its last state in SUMO
                left = [a for a in left if np.isfinite(tx[a, t0]) and a not in gone]
                if left:
                    gone.update({a: t0 for a in left})
                    obstacles.add([str(int(ids[a])) for a in left], length[left], width[left])
                    obs = np.r_[obs, np.array(left, np.int64)]
            for vid in departed:
                if not vid.startswith(OBSTACLE_PREFIX):
                    f = float(np.clip(rng.normal(1.0, SPEED_FACTOR_SD), 0.8, 1.2))
                    api.vehicle.setSpeedFactor(vid, f)
            if k > cur:
                v = sess.vehicles()
                _continue_routes(api, v, ends, bundle.parked, points)
                t = k - cur - 1
                sel = [(i, col[vid]) for i, vid in enumerate(v.ids)
                       if vid in col and vid not in bundle.parked]
                if sel:
                    i, a = (np.array(s) for s in zip(*sel))
                    tx[a, t], ty[a, t] = v.x[i], v.y[i]
                    lat = offsets[a]  # the recorded lateral offset, fading (LATERAL_OFFSET_TAU)
                    if LATERAL_OFFSET_TAU is not None:
                        lat = lat * np.exp(-(t + 1) * DT / LATERAL_OFFSET_TAU)
                    tx[a, t] -= lat * np.sin(v.yaw[i])
                    ty[a, t] += lat * np.cos(v.yaw[i])
                    tyaw[a, t], tspeed[a, t] = v.yaw[i], v.speed[i]
    return tx, ty, tyaw, tspeed
