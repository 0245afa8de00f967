"""The lanes a SUMO vehicle's route drives through, as one centreline polyline (its reference
path for route-relative control, :mod:`magail_sumo.sim.tracking`).

From the vehicle's current lane, a vehicle length behind its front, the path runs along the lane to its end, through
the junction's internal lane(s) of the connection to the route's next edge, along the lane that
connection reaches, and so on to the end of the route's last edge (SUMO's default arrival
position). Where the current lane has no connection to the next edge, the path changes lane
on the way: it leaves the current lane at the vehicle's position and joins, ``change_length``
metres further (at most at the lane's end), the nearest lane of the edge that has one (a lane
change SUMO's lane-change model would make). Only lanes the vehicle's class may use count.
A route whose next edge cannot be reached from any usable lane (SUMO would teleport) ends the
path there; :class:`RoutePath` says so.

The network does not change during a run, so lane shapes and connections are read from SUMO
once per lane (:class:`LaneGraph` caches them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: metres over which the path moves to a lane that connects to the route's next edge
CHANGE_LENGTH = 25.0


@dataclass(frozen=True)
class RoutePath:
    """A vehicle's reference path: ``points`` ((M, 2), m, network frame), whether it runs
    to the end of the route (``complete``; False: cut where the next edge is unreachable) and
    the lanes' speed limits along it (``limits``)."""

    points: np.ndarray
    complete: bool
    #: (M,) the speed limit (m/s) of the lane from each point to the next (SUMO's lane speed)
    limits: np.ndarray | None = None


class LaneGraph:
    """Lane shapes, lengths, permissions and connections of a running SUMO network, read
    through libsumo's API once per lane.

    :param api: the ``libsumo`` module of a started simulation.
    """

    def __init__(self, api) -> None:
        self.api = api
        self._shape: dict[str, np.ndarray] = {}
        self._links: dict[str, list[tuple[str, str]]] = {}
        self._lanes: dict[str, list[str]] = {}
        self._allows: dict[tuple[str, str], bool] = {}
        self._speed: dict[str, float] = {}

    def shape(self, lane: str) -> np.ndarray:
        """(M, 2) centreline of ``lane`` (m)."""
        out = self._shape.get(lane)
        if out is None:
            out = self._shape[lane] = np.asarray(self.api.lane.getShape(lane), np.float64)
        return out

    def speed(self, lane: str) -> float:
        """Speed limit of ``lane`` (m/s; inside a junction, the one netconvert gives the
        turn)."""
        out = self._speed.get(lane)
        if out is None:
            out = self._speed[lane] = float(self.api.lane.getMaxSpeed(lane))
        return out

    def links(self, lane: str) -> list[tuple[str, str]]:
        """(lane reached, first internal lane on the way or "") of each connection of
        ``lane``."""
        out = self._links.get(lane)
        if out is None:
            out = self._links[lane] = [(link[0], link[4]) for link in self.api.lane.getLinks(lane)]
        return out

    def lanes(self, edge: str) -> list[str]:
        """Lane ids of ``edge``, rightmost first."""
        out = self._lanes.get(edge)
        if out is None:
            out = self._lanes[edge] = [f"{edge}_{i}"
                                       for i in range(self.api.edge.getLaneNumber(edge))]
        return out

    def allows(self, lane: str, vclass: str) -> bool:
        """Whether vehicles of class ``vclass`` may use ``lane``."""
        key = (lane, vclass)
        out = self._allows.get(key)
        if out is None:
            allowed = self.api.lane.getAllowed(lane)
            out = vclass in allowed if allowed else \
                vclass not in self.api.lane.getDisallowed(lane)
            self._allows[key] = out
        return out

    def _via(self, lane: str, edge: str) -> tuple[str, list[str]] | None:
        """(lane of ``edge`` reached, internal lanes on the way) of ``lane``'s connection to
        ``edge``; None when it has none."""
        for reached, internal in self.links(lane):
            if reached.rsplit("_", 1)[0] != edge:
                continue
            return reached, self.internal_chain(internal)
        return None

    def internal_chain(self, internal: str) -> list[str]:
        """The internal lanes from ``internal`` on to the junction's exit lane, in order.

        A connection can cross its junction on more than one internal lane (a left turn that
        waits inside the junction: the internal junction lane that follows, the ``via`` of the
        first internal lane's own link). libsumo reports an internal lane's link as (the normal
        lane reached, the next internal lane or ""), so the chain follows the ``via``."""
        chain: list[str] = []
        while internal.startswith(":") and len(chain) < 8:
            chain.append(internal)
            nxt = self.links(internal)
            if not nxt:
                break
            reached, via = nxt[0]
            internal = via or reached
        return chain

    def route_path(self, vehicle: str, change_length: float = CHANGE_LENGTH) -> RoutePath:
        """The reference path of SUMO vehicle ``vehicle`` from where it is now (module doc)."""
        v = self.api.vehicle
        lane, pos = v.getLaneID(vehicle), float(v.getLanePosition(vehicle))
        # SUMO's position is the front bumper's: start a length behind it (the box centre is
        # behind the front; before the lane's start, the path runs straight back from it)
        pos -= float(v.getLength(vehicle)) + 1.0
        before = max(0.0, -pos)
        pos = max(pos, 0.0)
        route = list(v.getRoute(vehicle))
        i = max(int(v.getRouteIndex(vehicle)), 0)
        vclass = v.getVehicleClass(vehicle)
        parts: list[np.ndarray] = []
        speeds: list[np.ndarray] = []

        def part(points: np.ndarray, on: str) -> None:
            parts.append(points)
            speeds.append(np.full(len(points), self.speed(on)))

        if lane.startswith(":"):  # inside a junction: finish its internal lane(s) first
            part(_from(self.shape(lane), pos, self.api.lane.getLength(lane)), lane)
            chain = self.internal_chain(lane)
            for x in chain[1:]:
                part(self.shape(x), x)
            nxt = self.links(chain[-1])
            if not nxt:
                return RoutePath(np.concatenate(parts), False, np.concatenate(speeds))
            lane = nxt[0][0]
            pos = 0.0
            edge = lane.rsplit("_", 1)[0]
            i = route.index(edge, i) if edge in route[i:] else i + 1
        elif before > 0:
            shape = self.shape(lane)
            d = shape[1] - shape[0]
            n = float(np.hypot(*d))
            if n > 0:
                part(shape[:1] - d / n * before, lane)
        complete = True
        while True:
            shape = self.shape(lane)
            length = self.api.lane.getLength(lane)
            last = i + 1 >= len(route)
            via = None if last else self._via(lane, route[i + 1])
            if not last and via is None:  # change to a lane that connects on
                edge = route[i]
                here = int(lane.rsplit("_", 1)[1])
                options = sorted((abs(int(c.rsplit("_", 1)[1]) - here), c)
                                 for c in self.lanes(edge)
                                 if c != lane and self.allows(c, vclass)
                                 and self._via(c, route[i + 1]) is not None)
                if options:
                    target = options[0][1]
                    part(_cut(shape, pos, length)[0], lane)
                    t_len = self.api.lane.getLength(target)
                    pos = min(pos + change_length, max(t_len - 1.0, pos))
                    lane, shape, length = target, self.shape(target), t_len
                    via = self._via(lane, route[i + 1])
                else:
                    complete = False
            part(_from(shape, pos, length), lane)
            if last or via is None:
                break
            reached, internal = via
            for x in internal:
                part(self.shape(x), x)
            lane, pos, i = reached, 0.0, i + 1
        return RoutePath(np.concatenate(parts), complete and i + 1 >= len(route),
                         np.concatenate(speeds))


