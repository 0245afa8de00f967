"""Synthesised lanes for recorded driving that the map has no lanes for (lots, driveways).

An *off-map stretch* of a moving vehicle or cyclist (moved > 2 m) is a run of consecutive valid
states, spanning (last step - first step + 1) x 0.1 s >= :data:`MIN_DURATION` s (or two states
or more at the track's first or last valid state) and at least
:data:`MIN_LENGTH` m of path, whose box centres all lie farther than half the lane width + 0.5 m
from every planned lane (edge lanes and junction connection shapes) whose direction is within
45° of the heading -- the on-network test of :mod:`.quality`, applied to the plan. Stretches
less than :data:`MIN_DURATION` s apart are merged. Each stretch becomes one single-lane edge
(two when it leaves and re-enters at the same node) whose shape is the smoothed recorded path in
the scene frame (m); width = median vehicle width + :data:`WIDTH_MARGIN`; speed = the stretch's
95th-percentile recorded speed; bicycle-only for cyclists, otherwise every vehicle class.

Joins use the same map matching as the routes: where the track leaves the map the lane starts at
the end node of the edge of the last matched state when that node is within :data:`SNAP` m of it
(or the track passed a junction lane since, or the state lies within :data:`MIN_SPLIT` +
:data:`SPLIT_SHIFT` m of the end of its edge piece), otherwise at a new node splitting that edge
at the matched position; where it re-enters, likewise at the start node of the next matched edge
or a split. The lane's shape starts (ends) at the end (start) of the lane of the edge it joins, not
at the node's position (the mean of its lane ends, far off the path in a wide junction). Without a
matched state within :data:`MAX_JOIN` - :data:`SNAP` m of the stretch it starts
/ends at a new dead-end node (where the track starts/ends, or at the map border); a lane from
a dead end also carries the junction states before the stretch (back to the last road state)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.scene import ObjectType, Scene
from magail_sumo.scene.types import STEP_LENGTH

from .geometry import length, point_segment, resample, simplify
from .matching import LaneIndex, Match, match_track
from .lanes import LaneSegments, on_lanes
from .routes import PARKED_MOVE, _piece, moved_distance
from .topology import ConnectionPlan, EdgePlan, NetworkPlan

DT = STEP_LENGTH  #: s, WOMD step (10 Hz)
MIN_DURATION = 1.0  #: s, shortest off-map stretch that gets a lane
MIN_LENGTH = PARKED_MOVE  #: m, shortest recorded path of a stretch that gets a lane
SMOOTH = 5  #: states in the moving average of the recorded path
WIDTH_MARGIN = 1.0  #: m added to the median vehicle width
MIN_WIDTH, MIN_WIDTH_BIKE, MAX_WIDTH = 2.5, 1.5, 4.5  #: m, clip of the synthesised lane width
SNAP = 3.0  #: m, a join node this close to the last/first matched state is used (no split)
MIN_SPLIT = 1.0  #: m, shortest edge part left by a split
MAX_JOIN = 25.0  #: m, farthest join from the first/last off-map state
SPLIT_SHIFT = 0.5  #: m, split beyond the matched position so it falls on the right part
MAX_CHANGE_GAP = 2.0  #: s, longest gap between the two matched states of a recorded lane move


@dataclass(frozen=True)
class SynthesizedLane:
    """A lane made from one track's off-map stretch: SUMO edges with the steps they carry."""

    track: int  # index into scene.tracks
    track_id: int
    edges: tuple[tuple[str, int, int], ...]  # (edge id, first step, last step)
    length: float  # m, along the edge shapes
    width: float  # m
    start: str  # "edge <id>" / "node <id>" joined where the track leaves, or "dead end"
    end: str  # likewise where the track re-enters

    def to_dict(self) -> dict:
        return {"track_id": self.track_id, "edges": [e for e, _, _ in self.edges],
                "steps": [self.edges[0][1], self.edges[-1][2]], "length_m": round(self.length, 2),
                "width_m": round(self.width, 2), "start": self.start, "end": self.end}


