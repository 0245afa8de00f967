"""Sidewalks and crossings for SUMO pedestrians (``ConvertOptions.pedestrians``).

* **Sidewalks**: every road edge (not bike-only, not synthesised) whose right-hand side is free
  (no other lane's centre line within half its width of the sidewalk's centre) gets a sidewalk
  of :data:`SIDEWALK_WIDTH` m beside its rightmost lane. As in SUMO, the sidewalk is **lane
  index 0** of the edge: :func:`add_sidewalks` shifts every lane index of the plan
  (``EdgePlan`` lanes, ``lane_edges``, connections) by one on those edges, so routes,
  traffic-light links and the lane lookups of the converter keep naming the right SUMO lanes.
  Its ``EdgePlan.lanes`` entry is :data:`SIDEWALK`.
* **Crossings**: each crosswalk polygon of the map becomes a SUMO ``<crossing>`` at the plan
  node nearest to it (within :data:`MAX_NODE_DISTANCE` m) that has road edges whose lanes pass
  through the polygon (within :data:`CROSS_TOLERANCE` m); the crossing spans those edges and is
  ``priority="true"`` (vehicles yield). netconvert builds the crossing and the walking areas.
  Crosswalks with no such node (mid-block crosswalks), one whose edges another crosswalk already
  crosses at that node, and those netconvert refuses are dropped; ``conversion.json`` lists
  them under ``pedestrians.dropped`` with the reason.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magail_sumo.scene import Scene

from .geometry import point_segment, segments
from .topology import NetworkPlan

SIDEWALK = -1000  #: ``EdgePlan.lanes`` entry of a sidewalk lane (no WOMD lane; -1 is a synthesised one)
SIDEWALK_WIDTH = 2.0  #: m
CROSSING_WIDTH = (2.0, 6.0)  #: m, range of a crossing's width (the crosswalk's short side)
MAX_NODE_DISTANCE = 30.0  #: m, farthest junction node from a crosswalk's centre
CROSS_TOLERANCE = 1.0  #: m, beyond the crosswalk's ends a lane end still counts as crossing it
REACH = 12.0  #: m, farthest a crossing lane's end at the node lies before or beyond the crosswalk
#: vClass of the obstacles (:class:`magail_sumo.sim.session.Obstacles`) on a pedestrian
#: network: every vehicle lane allows it (bike lanes name it), walking lanes do not, so an
#: obstacle is never placed on a sidewalk, crossing or walking area (SUMO crashes on a vehicle
#: there); elsewhere obstacles are of class ``ignoring``
OBSTACLE_CLASS = "custom1"
#: netconvert options that differ from :data:`.network.NETCONVERT_OPTIONS` with pedestrians
NETCONVERT_WALKING = ["--walkingareas", "true"]


@dataclass
class CrossingPlan:
    """A crossing built from crosswalk ``crosswalk`` at ``node`` over ``edges`` (SUMO ids)."""

    crosswalk: int
    node: str
    edges: tuple[str, ...]
    width: float


@dataclass
class PedestrianPlan:
    """What :func:`plan_pedestrians` added; ``to_dict`` is ``conversion.json``'s ``pedestrians``."""

    sidewalks: int = 0
    crossings: list[CrossingPlan] = field(default_factory=list)
    dropped: list[dict] = field(default_factory=list)  # {"crosswalk": id, "reason": ...}
    built: int | None = None  # crossings netconvert built (None: not checked yet)

    def to_dict(self) -> dict:
        return {"sidewalks": self.sidewalks,
                "crosswalks": len(self.crossings) + len(self.dropped),
                "crossings": self.built if self.built is not None else len(self.crossings),
                "crossing_list": [{"crosswalk": c.crosswalk, "node": c.node,
                                   "edges": list(c.edges)} for c in self.crossings],
                "dropped": self.dropped}


def _offset(points: np.ndarray, offset: float) -> np.ndarray:
    """(P, k) polyline shifted sideways by ``offset`` m (positive: left of travel); z kept."""
    p = np.asarray(points, np.float64)
    xy = p[:, :2]
    seg = np.diff(xy, axis=0)
    norm = np.linalg.norm(seg, axis=1, keepdims=True)
    seg = seg / np.where(norm > 1e-9, norm, 1.0)
    left = np.stack([-seg[:, 1], seg[:, 0]], axis=1)
    vert = np.vstack([left[:1], left[:-1] + left[1:], left[-1:]])
    vert /= np.maximum(np.linalg.norm(vert, axis=1, keepdims=True), 1e-9)
    out = p.copy()
    out[:, :2] = xy + offset * vert
    return out


