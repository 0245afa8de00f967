"""PettingZoo ``ParallelEnv`` over a plain SUMO scenario (a city's net and demand, no recording).

The city counterpart of :class:`~magail_sumo.env.driving_env.SumoDrivingEnv`: every vehicle of
the SUMO demand that departs (or is present when the episode starts) becomes an agent with
probability ``control_fraction`` (seeded); the rest stay SUMO-driven background traffic that
reacts to the agents (as do vehicles of other classes than ``agent_classes``, vehicles with
stops, and vehicles whose route turns tighter than a car can, ``agent_tight_turns``). Agents
move by the kinematic bicycle model from normalised actions in [-1, 1]² (``[accel, steer]``, or
route-relative ``[accel, offset]`` in the ``accel_offset`` layout: steered along their route's
lanes, :mod:`magail_sumo.sim.tracking`) and are placed in SUMO with ``moveToXY``; they see the
same sensors as in recorded scenes, with the map taken from the SUMO network
(:func:`~magail_sumo.sim.sumo_map.network_map`) and the current-lane
light from SUMO's signal state. Each agent's route, from where it joined, is its reference
path (:func:`~magail_sumo.sim.lane_graph.LaneGraph.route_path`: the lane centrelines of its
SUMO route through the junctions' internal lanes); the route look-ahead and route command
features read it (``observation.route_points``, ``observation.command``). Their destination
is the end of that path.

An episode may start from a warmed-up network: ``warmup_s`` seconds are first simulated by
SUMO alone (1 s steps), the state is saved once and every reset loads it, so agents start in
realistic traffic. Steps are 0.1 s.

Events ending an agent (``infos[agent]["reason"]``): ``collision`` (oriented-box overlap with
any other vehicle), ``off_road`` (box centre farther than ``lane_width / 2 + margin`` from every
lane, junction lanes included), ``red_light`` (the agent passes the stop line of a red signal
that was its next signal at the step's start), ``destination`` (within ``destination_radius``
of its route's end); truncation reasons: ``arrived`` (SUMO took the vehicle out: it reached
its route's end) and ``end_of_episode`` (``max_steps`` reached). Rewards are 0, or with
``progress_reward`` that many per metre an agent moved along its route in the step.

The step runs the stages of :class:`~magail_sumo.env.step.FleetEnv` over the agents'
:class:`~magail_sumo.env.fleet.Fleet` state (rows appended as agents join), and ``infos`` follow
both envs' contract (:mod:`magail_sumo.env.step`): ``step`` (steps since reset), ``events``,
``reason``, ``collided_with`` (the other vehicle's SUMO id; ``""`` when none),
``nan_actions``, ``clipped_actions`` and ``state`` (the agent's bicycle state
``(x, y, yaw, speed)`` after the step, scene frame = SUMO's network frame).
"""

from __future__ import annotations

import hashlib
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from magail_sumo.errors import MagailSumoError
from magail_sumo.sensors.command import command_index, one_hot
from magail_sumo.sensors.lanes import LaneQuery
from magail_sumo.sensors.observation import (
    Boxes, EgoState, ObservationConfig, PathAhead, SensorSuite, observation_bounds,
)
from magail_sumo.sensors.units.give_way import COMMITTED, GIVE_WAY_RANGE
from magail_sumo.sensors.units.light_gap import LIGHT_RANGE
from magail_sumo.sensors.units.path_leader import along_path
from magail_sumo.sim import dynamics
from magail_sumo.sim.fcd import FcdRecorder, ReplayFiles, write_replay
from magail_sumo.sim.lane_graph import LaneGraph, crossing
from magail_sumo.sim.paths import TURN_ARC, Paths, tightest_turn
from magail_sumo.sim.saved_state import mend_routes
from magail_sumo.sim.tracking import trials
from magail_sumo.sim.session import STEP_LENGTH, SessionConfig, SumoSession
from magail_sumo.sim.sumo_config import (SumoConfigError, SumoInputs, check_demand, read_config,
                                         scenario_name)
from magail_sumo.sim.sumo_map import NetworkMap, internal_junctions, network_map

from .actions import ACTION_COUNTS
from .guard import GuardConfig
from .fleet import Fleet, resized
from .events import off_road
from .fcd import EpisodeFcd
from .step import END_OF_EPISODE, FleetEnv
from .unblock import FREE, HELD, MUTUAL, STAND_SPEED, release

#: m/s above which a foe at an internal junction counts as coming (a standing one is waiting)
MOVING = 0.5
#: SUMO link states without the right of way (minor, green minor, stop, equal, all-way stop,
#: off-blinking) and with it (green major, major, off-no-signal)
MINOR, MAJOR = frozenset("mgs=wo"), frozenset("GMO")
#: steps between two looks for agents and SUMO's drivers blocking each other (1 s)
UNBLOCK_EVERY = 10

#: Events of the city env, in the order the first one found becomes the reason.
CITY_EVENTS: tuple[str, ...] = ("collision", "off_road", "red_light", "destination")
#: SUMO's vehicle classes (``vClass``)
VEHICLE_CLASSES: tuple[str, ...] = (
    "passenger", "private", "taxi", "hov", "emergency", "authority", "army", "vip",
    "delivery", "truck", "trailer", "coach", "bus", "motorcycle", "moped", "bicycle",
    "scooter", "evehicle", "tram", "rail_urban", "rail", "rail_electric", "rail_fast", "ship",
    "container", "cable_car", "subway", "aircraft", "wheelchair", "drone", "pedestrian",
    "custom1", "custom2")
_LIGHT = {"G": 1, "g": 1, "y": 2, "Y": 2, "r": 3, "R": 3, "u": 3, "s": 3, "o": 0, "O": 0}


def demand_args(demand_scale: float) -> tuple[str, ...]:
    """SUMO's ``--scale`` option for ``CityEnvConfig.demand_scale`` (none at 1): what the env's
    runs and a SUMO-only run of the same window both pass."""
    return () if demand_scale == 1.0 else ("--scale", f"{demand_scale:g}")