def carried_states(scene: Scene, lanes: list[SynthesizedLane]) -> np.ndarray:
    """(N, T) bool: the valid states that ``lanes`` were made from."""
    out = np.zeros_like(scene.tracks.valid)
    for syn in lanes:
        for _, s0, s1 in syn.edges:
            out[syn.track, s0:s1 + 1] = True
    return out & scene.tracks.valid


def plan_segments(plan: NetworkPlan) -> LaneSegments:
    """Segments of every planned lane shape (edges, and junction connections with a shape)."""
    widths = {e.id: e.widths for e in plan.edges}
    lanes = [(shape, w, e.id) for e in plan.edges for shape, w in zip(e.shapes, e.widths)]
    lanes += [(c.shape, widths[c.from_edge][c.from_lane], ":" + c.from_edge)
              for c in plan.connections if c.shape is not None]
    return LaneSegments.from_shapes(lanes)


def off_map_stretches(off: np.ndarray, steps: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) indices into the valid states of off-map runs lasting >= MIN_DURATION s
    or of two or more states at the track's start or end (no route around them covers those),
    merged when less than MIN_DURATION s of on-map states separate them."""
    idx = np.flatnonzero(off)
    if not len(idx):
        return []
    cut = np.flatnonzero(np.diff(idx) > 1)
    runs = [(int(s), int(e)) for s, e in zip(np.r_[idx[0], idx[cut + 1]], np.r_[idx[cut], idx[-1]])
            if (steps[e] - steps[s] + 1) * DT >= MIN_DURATION - 1e-9
            or (e > s and (s == 0 or e == len(off) - 1))]
    merged: list[tuple[int, int]] = []
    for s, e in runs:
        if merged and (steps[s] - steps[merged[-1][1]] - 1) * DT < MIN_DURATION:
            merged[-1] = (merged[-1][0], e)
        else:
            merged.append((s, e))
    return merged


def _smooth(points: np.ndarray) -> np.ndarray:
    """Moving average over :data:`SMOOTH` states of a (M, k) path (ends padded)."""
    if len(points) < 3:
        return points
    w = min(SMOOTH, len(points) | 1)
    pad = np.concatenate([np.repeat(points[:1], w // 2, 0), points,
                          np.repeat(points[-1:], w // 2, 0)])
    kernel = np.ones(w) / w
    return np.stack([np.convolve(pad[:, k], kernel, "valid") for k in range(points.shape[1])], 1)


def _cut(shape: np.ndarray, pt: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Split a (P, 3) polyline at the projection of ``pt`` (2,): (head, tail, arc of the cut in m)."""
    d, t = point_segment(pt[None, :2], shape[:-1, :2], shape[1:, :2])
    k = int(np.argmin(d[0]))
    q = shape[k] + t[0, k] * (shape[k + 1] - shape[k])
    head = np.vstack([shape[:k + 1], q])
    tail = np.vstack([q, shape[k + 1:]])
    head = head[np.r_[True, np.linalg.norm(np.diff(head[:, :2], axis=0), axis=1) > 1e-6]]
    tail = tail[np.r_[np.linalg.norm(np.diff(tail[:, :2], axis=0), axis=1) > 1e-6, True]]
    return head, tail, length(head)


