"""Configuration of :class:`~magail_sumo.env.driving_env.SumoDrivingEnv`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from magail_sumo.config import check, check_positive, show

from magail_sumo.sensors.observation import ObservationConfig
from magail_sumo.sim.dynamics import ACTION_LAYOUTS, BicycleLimits

from .guard import GuardConfig

#: Event names, in the order the first one found becomes ``infos[agent]["reason"]``.
EVENTS: tuple[str, ...] = ("collision", "off_road", "red_light", "destination", "end_of_life")
#: named controlled sets (``EnvConfig.controlled``; an int K is the other choice)
CONTROLLED: tuple[str, ...] = ("all", "sdc", "tracks_to_predict", "scored")
#: scene envs a pool worker keeps built (the most recent; :class:`~magail_sumo.env.scene_pool.
#: PoolCursor`): a recorded scene's env holds about 3.5 MiB (the 10 womd14 train scenes: 0.1 to
#: 7.4 MiB), and a rebuild re-reads the scene file and its bundle (20 to 100 ms), so a shard of up
#: to this many scenes builds each once
SCENE_CACHE = 16
#: ``EnvConfig.off_road_rule`` choices
OFF_ROAD_RULES: tuple[str, ...] = ("lane", "road_edge")
#: ``EnvConfig.start_window`` choices
START_WINDOWS: tuple[str, ...] = ("fixed", "random")


@dataclass(frozen=True)
class EnvConfig:
    """What the environment controls, how the rest moves and when agents leave.

    :param controlled: ``"all"`` (every vehicle and cyclist in the SUMO routes), ``"sdc"``,
        ``"tracks_to_predict"``, ``"scored"`` (the SDC plus the tracks to predict: the agents
        WOSAC scores), or an int K: the K route vehicles nearest to the SDC at the episode's
        start step (the SDC included when it is in the routes); always restricted to the
        route vehicles, less those parked in a space off the lanes (scenery SUMO holds where it
        was recorded, ``SceneBundle.spaces``) unless the SDC or a track to predict.
    :param background: ``"log"`` (uncontrolled route vehicles replay their recorded poses and are
        placed there in SUMO) or ``"sumo"`` (SUMO drives them from their departure on).
    :param terminate_on: events that end an agent (``terminated``); the others are only
        reported in infos. ``end_of_life`` (the last recorded step of the agent's track) and
        the end of the scene always truncate.
    :param lane_width: nominal lane width for off-road and red-light rules (m).
    :param off_road_rule: ``"lane"`` (the box centre far from every lane centre line) or
        ``"road_edge"`` (a box corner beyond the road edges: WOSAC's off-road test, the lane
        rule in scenes without road edges) (:mod:`magail_sumo.env.events`).
    :param off_road_margin: tolerance added to half the lane width for off-road (m).
    :param off_road_edge_margin: with ``off_road_rule: road_edge``, how far (m) a corner may
        lie beyond the road edge (0: WOSAC's test).
    :param destination_radius: distance to the last recorded position that counts as reached (m).
    :param start_window: where episodes start: ``"fixed"`` (at ``start_step``) or
        ``"random"`` (each episode at a step drawn uniformly from the window starts,
        :func:`window_starts`, and run for ``max_steps`` steps; ``max_steps`` must be set and
        ``start_step`` left 0). A start ``t > 0`` replays log steps ``0 .. t`` as the
        agents' history (in SUMO, and their previous action in the first observation).
    :param min_history: with ``start_window: random``, the earliest start step (log steps
        before it are history; WOMD's current step is 10, WOSAC's history).
    :param start_step: log step at which episodes start (``start_window: fixed``).
    :param max_steps: steps per episode (None: until the end of the scene log; required with
        ``start_window: random``, where it is the window length, e.g. WOSAC's 80).
    :param render_size: (height, width) of :meth:`render` frames in pixels.
    :param sumo_seed: added to the reset seed to seed SUMO.
    :param action_layout: the normalised action: ``"accel_steer"``, the seed's
        ``"steer_throttle"``, or route-relative ``"accel_offset"`` (acceleration and lateral
        offset from the agent's recorded route, steered by pure pursuit:
        :mod:`magail_sumo.sim.tracking`).
    :param fcd_dir: folder for SUMO FCD recordings of episodes (with a ``.sumocfg`` replaying
        each in ``sumo-gui``; :mod:`magail_sumo.sim.fcd`); None: none.
    :param fcd_every: with ``fcd_dir``, record episode 0, N, 2N, ... of each env instance
        (``<scenario>-<pid>-ep<k>.fcd.xml``); 0: none.
    :param sumo_mirror: with ``background: log``, mirror the episode in SUMO (the agents and
        the log-replayed vehicles placed there each step, as :class:`~magail_sumo.env.
        driving_env.SumoDrivingEnv` always did). Nothing an agent observes, no event and no
        info reads SUMO then (the log and the bicycle model drive everything, the sensors,
        collisions and red lights work on the recorded map and signals), so ``false`` runs
        the same episodes, bit for bit (``tests/test_env.py``), without starting or stepping
        SUMO: for training throughput. Must stay ``true`` with ``background: sumo``, whose
        vehicles SUMO drives.
    :param guard: the gap guard on the agents' accelerations (:mod:`magail_sumo.env.guard`;
        off by default).
    :param end_of_life: an agent ends at the last recorded step of its track (truncation,
        reason ``end_of_life``: its log has nothing later to imitate); False: it drives on to
        the end of the episode, as WOSAC simulates every object valid at the current step for
        all 80 steps (evaluation sets it: an agent removed earlier would vanish from the others'
        world while its scored trajectory goes on at constant velocity through them).
    """

    controlled: str | int = "all"
    background: str = "log"
    terminate_on: tuple[str, ...] = ("collision", "off_road", "red_light", "destination")
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    limits: BicycleLimits = field(default_factory=BicycleLimits)
    lane_width: float = 3.7
    off_road_rule: str = "lane"
    off_road_margin: float = 1.0
    off_road_edge_margin: float = 0.0
    destination_radius: float = 2.0
    start_window: str = "fixed"
    min_history: int = 10
    start_step: int = 0
    max_steps: int | None = None
    render_size: tuple[int, int] = (512, 512)
    sumo_seed: int = 0
    action_layout: str = "accel_steer"
    fcd_dir: str | None = None
    fcd_every: int = 0
    sumo_mirror: bool = True
    guard: GuardConfig = field(default_factory=GuardConfig)
    end_of_life: bool = True

    def __post_init__(self) -> None:
        check(self.action_layout in ACTION_LAYOUTS, "action_layout",
              f"must be one of {ACTION_LAYOUTS}, got {show(self.action_layout)}")
        check(self.controlled in CONTROLLED
              or (isinstance(self.controlled, int) and not isinstance(self.controlled, bool)
                  and self.controlled > 0), "controlled",
              f"must be one of {list(CONTROLLED)} or a positive int, got "
              f"{show(self.controlled)}")
        check(self.background in ("log", "sumo"), "background",
              f"must be 'log' or 'sumo', got {show(self.background)}")
        check(isinstance(self.sumo_mirror, bool), "sumo_mirror",
              f"must be true or false, got {show(self.sumo_mirror)}")
        check(isinstance(self.end_of_life, bool), "end_of_life",
              f"must be true or false, got {show(self.end_of_life)}")
        check(self.sumo_mirror or self.background == "log", "sumo_mirror",
              "must be true with background: sumo (SUMO drives the background vehicles)")
        bad = set(self.terminate_on) - set(EVENTS)
        check(not bad, "terminate_on", f"unknown events {sorted(bad)} (events: {list(EVENTS)})")
        check(isinstance(self.fcd_every, int) and not isinstance(self.fcd_every, bool)
              and self.fcd_every >= 0, "fcd_every",
              f"must be an int >= 0 (0: no recording), got {show(self.fcd_every)}")
        check(self.fcd_dir is None or (isinstance(self.fcd_dir, str) and self.fcd_dir != ""),
              "fcd_dir", f"must be a folder name or null, got {show(self.fcd_dir)}")
        check(self.off_road_rule in OFF_ROAD_RULES, "off_road_rule",
              f"must be one of {list(OFF_ROAD_RULES)}, got {show(self.off_road_rule)}")
        check(isinstance(self.off_road_edge_margin, (int, float))
              and math.isfinite(self.off_road_edge_margin), "off_road_edge_margin",
              f"must be a number (m), got {show(self.off_road_edge_margin)}")
        check_positive(self, "lane_width")
        check_positive(self, "off_road_margin", "destination_radius", "start_step",
                       allow_zero=True)
        check(self.max_steps is None or self.max_steps >= 1, "max_steps",
              f"must be >= 1 (or null: to the end of the log), got {self.max_steps}")
        check(self.start_window in START_WINDOWS, "start_window",
              f"must be one of {list(START_WINDOWS)}, got {show(self.start_window)}")
        check(isinstance(self.min_history, int) and not isinstance(self.min_history, bool)
              and self.min_history >= 0, "min_history",
              f"must be an int >= 0, got {show(self.min_history)}")
        if self.start_window == "random":
            check(self.max_steps is not None, "max_steps",
                  "must be set with start_window 'random' (the window length, e.g. 80), got null")
            check(self.start_step == 0, "start_step",
                  "is not used with start_window 'random' (episodes start at a random step >= "
                  f"min_history): leave it 0, got {show(self.start_step)}")
        check(len(self.render_size) == 2 and min(self.render_size) >= 1, "render_size",
              f"must be (height, width) >= 1, got {show(self.render_size)}")
        lim = self.limits
        for name in ("max_accel", "max_brake", "max_steer", "max_speed", "max_reverse_speed",
                     "max_offset", "max_steer_rate"):
            v = getattr(lim, name)
            zero_ok = name in ("max_reverse_speed", "max_steer_rate")
            ok = math.isfinite(v) and (v >= 0 if zero_ok else v > 0)
            check(ok, f"limits.{name}", f"must be {'>= 0' if zero_ok else '> 0'}"
                  f", got {show(v)}")
        obs = self.observation
        for name in ("lidar", "side", "lane_line"):
            beam = getattr(obs, name)
            key = f"observation.{name}"
            check(0 <= beam.beams <= 4096, f"{key}.beams",
                  f"must be in [0, 4096], got {show(beam.beams)}")
            check(math.isfinite(beam.range) and beam.range > 0, f"{key}.range",
                  f"must be > 0, got {show(beam.range)}")
            check(0 < beam.fov <= 2 * math.pi + 1e-9, f"{key}.fov",
                  f"must be in (0, 2 pi], got {show(beam.fov)}")
        check(math.isfinite(obs.lane_cell) and obs.lane_cell > 0, "observation.lane_cell",
              f"must be > 0, got {show(obs.lane_cell)}")


def window_starts(config: EnvConfig, num_steps: int) -> tuple[int, int]:
    """The inclusive range ``(lo, hi)`` of episode start steps in a scene of ``num_steps`` log
    steps (``T``).

    ``start_window: fixed``: ``lo = hi = min(start_step, T - 1)``. ``random``: ``lo =
    min(min_history, T - 2)`` and ``hi = max(lo, T - 1 - max_steps)``, so a window of
    ``max_steps`` steps fits in the log after ``min_history`` steps of history; when the scene
    is too short for that, the start is ``lo`` and the episode ends with the log (fewer than
    ``max_steps`` steps). A scene of one step has ``lo = hi = 0``.
    """
    t_last = num_steps - 1
    if config.start_window == "fixed":
        s = max(0, min(config.start_step, t_last))
        return s, s
    lo = max(0, min(config.min_history, num_steps - 2))
    steps = config.max_steps if config.max_steps is not None else 1
    return lo, max(lo, t_last - steps)


def draw_start(config: EnvConfig, num_steps: int, rng: np.random.Generator) -> int:
    """One episode start step, uniform over :func:`window_starts` (``rng`` is drawn from only
    with ``start_window: random``)."""
    lo, hi = window_starts(config, num_steps)
    return lo if config.start_window == "fixed" else int(rng.integers(lo, hi + 1))