def add_sidewalks(plan: NetworkPlan) -> int:
    """Give road edges with a free right-hand side a sidewalk at lane index 0 (module doc);
    shifts the plan's lane indices on those edges. Returns the number of sidewalks."""
    cands = [e for e in plan.edges if not e.bike_only and e.synthesized_for is None
             and len(e.shapes[0]) >= 2]
    if not cands:
        return 0
    a, b, owner = segments([s for e in plan.edges for s in e.shapes])
    half = np.array([w / 2 for e in plan.edges for w in e.widths])[owner]
    first = np.cumsum([0] + [len(e.shapes) for e in plan.edges])
    span = {e.id: (int(first[k]), int(first[k + 1])) for k, e in enumerate(plan.edges)}
    shifted: set[str] = set()
    for e in cands:
        walk = _offset(e.shapes[0], -(e.widths[0] + SIDEWALK_WIDTH) / 2)
        # the sidewalk's points (ends left out: they meet the junction's lanes)
        probe = walk[1:-1, :2] if len(walk) > 2 else (walk[:1, :2] + walk[1:, :2]) / 2
        d, _ = point_segment(probe, a, b)
        own = (owner >= span[e.id][0]) & (owner < span[e.id][1])
        d[:, own] = np.inf
        if (d < half[None] + SIDEWALK_WIDTH / 4).any():
            continue  # another lane runs there: a median or a neighbouring edge, not a curb
        e.lanes.insert(0, SIDEWALK)
        e.shapes.insert(0, walk)
        e.widths.insert(0, SIDEWALK_WIDTH)
        shifted.add(e.id)
    for lane, pieces in plan.lane_edges.items():
        plan.lane_edges[lane] = [(ed, i + (ed in shifted), s0, s1) for ed, i, s0, s1 in pieces]
    for c in plan.connections:
        c.from_lane += c.from_edge in shifted
        c.to_lane += c.to_edge in shifted
    return len(shifted)


