"""String vocabularies of the ScenarioNet / MetaDrive scenario dict (Waymo converter flavour)."""

from __future__ import annotations

from magail_sumo.scene import LaneType, ObjectType, RoadEdgeType, RoadLineType, SignalState

OBJECT_TYPES: dict[ObjectType, str] = {
    ObjectType.UNSET: "UNSET", ObjectType.VEHICLE: "VEHICLE", ObjectType.PEDESTRIAN: "PEDESTRIAN",
    ObjectType.CYCLIST: "CYCLIST", ObjectType.OTHER: "OTHER",
}
LANE_TYPES: dict[LaneType, str] = {
    LaneType.UNDEFINED: "LANE_UNKNOWN", LaneType.FREEWAY: "LANE_FREEWAY",
    LaneType.SURFACE_STREET: "LANE_SURFACE_STREET", LaneType.BIKE_LANE: "LANE_BIKE_LANE",
}
#: Road-line feature types. ScenarioNet's Waymo converter writes "UNKNOWN" for an unknown road
#: line *and* an unknown road edge; we write MetaDrive's "UNKNOWN_LINE" for lines so the two stay
#: apart, and read a bare "UNKNOWN" feature as a road edge (as MetaDrive treats it).
ROAD_LINE_TYPES: dict[RoadLineType, str] = {
    t: ("UNKNOWN_LINE" if t is RoadLineType.UNKNOWN else f"ROAD_LINE_{t.name}") for t in RoadLineType
}
#: ``boundary_type`` strings of lane boundary segments ("UNKNOWN" for type 0, as ScenarioNet).
BOUNDARY_TYPES: dict[RoadLineType, str] = {
    t: ("UNKNOWN" if t is RoadLineType.UNKNOWN else f"ROAD_LINE_{t.name}") for t in RoadLineType
}
ROAD_EDGE_TYPES: dict[RoadEdgeType, str] = {
    RoadEdgeType.UNKNOWN: "UNKNOWN", RoadEdgeType.BOUNDARY: "ROAD_EDGE_BOUNDARY",
    RoadEdgeType.MEDIAN: "ROAD_EDGE_MEDIAN",
}
SIGNAL_STATES: dict[SignalState, str] = {s: f"LANE_STATE_{s.name}" for s in SignalState}
STOP_SIGN, CROSSWALK, SPEED_BUMP, DRIVEWAY = "STOP_SIGN", "CROSSWALK", "SPEED_BUMP", "DRIVEWAY"
TRAFFIC_LIGHT = "TRAFFIC_LIGHT"

# Spellings only read (older MetaDrive layout, non-WOMD ScenarioNet datasets); we write the ones above.
#: MetaDrive object types without a WOMD counterpart, read as ObjectType.OTHER (nuScenes, nuPlan:
#: cones, barriers and other static objects).
OTHER_OBJECT_TYPES = ("TRAFFIC_CONE", "TRAFFIC_BARRIER", "TRAFFIC_OBJECT")
#: Map feature type aliases -> the spelling above.
FEATURE_TYPE_ALIASES = {"CROSS_WALK": CROSSWALK, "ROAD_LINE_UNKNOWN": "UNKNOWN_LINE",
                        "ROAD_EDGE_UNKNOWN": "UNKNOWN", "ROAD_EDGE_SIDEWALK": "ROAD_EDGE_BOUNDARY",
                        # nuScenes lane connectors (across junctions), as ScenarioNet's nuScenes
                        # converter names them: read as surface-street lanes (marking them
                        # interpolating cut route rates from 0.6 to 0.2 on trainval scene-0270)
                        "LANE_SURFACE_UNSTRUCTURE": "LANE_SURFACE_STREET"}


def inverse(mapping: dict) -> dict:
    return {v: k for k, v in mapping.items()}
