"""Ray sensors: ``B`` beams of a :class:`~magail_sumo.sensors.config.BeamSpec` (the config
field named by the sensor), readings in metres to the first hit, ``range`` when nothing is hit
(:mod:`magail_sumo.sensors.raycast`). Beam ``j`` points at ``-fov/2 + j·fov/B`` rad from the
heading (``fov = 2·pi``: beam 0 straight ahead, counter-clockwise from there)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from magail_sumo.scene import RoadMap

from ..base import Sensor, SensorInput, SensorMaps, bounded
from ..raycast import SegmentGrid, polyline_segments


class BeamSensor(Sensor):
    """A ray sensor: features ``<spec>_00`` .. one per beam, bounds [0, range].

    :cvar spec: the :class:`ObservationConfig` field holding the beams (also the name prefix).
    """

    spec: ClassVar[str]

    def __init__(self, config, maps: SensorMaps) -> None:
        super().__init__(config, maps)
        self.beams = getattr(config, self.spec)
        self.offsets = self.beams.offsets()

    @classmethod
    def names(cls, config) -> list[str]:
        return [f"{cls.spec}_{j:02d}" for j in range(getattr(config, cls.spec).beams)]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        spec = getattr(config, cls.spec)
        return bounded(spec.beams, 0.0, spec.range)

    def angles(self, inp: SensorInput) -> np.ndarray:
        """(A, B) scene-frame beam angles of the agents (rad)."""
        return inp.yaw[:, None] + self.offsets[None, :]


class MapRaySensor(BeamSensor):
    """A ray sensor against static map polylines, indexed once in a grid of ``range`` m cells."""

    def __init__(self, config, maps: SensorMaps) -> None:
        super().__init__(config, maps)
        self.grid = SegmentGrid.build(*polyline_segments(self.polylines(maps.roadmap)),
                                      cell=max(self.beams.range, 1.0))

    @staticmethod
    def polylines(roadmap: RoadMap) -> list[np.ndarray]:
        """The map polylines the beams hit."""
        raise NotImplementedError

    def read(self, inp: SensorInput) -> np.ndarray:
        return self.grid.cast(inp.origins, self.angles(inp), self.beams.range)
