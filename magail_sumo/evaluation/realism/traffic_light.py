"""Red-light violations (the WOSAC ``traffic_light_violation`` feature): the rule lives with the
scene model, :mod:`magail_sumo.scene.traffic_light` (the recorded data's signal check uses it
too); re-exported here beside the other realism features."""

from magail_sumo.scene.traffic_light import SignalLanes, red_light_violation, signal_lanes

__all__ = ["SignalLanes", "red_light_violation", "signal_lanes"]