def split_edge(plan: NetworkPlan, eid: str, lane: int, pos: float, tag: str) -> tuple[str, str]:
    """Cut edge ``eid`` at ``pos`` m (WOMD arc from the piece start) along its lane ``lane``.

    The first part keeps ``eid``; the second is ``<eid>s<tag>`` and takes over the outgoing
    connections. Returns (new node id, second part id); ``plan.lane_edges`` is updated.
    """
    k = next(i for i, e in enumerate(plan.edges) if e.id == eid)
    e = plan.edges[k]
    piece = {idx: (s0, s1) for entries in plan.lane_edges.values()
             for edge, idx, s0, s1 in entries if edge == eid}
    s0, s1 = piece[lane]
    ref = e.shapes[lane]
    scale = length(ref) / max(s1 - s0, 1e-9)  # WOMD arc -> simplified-shape arc
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref[:, :2], axis=0), axis=1))])
    at = float(np.clip(pos * scale, MIN_SPLIT, s[-1] - MIN_SPLIT))
    pt = np.array([np.interp(at, s, ref[:, 0]), np.interp(at, s, ref[:, 1])])
    node, second = f"s{tag}", f"{eid}s{tag}"
    plan.nodes[node] = pt
    plan.split_nodes.add(node)
    heads, tails, cut_arc = [], [], {}
    for j, shape in enumerate(e.shapes):
        h, t, a = _cut(shape, pt)
        heads.append(h)
        tails.append(t)
        a0, a1 = piece[j]
        cut_arc[j] = a0 + a * (a1 - a0) / max(length(shape), 1e-9)
    plan.edges.insert(k + 1, EdgePlan(second, node, e.to_node, list(e.lanes), tails,
                                      list(e.widths), e.speed, e.bike_only))
    e.to_node, e.shapes = node, heads
    for c in plan.connections:
        if c.from_edge == eid:
            c.from_edge = second
    plan.connections.extend(ConnectionPlan(eid, j, second, j, (), None)
                            for j in range(len(e.lanes)))
    for womd, entries in plan.lane_edges.items():
        out = []
        for edge, idx, a0, a1 in entries:
            if edge == eid:
                out += [(eid, idx, a0, cut_arc[idx]), (second, idx, cut_arc[idx], a1)]
            else:
                out.append((edge, idx, a0, a1))
        plan.lane_edges[womd] = out
    return node, second


def _between_joins(path: np.ndarray, fwd: np.ndarray, a_pt: np.ndarray | None,
                   b_pt: np.ndarray | None) -> np.ndarray:
    """``path`` (M, 3) without the recorded points behind or within 1 m of the join point
    ``a_pt`` (2,) it starts from, nor those beyond or within 1 m of ``b_pt`` it ends at (None:
    no join); ``fwd`` (M, 2) are the unit headings. At least one point stays."""
    if a_pt is not None:
        rel = path[:, :2] - a_pt
        keep = ((rel * fwd).sum(1) > 0) & (np.linalg.norm(rel, axis=1) > 1.0)
        path = path[np.argmax(keep):] if keep.any() else path[-1:]
    if b_pt is not None:
        rel = b_pt - path[:, :2]
        keep = ((rel * fwd[-len(path):]).sum(1) > 0) & (np.linalg.norm(rel, axis=1) > 1.0)
        path = path[:len(keep) - np.argmax(keep[::-1])] if keep.any() else path[:1]
    return path


def _edge(plan: NetworkPlan, eid: str) -> EdgePlan:
    return next(e for e in plan.edges if e.id == eid)


def _side(plan: NetworkPlan, lane: int, pos: float, leaving: bool) -> tuple[str, int] | None:
    """(edge, lane index) a track is on when it leaves (enters) WOMD lane ``lane`` at arc
    ``pos`` m: the road piece there, or for a junction lane the edge its connection comes from
    (goes to); None when the lane has neither."""
    piece = _piece(plan, lane, pos)
    if piece is not None:
        return piece[0], piece[1]
    c = next((c for c in plan.connections if lane in c.via), None)
    if c is None:
        return None
    return (c.from_edge, c.from_lane) if leaving else (c.to_edge, c.to_lane)


def track_matches(scene: Scene, tracks: np.ndarray, index_car: LaneIndex,
                  index_bike: LaneIndex) -> dict[int, Match]:
    """Map matches of tracks ``tracks`` (valid states; cyclists on ``index_bike``)."""
    tr = scene.tracks
    out = {}
    for n in tracks.tolist():
        steps = np.flatnonzero(tr.valid[n])
        xy = np.stack([tr.x[n, steps], tr.y[n, steps]], axis=1)
        index = index_bike if int(tr.type[n]) == ObjectType.CYCLIST else index_car
        out[n] = match_track(index, xy, tr.heading[n, steps].astype(np.float64), steps)
    return out


