"""Format-independent scene model: typed, frozen dataclasses over numpy arrays.

Units everywhere: metres, radians, metres/second, seconds; coordinates in the scene frame
of the recording (WOMD's frame: x east-ish, y north-ish, z up, arbitrary origin).
"""

from .roadmap import (
    FEATURE_KINDS, AreaFeature, BoundarySegment, Crosswalk, Driveway, Lane, LaneNeighbor,
    RoadEdge, RoadLine, RoadMap, SpeedBump, StopSign,
)
from .quality import DataQuality, DroppedReference, SourceIds
from .scene import RequiredPrediction, Scene
from .connectivity import infer_lane_connectivity, link_isolated_lanes
from .edit import drop_tracks
from .signals import SignalStates
from .tracks import STATE_FIELDS, Tracks
from .types import Difficulty, LaneType, ObjectType, RoadEdgeType, RoadLineType, SignalState
from .validation import SceneValidationError, validate_scene
from .window import WindowError, choose_tracks_to_predict, window, window_id

__all__ = [
    "FEATURE_KINDS", "STATE_FIELDS", "AreaFeature", "BoundarySegment", "Crosswalk", "DataQuality",
    "Difficulty", "DroppedReference", "Driveway", "Lane", "LaneNeighbor", "LaneType", "ObjectType", "RequiredPrediction",
    "RoadEdge", "RoadEdgeType", "RoadLine", "RoadLineType", "RoadMap", "Scene",
    "SceneValidationError", "SignalState", "SignalStates", "SourceIds", "SpeedBump", "StopSign",
    "Tracks", "WindowError", "choose_tracks_to_predict", "drop_tracks", "infer_lane_connectivity",
    "link_isolated_lanes",
    "validate_scene", "window", "window_id",
]