def crossing(path: np.ndarray, other: np.ndarray) -> float | None:
    """Arc length (m) along polyline ``other`` ((M, 2)) of its first crossing with polyline
    ``path`` ((K, 2)); None when they do not cross (two lanes that merge only touch at their
    ends, which counts as no crossing)."""
    a0, a1 = path[:-1, None, :], path[1:, None, :]
    b0, b1 = other[None, :-1, :], other[None, 1:, :]
    da, db = a1 - a0, b1 - b0
    den = da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]
    w = b0 - a0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * db[..., 1] - w[..., 1] * db[..., 0]) / den
        u = (w[..., 0] * da[..., 1] - w[..., 1] * da[..., 0]) / den
    eps = 1e-6
    hit = (np.abs(den) > 1e-12) & (t > eps) & (t < 1 - eps) & (u > eps) & (u < 1 - eps)
    if not hit.any():
        return None
    seg = np.hypot(*np.diff(other, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    j = np.nonzero(hit)[1]
    return float(min(arc[k] + u[i, k] * seg[k] for i, k in zip(np.nonzero(hit)[0], j)))


def _from(shape: np.ndarray, pos: float, length: float) -> np.ndarray:
    """The part of lane ``shape`` from lane position ``pos`` (m, SUMO's lane length
    ``length``, which may differ from the shape's geometric length) to its end."""
    point, after = _cut(shape, pos, length)
    return np.concatenate([point, shape[after:]])


def _cut(shape: np.ndarray, pos: float, length: float) -> tuple[np.ndarray, int]:
    """(1, 2) point of lane position ``pos`` on ``shape`` (``length`` as in :func:`_from`)
    and the index of the first shape point past it."""
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(shape, axis=0).T))])
    g = float(np.clip(pos * (arc[-1] / length if length > 0 else 1.0), 0.0, arc[-1]))
    point = np.array([[np.interp(g, arc, shape[:, 0]), np.interp(g, arc, shape[:, 1])]])
    return point, int(np.searchsorted(arc, g, side="right"))
