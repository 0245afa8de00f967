"""Lane-line detector: beams against the road lines, the painted lane boundaries that WOMD lane
boundaries reference (``ObservationConfig.lane_line``, 10 beams / 3 m by default)."""

from __future__ import annotations

import numpy as np

from magail_sumo.scene import RoadMap

from ..base import register
from .beams import MapRaySensor


@register
class LaneLineDetector(MapRaySensor):
    """``lane_line_00`` ..: distance (m) to the first road line along each beam."""

    name = "lane_line"
    spec = "lane_line"

    @staticmethod
    def polylines(roadmap: RoadMap) -> list[np.ndarray]:
        return [line.polyline for line in roadmap.road_lines]