@dataclass(frozen=True)
class CityEnvConfig:
    """Settings of :class:`SumoCityEnv`.

    :param control_fraction: share of the demand's vehicles that become agents (0, 1].
    :param warmup_s: seconds SUMO simulates alone before the episode (0: start at the
        scenario's begin time).
    :param max_steps: 0.1-s steps per episode.
    :param terminate_on: events that end an agent (others are only reported in infos).
    :param lane_width: event rule (m).
    :param off_road_margin: event rule (m).
    :param destination_radius: event rule (m).
    :param sumo_seed: added to the reset seed to seed SUMO.
    :param action_layout: ``"accel_steer"``, the seed's ``"steer_throttle"`` or route-relative
        ``"accel_offset"`` (:mod:`magail_sumo.sim.tracking`).
    :param max_agents: at most this many agents alive at once (None: no cap; a fixed number of
        slots for training); a vehicle chosen to be an agent while the cap is reached is
        SUMO-driven until a place frees, then joins mid-trip (first come, first served), so
        the city keeps ``max_agents`` agents while its demand allows.
    :param guard: the gap guard on the agents' accelerations (:mod:`magail_sumo.env.guard`).
    :param agent_classes: SUMO vehicle classes (``vClass`` of a vehicle's type) that may
        become agents; the others (buses, trams, trucks, bicycles, ... by default) stay
        SUMO-driven. A vehicle with stops on its route (a bus line, a delivery) stays
        SUMO-driven whatever its class: the policy cannot serve stops.
    :param agent_tight_turns: a vehicle whose route, from where it would join, turns tighter
        than the vehicle can where the wider turn it makes leaves the road (SUMO's on-the-spot
        turnarounds, 1.3-1.6 m, against 3.6 m for a 5 m car; ``SumoCityEnv._too_tight``)
        stays SUMO-driven (False, the default: the bicycle model cannot follow the route there;
        counted in ``SumoCityEnv.tight_turns``) or becomes an agent all the same (True).
    :param unblock_s: a SUMO-driven vehicle that has waited this long (s) next to an agent
        standing as long on a junction stops giving way to the standing agents among its
        junction foes, so the two cannot wait for each other for ever; where the agent stands
        in that vehicle's path too, after three times as long the vehicle jumps on to the lane
        after the junction (:mod:`magail_sumo.env.unblock`; counted in
        ``SumoCityEnv.unblocked`` and ``SumoCityEnv.jumped``; 0: neither).
    :param fcd_dir: folder for SUMO FCD recordings of episodes, each with a ``.sumocfg`` that
        replays it in ``sumo-gui`` on the city's network (None: none; as ``EnvConfig.fcd_dir``).
    :param fcd_every: with ``fcd_dir``, record episode 0, N, 2N, ... of each env instance
        (0: none).
    :param progress_reward: each agent's reward per metre it moves along its route in a
        step (its reference path, :mod:`magail_sumo.sim.paths`; 0: rewards are 0). The task
        reward of city training (with the trainer's penalties for the reason an agent left).
    :param demand_scale: the scenario's demand times this (SUMO's ``--scale``: vehicles of
        its routes and flows duplicated or left out, seeded), in the warm-up and the episodes
        alike; 1: the scenario as it is. A denser city from the same counts.
    """

    control_fraction: float = 1.0
    warmup_s: float = 0.0
    max_steps: int = 600
    terminate_on: tuple[str, ...] = ("collision", "off_road", "red_light", "destination")
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    limits: dynamics.BicycleLimits = field(default_factory=dynamics.BicycleLimits)
    lane_width: float = 3.2
    off_road_margin: float = 1.0
    destination_radius: float = 5.0
    sumo_seed: int = 0
    action_layout: str = "accel_steer"
    max_agents: int | None = None
    guard: GuardConfig = field(default_factory=GuardConfig)
    agent_classes: tuple[str, ...] = ("passenger",)
    agent_tight_turns: bool = False
    unblock_s: float = 10.0
    fcd_dir: str | None = None
    fcd_every: int = 0
    progress_reward: float = 0.0
    demand_scale: float = 1.0

    @classmethod
    def from_env(cls, env, *, max_agents: int | None, control_fraction: float,
                 warmup_s: float, max_steps: int,
                 agent_classes: tuple[str, ...] = ("passenger",),
                 progress_reward: float = 0.0,
                 agent_tight_turns: bool = False,
                 unblock_s: float = 10.0, demand_scale: float = 1.0) -> "CityEnvConfig":
        """A city's settings with the observation, limits, event rules (the city's events of
        ``env.terminate_on``), SUMO seed and action layout of a recorded-scene
        :class:`~magail_sumo.env.config.EnvConfig` ``env``, so one policy drives both."""
        return cls(control_fraction=control_fraction, warmup_s=warmup_s, max_steps=max_steps,
                   terminate_on=tuple(e for e in env.terminate_on if e in CITY_EVENTS),
                   observation=env.observation, limits=env.limits, lane_width=env.lane_width,
                   off_road_margin=env.off_road_margin,
                   destination_radius=env.destination_radius, sumo_seed=env.sumo_seed,
                   action_layout=env.action_layout, max_agents=max_agents, guard=env.guard,
                   agent_classes=tuple(agent_classes),
                   agent_tight_turns=bool(agent_tight_turns),
                   unblock_s=float(unblock_s), fcd_dir=env.fcd_dir,
                   fcd_every=env.fcd_every, progress_reward=progress_reward,
                   demand_scale=float(demand_scale))

    def __post_init__(self) -> None:
        if not (np.isfinite(self.progress_reward) and self.progress_reward >= 0):
            raise ValueError(f"progress_reward must be >= 0, got {self.progress_reward}")
        if not (np.isfinite(self.unblock_s) and self.unblock_s >= 0):
            raise ValueError(f"unblock_s must be >= 0, got {self.unblock_s}")
        if not (np.isfinite(self.demand_scale) and self.demand_scale > 0):
            raise ValueError(f"demand_scale must be > 0, got {self.demand_scale}")
        if self.max_agents is not None and self.max_agents < 1:
            raise ValueError(f"max_agents must be >= 1 or None, got {self.max_agents}")
        if self.action_layout not in dynamics.ACTION_LAYOUTS:
            raise ValueError(f"action_layout must be one of {dynamics.ACTION_LAYOUTS}, "
                             f"got {self.action_layout!r}")
        if not 0.0 < self.control_fraction <= 1.0:
            raise ValueError(f"control_fraction must be in (0, 1], got {self.control_fraction}")
        bad = set(self.terminate_on) - set(CITY_EVENTS)
        if bad:
            raise ValueError(f"unknown events in terminate_on: {sorted(bad)}")
        unknown = sorted(set(self.agent_classes) - set(VEHICLE_CLASSES))
        if unknown or not self.agent_classes:
            raise ValueError(f"agent_classes must be SUMO vehicle classes, got {unknown or '[]'}"
                             f" (e.g. {', '.join(VEHICLE_CLASSES[:8])})")


