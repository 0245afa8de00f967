"""Plan a SUMO network from WOMD lanes: junction lanes, nodes, multi-lane edges, connections.

In-junction lanes (interpolating, signalled, or crossing another lane at > 20°) that lie on a
path between two road lanes become connections with their own shapes; every other lane is
part of an edge. Road lanes that share start and end nodes and are neighbours form one
multi-lane edge (lane 0 = rightmost). Coordinates stay in the scene frame (m).

Junctions stay the size of one real junction: a junction path spanning more than
:data:`MAX_JUNCTION_SPAN` m has its longest unsignalled lane made a road lane, a stub shorter than
:data:`MIN_PIECE` inside a junction joins it, a neighbour relation joins nodes only where its
ends lie within :data:`MAX_NEIGHBOUR_GAP` m, and a cut of a lane is carried to the lanes beside
it (so their pieces form one edge) unless that would put two cuts of one lane into one node.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magail_sumo.scene import Lane, LaneType, Scene, link_isolated_lanes

from .geometry import angle_diff, length, resample, segments, segments_cross, simplify

#: Default speeds (m/s) by lane type where the log has none.
DEFAULT_SPEED = {LaneType.UNDEFINED: 13.89, LaneType.FREEWAY: 29.06,
                 LaneType.SURFACE_STREET: 13.89, LaneType.BIKE_LANE: 5.56}
DEFAULT_WIDTH = 3.6  #: m, road lanes without a measurable neighbour distance
BIKE_WIDTH = 1.8  #: m
CROSS_ANGLE = np.radians(20.0)
MAX_VIA = 4  #: longest chain of junction lanes folded into one connection
MIN_PIECE = 4.0  #: m, shortest edge piece cut out of a lane at a neighbour boundary
#: m, farthest a junction path may carry a vehicle in a straight line (road lane end to road lane
#: start); the longest turning lanes of the recorded junctions span about 65 m. A longer path is
#: a road lane taken for a junction lane (e.g. a long lane that a lane-change lane crosses): its
#: longest unsignalled junction lane becomes a road lane, so that the junction is not chained to
#: a far one into one giant SUMO junction (routes cannot follow its internal lanes).
MAX_JUNCTION_SPAN = 70.0
#: m, farthest apart the two ends of a neighbour relation (snapped to kept cuts) that are made
#: one node; farther ones come from a neighbour relation that does not match the geometry
#: (e.g. inferred for a short lane along the whole of a long one) and would chain nodes
MAX_NEIGHBOUR_GAP = 15.0
#: m, a recorded successor link whose lanes' end and start lie farther apart is dropped
MAX_LINK_GAP = 5.0
#: search steps (lanes looked at) of the exhaustive junction path search from one road lane
#: before it falls back to shortest paths (the bundled recorded scenes need under 50)
MAX_PATH_EXPANSIONS = 20_000


class TimeBudgetExceeded(RuntimeError):
    """A conversion ran past its time budget (see ``ConvertOptions.time_budget_s``)."""


@dataclass
class EdgePlan:
    """One SUMO edge: WOMD lanes right (index 0) to left, each with its shape (P, 3)."""

    id: str
    from_node: str
    to_node: str
    lanes: list[int]
    shapes: list[np.ndarray]
    widths: list[float]
    speed: float
    bike_only: bool
    synthesized_for: int | None = None  # track id whose off-map path this edge was made from


@dataclass
class ConnectionPlan:
    """A SUMO connection from (edge, lane) to (edge, lane) through WOMD junction lanes ``via``."""

    from_edge: str
    from_lane: int
    to_edge: str
    to_lane: int
    via: tuple[int, ...]
    shape: np.ndarray | None  # (P, 3) in-junction shape, None for a plain lane continuation


@dataclass
class NetworkPlan:
    """All that the plain-XML writer needs, plus the WOMD lane -> SUMO element maps."""

    nodes: dict[str, np.ndarray]  # node id -> (x, y)
    edges: list[EdgePlan]
    connections: list[ConnectionPlan]
    lane_edges: dict[int, list[tuple[str, int, float, float]]]  # road lane -> [(edge, index, s0, s1)]
    junction_lanes: set[int]
    node_of_lane: dict[int, str]  # lane -> the node it ends in (road) or crosses (junction)
    unconverted: list[dict] = field(default_factory=list)
    synthesized: list = field(default_factory=list)  # synthesis.SynthesizedLane, added later
    split_nodes: set[str] = field(default_factory=set)  # nodes cutting an edge for a synthesised lane
    #: lanes recorded without any entry or exit lane, joined by geometry to the lanes their ends
    #: meet (:func:`magail_sumo.scene.link_isolated_lanes`): lane -> (entries, exits) added
    linked: dict[int, tuple[tuple[int, ...], tuple[int, ...]]] = field(default_factory=dict)


class _UnionFind:
    def __init__(self) -> None:
        self.parent: dict = {}

    def find(self, k):
        self.parent.setdefault(k, k)
        while self.parent[k] != k:
            self.parent[k] = self.parent[self.parent[k]]
            k = self.parent[k]
        return k

    def union(self, a, b) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[rb] = ra


def _crossing_lanes(lanes: dict[int, Lane]) -> set[int]:
    """Lanes that properly cross another lane at more than :data:`CROSS_ANGLE`."""
    ids = list(lanes)
    a, b, owner = segments([simplify(lanes[i].polyline, 2.0) for i in ids])
    d = b - a
    ang = np.arctan2(d[:, 1], d[:, 0])
    lo = np.minimum(a, b)
    hi = np.maximum(a, b)
    n = len(ids)
    blo = np.full((n, 2), np.inf)
    bhi = np.full((n, 2), -np.inf)
    np.minimum.at(blo, owner, lo)
    np.maximum.at(bhi, owner, hi)
    overlap = np.all((blo[:, None] <= bhi[None]) & (blo[None] <= bhi[:, None]), axis=2)
    out: set[int] = set()
    for k in range(n):
        others = np.flatnonzero(overlap[k])
        others = others[others > k]
        if not len(others):
            continue
        mine = owner == k
        theirs = np.isin(owner, others)
        hit = segments_cross(a[mine], b[mine], a[theirs], b[theirs])
        i, j = np.nonzero(hit)
        keep = angle_diff(ang[mine][i], ang[theirs][j]) > CROSS_ANGLE
        if keep.any():
            out.add(ids[k])
            out.update(ids[m] for m in np.unique(owner[theirs][j[keep]]))
    return out


def _lane_width(lane: Lane, lanes: dict[int, Lane]) -> float:
    """Width (m) from the distance to a same-direction neighbour at mid-lane, else a default."""
    if lane.type == LaneType.BIKE_LANE:
        return BIKE_WIDTH
    p = lane.polyline[len(lane.polyline) // 2, :2]
    dists = []
    for nb in lane.left_neighbors + lane.right_neighbors:
        other = lanes.get(nb.feature_id)
        if other is not None:
            dists.append(np.min(np.linalg.norm(other.polyline[:, :2] - p, axis=1)))
    return float(np.clip(min(dists), 2.8, 4.5)) if dists else DEFAULT_WIDTH


def _shortest_paths(start: int, exits: dict[int, list[int]], junction: set[int]
                    ) -> tuple[list[tuple[int, tuple[int, ...]]], set[int]]:
    """Junction paths from road lane ``start`` at bounded cost: one shortest path (at most
    :data:`MAX_VIA` junction lanes) to every road lane reached, and the junction lanes that lie
    on some walk of at most :data:`MAX_VIA` junction lanes from ``start`` to a road lane
    (forward and backward breadth-first distances; each lane expanded once, so the cost is
    linear in the junction's connections)."""
    fwd: dict[int, tuple[int, ...]] = {}  # junction lane -> shortest via from start to it
    frontier: list[int] = []
    for e in exits[start]:
        if e in junction and e not in fwd:
            fwd[e] = (e,)
            frontier.append(e)
    out: list[tuple[int, tuple[int, ...]]] = []
    reached: set[int] = set()
    while frontier:
        nxt_frontier = []
        for lane in frontier:
            via = fwd[lane]
            for nxt in exits[lane]:
                if nxt not in junction:
                    if nxt not in reached:
                        reached.add(nxt)
                        out.append((nxt, via))
                elif nxt not in fwd and len(via) < MAX_VIA:
                    fwd[nxt] = via + (nxt,)
                    nxt_frontier.append(nxt)
        frontier = nxt_frontier
    # junction lanes left to a road lane within k junction lanes (itself included)
    to_road = {j: 1 for j in fwd if any(x not in junction for x in exits[j])}
    level = list(to_road)
    entries: dict[int, list[int]] = {}
    for j in fwd:
        for x in exits[j]:
            if x in fwd:
                entries.setdefault(x, []).append(j)
    while level:
        nxt_level = []
        for j in level:
            for p in entries.get(j, ()):
                if p not in to_road and to_road[j] < MAX_VIA:
                    to_road[p] = to_road[j] + 1
                    nxt_level.append(p)
        level = nxt_level
    on_path = {j for j, via in fwd.items() if j in to_road and len(via) + to_road[j] - 1 <= MAX_VIA}
    return out, on_path


def plan_network(scene: Scene, deadline: float | None = None) -> NetworkPlan:
    """Turn the scene's lanes into nodes, edges and connections (no lane silently dropped).

    Junction paths are enumerated exhaustively (depth first, :data:`MAX_VIA` junction lanes at
    most); from a road lane whose enumeration takes more than :data:`MAX_PATH_EXPANSIONS` steps
    (a densely interconnected junction, never met in the recorded scenes) only one shortest
    path per reached road lane is kept (see :func:`_shortest_paths`), and the lane is listed in
    ``unconverted``: planning costs at most that many steps per road lane and round.

    :param deadline: ``time.monotonic()`` value after which planning stops with
        :class:`TimeBudgetExceeded` (None: no limit).
    """
    import time

    def check_deadline() -> None:
        if deadline is not None and time.monotonic() > deadline:
            raise TimeBudgetExceeded("time budget exceeded")

    unconverted: list[dict] = []
    lanes: dict[int, Lane] = {}
    for lane in scene.roadmap.lanes:
        if len(lane.polyline) < 2 or length(lane.polyline) < 0.1:
            unconverted.append({"kind": "lane", "id": int(lane.id), "reason": "degenerate polyline"})
        else:
            lanes[lane.id] = lane
    # links lost in the data (signalled junction lanes of MetaDrive and MetaVQA pickles, of WOMD
    # scenes re-encoded from them): lanes without any are joined where their ends meet others'
    linked = {}
    for new in link_isolated_lanes(list(lanes.values()))[0]:
        old = lanes[new.id]
        if new is not old:
            linked[new.id] = (tuple(i for i in new.entry_lanes if i not in old.entry_lanes),
                              tuple(i for i in new.exit_lanes if i not in old.exit_lanes))
            lanes[new.id] = new
    # a recorded link between lanes whose end and start lie apart is a data error: joining
    # them would pull a junction node between the two (a wedge-shaped junction polygon)
    far = {(i, e) for i, l in lanes.items() for e in l.exit_lanes if e in lanes and e != i
           and _gap(l, lanes[e]) > MAX_LINK_GAP}
    far |= {(e, i) for i, l in lanes.items() for e in l.entry_lanes if e in lanes and e != i
            and _gap(lanes[e], l) > MAX_LINK_GAP}
    unconverted.extend({"kind": "lane link", "id": int(a),
                        "reason": f"exit lane {b} starts {_gap(lanes[a], lanes[b]):.0f} m from "
                                  "its end: link dropped"} for a, b in sorted(far))
    exits = {i: [e for e in l.exit_lanes if e in lanes and e != i and (i, e) not in far]
             for i, l in lanes.items()}
    entries = {i: [e for e in l.entry_lanes if e in lanes and e != i and (e, i) not in far]
               for i, l in lanes.items()}
    for i in lanes:  # make the relation symmetric
        for e in exits[i]:
            if i not in entries[e]:
                entries[e].append(i)
        for e in entries[i]:
            if i not in exits[e]:
                exits[e].append(i)
    signalled = set(scene.signals.lanes.tolist()) & set(lanes)
    junction = {i for i, l in lanes.items() if l.interpolating} | signalled | _crossing_lanes(lanes)
    junction = {i for i in junction if entries[i] and exits[i]}

    dense: set[int] = set()  # road lanes whose junction paths are cut to the shortest ones

    def paths_from(start: int) -> list[tuple[int, tuple[int, ...]]]:
        """(road lane reached, junction lanes passed) for every junction path leaving ``start``
        (depth first); beyond :data:`MAX_PATH_EXPANSIONS` steps, see :func:`_shortest_paths`."""
        return search(start)[0]

    def search(start: int) -> tuple[list[tuple[int, tuple[int, ...]]], set[int]]:
        """:func:`paths_from` and the junction lanes on those paths."""
        check_deadline()
        if start in dense:  # found dense in an earlier round: the junction only shrinks since
            return _shortest_paths(start, exits, junction)
        out, stack = [], [(e, (e,)) for e in exits[start] if e in junction]
        budget = MAX_PATH_EXPANSIONS
        while stack:
            lane, via = stack.pop()
            budget -= len(exits[lane]) + 1
            if budget < 0:
                dense.add(start)
                return _shortest_paths(start, exits, junction)
            for nxt in exits[lane]:
                if nxt not in junction:
                    out.append((nxt, via))
                elif nxt not in via and len(via) < MAX_VIA:
                    stack.append((nxt, via + (nxt,)))
        return out, {v for _, via in out for v in via}

    stubs: set[int] = set()  # short road lanes taken into a junction (see below)
    while True:
        # junction lanes on no road-to-road path become road lanes, until stable
        while True:
            used: set[int] = set()
            for i in lanes:
                if i not in junction:
                    used |= search(i)[1]
            if used == junction:
                break
            junction = used
        road = [i for i in lanes if i not in junction]
        jpaths = {i: sorted(paths_from(i), key=lambda p: len(p[1])) for i in road}
        demote = _overlong_junction_lanes(lanes, jpaths, signalled) - stubs
        if demote:
            junction -= demote
            continue
        arc = {i: _arc(lanes[i].polyline) for i in road}
        cuts, snap, pairs = _breakpoints(lanes, road, junction, arc)
        uf = _UnionFind()
        for i in road:
            last = len(lanes[i].polyline) - 1
            for c in cuts[i]:
                uf.find((i, c))
            for e in exits[i]:
                if e not in junction:
                    uf.union((i, last), (e, 0))
            for target, _ in jpaths[i]:
                uf.union((i, last), (target, 0))
            for nb in lanes[i].left_neighbors + lanes[i].right_neighbors:
                j = nb.feature_id
                if j in arc:
                    for a, b in ((nb.self_start_index, nb.neighbor_start_index),
                                 (nb.self_end_index, nb.neighbor_end_index)):
                        a, b = snap(i, a), snap(j, b)
                        if np.hypot(*(lanes[i].polyline[a, :2] - lanes[j].polyline[b, :2])) \
                                <= MAX_NEIGHBOUR_GAP:
                            uf.union((i, a), (j, b))
        # a carried cut joins its source's node unless that node then holds two cuts of one
        # lane (the piece between them would leave the node and re-enter it)
        cut_lanes: dict = {}
        for i in road:
            for c in cuts[i]:
                cut_lanes.setdefault(uf.find((i, c)), []).append(i)
        for (i, a), (j, b) in pairs:
            ra, rb = uf.find((i, snap(i, a))), uf.find((j, snap(j, b)))
            if ra != rb and not set(cut_lanes[ra]) & set(cut_lanes[rb]):
                uf.union(ra, rb)
                cut_lanes[uf.find(ra)] = cut_lanes.pop(ra, []) + cut_lanes.pop(rb, [])
        # a stub shorter than MIN_PIECE next to junction lanes whose two ends fall into one node
        # is part of that junction (as a road edge it would leave the junction and re-enter it)
        new_stubs = {i for i in road if arc[i][-1] < MIN_PIECE and entries[i] and exits[i]
                     and any(e in junction for e in entries[i] + exits[i])
                     and uf.find((i, 0)) == uf.find((i, len(arc[i]) - 1))}
        if not new_stubs:
            break
        stubs |= new_stubs
        junction |= new_stubs
    members: dict = {}
    for i in road:
        for c in cuts[i]:
            members.setdefault(uf.find((i, c)), []).append(lanes[i].polyline[c, :2])
    node_name = {root: f"n{n}" for n, root in enumerate(members)}
    nodes = {node_name[r]: np.mean(pts, axis=0) for r, pts in members.items()}

    def node(i: int, c: int) -> str:
        return node_name[uf.find((i, c))]

    # pieces between consecutive cut points; split a piece that starts and ends in one node
    pieces: list[tuple[int, int, int, str, str]] = []  # lane, i0, i1, from, to
    for i in road:
        cs = cuts[i]
        for i0, i1 in zip(cs[:-1], cs[1:]):
            a, b = node(i, i0), node(i, i1)
            if a != b:
                pieces.append((i, i0, i1, a, b))
            else:
                h = (i0 + i1) // 2 if i1 - i0 >= 2 else i0
                mid = f"m{i}_{i0}"
                nodes[mid] = lanes[i].polyline[h, :2] if h != i0 else \
                    lanes[i].polyline[i0:i1 + 1, :2].mean(axis=0)
                pieces.append((i, i0, h, a, mid) if h != i0 else (i, i0, i1, a, mid))
                if h != i0:
                    pieces.append((i, h, i1, mid, b))
    # group neighbouring pieces with equal end nodes into multi-lane edges
    nbrs = {i: {nb.feature_id for nb in lanes[i].left_neighbors + lanes[i].right_neighbors}
            for i in road}
    by_nodes: dict[tuple[str, str], list[int]] = {}
    for k, (i, _, _, a, b) in enumerate(pieces):
        by_nodes.setdefault((a, b), []).append(k)
    guf = _UnionFind()
    for ks in by_nodes.values():
        for k in ks:
            guf.find(k)
            for m in ks:
                li, lm = pieces[k][0], pieces[m][0]
                if m > k and lm in nbrs[li] and \
                        (lanes[li].type == LaneType.BIKE_LANE) == (lanes[lm].type == LaneType.BIKE_LANE):
                    guf.union(k, m)
    groups: dict[int, list[int]] = {}
    for k in range(len(pieces)):
        groups.setdefault(guf.find(k), []).append(k)

    edges: list[EdgePlan] = []
    piece_edge: dict[int, tuple[str, int]] = {}
    for ks in groups.values():
        shapes_full = {k: lanes[pieces[k][0]].polyline[pieces[k][1]:pieces[k][2] + 1] for k in ks}
        ref = shapes_full[ks[0]][:, :2]
        r = resample(ref, 3)
        tangent = (r[2] - r[0]) / max(float(np.linalg.norm(r[2] - r[0])), 1e-9)

        def lateral(k: int) -> float:
            p = resample(shapes_full[k][:, :2], 3)[1] - r[1]
            return float(tangent[0] * p[1] - tangent[1] * p[0])  # left positive
        ks.sort(key=lateral)
        ids_ = [pieces[k][0] for k in ks]
        speeds = [lanes[i].speed_limit for i in ids_ if lanes[i].speed_limit > 0]
        speed = max(speeds) if speeds else DEFAULT_SPEED[LaneType(lanes[ids_[0]].type)]
        bike = all(lanes[i].type == LaneType.BIKE_LANE for i in ids_)
        eid = f"e{ids_[0]}" + (f"p{pieces[ks[0]][1]}" if pieces[ks[0]][1] or
                               pieces[ks[0]][2] != len(lanes[ids_[0]].polyline) - 1 else "")
        edges.append(EdgePlan(eid, pieces[ks[0]][3], pieces[ks[0]][4], ids_,
                              [simplify(shapes_full[k], 2.0) for k in ks],
                              [_lane_width(lanes[i], lanes) for i in ids_], speed, bike))
        for idx, k in enumerate(ks):
            piece_edge[k] = (eid, idx)
    lane_edges: dict[int, list[tuple[str, int, float, float]]] = {}
    for k, (i, i0, i1, _, _) in enumerate(pieces):
        lane_edges.setdefault(i, []).append((*piece_edge[k], float(arc[i][i0]), float(arc[i][i1])))

    connections: list[ConnectionPlan] = []
    seen: set[tuple] = set()
    represented: set[int] = set()

    def connect(f: tuple, t: tuple, via: tuple[int, ...], shape) -> bool:
        key = (f[0], f[1], t[0], t[1])
        if key in seen:
            return False
        seen.add(key)
        connections.append(ConnectionPlan(f[0], f[1], t[0], t[1], via, shape))
        return True

    for i in road:
        chain = lane_edges[i]
        for f, t in zip(chain[:-1], chain[1:]):
            connect(f, t, (), None)
        for e in exits[i]:
            if e not in junction:
                connect(chain[-1], lane_edges[e][0], (), None)
        for target, via in jpaths[i]:
            shape = simplify(np.concatenate([lanes[v].polyline for v in via]), 2.0)
            if connect(chain[-1], lane_edges[target][0], via, shape):
                represented.update(via)
    edge_by_id = {e.id: e for e in edges}
    node_of_lane: dict[int, str] = {i: edge_by_id[lane_edges[i][-1][0]].to_node for i in road}
    for c in connections:
        for v in c.via:
            node_of_lane.setdefault(v, edge_by_id[c.from_edge].to_node)
    for i in sorted(dense & set(road)):
        unconverted.append({"kind": "lane", "id": int(i),
                            "reason": f"densely connected junction (over {MAX_PATH_EXPANSIONS} "
                                      "path search steps): only shortest junction paths kept"})
    for j in sorted(junction - represented):
        unconverted.append({"kind": "lane", "id": int(j),
                            "reason": "junction lane duplicates another connection between the same lanes"})
    return NetworkPlan(nodes, edges, connections, lane_edges, junction, node_of_lane, unconverted,
                       linked=linked)


def _gap(a: Lane, b: Lane) -> float:
    """m from the end of lane ``a`` to the start of lane ``b``."""
    return float(np.hypot(*(b.polyline[0, :2] - a.polyline[-1, :2])))


def _overlong_junction_lanes(lanes: dict[int, Lane], jpaths: dict[int, list[tuple[int, tuple[int, ...]]]],
                             signalled: set[int]) -> set[int]:
    """Junction lanes to make road lanes: of every junction path spanning more than
    :data:`MAX_JUNCTION_SPAN` m (straight line from the end of its road lane to the start of the
    road lane it reaches), its longest junction lane without a signal (signalled lanes keep
    their traffic-light links); none where all of its lanes are signalled."""
    out: set[int] = set()
    for i, paths in jpaths.items():
        end = lanes[i].polyline[-1, :2]
        for target, via in paths:
            if out & set(via) or \
                    np.hypot(*(lanes[target].polyline[0, :2] - end)) <= MAX_JUNCTION_SPAN:
                continue
            free = [v for v in via if v not in signalled]
            if free:
                out.add(max(free, key=lambda v: length(lanes[v].polyline)))
    return out


def _arc(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length (m) at each polyline point."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1))])


def _breakpoints(lanes: dict[int, Lane], road: list[int], junction: set[int],
                 arc: dict[int, np.ndarray]):
    """Cut indices per road lane (ends + where neighbours start/end, carried across
    neighbours, >= MIN_PIECE m apart), ``snap(lane, index)`` giving the kept cut nearest to an
    index, and the pairs of (lane, index) cuts carried from one lane to its neighbour."""
    cuts: dict[int, list[int]] = {}
    for i in road:
        last = len(lanes[i].polyline) - 1
        cand = {0, last}
        for nb in lanes[i].left_neighbors + lanes[i].right_neighbors:
            if nb.feature_id in arc:
                cand.update((nb.self_start_index, nb.self_end_index))
        cuts[i] = sorted(c for c in cand if 0 <= c <= last)
    for i in road:  # the neighbour's side of every relation is a cut of the neighbour too
        for nb in lanes[i].left_neighbors + lanes[i].right_neighbors:
            j = nb.feature_id
            if j in arc:
                last = len(lanes[j].polyline) - 1
                cuts[j] = sorted(set(cuts[j]) | {min(max(nb.neighbor_start_index, 0), last),
                                                 min(max(nb.neighbor_end_index, 0), last)})
    # a cut inside a stretch where a lane runs beside a neighbour cuts the neighbour too, at
    # the nearest point (repeated across neighbours of neighbours): both pieces then end in one
    # node and form one multi-lane edge, so that a lane change between them stays on the edge
    pairs: list[tuple[tuple[int, int], tuple[int, int]]] = []
    todo = [(i, c) for i in road for c in cuts[i]]
    done = {(i, c) for i, c in todo}
    while todo:
        i, c = todo.pop()
        for nb in lanes[i].left_neighbors + lanes[i].right_neighbors:
            j = nb.feature_id
            if j not in arc or not nb.self_start_index <= c <= nb.self_end_index:
                continue
            if c in (nb.self_start_index, nb.self_end_index):
                # an end of the relation is carried only where the relation's own end on the
                # neighbour lies too far off to be joined (see MAX_NEIGHBOUR_GAP)
                other = nb.neighbor_start_index if c == nb.self_start_index else nb.neighbor_end_index
                other = min(max(other, 0), len(arc[j]) - 1)
                if np.hypot(*(lanes[i].polyline[c, :2] - lanes[j].polyline[other, :2])) \
                        <= MAX_NEIGHBOUR_GAP:
                    continue
            lo = max(min(nb.neighbor_start_index, nb.neighbor_end_index), 0)
            hi = min(max(nb.neighbor_start_index, nb.neighbor_end_index), len(arc[j]) - 1)
            if hi <= lo:
                continue
            pts = lanes[j].polyline[lo:hi + 1, :2]
            k = lo + int(np.argmin(np.linalg.norm(pts - lanes[i].polyline[c, :2], axis=1)))
            if c in (nb.self_start_index, nb.self_end_index) and k in (lo, hi):
                continue  # the end of the longer lane of the two: carried from the shorter one
            pairs.append(((i, c), (j, k)))
            if (j, k) not in done:
                done.add((j, k))
                cuts[j] = sorted(set(cuts[j]) | {k})
                todo.append((j, k))
    kept: dict[int, np.ndarray] = {}
    for i in road:
        s, last = arc[i], len(lanes[i].polyline) - 1
        keep = [0]
        for c in cuts[i]:
            if s[c] - s[keep[-1]] >= MIN_PIECE and s[last] - s[c] >= MIN_PIECE:
                keep.append(c)
        keep.append(last)
        kept[i] = np.array(keep)
        cuts[i] = keep

    def snap(i: int, index: int) -> int:
        s = arc[i]
        index = min(max(index, 0), len(s) - 1)
        k = kept[i]
        return int(k[np.argmin(np.abs(s[k] - s[index]))])
    return cuts, snap, pairs
