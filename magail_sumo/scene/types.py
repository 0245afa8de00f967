"""Enumerations of the scene model.

Integer values equal the Waymo Open Motion Dataset enum values, so arrays of them can be
written to and read from the WOMD protos without a lookup.
"""

from __future__ import annotations

from enum import IntEnum

#: s between the steps of a recorded scene (WOMD's 10 Hz) and of every simulation of one:
#: the one definition of the step length (SUMO's ``step-length``, the env's and the metrics' dt)
STEP_LENGTH = 0.1


class ObjectType(IntEnum):
    """Kind of a tracked road user."""

    UNSET = 0
    VEHICLE = 1
    PEDESTRIAN = 2
    CYCLIST = 3
    OTHER = 4


class LaneType(IntEnum):
    """Kind of a lane centre line."""

    UNDEFINED = 0
    FREEWAY = 1
    SURFACE_STREET = 2
    BIKE_LANE = 3


class RoadLineType(IntEnum):
    """Painted line type (also the type of a lane's boundary segment)."""

    UNKNOWN = 0
    BROKEN_SINGLE_WHITE = 1
    SOLID_SINGLE_WHITE = 2
    SOLID_DOUBLE_WHITE = 3
    BROKEN_SINGLE_YELLOW = 4
    BROKEN_DOUBLE_YELLOW = 5
    SOLID_SINGLE_YELLOW = 6
    SOLID_DOUBLE_YELLOW = 7
    PASSING_DOUBLE_YELLOW = 8


class RoadEdgeType(IntEnum):
    """Physical road boundary type."""

    UNKNOWN = 0
    BOUNDARY = 1  # curb or rail with no traffic beyond it
    MEDIAN = 2  # separates the road from opposing traffic


class SignalState(IntEnum):
    """State of a traffic signal for one controlled lane."""

    UNKNOWN = 0
    ARROW_STOP = 1
    ARROW_CAUTION = 2
    ARROW_GO = 3
    STOP = 4
    CAUTION = 5
    GO = 6
    FLASHING_STOP = 7
    FLASHING_CAUTION = 8


class Difficulty(IntEnum):
    """Prediction difficulty of a track to predict."""

    NONE = 0
    LEVEL_1 = 1
    LEVEL_2 = 2