def connect_recorded_changes(scene: Scene, plan: NetworkPlan, matches: dict[int, Match]
                             ) -> list[ConnectionPlan]:
    """Add a connection for every recorded move between two edges that meet at one node and
    have none: a lane change inside a junction (onto the junction lane beside the one its lane
    leads into, or from a junction lane onto a road lane it does not lead into) leaves the
    track's matched edges unconnected, so no route could carry it. A move is two consecutive
    matched states (at most :data:`MAX_CHANGE_GAP` s apart) on different WOMD lanes; the
    connection goes from the edge of the first (for a junction lane: the edge its connection
    comes from) to the edge of the second (or where its connection goes), lane to lane, through
    the junction lanes among the two (for the traffic-light states), shaped along the recorded
    states between the two edges. ``matches``: the map match of each moving track (valid states).
    Returns the connections added (also in ``plan.connections``)."""
    tr = scene.tracks
    edges = {e.id: e for e in plan.edges}
    have = {(c.from_edge, c.to_edge) for c in plan.connections}
    added: list[ConnectionPlan] = []
    for n, m in matches.items():
        steps = m.steps
        xy = np.stack([tr.x[n, steps], tr.y[n, steps]], axis=1)
        heading = tr.heading[n, steps].astype(np.float64)
        k = np.flatnonzero(m.lane >= 0)
        moves = np.flatnonzero((m.lane[k[1:]] != m.lane[k[:-1]])
                               & (steps[k[1:]] - steps[k[:-1]] <= MAX_CHANGE_GAP / DT))
        for j in moves.tolist():
            a, b = k[j], k[j + 1]
            la, lb = int(m.lane[a]), int(m.lane[b])
            x = _side(plan, la, float(m.pos[a]), True)
            y = _side(plan, lb, float(m.pos[b]), False)
            if x is None or y is None or x[0] == y[0] or (x[0], y[0]) in have \
                    or edges[x[0]].to_node != edges[y[0]].from_node:
                continue
            via = tuple(v for v in (la, lb) if v in plan.junction_lanes)
            # the shape follows the recorded states between the two road pieces
            road = [q for q in k.tolist() if _piece(plan, int(m.lane[q]), float(m.pos[q]))]
            r0 = max((q for q in road if q <= a), default=int(k[0]) - 1)
            r1 = min((q for q in road if q >= b), default=int(k[-1]) + 1)
            a_pt = edges[x[0]].shapes[x[1]][-1]
            b_pt = edges[y[0]].shapes[y[1]][0]
            inner = np.arange(r0 + 1, r1)
            shape = np.vstack([a_pt, b_pt])
            if len(inner):
                path = np.column_stack([_smooth(xy[inner]), tr.z[n, steps[inner]]])
                fwd = np.stack([np.cos(heading[inner]), np.sin(heading[inner])], axis=1)
                shape = np.vstack([a_pt, _between_joins(path, fwd, a_pt[:2], b_pt[:2]), b_pt])
            added.append(ConnectionPlan(x[0], x[1], y[0], y[1], via, shape))
            have.add((x[0], y[0]))
    plan.connections.extend(added)
    return added


