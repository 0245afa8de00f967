"""Vehicle and cyclist routes from map-matched tracks; parked vehicles; unconverted objects.

A track's matched WOMD lanes become the SUMO edges that carry them; gaps between consecutive
edges are closed with the shortest path in the built network when one exists. Departure is
at the first matched valid step with lane, front-bumper position and speed from that state.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magail_sumo.scene import ObjectType, Scene

from sumolib.geomhelper import polygonOffsetWithMinimumDistanceToPoint

from .matching import LaneIndex, match_track
from .parking import (PARK_SEARCH, ParkedSpot, block_clearance, class_lanes, parked_pose,
                      place_parked)
from .topology import NetworkPlan
from .lanes import LaneSegments, lane_segments, on_lanes

PARKED_MOVE = 2.0  #: m, tracks moving less than this are parked (see :func:`moved_distance`)
SPIKE = 1.0  #: m, a one-state jump of a box at least this far is a spike (not motion)
SPIKE_TURN = np.radians(45.0)  #: rad, heading jump marking a spike at a track's first/last state
#: SUMO insertion checks kept: all but the speed limit (recorded speeds may exceed it).
CHECKS = "collision leaderGap followerGap stop"
#: m/s, SUMO's default vType maxSpeed of the classes routes are written for
CLASS_MAX_SPEED = {"passenger": 55.56, "bicycle": 13.89}
MAX_DETOUR = 150.0  #: m, longest shortest-path filler between two matched edges
BLIP_STATES = 10  #: fewer valid states than this on an edge a route cannot reach is a blip
SYNTHESIZED = -2  #: matched-lane code of states on a synthesised lane (-1 = unmatched)


@dataclass
class VehicleRoute:
    """One converted track: SUMO route edges and departure state."""

    track: int  # index into scene.tracks
    id: str
    vclass: str
    length: float
    width: float
    edges: list[str]
    depart_step: int
    depart_lane: int
    depart_pos: float  # m, front bumper along the first edge's lane
    depart_speed: float  # m/s
    connected: bool
    parked: bool
    depart_edge: int = 0  # index into edges where the vehicle departs
    speed_factor: float = 1.0  # desired speed / speed limit, from the recorded speeds
    #: m/s, the vType's maxSpeed where the recording is faster than SUMO's default for the
    #: class allows (a motorcycle recorded as a cyclist); None: SUMO's default
    max_speed: float | None = None
    #: WOMD lane per valid step (-1 unmatched, :data:`SYNTHESIZED` on a synthesised lane)
    matched: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    #: a parked vehicle's stop: on the lane it blocks or in a space at its recorded pose
    #: (:mod:`.parking`)
    spot: ParkedSpot | None = None


def moved_distance(scene: Scene) -> np.ndarray:
    """(N,) largest distance (m) of any valid state from the track's first valid state, both
    leaving out *spikes*: a box recorded for one state :data:`SPIKE` m or more away from its
    valid neighbours -- between two (whose positions lie within ``SPIKE`` m of each other) or,
    at the first or last valid state, beside one with a heading more than
    :data:`SPIKE_TURN` rad apart. A stationary car whose box jumps for one step is no motion;
    a moving track is no spike (its neighbours lie apart, its heading turns slowly)."""
    tr = scene.tracks
    if not tr.num_steps or not tr.num_tracks:
        return np.zeros(tr.num_tracks)
    # valid states first, in step order
    order = np.argsort(~tr.valid, axis=1, kind="stable")
    ok = np.take_along_axis(tr.valid, order, axis=1)
    x = np.take_along_axis(tr.x, order, axis=1).astype(np.float64)
    y = np.take_along_axis(tr.y, order, axis=1).astype(np.float64)
    h = np.take_along_axis(tr.heading, order, axis=1).astype(np.float64)
    count = ok.sum(axis=1, keepdims=True)
    k = np.arange(tr.num_steps)[None]
    has_prev, has_next = ok & (k > 0), ok & (k < count - 1)

    def shift(a: np.ndarray, by: int) -> np.ndarray:  # a[:, k - by], edge-padded
        return np.concatenate([np.repeat(a[:, :1], by, 1), a[:, :-by]], 1) if by > 0 else \
            np.concatenate([a[:, -by:], np.repeat(a[:, -1:], -by, 1)], 1)

    def gap(by: int) -> np.ndarray:
        return np.hypot(x - shift(x, by), y - shift(y, by))

    d_prev, d_next = gap(1), gap(-1)
    d_across = np.hypot(shift(x, 1) - shift(x, -1), shift(y, 1) - shift(y, -1))
    turn = lambda by: np.abs((h - shift(h, by) + np.pi) % (2 * np.pi) - np.pi)  # noqa: E731
    spike = (has_prev & has_next & (d_prev >= SPIKE) & (d_next >= SPIKE) & (d_across < SPIKE)) \
        | (~has_prev & has_next & (d_next >= SPIKE) & (turn(-1) > SPIKE_TURN)) \
        | (has_prev & ~has_next & (d_prev >= SPIKE) & (turn(1) > SPIKE_TURN))
    keep = ok & ~spike
    first = np.argmax(keep, axis=1)
    n = np.arange(tr.num_tracks)
    d = np.hypot(x - x[n, first][:, None], y - y[n, first][:, None])
    return np.where(keep, d, 0.0).max(axis=1)


def parked_tracks(scene: Scene, moved: np.ndarray | None = None) -> np.ndarray:
    """Rows of the parked tracks: vehicles and cyclists with a valid state that move less than
    :data:`PARKED_MOVE` m (:func:`moved_distance`, or ``moved`` when already computed)."""
    tr = scene.tracks
    moved = moved_distance(scene) if moved is None else moved
    return np.flatnonzero(np.isin(tr.type, (ObjectType.VEHICLE, ObjectType.CYCLIST))
                          & (moved < PARKED_MOVE) & tr.valid.any(axis=1))


def _piece(plan: NetworkPlan, lane: int, pos: float) -> tuple[str, int, float] | None:
    """(edge, lane index, position on the piece in m) of a road lane position; None in junctions."""
    pieces = plan.lane_edges.get(lane)
    if not pieces:
        return None
    for edge, idx, s0, s1 in pieces:
        if pos <= s1 + 1e-6:
            return edge, idx, max(pos - s0, 0.0)
    edge, idx, s0, s1 = pieces[-1]
    return edge, idx, s1 - s0


def _junction_connection(plan: NetworkPlan, lane: int, from_edge: str | None = None,
                         to_edge: str | None = None):
    """The connection whose junction lanes include ``lane`` (preferring the given ends)."""
    cands = [c for c in plan.connections if lane in c.via]
    for c in cands:
        if (from_edge is None or c.from_edge == from_edge) and (to_edge is None or c.to_edge == to_edge):
            return c
    return cands[0] if cands else None


def _connect(net, edges: list[str], vclass: str) -> tuple[list[str], bool]:
    """Close gaps between consecutive edges with shortest paths that vehicle class ``vclass``
    may drive (:func:`_joins`); (edges, all connected). Where no such path exists the route
    stops before the gap (a route SUMO refuses would stop ``sumo -c``), so the edges returned
    are always one connected route."""
    out = [edges[0]]
    for nxt in edges[1:]:
        hop = _joins(net, out[-1], nxt, vclass)
        if hop is None:
            return out, False
        out.extend(hop)
    return out, True


def _joins(net, a: str, b: str, vclass: str) -> list[str] | None:
    """The edges after ``a`` up to ``b`` on the shortest path (at most :data:`MAX_DETOUR` m)
    whose connections let vehicle class ``vclass`` through (``[b]`` when ``a`` leads straight
    into it); None when there is none."""
    cur, tgt = net.getEdge(a), net.getEdge(b)
    if tgt in cur.getAllowedOutgoing(vclass):
        return [b]
    path, _ = net.getShortestPath(cur, tgt, maxCost=MAX_DETOUR, vClass=vclass)
    return [e.getID() for e in path[1:]] if path else None


def _connect_trimmed(net, seq: list[str], head_added: bool, tail_added: bool, vclass: str
                     ) -> tuple[list[str], bool]:
    """:func:`_connect` of ``seq``; where that leaves a gap, the same without the edge put in
    front of the matched edges for a start inside a junction (``head_added``), without the one
    put behind them for an end inside a junction (``tail_added``), or without both -- the first
    of these that connects. Such an edge comes from the connection owning the first (last)
    matched junction lane; when the match jumped onto a junction lane of a connection that
    does not join the route (or the route starts on a synthesised lane from a dead end), the
    edge leads nowhere on the route and would cut it short."""
    edges, ok = _connect(net, seq, vclass)
    if ok:
        return edges, ok
    for drop_head, drop_tail in ((True, False), (False, True), (True, True)):
        if (drop_head and not head_added) or (drop_tail and not tail_added):
            continue
        trimmed = seq[int(drop_head):len(seq) - int(drop_tail)]
        if trimmed:
            out, ok = _connect(net, trimmed, vclass)
            if ok:
                return out, ok
    return edges, False


def _connect_best(net, seq: list[str], weight: list[int], vclass: str
                  ) -> tuple[list[str], bool]:
    """Where :func:`_connect_trimmed` leaves a gap: the connected route through the ordered
    subsequence of ``seq`` that carries the most states (``weight[i]``: the valid states matched
    to ``seq[i]``), gaps closed as in :func:`_connect`; connected when each edge left out
    carries less than :data:`BLIP_STATES` states (a momentary match onto a lane beside the
    route, which no route can reach and come back from)."""
    n = len(seq)
    reach: dict[tuple[int, int], bool] = {}

    def joins(i: int, j: int) -> bool:
        if (i, j) not in reach:
            reach[i, j] = _joins(net, seq[i], seq[j], vclass) is not None
        return reach[i, j]

    best = [float(w) for w in weight]
    prev = [-1] * n
    for j in range(n):
        for i in range(j):
            if best[i] + weight[j] > best[j] and seq[i] != seq[j] and joins(i, j):
                best[j], prev[j] = best[i] + weight[j], i
    j = int(np.argmax(best))
    keep = []
    while j >= 0:
        keep.append(j)
        j = prev[j]
    keep.reverse()
    edges, _ = _connect(net, [seq[i] for i in keep], vclass)
    dropped = set(range(n)) - set(keep)
    return edges, all(weight[i] < BLIP_STATES for i in dropped)


def _via_edges(net, a: str, b: str) -> set[str]:
    """Internal edges a vehicle passes from edge ``a`` into edge ``b`` (every lane pair)."""
    names: set[str] = set()
    for c in net.getEdge(a).getOutgoing().get(net.getEdge(b), []):
        via = c.getViaLaneID()
        while via:
            names.add(via.rsplit("_", 1)[0])
            nxt = net.getLane(via).getOutgoing()
            via = nxt[0].getViaLaneID() if nxt and nxt[0].getViaLaneID() else ""
    return names


def _extend_into_junctions(net, seg, xy: np.ndarray, heading: np.ndarray, edges: list[str],
                           vclass: str) -> tuple[list[str], int]:
    """(edges, number of edges put in front): where the recorded states before the route's
    first covered state (after its last one) lie on the junction lanes that lead into its first
    edge (out of its last edge) in the built network -- netconvert's junction took that part of
    the mapped lane -- the route starts one edge earlier (ends one edge later), through them.
    The edge whose junction lanes carry the most of those states is taken, among those whose
    connection vehicle class ``vclass`` may drive."""
    def covered(names: set[str], rows: np.ndarray) -> np.ndarray:
        return on_lanes(seg, xy[rows], heading[rows], np.isin(seg.edge, list(names)))

    names = set(edges)
    for a, b in zip(edges[:-1], edges[1:]):
        names |= _via_edges(net, a, b)
    on = covered(names, np.arange(len(xy)))
    head = np.arange(int(np.argmax(on)) if on.any() else len(on))  # none covered: all of them
    tail = np.arange(len(on) - int(np.argmax(on[::-1])), len(on)) if on.any() else head
    added = 0
    if len(head):
        best = max(((covered(_via_edges(net, e.getID(), edges[0]), head).sum(), e.getID())
                    for e in net.getEdge(edges[0]).getIncoming()
                    if net.getEdge(edges[0]) in e.getAllowedOutgoing(vclass)), default=(0, ""))
        if best[0] > 0 and best[1] not in edges:
            edges, added = [best[1], *edges], 1
    if len(tail) and (on.any() or not added):
        best = max(((covered(_via_edges(net, edges[-1], e.getID()), tail).sum(), e.getID())
                    for e in net.getEdge(edges[-1]).getAllowedOutgoing(vclass)), default=(0, ""))
        if best[0] > 0 and best[1] not in edges:
            edges = [*edges, best[1]]
    return edges, added


def _route_score(scene: Scene, seg, route: VehicleRoute, net) -> tuple[bool, float]:
    """(connected, share of the track's valid states the route covers): larger is better."""
    return route.connected, route_covers(scene, seg, route, net)


def _track_route(plan: NetworkPlan, net, seg, scene: Scene, n: int, kind: ObjectType,
                 steps: np.ndarray, xy: np.ndarray, heading: np.ndarray,
                 lane_of: np.ndarray, pieces: list) -> "VehicleRoute | str":
    """The route of moving track ``n`` from its matched lanes ``lane_of`` (per valid state; -1
    unmatched, :data:`SYNTHESIZED`) and their edge ``pieces``, or why there is none.

    :param seg: callable giving the built network's lane segments.
    """
    tr = scene.tracks
    tid = int(tr.id[n])
    vclass = "bicycle" if kind == ObjectType.CYCLIST else "passenger"
    matched = np.flatnonzero(lane_of != -1)
    if not len(matched):
        return "no state matches a lane (distance and heading)"
    seq: list[str] = []
    weight: list[int] = []  # valid states matched to each edge of seq
    for p in pieces:
        if p is not None and (not seq or seq[-1] != p[0]):
            seq.append(p[0])
            weight.append(0)
        if p is not None:
            weight[-1] += 1
    first = int(matched[0])
    head = tail = None
    if int(lane_of[first]) in plan.junction_lanes:  # starts inside a junction
        head = _junction_connection(plan, int(lane_of[first]), to_edge=seq[0] if seq else None)
    last_lane = int(lane_of[matched[-1]])
    if last_lane in plan.junction_lanes:
        tail = _junction_connection(plan, last_lane, from_edge=seq[-1] if seq else None)
    head_added = tail_added = False
    if head is not None and (not seq or seq[0] != head.from_edge):
        seq.insert(0, head.from_edge)
        weight.insert(0, 0)
        head_added = True
    if not seq and tail is not None:
        seq.append(tail.from_edge)
        weight.append(0)
    if tail is not None and seq[-1] != tail.to_edge:
        seq.append(tail.to_edge)
        weight.append(0)
        tail_added = True
    if not seq:
        return "matched junction lanes belong to no connection"
    edges, connected = _connect_trimmed(net, seq, head_added, tail_added, vclass)
    if not connected:
        edges, connected = _connect_best(net, seq, weight, vclass)
    depart_edge = 0
    first = next((k for k in matched if pieces[k] is not None and pieces[k][0] == edges[0]), None)
    if first is None and head is not None and edges[0] == head.from_edge and len(edges) > 1:
        # starts inside a junction: keep the incoming edge in the route, depart on the next
        # edge when the vehicle reaches it
        depart_edge = 1
        first = next((k for k in matched if pieces[k] is not None and pieces[k][0] == edges[1]),
                     None)
    length = float(np.median(tr.length[n, steps]))
    width = float(np.median(tr.width[n, steps]))
    if first is not None:
        edge0, lane0 = pieces[first][:2]
        st = steps[first]
        front = xy[first] + length / 2 * np.array([np.cos(heading[first]), np.sin(heading[first])])
        shape = net.getLane(f"{edge0}_{lane0}").getShape()
        pos0 = polygonOffsetWithMinimumDistanceToPoint(tuple(front), shape)
    elif head is not None and edges[0] == head.from_edge:  # whole track inside the junction
        edge0, lane0 = head.from_edge, head.from_lane
        depart_edge = 0  # departs at the end of the incoming edge, not on the next one
        st = steps[matched[0]]
        pos0 = net.getLane(f"{edge0}_{lane0}").getLength()
    else:
        return "no connected route through the matched lanes"
    if connected:
        edges, added = _extend_into_junctions(net, seg(), xy, heading, edges, vclass)
        depart_edge += added
    lane_len = net.getLane(f"{edge0}_{lane0}").getLength()
    speed = float(np.hypot(tr.vx[n, st], tr.vy[n, st]))
    speeds = np.hypot(tr.vx[n, steps], tr.vy[n, steps])
    limit = net.getEdge(edge0).getSpeed()
    factor = float(np.clip(np.quantile(speeds, 0.95) / max(limit, 0.1), 1.0, 2.0))
    top = float(speeds.max()) * 1.1
    return VehicleRoute(
        track=n, id=str(tid), vclass=vclass,
        length=max(length, 0.5), width=max(width, 0.3), edges=edges, depart_step=int(st),
        depart_lane=lane0, depart_pos=float(np.clip(pos0, 0.1, lane_len)), depart_edge=depart_edge,
        depart_speed=speed, connected=connected, parked=False,
        speed_factor=factor, matched=lane_of,
        max_speed=round(top, 2) if top > CLASS_MAX_SPEED[vclass] else None)


def build_routes(scene: Scene, plan: NetworkPlan, index_car: LaneIndex, index_bike: LaneIndex,
                 net) -> tuple[list[VehicleRoute], list[dict]]:
    """Routes for every vehicle and cyclist track; the rest listed as unconverted."""
    cache: list = []

    def seg():
        """The built network's lane segments (computed once, when first needed)."""
        if not cache:
            cache.append(lane_segments(net))
        return cache[0]

    tr = scene.tracks
    moved = moved_distance(scene)
    routes: list[VehicleRoute] = []
    unconverted: list[dict] = []
    parked = parked_tracks(scene, moved)  # placed together below (.parking.place_parked)
    is_parked = set(parked.tolist())
    for n in range(tr.num_tracks):
        kind = ObjectType(int(tr.type[n]))
        tid = int(tr.id[n])
        if kind == ObjectType.PEDESTRIAN:
            unconverted.append({"kind": "pedestrian", "id": tid,
                                "reason": "network has no sidewalks or crossings to walk on"})
            continue
        if kind not in (ObjectType.VEHICLE, ObjectType.CYCLIST):
            unconverted.append({"kind": kind.name.lower(), "id": tid,
                                "reason": "object type is not simulated"})
            continue
        steps = np.flatnonzero(tr.valid[n])
        if not len(steps):
            unconverted.append({"kind": kind.name.lower(), "id": tid, "reason": "no valid state"})
            continue
        if n in is_parked:
            continue
        xy = np.stack([tr.x[n, steps], tr.y[n, steps]], axis=1)
        heading = tr.heading[n, steps].astype(np.float64)
        m = match_track(index_bike if kind == ObjectType.CYCLIST else index_car, xy, heading, steps)
        map_pieces = [_piece(plan, int(lane), float(pos)) if lane >= 0 else None
                      for lane, pos in zip(m.lane, m.pos)]
        pieces = list(map_pieces)
        lane_of = m.lane.copy()
        for syn in plan.synthesized:  # off-map stretches drive on their synthesised edges
            if syn.track == n:
                for eid, s0, s1 in syn.edges:
                    on = np.flatnonzero((steps >= s0) & (steps <= s1))
                    lane_of[on] = SYNTHESIZED
                    for k in on.tolist():
                        pieces[k] = (eid, 0, 0.0)
        args = (plan, net, seg, scene, n, kind, steps, xy, heading)
        res = _track_route(*args, lane_of, pieces)
        if isinstance(res, VehicleRoute) and (lane_of == SYNTHESIZED).any():
            # a short synthesised stretch may break a route that the map's lanes carry (the
            # track leaves a junction lane for a moment and comes back): the route without the
            # synthesised lanes is taken where it covers more of the track
            plain = _track_route(*args, m.lane.copy(), map_pieces)
            if isinstance(plain, VehicleRoute) and _route_score(scene, seg(), plain, net) > \
                    _route_score(scene, seg(), res, net):
                res = plain
        if isinstance(res, str):
            unconverted.append({"kind": kind.name.lower(), "id": tid, "reason": res})
        else:
            routes.append(res)
    taken: dict[str, list] = {}  # vehicles stopped on each lane, cars' and cyclists'
    clearance = block_clearance(scene, np.array([r.track for r in routes], np.int64))
    for vclass, cyclist in (("passenger", False), ("bicycle", True)):
        rows = [n for n in parked.tolist() if (tr.type[n] == ObjectType.CYCLIST) == cyclist]
        if rows:
            got, missed = _parked_routes(scene, rows, vclass, net, taken, clearance)
            routes += got
            unconverted += missed
    return routes, unconverted


def _parked_routes(scene: Scene, rows: list[int], vclass: str, net,
                   taken: dict[str, list], clearance: float
                   ) -> tuple[list[VehicleRoute], list[dict]]:
    """Routes of the non-moving tracks ``rows`` of vehicle class ``vclass`` (:mod:`.parking`;
    ``taken``: the lanes' stopped vehicles so far; ``clearance``: m from a centre line within
    which a parked box blocks the lane), and those left out with why."""
    tr = scene.tracks
    poses = [parked_pose(scene, n) for n in rows]
    spots = place_parked(poses, class_lanes(net, vclass), taken, clearance)
    routes, missed = [], []
    for n, pose, spot in zip(rows, poses, spots):
        tid = int(tr.id[n])
        if spot is None:
            missed.append({"kind": ObjectType(int(tr.type[n])).name.lower(), "id": tid,
                           "reason": f"parked off the lane network (no {vclass} lane within "
                                     f"{PARK_SEARCH:g} m)"})
            continue
        edge, index = spot.lane.rsplit("_", 1)
        routes.append(VehicleRoute(
            track=n, id=str(tid), vclass=vclass, length=max(pose.length, 0.5),
            width=max(pose.width, 0.3), edges=[edge], depart_step=0, depart_lane=int(index),
            depart_pos=spot.end_pos, depart_speed=0.0, connected=True, parked=True, spot=spot))
    return routes, missed


def write_routes(path: Path, routes: list[VehicleRoute], dt: float, end_time: float) -> None:
    """Write vTypes (one per track), vehicles sorted by departure (the parked ones first), and
    their stops."""
    routes = sorted(routes, key=lambda r: (r.depart_step, not r.parked, r.id))
    with open(path, "w") as fh:
        fh.write("<routes>\n")
        for r in routes:
            fh.write(f'  <vType id="t{r.id}" vClass="{r.vclass}" length="{r.length:.2f}" '
                     f'width="{r.width:.2f}" minGap="1.0" speedFactor="{r.speed_factor:.2f}"'
                     + ("" if r.max_speed is None else f' maxSpeed="{r.max_speed:.2f}"') + '/>\n')
        for r in routes:
            if r.spot is not None:  # parked (module doc of .parking)
                fh.write(f'  <vehicle id="{r.id}" type="t{r.id}" depart="{r.depart_step * dt:.1f}" '
                         f'departEdge="0" departLane="{r.depart_lane}" departPos="stop" '
                         'insertionChecks="none" '
                         'departSpeed="0.00">\n')
            else:
                fh.write(f'  <vehicle id="{r.id}" type="t{r.id}" depart="{r.depart_step * dt:.1f}" '
                         f'departEdge="{r.depart_edge}" departLane="{r.depart_lane}" departPos="{r.depart_pos:.2f}" insertionChecks="{CHECKS}" '
                         f'departSpeed="{r.depart_speed:.2f}">\n')
            fh.write(f'    <route edges="{" ".join(r.edges)}"/>\n')
            if r.spot is not None and r.spot.blocking:
                fh.write(f'    <stop lane="{r.spot.lane}" startPos="{r.spot.start_pos:.2f}" '
                         f'endPos="{r.spot.end_pos:.2f}" until="{end_time + 1:.1f}" '
                         'parking="false"/>\n')
            elif r.spot is not None:
                fh.write(f'    <stop parkingArea="park_{r.id}" until="{end_time + 1:.1f}" '
                         'parking="true"/>\n')
            fh.write("  </vehicle>\n")
        fh.write("</routes>\n")


def route_covers(scene: Scene, seg: LaneSegments, route: VehicleRoute, net) -> float:
    """Share of the track's valid states on the route's lanes or its internal lanes."""
    tr = scene.tracks
    n = route.track
    steps = np.flatnonzero(tr.valid[n])
    names = set(route.edges)
    for a, b in zip(route.edges[:-1], route.edges[1:]):
        for c in net.getEdge(a).getOutgoing().get(net.getEdge(b), []):
            via = c.getViaLaneID()
            while via:
                names.add(via.rsplit("_", 1)[0])
                lane = net.getLane(via)
                nxt = lane.getOutgoing()
                via = nxt[0].getViaLaneID() if nxt and nxt[0].getViaLaneID() else ""
    mask = np.isin(seg.edge, list(names))
    xy = np.stack([tr.x[n, steps], tr.y[n, steps]], axis=1)
    return float(on_lanes(seg, xy, tr.heading[n, steps].astype(np.float64), mask).mean())