def scenario_inputs(sumocfg: Path) -> tuple[SumoInputs, list[str]]:
    """The scenario's :class:`~magail_sumo.sim.sumo_config.SumoInputs` (its configuration
    read, inputs checked, outputs and ports dropped) and the vehicle ids of its route files."""
    try:
        inputs = read_config(sumocfg)
        return inputs, check_demand(inputs.routes)
    except SumoConfigError as exc:
        raise MagailSumoError(str(exc)) from None


class SumoCityEnv(FleetEnv):
    """Many policy-driven vehicles in a SUMO city scenario (module doc).

    :param sumocfg: the scenario's ``.sumocfg`` (net and route files are read from it).
    :param sumo_args: extra SUMO options for every episode (e.g. ``--tripinfo-output FILE``
        for SUMO's own traffic outputs of a run).
    """

    metadata = {"name": "magail_sumo_city_v0", "render_modes": [], "render_fps": 10}
    render_mode = None
    events = CITY_EVENTS

    def __init__(self, sumocfg: str | Path, config: CityEnvConfig | None = None,
                 sumo_args: tuple[str, ...] = ()) -> None:
        self.sumocfg = Path(sumocfg)
        #: the scenario's name (its ``.sumocfg`` stem)
        self.scenario_id = scenario_name(self.sumocfg)
        self.sumo_args = tuple(sumo_args)
        self.config = cfg = config or CityEnvConfig()
        self.action_counts = dict.fromkeys(ACTION_COUNTS, 0)
        self.guarded = 0  # agent-steps whose acceleration the gap guard lowered
        #: what SUMO is started with (:func:`~magail_sumo.sim.sumo_config.read_config`)
        self.inputs, vehicle_ids = scenario_inputs(self.sumocfg)
        self.net_file = net_file = self.inputs.net
        #: FCD recording (:meth:`record_fcd`)
        self._fcd = EpisodeFcd(STEP_LENGTH, self._fcd_frame, self._fcd_replay, cfg.fcd_dir,
                               cfg.fcd_every)
        self.network: NetworkMap = network_map(net_file)
        self._net_file = net_file
        #: each internal junction's lanes to let pass (the give-way fallback, read on first use)
        self._internal: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] | None = None
        self._link: dict[str, tuple] = {}  # internal lane -> its link (reached, prio, ..., via)
        self._crossings: dict[tuple[str, str], float] = {}  # (lane, foe lane) -> position
        self._approach: dict[str, tuple[str, int]] = {}  # first internal lane -> (lane, link)
        self._foes: dict[str, tuple[str, ...]] = {}  # internal lane -> crossing internal lanes
        self._conflicts: dict[tuple[str, str], bool] = {}  # (lane, foe lane) -> in the way
        self._path_through: dict[str, tuple[tuple[str, ...], str]] = {}  # lane -> its connection
        self._lane_of = {lid: k for k, lid in enumerate(self.network.lane_ids)}
        # no recorded signals: _observe passes each agent's live SUMO light
        self.suite = SensorSuite.from_map(self.network.roadmap, None, cfg.observation)
        self.dt = STEP_LENGTH
        self.possible_agents = vehicle_ids
        low, high = observation_bounds(cfg.observation)
        self._obs_space = spaces.Box(low, high, dtype=np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (dynamics.ACTION_SIZE,), np.float32)
        self._session: SumoSession | None = None
        self._state_dir = tempfile.TemporaryDirectory(prefix="magail_city_")
        self._state_file: Path | None = None
        self.agents: list[str] = []
        self.sensor_time = 0.0
        self.t = 0

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    # ------------------------------------------------------------------ lifecycle
    def _scale_args(self) -> tuple[str, ...]:
        return demand_args(self.config.demand_scale)

    def warm_state(self) -> Path | None:
        """The saved warm-up state every episode loads (``--load-state``): SUMO run alone for
        ``warmup_s`` (1 s steps, seed ``sumo_seed``) on the first call; None when ``warmup_s``
        is 0. The file lives as long as the env."""
        cfg = self.config
        if cfg.warmup_s <= 0:
            return None
        if self._state_file is None:
            sim = SumoSession(inputs=self.inputs,
                             config=SessionConfig(step_length=1.0, seed=cfg.sumo_seed,
                                                  extra_args=self._scale_args()))
            with sim:
                begin = sim.time
                target = begin + cfg.warmup_s
                while sim.time < target:
                    sim.step()
                path = Path(self._state_dir.name) / "warm.xml.gz"
                sim.api.simulation.saveState(str(path))
                if cfg.demand_scale > 1.0:  # copies whose original has left lose its route
                    mend_routes(path, sim.api.vehicle.getRoute)
            self._state_file = path
        return self._state_file

    def reset(self, seed: int | None = None, options: dict | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        cfg = self.config
        self.close()
        self._fcd.begin_episode(self.scenario_id)
        state = self.warm_state()
        extra = (("--load-state", str(state)) if state is not None else ()) \
            + self._scale_args() + self.sumo_args
        self._seed = 0 if seed is None else int(seed)
        self._session = SumoSession(inputs=self.inputs, config=SessionConfig(
            seed=cfg.sumo_seed + self._seed, extra_args=extra)).start()
        n_max = 64
        #: the agents' state (rows appended as they join, :class:`Fleet`)
        self.fleet = Fleet.empty(n_max)
        #: this episode's fixed-up actions (:data:`~magail_sumo.env.actions.ACTION_COUNTS`)
        self.action_counts = dict.fromkeys(ACTION_COUNTS, 0)
        self.guarded = 0  # agent-steps whose acceleration the gap guard lowered
        #: the agents' reference paths (their SUMO routes' lanes from where they joined)
        self.paths = Paths.empty(n_max)
        self._graph = LaneGraph(self._session.api)
        #: agents whose route's next edge could not be reached from their lanes (path cut)
        self.cut_paths = 0
        #: chosen vehicles left SUMO-driven for a turn tighter than they can make
        #: (``agent_tight_turns``)
        self.tight_turns = 0
        #: SUMO-driven vehicles released from giving way to standing agents (``unblock_s``)
        self.unblocked = 0
        #: SUMO-driven vehicles moved on past a junction where they and an agent stood in
        #: each other's path (:func:`magail_sumo.env.unblock.jump`)
        self.jumped = 0
        self._stood = np.zeros(n_max)  # seconds each agent has stood
        self._lc = np.zeros(n_max)  # next-signal light code seen at the last observation
        self._ld = np.full(n_max, np.inf)  # and the distance to it (m)
        self._decided: set[str] = set()
        self._waiting: dict[str, None] = {}  # chosen vehicles waiting for an agent place
        self.sensor_time = 0.0
        self.t = 0
        self._end = cfg.max_steps
        self._session.step()
        self._sumo = self._session.vehicles()
        joiners = self._join(self._sumo.ids)
        self.agents = self.fleet.names_of(self.fleet.live())
        obs, _ = self._observe(joiners)
        self._record_fcd()
        info = self._infos_of(self.fleet.rows_of(self.agents))
        return obs, {a: info(i, {}, None) for i, a in enumerate(self.agents)}

    def _progress_reward(self) -> float:
        return self.config.progress_reward

    @property
    def sumo_time(self) -> float | None:
        """SUMO's clock now (s, the scenario's time of day); None outside an episode."""
        return None if self._session is None else self._session.time

    def close(self) -> None:
        self._fcd.end_episode()
        if self._session is not None:
            self._session.close()
            self._session = None

    def step(self, actions: dict[str, Any]):
        """One step (the stages: :class:`~magail_sumo.env.step.FleetEnv`); the episode's
        automatic FCD recording is written when its last step is taken."""
        out = super().step(actions)
        if self.t >= self._end:
            self._fcd.end_episode()
        return out

    # ------------------------------------------------------------------ agents
    def _controlled(self, vid: str) -> bool:
        """Seeded, order-independent choice of controlled vehicles, among those of
        ``agent_classes`` with no stops on their route."""
        api = self._session.api
        if api.vehicle.getVehicleClass(vid) not in self.config.agent_classes or \
                api.vehicle.getStops(vid):
            return False
        if self.config.control_fraction >= 1.0:
            return True
        h = hashlib.blake2b(f"{self._seed}:{vid}".encode(), digest_size=8).digest()
        return int.from_bytes(h, "little") / 2**64 < self.config.control_fraction

    def _join(self, candidates) -> np.ndarray:
        """Vehicles seen for the first time become agents when chosen; their indices. With
        ``max_agents`` reached, a chosen vehicle is driven by SUMO and waits: it becomes an
        agent, mid-trip, when an agent place frees (first come, first served). Step stage 5."""
        v, f = self._sumo, self.fleet
        pos = {vid: i for i, vid in enumerate(v.ids)}
        cap = self.config.max_agents
        n_active = int(f.active.sum())
        new = []
        waiting = self._waiting
        chosen = []  # the chosen vehicles, in the order they are taken
        # vehicles that waited for a free agent place come first, in the order they appeared
        for vid in list(waiting) + [c for c in candidates if c not in waiting]:
            if vid not in pos:  # left SUMO
                waiting.pop(vid, None)
                continue
            if vid in self._decided:
                continue
            if not self._controlled(vid):
                self._decided.add(vid)
                continue
            chosen.append(vid)
        # in turn, as many as there are free places: each of those finds one (a vehicle with a
        # turn it cannot make takes none, so the next round offers its place to the next one);
        # a round's tight-turn tests run together (_too_tight)
        start = 0
        while start < len(chosen):
            room = len(chosen) - start if cap is None else min(cap - n_active,
                                                                len(chosen) - start)
            if room <= 0:
                for vid in chosen[start:]:  # SUMO drives it until a place frees
                    waiting[vid] = None
                break
            batch = chosen[start:start + room]
            start += room
            paths = [self._graph.route_path(vid) for vid in batch]
            tight = [False] * len(batch) if self.config.agent_tight_turns else \
                self._too_tight([p.points for p in paths],
                                     [v.length[pos[vid]] for vid in batch])
            for vid, path, too_tight in zip(batch, paths, tight):
                waiting.pop(vid, None)
                self._decided.add(vid)
                if too_tight:
                    self.tight_turns += 1  # SUMO drives it: the bicycle cannot make that turn
                    continue
                n_active += 1
                new.append(self._admit(vid, pos[vid], path))
        return np.array(new, np.int64)

    def _admit(self, vid: str, i: int, path) -> int:
        """Make SUMO vehicle ``vid`` (row ``i`` of the SUMO vehicles) an agent on reference
        path ``path``; its fleet row."""
        v, f = self._sumo, self.fleet
        k = f.add(vid, v.x[i], v.y[i], v.yaw[i], v.speed[i], v.length[i], v.width[i])
        if f.capacity > self._lc.shape[0]:
            self._lc, self._ld = resized(self._lc, f.capacity), resized(self._ld, f.capacity)
            self._stood = resized(self._stood, f.capacity)
        self._stood[k] = 0.0
        self.cut_paths += not path.complete
        f.path[k] = self.paths.add(path.points, path.limits)
        f.hint[k] = self.paths.project(f.path[k:k + 1], f.x[k:k + 1], f.y[k:k + 1])[0][0]
        end = self.paths.length(f.path[k:k + 1])
        px, py, heading = self.paths.at(f.path[k:k + 1], end)
        f.dest[k] = px[0], py[0]
        f.dest_yaw[k] = heading[0]
        if self.config.observation.speed_factor:  # SUMO drew it as the vehicle entered
            f.speed_factor[k] = float(self._session.api.vehicle.getSpeedFactor(vid))
        f.join(k)
        f.in_sumo[k] = True
        return k

    def _too_tight(self, points: list, lengths: list) -> list[bool]:
        """Per path ``points[j]``: it has a turn tighter than a vehicle of box ``lengths[j]``
        can make (:func:`~magail_sumo.sim.paths.tightest_turn` below its
        :func:`~magail_sumo.sim.dynamics.turning_radius`) where following it at a crawl
        (:func:`~magail_sumo.sim.tracking.trial`, from 8 m before to 12 m after the turn)
        takes it off the road (the env's off-road rule): a turnaround inside a wide junction,
        where the wider circle stays on its lanes, can be driven. The crawls are stepped
        together (:func:`~magail_sumo.sim.tracking.trials`: each one's poses as its own)."""
        cfg = self.config
        out = [False] * len(points)
        tests = []  # (which, points, start, end, length) of the paths with a turn that tight
        for j, (pts, length) in enumerate(zip(points, lengths)):
            radius, s = tightest_turn(pts)
            if radius < dynamics.turning_radius(length, cfg.limits):
                tests.append((j, pts, s - 8.0, s + TURN_ARC + 12.0, length))
        if not tests:
            return out
        which, pts, s0, s1, length = zip(*tests)
        runs = trials(pts, s0, s1, length, cfg.limits)
        lanes = self.suite.lane_query(np.concatenate([r.x for r in runs]),
                                      np.concatenate([r.y for r in runs]),
                                      np.concatenate([r.yaw for r in runs]))
        off = off_road(lanes.distance, cfg.lane_width, cfg.off_road_margin)
        ends = np.cumsum([len(r.x) for r in runs])
        for j, a, b in zip(which, np.r_[0, ends[:-1]], ends):
            out[j] = bool(off[a:b].any())
        return out

    def _world(self, agents: np.ndarray) -> tuple[Boxes, list[str]]:
        """Boxes of the agents (first rows) then every other SUMO vehicle, with their ids."""
        v, f = self._sumo, self.fleet
        # string ids: a set lookup per vehicle (~30 µs for 400) beats np.isin on object arrays
        # (~2.5 ms, measured)
        ctrl = set(f.names_of(f.live()))
        bg = [i for i, vid in enumerate(v.ids) if vid not in ctrl]
        boxes = Boxes(np.concatenate([f.x[agents], v.x[bg]]),
                      np.concatenate([f.y[agents], v.y[bg]]),
                      np.concatenate([f.yaw[agents], v.yaw[bg]]),
                      np.concatenate([f.length[agents], v.length[bg]]),
                      np.concatenate([f.width[agents], v.width[bg]]),
                      np.concatenate([f.speed[agents], v.speed[bg]]))
        return boxes, f.names_of(agents) + [v.ids[i] for i in bg]

    def _next_lights(self, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(A,) light code of each agent's next signal and (A,) distance to it (m, inf: none).

        libsumo has no bulk query for this; one ``getNextTLS`` call per agent (~µs each).
        """
        vehicle, names = self._session.api.vehicle, self.fleet.names
        code = np.zeros(agents.size)
        dist = np.full(agents.size, np.inf)
        for j, k in enumerate(agents.tolist()):
            try:
                nxt = vehicle.getNextTLS(names[k])
            except Exception:  # vehicle not (yet) in SUMO
                continue
            if nxt:
                _, _, d, state = nxt[0]
                code[j] = _LIGHT.get(state, 0)
                dist[j] = d
        return code, dist

    def _give_way(self, agents: np.ndarray) -> np.ndarray:
        """(A, 2) each agent's give-way conflict (:mod:`magail_sumo.sensors.units.give_way`):
        the distance (m) to the conflict of the road user it must respond to that reaches its
        conflict first, and that road user's time (s) to it; inf, inf when none.

        From SUMO's junction model: ``getJunctionFoes`` per agent (libsumo has no bulk query),
        keeping foes the agent must respond to, that have not left the conflict, while the
        agent is more than :data:`~magail_sumo.sensors.units.give_way.COMMITTED` m from it
        (an agent at or in the conflict is committed: it clears it). SUMO gives no foes for a
        vehicle moved onto an internal lane (it keeps no upcoming links for it), so for an
        agent inside a junction the foes are read from the network instead: before an
        internal junction it must wait at (a left turn across oncoming traffic,
        :meth:`_internal_give_way`) and standing on a connection without the right of way
        (:meth:`_minor_link_give_way`). With ``observation.give_way_conflicts`` both count only
        the road users whose connection is in the agent's way (:meth:`_conflicting`; on an
        approach lane, :meth:`_takes_one_of`).
        """
        vehicle, names, v = self._session.api.vehicle, self.fleet.names, self._sumo
        out = np.full((agents.size, 2), np.inf)
        speed = dict(zip(v.ids, v.speed.tolist()))
        for j, k in enumerate(agents.tolist()):  # one libsumo query per agent
            try:
                foes = vehicle.getJunctionFoes(names[k], GIVE_WAY_RANGE)
            except Exception:  # vehicle not (yet) in SUMO
                continue
            for foe, ego_d, foe_d, _, foe_exit, _, _, respond, _ in foes:
                if not respond or ego_d <= COMMITTED or foe_exit <= 0.0:
                    continue
                t = max(foe_d, 0.0) / max(speed.get(foe, 0.0), 0.1)
                if t < out[j, 1]:
                    out[j] = ego_d, t
        # agents SUMO named no foe for that are inside a junction (a few): the fallbacks
        edge = dict(zip(v.ids, v.edge))
        none = np.flatnonzero(~np.isfinite(out[:, 1]))
        inside = [(j, names[k]) for j, k in zip(none.tolist(), agents[none].tolist())
                  if edge.get(names[k], "").startswith(":")]
        if inside:
            self._internal_give_way(inside, out, speed)
            self._minor_link_give_way(inside, out, speed)
        return out

    def _internal_give_way(self, inside: list[tuple[int, str]], out: np.ndarray,
                           speed: dict[str, float]) -> None:
        """Fill rows ``j`` of ``out`` (:meth:`_give_way`) for agents ``(j, name)`` of
        ``inside`` (SUMO gave them no foe; on an internal lane) that stand on an
        internal lane whose link reaches an internal junction without priority: the distance
        (m) to the end of that lane (where the internal junction waits) and the time (s) of the
        first foe: a vehicle moving on one of the junction's foe internal lanes that has not
        passed where that lane crosses the agent's next internal lane (its distance to the
        crossing over its speed; a lane that only merges with it at its end crosses there), or
        one moving on a foe approach lane within the give-way range (its distance to the
        junction over its speed). The lanes are the network's (``<junction type="internal">``).
        """
        api = self._session.api
        for j, name in inside:
            try:
                lane = api.vehicle.getLaneID(name)
                ego_d = api.lane.getLength(lane) - api.vehicle.getLanePosition(name)
            except Exception:  # vehicle not (yet) in SUMO
                continue
            link = self._link.get(lane)
            if link is None:
                links = api.lane.getLinks(lane) if lane.startswith(":") else ()
                link = self._link[lane] = links[0] if links else ()
            if not link or link[1] or not link[4] or ego_d <= COMMITTED:
                continue  # no internal junction ahead, priority there, or committed
            if self._internal is None:
                self._internal = internal_junctions(self._net_file)
            incoming, internal = self._internal.get(link[4], ((), ()))
            if self.config.observation.give_way_conflicts:  # only foes in the agent's way
                internal = tuple(f for f in internal if self._conflicting(link[4], f))
            t = min((self._before_crossing(f, self._crossing_on(link[4], f), speed)
                     for f in internal), default=np.inf)
            t = min([t] + [self._approaching(src, 0.0, speed, internal) for src in incoming
                           if src != lane and not src.startswith(":")])
            if np.isfinite(t):
                out[j] = ego_d, t

    def _minor_link_give_way(self, inside: list[tuple[int, str]], out: np.ndarray,
                             speed: dict[str, float]) -> None:
        """Fill rows ``j`` of ``out`` (:meth:`_give_way`) still without a foe for agents
        ``(j, name)`` of ``inside`` (SUMO gave them no foe) that are inside a junction on a
        connection without the right of way (its live link state minor: ``m``,
        ``g``, ``s``, ``=``, ``w``, ``o``) standing there, e.g. a car turning out of a side road
        that stopped on the junction and is about to pull out (SUMO keeps no upcoming links for
        a vehicle moved onto an internal lane, so it names no foe; one still moving entered
        having given way, with SUMO's foes, and clears the junction): the first vehicle that
        comes on a crossing connection with the right of way (``lane.getInternalFoes``; live
        state ``G``, ``M`` or ``O``), on its internal lane before the crossing or on its
        approach lane within the give-way range, gives the distance (m) to the crossing and
        its time (s) to it."""
        api = self._session.api
        for j, name in inside:
            if np.isfinite(out[j, 1]) or speed.get(name, 0.0) > MOVING:
                continue  # a foe found, or moving: it entered having given way (SUMO's foes)
            try:
                lane = api.vehicle.getLaneID(name)
                pos = api.vehicle.getLanePosition(name)
            except Exception:  # vehicle not (yet) in SUMO
                continue
            if self._link_state(lane) not in MINOR:
                continue
            best_d, best_t = np.inf, np.inf
            conflicts = self.config.observation.give_way_conflicts
            for foe_lane in self._internal_foes(lane):
                if self._link_state(foe_lane) not in MAJOR or \
                        (conflicts and not self._conflicting(lane, foe_lane)):
                    continue
                ego_d = self._crossing_on(foe_lane, lane) - pos
                if ego_d <= COMMITTED:
                    continue  # at or past the crossing: it clears it
                cross = self._crossing_on(lane, foe_lane)
                t = min(self._before_crossing(foe_lane, cross, speed),
                        self._approaching(self._approaches()[foe_lane][0], cross, speed,
                                          (foe_lane,)))
                if t < best_t:
                    best_d, best_t = ego_d, t
            if np.isfinite(best_t):
                out[j] = best_d, best_t

    def _before_crossing(self, lane: str, cross: float, speed: dict[str, float]) -> float:
        """Time (s) the first vehicle moving on internal lane ``lane`` whose rear has not
        passed lane position ``cross`` (m) needs to reach it (0 when it is there; inf: none)."""
        vehicle, t = self._session.api.vehicle, np.inf
        for f in self._session.api.lane.getLastStepVehicleIDs(lane):
            v = speed.get(f, 0.0)
            if v <= MOVING:
                continue
            front = vehicle.getLanePosition(f)
            if front - vehicle.getLength(f) < cross:
                t = min(t, max(cross - front, 0.0) / v)
        return t

    def _approaching(self, lane: str, beyond: float, speed: dict[str, float],
                     via: tuple[str, ...] = ()) -> float:
        """Time (s) the first vehicle moving on approach lane ``lane`` within the give-way
        range of a point ``beyond`` m past the lane's end needs to reach it (inf: none); with
        ``observation.give_way_conflicts`` only a vehicle whose route leaves ``lane`` on a
        connection whose first internal lane is in ``via`` (one whose route is unknown past
        ``lane`` counts)."""
        api, t = self._session.api, np.inf
        end = api.lane.getLength(lane) + beyond
        conflicts = self.config.observation.give_way_conflicts
        for f in api.lane.getLastStepVehicleIDs(lane):
            d, v = end - api.vehicle.getLanePosition(f), speed.get(f, 0.0)
            if d < GIVE_WAY_RANGE and v > MOVING and \
                    (not conflicts or self._takes_one_of(f, lane, via)):
                t = min(t, d / v)
        return t

    def _takes_one_of(self, vehicle: str, lane: str, via: tuple[str, ...]) -> bool:
        """Whether ``vehicle`` on normal lane ``lane`` leaves it on a connection whose first
        internal lane is in ``via`` (the links of ``lane`` to the next edge of its route); True
        when its route does not go on or cannot be read."""
        api = self._session.api
        try:
            route, k = api.vehicle.getRoute(vehicle), api.vehicle.getRouteIndex(vehicle)
        except api.TraCIException:  # vehicle not (yet) in SUMO
            return True
        if not 0 <= k < len(route) - 1:
            return True
        nxt = route[k + 1]
        return any(link[4] in via for link in api.lane.getLinks(lane)
                   if link[0].rsplit("_", 1)[0] == nxt)

    def _through(self, lane: str) -> tuple[tuple[str, ...], str]:
        """The internal lanes of the connection from internal lane ``lane`` on (``lane`` and
        those its links lead through) and the normal lane after them ("": none). Cached."""
        out = self._path_through.get(lane)
        if out is None:
            lanes, nxt = [lane], ""
            while len(lanes) < 8:
                links = self._session.api.lane.getLinks(lanes[-1])
                nxt = links[0][0] if links else ""
                if not nxt.startswith(":"):
                    break
                lanes.append(nxt)
            out = self._path_through[lane] = (tuple(lanes), nxt)
        return out

    def _conflicting(self, lane: str, foe_lane: str) -> bool:
        """Whether the connection through internal lane ``lane`` (:meth:`_through`) is in
        the way of the one through ``foe_lane``: their centrelines cross or they lead onto the
        same lane (``observation.give_way_conflicts``). Cached."""
        key = (lane, foe_lane)
        out = self._conflicts.get(key)
        if out is None:
            (mine, to), (theirs, foe_to) = self._through(lane), self._through(foe_lane)
            g = self._graph
            out = self._conflicts[key] = bool(to and to == foe_to) or any(
                crossing(g.shape(a), g.shape(b)) is not None for a in mine for b in theirs)
        return out

    def _internal_foes(self, lane: str) -> tuple[str, ...]:
        """The internal lanes of vehicle classes that may cross internal lane ``lane``
        (SUMO's ``lane.getInternalFoes``, walking areas and crossings left out). Cached."""
        out = self._foes.get(lane)
        if out is None:
            out = self._foes[lane] = tuple(
                f for f in self._session.api.lane.getInternalFoes(lane)
                if f in self._approaches() and self._graph.allows(f, "passenger"))
        return out

    def _link_state(self, internal: str) -> str:
        """The live state (SUMO's link state letter) of the connection whose first internal
        lane is ``internal``; "" when ``internal`` is none's first."""
        src = self._approaches().get(internal)
        if src is None:
            return ""
        links = self._session.api.lane.getLinks(src[0])
        return links[src[1]][5] if src[1] < len(links) else ""

    def _approaches(self) -> dict[str, tuple[str, int]]:
        """Each connection's first internal lane -> (the normal lane it leaves, its index in
        that lane's links); read from every lane's links on first use."""
        if not self._approach:
            api = self._session.api
            for lane in api.lane.getIDList():
                if not lane.startswith(":"):
                    for i, link in enumerate(api.lane.getLinks(lane)):
                        if link[4]:
                            self._approach[link[4]] = (lane, i)
        return self._approach

    def _crossing_on(self, lane: str, foe_lane: str) -> float:
        """Lane position (m, SUMO's lane length) on internal lane ``foe_lane`` where it crosses
        internal lane ``lane`` (:func:`~magail_sumo.sim.lane_graph.crossing`); its length
        when they do not cross (they merge at its end). Cached."""
        key = (lane, foe_lane)
        out = self._crossings.get(key)
        if out is None:
            g = self._graph
            shape = g.shape(foe_lane)
            length = float(self._session.api.lane.getLength(foe_lane))
            at = crossing(g.shape(lane), shape)
            geometric = float(np.hypot(*np.diff(shape, axis=0).T).sum())
            out = length if at is None or geometric <= 0 else at * length / geometric
            self._crossings[key] = out
        return out

    def _observe(self, agents: np.ndarray, lanes: LaneQuery | None = None
                 ) -> tuple[dict[str, np.ndarray], tuple[Boxes, list[str]]]:
        """Step stage 6: observations of fleet rows ``agents`` (sorted) and the world
        (:meth:`_world`); ``lanes``: their lane query when already computed."""
        clock = time.perf_counter()
        f = self.fleet
        world = self._world(agents)
        light, dist = self._next_lights(agents)
        self._lc[agents], self._ld[agents] = light, dist
        ob = self.config.observation
        cmd = route = ahead = None
        if ob.command or ob.route_points or ob.path_leader or ob.speed_limit:
            paths = f.path[agents]
            s = self._route_progress(agents)
            if ob.command:
                cmd = one_hot(command_index(self.paths.turn(paths, s, ob.command_lookahead)))
            if ob.route_points:
                route = self.paths.ahead(paths, s, f.x[agents], f.y[agents], f.yaw[agents],
                                         ob.route_points)
            if ob.path_leader or ob.speed_limit:
                ahead = PathAhead(self.paths, paths, f.hint[agents], s)
        ego = EgoState(np.arange(agents.size), f.speed[agents], f.prev_action[agents],
                       f.dest[agents], f.dest_yaw[agents], cmd, route, ahead,
                       speed_factor=f.speed_factor[agents] if ob.speed_factor else None)
        give_way = self._give_way(agents) if ob.give_way else None
        obs = self.suite.observe(world[0], ego, 0, lanes,
                                 light=np.where(dist < LIGHT_RANGE, light, 0), light_gap=dist,
                                 give_way=give_way)
        self.sensor_time += time.perf_counter() - clock
        return {f.names[k]: obs[i] for i, k in enumerate(agents)}, world

    # ------------------------------------------------------------------ step hooks
    def _push(self) -> None:
        """Step stage 3: place the live agents in SUMO at their poses."""
        f = self.fleet
        act = f.live()
        # route-relative agents stay on their SUMO routes' lanes (keepRoute 3), so SUMO's
        # signals and junction foes of them are those of their routes; free steering may leave
        # the route (2: mapped anywhere)
        keep = 3 if self.config.action_layout == "accel_offset" else 2
        self._session.move(f.names_of(act), f.x[act], f.y[act], f.yaw[act], f.length[act],
                           keep_route=keep)

    def _sumo_step(self) -> tuple[list[str], list[str]]:
        """Step stage 4: SUMO steps; its vehicles are read; agents SUMO took out are noted."""
        departed, arrived = self._session.step()
        self.t += 1
        self._sumo = self._session.vehicles()
        f = self.fleet
        for vid in arrived:
            k = f.index.get(vid)
            if k is not None:
                f.in_sumo[k] = False
        self._unblock()
        return departed, arrived

    def _unblock(self) -> None:
        """The agents' standing times; once a second, SUMO-driven vehicles waiting next to an
        agent standing on a junction stop giving way to standing agents, or jump on past the
        junction when the two stand in each other's path
        (:func:`magail_sumo.env.unblock.release`, ``unblock_s``)."""
        f, after = self.fleet, self.config.unblock_s
        live = f.live()
        self._stood[live] = np.where(f.speed[live] < STAND_SPEED, self._stood[live] + self.dt,
                                     0.0)
        if after <= 0 or self.t % UNBLOCK_EVERY or not live.size:
            return
        v = self._sumo
        stood = self._stood[live]
        rng = self.config.observation.leader_range

        def blocks(i: int, j: int) -> int:
            """Whether SUMO vehicle j stands in agent live[i]'s path (FREE: no), and the agent
            in j's (along its SUMO route's lanes): HELD (no: SUMO's junction model, not the
            agent's box, holds j) or MUTUAL (yes)."""
            k = live[i:i + 1]
            pair = Boxes(*(np.array([getattr(f, a)[k[0]], getattr(v, a)[j]])
                           for a in ("x", "y", "yaw", "length", "width", "speed")))
            ahead = PathAhead(self.paths, f.path[k], f.hint[k], self._route_progress(k))
            if not along_path(pair, np.zeros(1, np.int64), ahead, rng)[2][0]:
                return FREE
            theirs = Paths.of([self._graph.route_path(v.ids[j]).points])
            row = np.zeros(1, np.int64)
            at, s = theirs.project(row, v.x[j:j + 1], v.y[j:j + 1])
            mutual = along_path(pair, np.ones(1, np.int64), PathAhead(theirs, row, at, s),
                                rng)[2][0]
            return MUTUAL if mutual else HELD

        released, jumped = release(self._session.api, v.ids, v.x, v.y, v.speed, v.edge,
                                   f.names_of(live), f.x[live], f.y[live], stood, after, blocks)
        self.unblocked += released
        self.jumped += jumped

    def _before_move(self, act: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each stepped agent's next signal as last observed: red, and its distance (m)."""
        return self._lc[act] == 3, self._ld[act].copy()

    def _red_light(self, act: np.ndarray, p0: np.ndarray, ctx) -> np.ndarray:
        """The step moved the agent past the stop line of a signal that was red before it."""
        red_before, dist_before = ctx
        f = self.fleet
        moved = np.hypot(f.x[act] - p0[:, 0], f.y[act] - p0[:, 1])
        return red_before & (dist_before < moved)

    def _time_up(self, act: np.ndarray, flags: dict[str, np.ndarray], end: bool,
                 arrived: list[str]) -> tuple[np.ndarray, list[str]]:
        """Out of time: SUMO took the vehicle out (``arrived``) or the episode ends."""
        gone_in_sumo = ~self.fleet.in_sumo[act]
        return gone_in_sumo | end, \
            np.where(gone_in_sumo, "arrived", END_OF_EPISODE).tolist()

    def _road_user(self, ids: list[str], j: int) -> str:
        """Name of world box ``j``: its SUMO vehicle id."""
        return ids[j]

    # ------------------------------------------------------------------ FCD
    def _fcd_frame(self, recorder: FcdRecorder) -> None:
        """Add the step's vehicles to ``recorder`` (agents from their bicycle state, the others
        from SUMO)."""
        agents = self.fleet.live()
        boxes, ids = self._world(agents)
        if not ids:
            return
        kind = ["agent"] * agents.size + ["sumo"] * (len(ids) - agents.size)
        ctrl = set(ids[:agents.size])
        v = self._sumo
        speed = np.concatenate([self.fleet.speed[agents],
                                [sp for vid, sp in zip(v.ids, v.speed) if vid not in ctrl]])
        recorder.add(self.t * self.dt, ids, boxes.x, boxes.y, boxes.yaw, boxes.length,
                     boxes.width, kind, "passenger", speed)

    def _fcd_replay(self, recorder: FcdRecorder, path: Path) -> ReplayFiles:
        """The recording replayed on the scenario's network."""
        return write_replay(recorder, path, self.net_file)