def _axes(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Centre, unit long axis, half length and half width of a crosswalk polygon (its principal
    axes)."""
    c = poly.mean(axis=0)
    _, _, vt = np.linalg.svd(poly - c, full_matrices=False)
    proj = (poly - c) @ vt.T
    return c, vt[0], float(np.ptp(proj[:, 0]) / 2), float(np.ptp(proj[:, 1]) / 2)


def _crosses(shape: np.ndarray, at_end: bool, poly: np.ndarray) -> bool:
    """Whether a lane (its end at the node: the last point when ``at_end``, else the first)
    crosses the crosswalk: the lane runs across its long axis (within 45° of perpendicular),
    its end at the node lies within the crosswalk's length and at most :data:`REACH` m before
    or beyond it (lanes of a junction end a little before the crosswalk, exit lanes start a
    little after it)."""
    xy = shape[:, :2]
    if len(xy) < 2:
        return False
    p, q = (xy[-1], xy[-2]) if at_end else (xy[0], xy[1])
    d = p - q
    d = d / max(float(np.hypot(*d)), 1e-9)
    c, u, half_len, half_wid = _axes(poly)
    along, across = float((p - c) @ u), float((p - c) @ np.array([-u[1], u[0]]))
    return (abs(float(d @ u)) < np.sqrt(0.5) and abs(along) <= half_len + CROSS_TOLERANCE
            and abs(across) <= half_wid + REACH)


def _width(poly: np.ndarray) -> float:
    """Short side of the crosswalk's minimum-area box, clipped to :data:`CROSSING_WIDTH`."""
    return float(np.clip(2 * _axes(poly)[3], *CROSSING_WIDTH))


def plan_crossings(scene: Scene, plan: NetworkPlan) -> tuple[list[CrossingPlan], list[dict]]:
    """Crossings from the scene's crosswalks (module doc): (crossings, dropped)."""
    out: list[CrossingPlan] = []
    dropped: list[dict] = []
    if not plan.nodes:
        return out, [{"crosswalk": int(c.id), "reason": "the network has no junction"}
                     for c in scene.roadmap.crosswalks]
    names = list(plan.nodes)
    nodes = np.array([plan.nodes[n][:2] for n in names], np.float64)
    incident: dict[str, list] = {}
    for e in plan.edges:
        if e.bike_only or e.synthesized_for is not None:
            continue
        incident.setdefault(e.from_node, []).append(e)
        incident.setdefault(e.to_node, []).append(e)
    used: dict[tuple[str, tuple[str, ...]], int] = {}
    for cw in scene.roadmap.crosswalks:
        poly = np.asarray(cw.polygon, np.float64)[:, :2]
        if len(poly) < 3:
            dropped.append({"crosswalk": int(cw.id), "reason": "polygon has fewer than 3 points"})
            continue
        dist = np.linalg.norm(nodes - poly.mean(axis=0), axis=1)
        order = [k for k in np.argsort(dist, kind="stable") if dist[k] <= MAX_NODE_DISTANCE]
        found = None  # the node with the most crossing edges, junctions (3+ edges) first
        best = (0, False)
        for k in order:
            n = names[k]
            inc = incident.get(n, ())
            edges = tuple(sorted({e.id for e in inc
                                  if any(_crosses(sh, e.to_node == n, poly)
                                         for sh, ln in zip(e.shapes, e.lanes) if ln != SIDEWALK)}))
            score = (len(inc) >= 3, len(edges)) if edges else (False, 0)
            if edges and score > best:
                found, best = (n, edges), score
        if found is None:
            dropped.append({"crosswalk": int(cw.id), "reason":
                            f"no junction within {MAX_NODE_DISTANCE:g} m with a road edge "
                            "through it (mid-block or off the converted roads)"})
        elif found in used:
            dropped.append({"crosswalk": int(cw.id), "reason":
                            f"crosses the same edges at node {found[0]} as crosswalk "
                            f"{used[found]}"})
        else:
            used[found] = int(cw.id)
            out.append(CrossingPlan(int(cw.id), found[0], found[1], _width(poly)))
    return out, dropped


def plan_pedestrians(scene: Scene, plan: NetworkPlan) -> PedestrianPlan:
    """Add sidewalks to ``plan`` (in place) and plan the crossings (module doc)."""
    ped = PedestrianPlan(sidewalks=add_sidewalks(plan))
    ped.crossings, ped.dropped = plan_crossings(scene, plan)
    return ped


def crossing_xml(ped: PedestrianPlan) -> str:
    """The ``<crossing>`` lines of the connection file."""
    return "".join(f'  <crossing node="{c.node}" edges="{" ".join(c.edges)}" priority="true" '
                   f'width="{c.width:.2f}"/>\n' for c in ped.crossings)


def check_built(ped: PedestrianPlan, net_file: Path, warnings: list[str]) -> None:
    """Move the planned crossings netconvert did not build into ``ped.dropped`` (with its
    warning when it gave one) and set ``ped.built``."""
    built: set[tuple[str, tuple[str, ...]]] = set()
    for _, el in ET.iterparse(str(net_file)):
        if el.tag == "edge" and el.get("function") == "crossing":
            node = el.get("id", "")[1:].rsplit("_c", 1)[0]
            built.add((node, tuple(sorted(el.get("crossingEdges", "").split()))))
        el.clear()
    keep = []
    for c in ped.crossings:
        if (c.node, c.edges) in built:
            keep.append(c)
            continue
        why = next((w for w in warnings if f"{c.node}_c" in w and _warned_edges(w) == set(c.edges)),
                   "")
        ped.dropped.append({"crosswalk": c.crosswalk, "reason": "netconvert did not build the "
                            f"crossing at node {c.node} over {' '.join(c.edges)}"
                            + (f": {why}" if why else "")})
    ped.crossings = keep
    ped.built = len(keep)


def _warned_edges(warning: str) -> set[str]:
    """The edges a netconvert crossing warning names (``[e1 e2]``), else none."""
    m = re.search(r"\[([^\]]*)\]", warning)
    return set(m.group(1).split()) if m else set()


def is_walking_lane(lane) -> bool:
    """Whether a sumolib lane is for pedestrians only (sidewalk, crossing, walking area)."""
    if lane.getEdge().getFunction() in ("crossing", "walkingarea"):
        return True
    return lane.allows("pedestrian") and not (lane.allows("passenger") or lane.allows("bicycle"))
