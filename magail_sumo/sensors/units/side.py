"""Side detector: beams against the road edges (``ObservationConfig.side``, 10 beams / 8 m by
default)."""

from __future__ import annotations

import numpy as np

from magail_sumo.scene import RoadMap

from ..base import register
from .beams import MapRaySensor


@register
class SideDetector(MapRaySensor):
    """``side_00`` ..: distance (m) to the first road edge along each beam."""

    name = "side"
    spec = "side"

    @staticmethod
    def polylines(roadmap: RoadMap) -> list[np.ndarray]:
        return [e.polyline for e in roadmap.road_edges]
