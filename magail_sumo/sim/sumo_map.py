"""A SUMO network as the scene model's road map, for sensors and events on plain SUMO scenarios.

Lanes (normal and junction-internal) become :class:`~magail_sumo.scene.Lane` centre lines with
integer ids (their index in :attr:`NetworkMap.lane_ids`); the outer borders of every normal
edge (right border of lane 0, left border of the last lane) become road edges, and the borders
between neighbouring lanes of an edge become road lines. Coordinates are SUMO's (metres);
z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.scene import Lane, RoadEdge, RoadEdgeType, RoadLine, RoadLineType, RoadMap


def offset_polyline(points: np.ndarray, offset: float) -> np.ndarray:
    """(P, 2) polyline shifted sideways by ``offset`` metres (positive = left of travel).

    Each vertex moves along the mean of its neighbouring segments' left normals.
    """
    p = np.asarray(points, np.float64)[:, :2]
    if len(p) < 2:
        return p.copy()
    seg = np.diff(p, axis=0)
    norm = np.linalg.norm(seg, axis=1, keepdims=True)
    seg = seg / np.where(norm > 1e-9, norm, 1.0)
    left = np.stack([-seg[:, 1], seg[:, 0]], axis=1)
    vert = np.vstack([left[:1], left[:-1] + left[1:], left[-1:]])
    vn = np.linalg.norm(vert, axis=1, keepdims=True)
    vert = vert / np.where(vn > 1e-9, vn, 1.0)
    return p + offset * vert


@dataclass(frozen=True)
class NetworkMap:
    """The road map of a SUMO network plus the SUMO id of each map lane (index = lane id)."""

    roadmap: RoadMap
    lane_ids: tuple[str, ...]
    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax


def _z(points: np.ndarray) -> np.ndarray:
    return np.column_stack([points[:, :2], np.zeros(len(points))])


def network_map(net_file: str | PathLike) -> NetworkMap:
    """Read a ``.net.xml`` into a :class:`NetworkMap`.

    :raises MagailSumoError: missing or unreadable network file.
    """
    import sumolib

    path = Path(net_file)
    if not path.is_file():
        raise MagailSumoError(f"{path}: SUMO network file not found")
    try:
        net = sumolib.net.readNet(str(path), withInternal=True)
    except Exception as exc:  # sumolib raises plain exceptions on bad XML
        raise MagailSumoError(f"{path}: cannot read SUMO network ({' '.join(str(exc).split())})") \
            from None
    lanes: list[Lane] = []
    ids: list[str] = []
    edges: list[RoadEdge] = []
    lines: list[RoadLine] = []
    next_id = 0
    for edge in net.getEdges(withInternal=True):
        e_lanes = edge.getLanes()
        for lane in e_lanes:
            shape = np.asarray(lane.getShape(), np.float64)
            if len(shape) < 2:
                continue
            lanes.append(Lane(id=len(ids), polyline=_z(shape)))
            ids.append(lane.getID())
        if edge.getFunction() == "internal" or not e_lanes:
            continue
        shapes = [np.asarray(l.getShape(), np.float64) for l in e_lanes]
        widths = [float(l.getWidth()) for l in e_lanes]
        first, last = shapes[0], shapes[-1]
        base = 1_000_000  # road edge / line ids start above any lane id
        if len(first) >= 2:
            edges.append(RoadEdge(base + next_id, _z(offset_polyline(first, -widths[0] / 2)),
                                  RoadEdgeType.BOUNDARY))
            next_id += 1
        if len(last) >= 2:
            edges.append(RoadEdge(base + next_id, _z(offset_polyline(last, widths[-1] / 2)),
                                  RoadEdgeType.BOUNDARY))
            next_id += 1
        for shape, width in zip(shapes[:-1], widths[:-1]):
            if len(shape) >= 2:
                lines.append(RoadLine(base + next_id, _z(offset_polyline(shape, width / 2)),
                                      RoadLineType.BROKEN_SINGLE_WHITE))
                next_id += 1
    (x0, y0), (x1, y1) = net.getBBoxXY()
    return NetworkMap(RoadMap(lanes=tuple(lanes), road_edges=tuple(edges), road_lines=tuple(lines)),
                      tuple(ids), (float(x0), float(y0), float(x1), float(y1)))


def internal_junctions(net_file: str | PathLike) -> dict[str, tuple[tuple[str, ...],
                                                                   tuple[str, ...]]]:
    """The internal junctions of a ``.net.xml`` (or ``.net.xml.gz``): for each (its id, which
    is the id of the internal lane that waits there, e.g. a left turn's second internal lane)
    the lanes whose vehicles it must let pass: ``incLanes`` (its own approach and the foes'
    approach lanes) and ``intLanes`` (the foes' internal lanes), as SUMO's net format gives
    them.

    :raises MagailSumoError: missing or unreadable network file.
    """
    import gzip
    import xml.etree.ElementTree as ET

    path = Path(net_file)
    opener = gzip.open if path.suffix == ".gz" else open
    out: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {}
    try:
        with opener(path, "rb") as fh:
            for _, el in ET.iterparse(fh):
                if el.tag == "junction" and el.get("type") == "internal":
                    out[el.get("id", "")] = (tuple(el.get("incLanes", "").split()),
                                             tuple(el.get("intLanes", "").split()))
                if el.tag in ("edge", "junction", "connection"):
                    el.clear()
    except (OSError, ET.ParseError, EOFError) as exc:
        raise MagailSumoError(f"{path}: cannot read SUMO network ({' '.join(str(exc).split())})") \
            from None
    return out