def synthesize_lanes(scene: Scene, plan: NetworkPlan, index_car: LaneIndex,
                     index_bike: LaneIndex) -> list[SynthesizedLane]:
    """Add a lane to ``plan`` for every off-map stretch; returns them (also ``plan.synthesized``).

    The off-map test and the joins use the same map matching as the routes, so each route
    reaches its synthesised lane from the edge it was matched to.
    """
    tr = scene.tracks
    moved = moved_distance(scene)
    kinds = np.isin(tr.type, [ObjectType.VEHICLE, ObjectType.CYCLIST]) & (moved > PARKED_MOVE)
    if not kinds.any() or not plan.edges:
        return []
    matches = track_matches(scene, np.flatnonzero(kinds), index_car, index_bike)
    connect_recorded_changes(scene, plan, matches)
    seg = plan_segments(plan)
    out: list[SynthesizedLane] = []
    for n in np.flatnonzero(kinds).tolist():
        steps = np.flatnonzero(tr.valid[n])
        xy = np.stack([tr.x[n, steps], tr.y[n, steps]], axis=1)
        heading = tr.heading[n, steps].astype(np.float64)
        stretches = off_map_stretches(~on_lanes(seg, xy, heading), steps)
        stretches = [(s, e) for s, e in stretches if length(xy[s:e + 1]) >= MIN_LENGTH]
        if not stretches:
            continue
        bike = int(tr.type[n]) == ObjectType.CYCLIST
        m = matches[n]
        z = tr.z[n, steps]
        width = float(np.clip(np.median(tr.width[n, steps]) + WIDTH_MARGIN,
                              MIN_WIDTH_BIKE if bike else MIN_WIDTH, MAX_WIDTH))
        speeds = np.hypot(tr.vx[n, steps], tr.vy[n, steps])
        for k, (s, e) in enumerate(stretches):
            out.append(_synthesize(plan, n, int(tr.id[n]), steps, xy, z, heading, m, s, e, width,
                                   max(float(np.quantile(speeds[s:e + 1], 0.95)), 1.0), bike,
                                   str(len(plan.synthesized)),
                                   stretches[k - 1][1] + 1 if k else 0))
            plan.synthesized.append(out[-1])
    return out


