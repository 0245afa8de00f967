"""Static road map of a scene: lanes, lines, edges, signs and area features.

All coordinates are metres in the scene frame; polylines are (P, 3) float64 arrays of x, y, z.
Feature ids are unique across all kinds of a map (as in WOMD).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .base import ArrayDataclass, frozen_array
from .types import LaneType, RoadEdgeType, RoadLineType

MPH_TO_MPS = 0.44704


def _points(values: object, owner: str) -> np.ndarray:
    try:
        return frozen_array(np.reshape(values, (-1, 3)) if np.size(values) else np.zeros((0, 3)),
                            np.float64, (-1, 3))
    except ValueError as exc:
        raise ValueError(f"{owner}: {exc}") from None


@dataclass(frozen=True, eq=False)
class BoundarySegment(ArrayDataclass):
    """A stretch of a lane bounded by one road line or road edge.

    :param lane_start_index, lane_end_index: indices into the lane polyline (inclusive).
    :param boundary_feature_id: id of the road line / road edge (0 when unset).
    :param boundary_type: :class:`RoadLineType` of the boundary (UNKNOWN for a road edge).
    """

    lane_start_index: int
    lane_end_index: int
    boundary_feature_id: int
    boundary_type: RoadLineType = RoadLineType.UNKNOWN


@dataclass(frozen=True, eq=False)
class LaneNeighbor(ArrayDataclass):
    """A same-direction lane adjacent to part of a lane.

    Indices are into the polylines of this lane (``self_*``) and of the neighbour (``neighbor_*``).
    """

    feature_id: int
    self_start_index: int
    self_end_index: int
    neighbor_start_index: int
    neighbor_end_index: int
    boundaries: tuple[BoundarySegment, ...] = ()


@dataclass(frozen=True, eq=False)
class Lane(ArrayDataclass):
    """A lane centre line.

    :param polyline: (P, 3) centre line in driving direction.
    :param speed_limit_mph: recorded speed limit in mph as stored by WOMD (0 = unknown);
        :attr:`speed_limit` gives m/s.
    :param interpolating: True for lanes that interpolate between others (e.g. in junctions).
    :param entry_lanes, exit_lanes: ids of predecessor / successor lanes.
    """

    id: int
    polyline: np.ndarray
    type: LaneType = LaneType.UNDEFINED
    speed_limit_mph: float = 0.0
    interpolating: bool = False
    entry_lanes: tuple[int, ...] = ()
    exit_lanes: tuple[int, ...] = ()
    left_neighbors: tuple[LaneNeighbor, ...] = ()
    right_neighbors: tuple[LaneNeighbor, ...] = ()
    left_boundaries: tuple[BoundarySegment, ...] = ()
    right_boundaries: tuple[BoundarySegment, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "polyline", _points(self.polyline, f"lane {self.id}"))

    @property
    def speed_limit(self) -> float:
        """Speed limit in m/s (0 = unknown)."""
        return self.speed_limit_mph * MPH_TO_MPS


@dataclass(frozen=True, eq=False)
class RoadLine(ArrayDataclass):
    """A painted line; ``polyline`` is (P, 3)."""

    id: int
    polyline: np.ndarray
    type: RoadLineType = RoadLineType.UNKNOWN

    def __post_init__(self) -> None:
        object.__setattr__(self, "polyline", _points(self.polyline, f"road line {self.id}"))


@dataclass(frozen=True, eq=False)
class RoadEdge(ArrayDataclass):
    """A physical road boundary; ``polyline`` is (P, 3)."""

    id: int
    polyline: np.ndarray
    type: RoadEdgeType = RoadEdgeType.UNKNOWN

    def __post_init__(self) -> None:
        object.__setattr__(self, "polyline", _points(self.polyline, f"road edge {self.id}"))


@dataclass(frozen=True, eq=False)
class StopSign(ArrayDataclass):
    """A stop sign at ``position`` (3,) controlling the lanes ``lanes``."""

    id: int
    lanes: tuple[int, ...]
    position: np.ndarray

    def __post_init__(self) -> None:
        pos = _points(self.position, f"stop sign {self.id}")
        if pos.shape[0] != 1:
            raise ValueError(f"stop sign {self.id}: position must be one point, got {pos.shape[0]}")
        object.__setattr__(self, "position", frozen_array(pos[0], np.float64))


@dataclass(frozen=True, eq=False)
class AreaFeature(ArrayDataclass):
    """A closed polygon (P, 3); the last point connects back to the first."""

    id: int
    polygon: np.ndarray

    def __post_init__(self) -> None:
        kind = type(self).__name__.lower()
        object.__setattr__(self, "polygon", _points(self.polygon, f"{kind} {self.id}"))


class Crosswalk(AreaFeature):
    """Pedestrian crossing area."""


class SpeedBump(AreaFeature):
    """Speed bump area."""


class Driveway(AreaFeature):
    """Driveway entrance area."""


#: Map feature kinds, in the order used for counting and writing.
FEATURE_KINDS: tuple[str, ...] = (
    "lane", "road_line", "road_edge", "stop_sign", "crosswalk", "speed_bump", "driveway",
)


@dataclass(frozen=True, eq=False)
class RoadMap(ArrayDataclass):
    """All static map features of a scene, grouped by kind (recorded order within a kind)."""

    lanes: tuple[Lane, ...] = ()
    road_lines: tuple[RoadLine, ...] = ()
    road_edges: tuple[RoadEdge, ...] = ()
    stop_signs: tuple[StopSign, ...] = ()
    crosswalks: tuple[Crosswalk, ...] = ()
    speed_bumps: tuple[SpeedBump, ...] = ()
    driveways: tuple[Driveway, ...] = ()
    _by_id: dict = field(default=None, init=False, repr=False, compare=False)  # type: ignore[assignment]

    def features(self, kind: str) -> tuple:
        """Features of one kind of :data:`FEATURE_KINDS`."""
        return getattr(self, kind + "s")

    def count_by_kind(self) -> dict[str, int]:
        """Number of features of each kind."""
        return {kind: len(self.features(kind)) for kind in FEATURE_KINDS}

    def feature(self, feature_id: int):
        """The feature with id ``feature_id`` (any kind); KeyError when absent."""
        if self._by_id is None:
            object.__setattr__(
                self, "_by_id", {f.id: f for kind in FEATURE_KINDS for f in self.features(kind)}
            )
        return self._by_id[feature_id]

    def lane(self, lane_id: int) -> Lane:
        """The lane with id ``lane_id``; KeyError when absent or not a lane."""
        feat = self.feature(lane_id)
        if not isinstance(feat, Lane):
            raise KeyError(lane_id)
        return feat
