"""Settings of the observation: the ray sensors' beams, the layout and the optional features.

The layout names an ordered list of registered sensor units
(:data:`magail_sumo.sensors.base.LAYOUTS`); :mod:`magail_sumo.sensors.observation` documents
the built-in ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .base import LAYOUTS, layout_name

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class BeamSpec:
    """A ray sensor: ``beams`` rays over ``fov`` rad centred on the heading, ``range`` m."""

    beams: int
    range: float
    fov: float = TWO_PI

    def offsets(self) -> np.ndarray:
        """(B,) beam angles relative to the heading (rad)."""
        return -0.5 * self.fov + np.arange(self.beams) * (self.fov / max(self.beams, 1)) \
            if self.fov < TWO_PI else np.arange(self.beams) * (TWO_PI / max(self.beams, 1))


@dataclass(frozen=True)
class ObservationConfig:
    """Sensors and layout of the observation vector (see :mod:`magail_sumo.sensors.observation`).

    :param layout: ``"ego"`` (ego-frame quantities), ``"scene_frame"`` (the MAGAIL4AutoDrive
        observation: 108 values, pose and destination in absolute map coordinates) or a layout
        registered with :func:`~magail_sumo.sensors.base.register_layout`. The deprecated
        ``"seed"`` is read as ``"scene_frame"`` (the config then holds the new name; a one-time
        ``FutureWarning`` says so), so configs, checkpoints and expert data recorded with it
        load and evaluate as before.
    :param lane_cell: grid cell of the lane index (m); lane distances are capped at it.
    :param command: append the route command (one-hot left / straight / right at the next
        junction, :mod:`magail_sumo.sensors.command`) as ``command_left``,
        ``command_straight``, ``command_right``; off by default (the default layout, expert
        data and checkpoints keep their 113 values).
    :param command_lookahead: route distance (m) ahead of the agent at which the command reads
        the route's turn.
    :param route_points: route look-ahead: distances (m, increasing, > 0) along the agent's
        recorded route ahead of its progress point at which the route's position is appended
        in the ego frame, as ``route_x_<d>``, ``route_y_<d>`` (m) per distance ``d``
        (:meth:`magail_sumo.sensors.command.RouteCommands.ahead`); empty (the default): none.
        The route is the recorded path (as the route command's and SUMO's routes), so this is
        navigation intent from the log, not a prediction of the policy's own.
    :param leader: append the leader sensor (:mod:`magail_sumo.sensors.units.leader`):
        ``leader_gap`` (m) and ``leader_closing`` (m/s) to the nearest road user ahead in the
        agent's path; off by default.
    :param leader_range: how far ahead the leader sensor looks (m); its gap reads this when
        nobody is ahead.
    :param light_gap: append ``light_gap``: the distance (m) to the stop line of the
        ``light`` the agent sees (:mod:`magail_sumo.sensors.units.light_gap`); off by default.
    :param give_way: append ``give_way_gap`` and ``give_way_time``: the distance (m) to the
        conflict point of the next road user the agent must give way to at a junction ahead,
        and the time (s) that road user needs to reach it (SUMO's junction model, so a city
        feature; :mod:`magail_sumo.sensors.units.give_way`); off by default.
    :param give_way_conflicts: inside a junction, where SUMO names no foe and the city env
        reads the give-way conflict from the network, count only the road users whose
        connection crosses the agent's (centrelines, its internal lanes up to the lane after
        the junction) or leads onto the same lane, and of those on an approach lane only the
        ones whose route takes such a connection (SUMO's junction model lets its drivers
        go past the others: on cologne8 a left turn waiting inside signal ``26110729`` read
        the oncoming right and left turners); off by default: every road user on the waiting
        place's foe lanes counts. The layout is the same either way.
    :param route_stop: append ``route_stop_gap``: the distance (m) along the agent's recorded
        route to its end where the recorded driver stands still at its end (its last valid
        state), capped at 50 m, which also reads where the route does not end standing and in
        a city (:mod:`magail_sumo.sensors.units.route_stop`); off by default.
    :param path_leader: append ``path_leader_gap`` (m) and ``path_leader_closing`` (m/s): the
        nearest road user in the agent's lane corridor ahead along its reference path, within
        ``leader_range`` (:mod:`magail_sumo.sensors.units.path_leader`; straight ahead for an
        agent without one); off by default.
    :param speed_limit: append ``speed_limit``, ``speed_limit_ahead`` (m/s) and
        ``speed_limit_gap`` (m): the road's speed limit at the agent's place on its reference
        path and the lowest one within ``leader_range`` ahead with its distance
        (:mod:`magail_sumo.sensors.units.speed_limit`; 0 where unknown); off by default.
    :param speed_factor: append ``speed_factor``: the agent's own desired speed as a multiple
        of the road's (a city: the factor SUMO drew for the vehicle from its type's
        ``speedFactor`` distribution; a recorded scene: 1, as the recorded driver's wish is not
        observed; :mod:`magail_sumo.sensors.units.speed_factor`); off by default.
    """

    lidar: BeamSpec = field(default_factory=lambda: BeamSpec(80, 30.0))
    side: BeamSpec = field(default_factory=lambda: BeamSpec(10, 8.0))
    lane_line: BeamSpec = field(default_factory=lambda: BeamSpec(10, 3.0))
    layout: str = "ego"
    lane_cell: float = 10.0
    command: bool = False
    command_lookahead: float = 30.0
    route_points: tuple[float, ...] = ()
    leader: bool = False
    leader_range: float = 50.0
    light_gap: bool = False
    give_way: bool = False
    give_way_conflicts: bool = False
    path_leader: bool = False
    speed_limit: bool = False
    route_stop: bool = False
    speed_factor: bool = False

    def __post_init__(self) -> None:
        layout = layout_name(self.layout)
        if layout != self.layout:  # a deprecated name: the config holds the name now
            object.__setattr__(self, "layout", layout)
        if self.layout not in LAYOUTS:
            raise ValueError(f"observation layout must be one of "
                             f"{', '.join(map(repr, LAYOUTS))}, got {self.layout!r}")
        if not (np.isfinite(self.command_lookahead) and self.command_lookahead > 0):
            raise ValueError(f"observation command_lookahead must be > 0 m, got "
                             f"{self.command_lookahead!r}")
        if not (np.isfinite(self.leader_range) and self.leader_range > 0):
            raise ValueError(f"observation leader_range must be > 0 m, got "
                             f"{self.leader_range!r}")
        pts = np.asarray(self.route_points, np.float64)
        if pts.size and not (np.isfinite(pts).all() and pts[0] > 0 and np.all(np.diff(pts) > 0)):
            raise ValueError(f"observation route_points must be increasing distances > 0 m, "
                             f"got {list(self.route_points)!r}")