def _synthesize(plan: NetworkPlan, n: int, tid: int, steps: np.ndarray, xy: np.ndarray,
                z: np.ndarray, heading: np.ndarray, m: Match, s: int, e: int, width: float,
                speed: float, bike: bool, tag: str, free: int) -> SynthesizedLane:
    """One synthesised lane for states ``s..e`` of track ``n`` (joins, shape, plan entries).

    A lane from a dead end also carries the states before the stretch back to the nearest state
    on a road lane: they lie on junction lanes (or match no lane), and a route starting on the
    new lane would leave them out -- a track that begins in a junction and cuts across its
    turn. It reaches back no further than state ``free`` (the first after the track's previous
    stretch). A lane to a dead end is not carried on alike: the route through the junction
    lanes after it covers those states, and a lane drawn through a wide junction to the track's
    end lies inside netconvert's junction shape, which cuts it away."""
    pieces = [_piece(plan, int(lane), float(pos)) if lane >= 0 else None
              for lane, pos in zip(m.lane, m.pos)]
    junction = np.isin(m.lane, list(plan.junction_lanes))

    def join(k: int, between: slice, leaving: bool):
        """(node, (edge, lane) to connect, description) for the matched state ``k``."""
        edge, idx, p = _piece(plan, int(m.lane[k]), float(m.pos[k]))  # fresh: splits move pieces
        ep = _edge(plan, edge)
        node = ep.to_node if leaving else ep.from_node
        s0, s1 = next((a0, a1) for e_, i_, a0, a1 in plan.lane_edges[int(m.lane[k])]
                      if e_ == edge and i_ == idx)
        # a split this near the piece's end (start) would fall short of (beyond) the matched
        # state, leaving it on the wrong part: the piece's end (start) node is the join
        at_end = p + SPLIT_SHIFT > s1 - s0 - MIN_SPLIT if leaving else p - SPLIT_SHIFT < MIN_SPLIT
        if junction[between].any() or at_end or np.hypot(*(plan.nodes[node] - xy[k])) < SNAP:
            return node, (edge, idx), f"node {node}"
        if leaving:
            node, _ = split_edge(plan, edge, idx, p + SPLIT_SHIFT, f"{tag}a")
            return node, (edge, idx), f"edge {edge} (split)"
        node, second = split_edge(plan, edge, idx, p - SPLIT_SHIFT, f"{tag}b")
        return node, (second, idx), f"edge {edge} (split)"

    before = next((k for k in range(s - 1, -1, -1) if pieces[k] is not None), None)
    after = next((k for k in range(e + 1, len(pieces)) if pieces[k] is not None), None)
    # a lane from a dead end reaches back over the junction states to the nearest road state
    s_dead = max(before + 1 if before is not None else 0, free)
    near = MAX_JOIN - SNAP  # the join node lies within SNAP of the matched state or on its lane
    if before is not None and np.hypot(*(xy[before] - xy[s])) > near:
        before = None
    if after is not None and np.hypot(*(xy[after] - xy[e])) > near:
        after = None
    start = join(before, slice(before + 1, s), True) if before is not None else None
    end = join(after, slice(e + 1, after), False) if after is not None else None
    if start is None:
        s = s_dead
    path = np.column_stack([_smooth(xy[s:e + 1]), z[s:e + 1]])
    h = heading[s:e + 1]
    fwd = np.stack([np.cos(h), np.sin(h)], axis=1)
    # the lane starts (ends) where the lane it joins ends (starts): a node's position is the
    # mean of its lane ends, which in a wide junction lies far off the recorded path
    a_pt = _edge(plan, start[1][0]).shapes[start[1][1]][-1, :2] if start else None
    b_pt = _edge(plan, end[1][0]).shapes[end[1][1]][0, :2] if end else None
    path = _between_joins(path, fwd, a_pt, b_pt)
    a_node = start[0] if start else f"d{tag}a"
    b_node = end[0] if end else f"d{tag}b"
    if start is None:
        plan.nodes[a_node] = path[0, :2]
    if end is None:
        plan.nodes[b_node] = path[-1, :2]
    head = [np.array([[*a_pt, path[0, 2]]])] if start else []
    tail = [np.array([[*b_pt, path[-1, 2]]])] if end else []
    shape = np.vstack(head + [path] + tail)
    shape = simplify(shape, 1.0)
    if len(shape) < 3:
        shape = resample(shape, 3)
    eids: list[tuple[str, int, int]] = []
    if a_node == b_node:  # leaves and re-enters at one node: two edges through a middle node
        mid_k = len(shape) // 2
        mid = f"d{tag}m"
        plan.nodes[mid] = shape[mid_k, :2]
        parts = [(f"syn{tag}a", a_node, mid, shape[:mid_k + 1]),
                 (f"syn{tag}b", mid, b_node, shape[mid_k:])]
        d_mid = np.linalg.norm(xy[s:e + 1] - shape[mid_k, :2], axis=1)
        k_mid = s + int(np.argmin(d_mid))
        spans = [(int(steps[s]), int(steps[k_mid])), (int(steps[k_mid]) + 1, int(steps[e]))]
    else:
        parts = [(f"syn{tag}", a_node, b_node, shape)]
        spans = [(int(steps[s]), int(steps[e]))]
    for (eid, fa, fb, sh), (s0, s1) in zip(parts, spans):
        plan.edges.append(EdgePlan(eid, fa, fb, [-1], [sh], [width], speed, bike,
                                   synthesized_for=tid))
        eids.append((eid, s0, s1))
    for (eid, _, _), nxt in zip(eids[:-1], eids[1:]):
        plan.connections.append(ConnectionPlan(eid, 0, nxt[0], 0, (), None))
    if start is not None:
        plan.connections.append(ConnectionPlan(start[1][0], start[1][1], eids[0][0], 0, (), None))
    if end is not None:
        plan.connections.append(ConnectionPlan(eids[-1][0], 0, end[1][0], end[1][1], (), None))
    return SynthesizedLane(n, tid, tuple(eids), length(shape), width,
                           start[2] if start else "dead end", end[2] if end else "dead end")

