"""Configuration of :class:`~magail_sumo.env.driving_env.SumoDrivingEnv`."""

from __future__ import annotations

from dataclasses import dataclass, field

from magail_sumo.sensors.observation import ObservationConfig
from magail_sumo.sim.dynamics import ACTION_LAYOUTS, BicycleLimits

#: Event names, in the order the first one found becomes ``infos[agent]["reason"]``.
EVENTS: tuple[str, ...] = ("collision", "off_road", "red_light", "destination", "end_of_life")


@dataclass(frozen=True)
class EnvConfig:
    """What the environment controls, how the rest moves and when agents leave.

    :param controlled: ``"all"`` (every vehicle and cyclist in the SUMO routes), ``"sdc"``,
        ``"tracks_to_predict"``, or an int K: the K route vehicles nearest to the SDC at
        ``start_step`` (the SDC included when it is in the routes).
    :param background: ``"log"`` (uncontrolled route vehicles replay their recorded poses and are
        placed there in SUMO) or ``"sumo"`` (SUMO drives them from their departure on).
    :param terminate_on: events that end an agent (``terminated``); the others are only
        reported in infos. ``end_of_life`` (the last recorded step of the agent's track) and
        the end of the scene always truncate.
    :param lane_width: nominal lane width for off-road and red-light rules (m).
    :param off_road_margin: tolerance added to half the lane width for off-road (m).
    :param destination_radius: distance to the last recorded position that counts as reached (m).
    :param start_step: log step at which episodes start.
    :param max_steps: steps per episode (None: until the end of the scene log).
    :param render_size: (height, width) of :meth:`render` frames in pixels.
    :param sumo_seed: added to the reset seed to seed SUMO.
    :param action_layout: order of the normalised action: ``"accel_steer"`` or the seed's
        ``"steer_throttle"``.
    """

    controlled: str | int = "all"
    background: str = "log"
    terminate_on: tuple[str, ...] = ("collision", "off_road", "red_light", "destination")
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    limits: BicycleLimits = field(default_factory=BicycleLimits)
    lane_width: float = 3.7
    off_road_margin: float = 1.0
    destination_radius: float = 2.0
    start_step: int = 0
    max_steps: int | None = None
    render_size: tuple[int, int] = (512, 512)
    sumo_seed: int = 0
    action_layout: str = "accel_steer"

    def __post_init__(self) -> None:
        if self.action_layout not in ACTION_LAYOUTS:
            raise ValueError(f"action_layout must be one of {ACTION_LAYOUTS}, "
                             f"got {self.action_layout!r}")
        if not (self.controlled in ("all", "sdc", "tracks_to_predict")
                or (isinstance(self.controlled, int) and self.controlled > 0)):
            raise ValueError("controlled must be 'all', 'sdc', 'tracks_to_predict' or a positive "
                             f"int, got {self.controlled!r}")
        if self.background not in ("log", "sumo"):
            raise ValueError(f"background must be 'log' or 'sumo', got {self.background!r}")
        bad = set(self.terminate_on) - set(EVENTS)
        if bad:
            raise ValueError(f"unknown events in terminate_on: {sorted(bad)}")
