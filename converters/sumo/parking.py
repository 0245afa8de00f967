"""Non-moving vehicles in the SUMO files, where SUMO's drivers respect them.

A vehicle or cyclist track that moves less than :data:`~.routes.PARKED_MOVE` m is parked. Its
pose (:func:`parked_pose`) is the valid state nearest the median of its recorded centres (box
centre x, y in m, heading in rad CCW from +x), with the median length and width. Each becomes
one of (:func:`place_parked`):

* **stopped on a lane** -- its box comes within :func:`block_clearance` m of the centre line
  of a lane its class may use, so a SUMO vehicle driving that lane would touch it (SUMO,
  without its sublane model, drives every vehicle on its lane's centre line). It is written as
  a vehicle stopped on that lane (``<stop parking="false">``) at the lane position of its box:
  SUMO's drivers brake and queue behind it or change lanes, as for any stopped leader;
* **parked in a space** -- otherwise: a ``parkingArea`` of one space on the nearest lane its
  class may use (within :data:`PARK_SEARCH` m), the space at the recorded pose (SUMO places a
  parked vehicle's front bumper at the space's x, y; the space's ``angle`` is
  ``90 + heading`` in degrees), and a parking stop there: SUMO holds it off the lane where it
  was recorded, and its drivers pass;
* **unconverted** -- no lane its class may use within :data:`PARK_SEARCH` m.

Both kinds are in SUMO from the scene's start (a non-moving vehicle first seen later stood there
unseen; inserted later, one bound for a space would stand on its lane for its insertion step, in
the way of the traffic), before the moving vehicles, with ``departPos="stop"`` and no
insertion checks (recorded neighbours stand closer than SUMO's gaps), and stay past the end of
the scene. The lane geometry is the built network's (:func:`class_lanes`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magail_sumo.scene import Scene

from .geometry import point_segment

#: m, a parked box this close to a lane's centre line blocks the lane (half a car's width; a
#: scene's own widest moving vehicle sets it when wider: :func:`block_clearance`)
BLOCK_CLEARANCE = 1.0
#: m, most clearance a scene's vehicles set (half a bus's width)
MAX_CLEARANCE = 1.5
#: m, farthest lane a parking space is attached to
PARK_SEARCH = 100.0
#: m, clear lane between two vehicles standing on one lane: the vTypes' ``minGap``
#: (:func:`.routes.write_routes`), within which SUMO counts a collision
#: (``collision.mingap-factor`` 1 for its default car-following model)
STOP_GAP = 1.0


@dataclass(frozen=True)
class ParkedPose:
    """Recorded pose of a non-moving track (module doc)."""

    x: float
    y: float
    heading: float
    length: float
    width: float


@dataclass(frozen=True)
class ParkedSpot:
    """Where a parked vehicle is written: ``lane`` (SUMO lane id) and the stop's ``end_pos``
    (m along it, its front bumper); ``space`` (x, y of the front bumper, SUMO space angle in
    degrees) for a parking space, None for a vehicle stopped on the lane."""

    lane: str
    start_pos: float
    end_pos: float
    space: tuple[float, float, float] | None

    @property
    def blocking(self) -> bool:
        return self.space is None


@dataclass(frozen=True)
class ClassLanes:
    """Segments (S, 2) ``a``/``b`` of the normal lanes one vehicle class may use, with their
    bounding boxes ``lo``/``hi`` (S, 2), each with its lane's index into ``ids`` / ``lengths``
    (SUMO's, m) / ``shapes`` / ``shape_lengths`` (m along the shape)."""

    a: np.ndarray
    b: np.ndarray
    lane: np.ndarray
    ids: tuple[str, ...]
    lengths: np.ndarray
    shapes: tuple[np.ndarray, ...]
    lo: np.ndarray
    hi: np.ndarray
    shape_lengths: np.ndarray


def class_lanes(net, vclass: str) -> ClassLanes:
    """The lanes of edges that are not internal (SUMO stops only on those) that ``vclass`` may
    use, as segments."""
    ids, shapes, a, b, owner = [], [], [], [], []
    for e in net.getEdges(withInternal=False):
        for lane in e.getLanes():
            if not lane.allows(vclass):
                continue
            shape = np.asarray(lane.getShape(), np.float64)[:, :2]
            if len(shape) < 2:
                continue
            owner.append(np.full(len(shape) - 1, len(ids)))
            ids.append(lane.getID())
            shapes.append(shape)
            a.append(shape[:-1])
            b.append(shape[1:])
    if not ids:
        z = np.zeros((0, 2))
        return ClassLanes(z, z, np.zeros(0, int), (), np.zeros(0), (), z, z, np.zeros(0))
    # SUMO's lane lengths (positions along a lane are SUMO's: its length can differ from its
    # shape's), a centimetre short so that rounded positions stay on the lane
    lengths = np.array([net.getLane(i).getLength() - 0.01 for i in ids])
    a_, b_ = np.concatenate(a), np.concatenate(b)
    return ClassLanes(a_, b_, np.concatenate(owner), tuple(ids), lengths, tuple(shapes),
                      np.minimum(a_, b_), np.maximum(a_, b_),
                      np.array([np.linalg.norm(np.diff(sh, axis=0), axis=1).sum()
                                for sh in shapes]))


def block_clearance(scene: Scene, rows: np.ndarray) -> float:
    """How close to a lane's centre line a parked box blocks the lane: half the median width
    of the widest of the moving tracks ``rows`` that SUMO drives on lane centre lines, plus
    0.1 m, within [:data:`BLOCK_CLEARANCE`, :data:`MAX_CLEARANCE`] m."""
    tr = scene.tracks
    widths = [float(np.median(tr.width[n, tr.valid[n]])) for n in rows if tr.valid[n].any()]
    return float(np.clip(max(widths, default=0.0) / 2 + 0.1, BLOCK_CLEARANCE, MAX_CLEARANCE))


def parked_pose(scene: Scene, n: int) -> ParkedPose:
    """The pose of track ``n`` (module doc)."""
    tr = scene.tracks
    steps = np.flatnonzero(tr.valid[n])
    x, y = tr.x[n, steps].astype(np.float64), tr.y[n, steps].astype(np.float64)
    k = int(np.argmin(np.hypot(x - np.median(x), y - np.median(y))))
    return ParkedPose(float(x[k]), float(y[k]), float(tr.heading[n, steps[k]]),
                      float(np.median(tr.length[n, steps])), float(np.median(tr.width[n, steps])))


def box_segment_distance(pose: ParkedPose, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(S,) distance (m) from the box of ``pose`` to each segment ``a``-``b``; 0 where a
    segment enters the box."""
    c, s = np.cos(pose.heading), np.sin(pose.heading)
    rot = np.array([[c, -s], [s, c]])  # box frame (u along the heading, v to its left)
    pa = (a - (pose.x, pose.y)) @ rot
    pb = (b - (pose.x, pose.y)) @ rot
    hl, hw = pose.length / 2, pose.width / 2

    def to_box(p: np.ndarray) -> np.ndarray:
        return np.hypot(np.maximum(np.abs(p[:, 0]) - hl, 0), np.maximum(np.abs(p[:, 1]) - hw, 0))

    corners = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    d = np.minimum(np.minimum(to_box(pa), to_box(pb)), point_segment(corners, pa, pb)[0].min(0))
    # a segment passing through the box with both ends outside: Liang-Barsky clipping
    step = pb - pa
    t0, t1 = np.zeros(len(pa)), np.ones(len(pa))
    inside = np.ones(len(pa), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for p, q in ((-step[:, 0], pa[:, 0] + hl), (step[:, 0], hl - pa[:, 0]),
                     (-step[:, 1], pa[:, 1] + hw), (step[:, 1], hw - pa[:, 1])):
            r = q / p
            inside &= ~((p == 0) & (q < 0))
            t0 = np.where(p < 0, np.maximum(t0, r), t0)
            t1 = np.where(p > 0, np.minimum(t1, r), t1)
    return np.where(inside & (t0 <= t1), 0.0, d)


def place_parked(poses: list[ParkedPose], lanes: ClassLanes,
                 taken: dict[str, list[tuple[float, float]]] | None = None,
                 clearance: float = BLOCK_CLEARANCE) -> list[ParkedSpot | None]:
    """Where each parked vehicle of ``poses`` goes (module doc), among ``lanes``; None where no
    lane lies within :data:`PARK_SEARCH` m.

    SUMO's lane is one-dimensional: two vehicles stopped on one lane cannot stand side by side
    or overlap (SUMO would count a collision every step). The vehicles that block a lane
    (within ``clearance`` m of its centre line: :func:`block_clearance`) are stopped on it in
    driving order; one whose stretch of the lane (m from its start) comes within
    :data:`STOP_GAP` of one already stopped there gets a space at its recorded pose instead
    (SUMO's drivers stop behind the first), as does one whose lane is shorter than itself. A
    vehicle bound for a space stands on its lane for the step it is inserted, so a space's
    stretch is moved along the lane clear of the stopped vehicles. ``taken`` (lane id ->
    stretches of stopped vehicles) carries the lanes' stopped vehicles across calls
    (classes)."""
    taken = {} if taken is None else taken
    near = [_nearest_lane(p, lanes) for p in poses]
    out: list[ParkedSpot | None] = [None] * len(poses)
    spaces = []
    stretch = {}
    for i, m in enumerate(near):
        if m is None:
            continue
        _, k, at = m
        lane_len = float(lanes.lengths[k])
        end = float(np.clip(at + poses[i].length / 2, min(poses[i].length, lane_len), lane_len))
        stretch[i] = (max(0.0, end - poses[i].length), end)
    # along each lane in driving order: its drivers stop behind the first vehicle that blocks
    # it and never reach one overlapping it further on, which gets a space instead
    for i in sorted(stretch, key=lambda i: (near[i][1], stretch[i])):
        d, k, _ = near[i]
        lane, (start, end) = lanes.ids[k], stretch[i]
        # a lane shorter than the vehicle cannot hold it: its back would stand on the lane
        # before, in the way of whatever stops there
        fits = float(lanes.lengths[k]) >= poses[i].length
        if d < clearance and fits and _free(taken.get(lane, ()), start, end):
            taken.setdefault(lane, []).append((start, end))
            out[i] = ParkedSpot(lane, start, end, None)
        else:
            spaces.append(i)
    for i in spaces:
        _, k, at = near[i]
        pose, lane_len, lane = poses[i], float(lanes.lengths[k]), lanes.ids[k]
        half = pose.length / 2
        start, end = _clear_stretch(taken.get(lane, ()), at - half, min(pose.length, lane_len),
                                    lane_len)
        front = (pose.x + half * np.cos(pose.heading), pose.y + half * np.sin(pose.heading))
        angle = (90.0 + np.degrees(pose.heading)) % 360.0
        out[i] = ParkedSpot(lane, start, end, (float(front[0]), float(front[1]), float(angle)))
    return out


def _free(stretches, start: float, end: float) -> bool:
    """Whether [start, end] keeps :data:`STOP_GAP` m from each of ``stretches``."""
    return all(end + STOP_GAP <= s0 or start >= e0 + STOP_GAP for s0, e0 in stretches)


def _clear_stretch(stretches, want: float, size: float, lane_len: float
                   ) -> tuple[float, float]:
    """The stretch of ``size`` m on a lane of ``lane_len`` m nearest to starting at ``want``
    that overlaps none of ``stretches`` (the nearest to ``want`` overall when none is clear)."""
    size = max(min(size, lane_len), 0.1)
    cands = [want] + [e0 + STOP_GAP for _, e0 in stretches] + \
        [s0 - STOP_GAP - size for s0, _ in stretches]
    cands = [float(np.clip(c, 0.0, max(lane_len - size, 0.0))) for c in cands]
    clear = [c for c in cands if _free(stretches, c, c + size)]
    best = min(clear or cands[:1], key=lambda c: abs(c - want))
    return best, min(best + size, lane_len)


def _nearest_lane(pose: ParkedPose, lanes: ClassLanes) -> tuple[float, int, float] | None:
    """(distance m from the box, lane index, position m of the box centre along it) of the lane
    nearest the box of ``pose``; None beyond :data:`PARK_SEARCH` m."""
    if not len(lanes.a):
        return None
    reach = PARK_SEARCH + np.hypot(pose.length, pose.width)
    near = np.flatnonzero(np.all((lanes.lo <= (pose.x + reach, pose.y + reach))
                                 & (lanes.hi >= (pose.x - reach, pose.y - reach)), axis=1))
    if not len(near):
        return None
    d = box_segment_distance(pose, lanes.a[near], lanes.b[near])
    best = int(np.argmin(d))
    if d[best] > PARK_SEARCH:
        return None
    k = int(lanes.lane[near[best]])
    at = _offset_along(lanes.shapes[k], np.array([pose.x, pose.y])) * float(lanes.lengths[k]) \
        / max(float(lanes.shape_lengths[k]), 1e-9)
    return float(d[best]), k, at


def _offset_along(shape: np.ndarray, p: np.ndarray) -> float:
    """Distance along polyline ``shape`` of its point nearest ``p``."""
    d, t = point_segment(p[None], shape[:-1], shape[1:])
    i = int(np.argmin(d[0]))
    seg = np.linalg.norm(np.diff(shape, axis=0), axis=1)
    return float(seg[:i].sum() + t[0, i] * seg[i])


def write_parking(path: Path, spots: list[tuple[str, ParkedSpot, float, float]]) -> None:
    """The additional file of the parking spaces: one ``parkingArea`` ``park_<vehicle id>`` per
    ``(vehicle id, spot, length, width)`` with a space (module doc); ``spots`` without a space
    are skipped."""
    with open(path, "w") as fh:
        fh.write("<additional>\n")
        for vid, spot, length, width in spots:
            if spot.space is None:
                continue
            x, y, angle = spot.space
            fh.write(f'  <parkingArea id="park_{vid}" lane="{spot.lane}" '
                     f'startPos="{spot.start_pos:.2f}" endPos="{spot.end_pos:.2f}" '
                     f'roadsideCapacity="0">\n'
                     f'    <space x="{x:.2f}" y="{y:.2f}" width="{width:.2f}" '
                     f'length="{length:.2f}" angle="{angle:.1f}"/>\n'
                     "  </parkingArea>\n")
        fh.write("</additional>\n")
