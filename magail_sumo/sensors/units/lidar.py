"""Lidar: beams against the other road users' oriented boxes (``ObservationConfig.lidar``,
80 beams / 30 m by default); an agent never sees its own box (nor, in a batched env, another
world's boxes). One numba kernel over all agents (:func:`~magail_sumo.sensors.raycast.
cast_boxes`): boxes beyond range are skipped whole, and only the edges facing the agent are
cast."""

from __future__ import annotations

import numpy as np

from ..base import SensorInput, register
from ..raycast import cast_boxes
from ..worlds import BoxGroups
from .beams import BeamSensor


@register
class Lidar(BeamSensor):
    """``lidar_00`` ..: distance (m) to the first box edge along each beam."""

    name = "lidar"
    spec = "lidar"

    def read(self, inp: SensorInput) -> np.ndarray:
        boxes = inp.boxes
        starts, ends, _ = boxes.edges()
        # a batched env's boxes come grouped by world; one world's are one group
        groups = boxes.groups if boxes.groups is not None else BoxGroups.single(len(boxes))
        return cast_boxes(inp.origins, self.angles(inp), self.beams.range, starts, ends,
                          inp.index, groups)

