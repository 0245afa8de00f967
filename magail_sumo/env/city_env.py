"""PettingZoo ``ParallelEnv`` over a plain SUMO scenario (a city's net and demand, no recording).

The city counterpart of :class:`~magail_sumo.env.driving_env.SumoDrivingEnv`: every vehicle of
the SUMO demand that departs (or is present when the episode starts) becomes an agent with
probability ``control_fraction`` (seeded); the rest stay SUMO-driven background traffic that
reacts to the agents. Agents move by the kinematic bicycle model from normalised actions
``[accel, steer]`` in [-1, 1]² and are placed in SUMO with ``moveToXY``; they see the same
sensors as in recorded scenes, with the map taken from the SUMO network
(:func:`~magail_sumo.sim.sumo_map.network_map`) and the current-lane light from SUMO's signal
state. Their destination is the end of their SUMO route.

An episode may start from a warmed-up network: ``warmup_s`` seconds are first simulated by
SUMO alone (1 s steps), the state is saved once and every reset loads it, so agents start in
realistic traffic. Steps are 0.1 s.

Events ending an agent (``infos[agent]["reason"]``): ``collision`` (oriented-box overlap with
any other vehicle), ``off_road`` (box centre farther than ``lane_width / 2 + margin`` from every
lane, junction lanes included), ``red_light`` (the agent passes the stop line of a red signal
that was its next signal at the step's start), ``destination`` (within ``destination_radius``
of its route's end); ``end_of_episode`` truncates. Rewards are 0.
"""

from __future__ import annotations

import hashlib
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from magail_sumo.errors import MagailSumoError
from magail_sumo.sensors.lanes import LaneQuery
from magail_sumo.sensors.observation import (
    Boxes, EgoState, ObservationConfig, SensorSuite, observation_bounds,
)
from magail_sumo.sim import dynamics
from magail_sumo.sim.session import STEP_LENGTH, SessionConfig, SumoSession, VehicleArrays
from magail_sumo.sim.sumo_map import NetworkMap, network_map

from .actions import ACTION_COUNTS, checked_actions, count_actions
from .collision import first_overlap
from .events import off_road, reached
from .outcomes import StepDicts

#: Events of the city env, in the order the first one found becomes the reason.
CITY_EVENTS: tuple[str, ...] = ("collision", "off_road", "red_light", "destination")
_LIGHT = {"G": 1, "g": 1, "y": 2, "Y": 2, "r": 3, "R": 3, "u": 3, "s": 3, "o": 0, "O": 0}


@dataclass(frozen=True)
class CityEnvConfig:
    """Settings of :class:`SumoCityEnv`.

    :param control_fraction: share of the demand's vehicles that become agents (0, 1].
    :param warmup_s: seconds SUMO simulates alone before the episode (0: start at the
        scenario's begin time).
    :param max_steps: 0.1-s steps per episode.
    :param terminate_on: events that end an agent (others are only reported in infos).
    :param lane_width, off_road_margin, destination_radius: event rules (m).
    :param sumo_seed: added to the reset seed to seed SUMO.
    :param action_layout: ``"accel_steer"`` or the seed's ``"steer_throttle"``.
    :param max_agents: at most this many agents alive at once (None: no cap; a fixed number of
        slots for training); a vehicle chosen to be an agent while the cap is reached is
        SUMO-driven until a place frees, then joins mid-trip (first come, first served), so
        the city keeps ``max_agents`` agents while its demand allows.
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

    def __post_init__(self) -> None:
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


def _scenario_files(sumocfg: Path) -> tuple[Path, list[str]]:
    """Net file and vehicle ids of the route files named by a ``.sumocfg``."""
    if not sumocfg.is_file():
        raise MagailSumoError(f"{sumocfg}: SUMO config file not found")
    try:
        root = ET.parse(sumocfg).getroot()
    except ET.ParseError as exc:
        raise MagailSumoError(f"{sumocfg}: not valid XML ({exc})") from None
    net = root.find("./input/net-file")
    if net is None or not net.get("value"):
        raise MagailSumoError(f"{sumocfg}: no input/net-file")
    ids: list[str] = []
    routes = root.find("./input/route-files")
    for name in (routes.get("value", "").split(",") if routes is not None else []):
        path = sumocfg.parent / name.strip()
        try:
            for _, el in ET.iterparse(path):
                if el.tag in ("vehicle", "trip", "flow") and el.get("id"):
                    ids.append(el.get("id"))
                el.clear()
        except (OSError, ET.ParseError) as exc:
            raise MagailSumoError(f"{path}: cannot read route file ({exc})") from None
    return sumocfg.parent / net.get("value"), ids


class SumoCityEnv(ParallelEnv):
    """Many policy-driven vehicles in a SUMO city scenario (module doc).

    :param sumocfg: the scenario's ``.sumocfg`` (net and route files are read from it).
    :param sumo_args: extra SUMO options for every episode (e.g. ``--tripinfo-output FILE``
        for SUMO's own traffic outputs of a run).
    """

    metadata = {"name": "magail_sumo_city_v0", "render_modes": [], "render_fps": 10}
    render_mode = None

    def __init__(self, sumocfg: str | Path, config: CityEnvConfig | None = None,
                 sumo_args: tuple[str, ...] = ()) -> None:
        self.sumocfg = Path(sumocfg)
        #: the scenario's name (its ``.sumocfg`` stem)
        self.scenario_id = self.sumocfg.stem
        self.sumo_args = tuple(sumo_args)
        self.config = cfg = config or CityEnvConfig()
        self.action_counts = dict.fromkeys(ACTION_COUNTS, 0)
        net_file, vehicle_ids = _scenario_files(self.sumocfg)
        self.net_file = net_file
        #: FCD recorder (:meth:`record_fcd`), None when not recording
        self.fcd = None
        self.network: NetworkMap = network_map(net_file)
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
    def warm_state(self) -> Path | None:
        """The saved warm-up state every episode loads (``--load-state``): SUMO run alone for
        ``warmup_s`` (1 s steps, seed ``sumo_seed``) on the first call; None when ``warmup_s``
        is 0. The file lives as long as the env."""
        cfg = self.config
        if cfg.warmup_s <= 0:
            return None
        if self._state_file is None:
            sim = SumoSession(self.sumocfg, config=SessionConfig(step_length=1.0, seed=cfg.sumo_seed))
            with sim:
                begin = sim.time
                target = begin + cfg.warmup_s
                while sim.time < target:
                    sim.step()
                path = Path(self._state_dir.name) / "warm.xml.gz"
                import libsumo

                libsumo.simulation.saveState(str(path))
            self._state_file = path
        return self._state_file

    def reset(self, seed: int | None = None, options: dict | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        cfg = self.config
        self.close()
        state = self.warm_state()
        extra = (("--load-state", str(state)) if state is not None else ()) + self.sumo_args
        self._seed = 0 if seed is None else int(seed)
        self._session = SumoSession(self.sumocfg, config=SessionConfig(
            seed=cfg.sumo_seed + self._seed, extra_args=extra)).start()
        self._names: list[str] = []
        self._index: dict[str, int] = {}
        n_max = 64
        self._x, self._y, self._yaw, self._speed = (np.zeros(n_max) for _ in range(4))
        self._length, self._width = np.zeros(n_max), np.zeros(n_max)
        self._dest = np.zeros((n_max, 2))
        self._dest_yaw = np.zeros(n_max)
        self._prev_action = np.zeros((n_max, dynamics.ACTION_SIZE))
        self._active = np.zeros(n_max, bool)
        self._nan = np.zeros(n_max, np.int64)
        self._clipped = np.zeros(n_max, np.int64)
        #: this episode's fixed-up actions (:data:`~magail_sumo.env.actions.ACTION_COUNTS`)
        self.action_counts = dict.fromkeys(ACTION_COUNTS, 0)
        self._lc = np.zeros(n_max)  # next-signal light code seen at the last observation
        self._ld = np.full(n_max, np.inf)  # and the distance to it (m)
        self._decided: set[str] = set()
        self._waiting: dict[str, None] = {}  # chosen vehicles waiting for an agent place
        self.sensor_time = 0.0
        self.t = 0
        self._session.step()
        self._sumo = self._session.vehicles()
        joiners = self._join(self._sumo.ids)
        self.agents = [self._names[k] for k in np.flatnonzero(self._active)]
        obs, _ = self._observe(joiners)
        self._record_fcd()
        return obs, {a: self._info(self._index[a], {}, None) for a in self.agents}

    @property
    def sumo_time(self) -> float | None:
        """SUMO's clock now (s, the scenario's time of day); None outside an episode."""
        return None if self._session is None else self._session.time

    def close(self) -> None:
        if self._session is not None:
            self._session.close()
            self._session = None

    # ------------------------------------------------------------------ agents
    def _controlled(self, vid: str) -> bool:
        """Seeded, order-independent choice of controlled vehicles."""
        if self.config.control_fraction >= 1.0:
            return True
        h = hashlib.blake2b(f"{self._seed}:{vid}".encode(), digest_size=8).digest()
        return int.from_bytes(h, "little") / 2**64 < self.config.control_fraction

    def _grow(self, n: int) -> None:
        size = self._x.shape[0]
        if n <= size:
            return
        new = max(n, 2 * size)
        for name in ("_x", "_y", "_yaw", "_speed", "_length", "_width", "_dest_yaw", "_nan",
                     "_clipped", "_active", "_lc", "_ld"):
            old = getattr(self, name)
            arr = np.zeros(new, old.dtype)
            arr[:size] = old
            setattr(self, name, arr)
        for name in ("_dest", "_prev_action"):
            old = getattr(self, name)
            arr = np.zeros((new, 2), old.dtype)
            arr[:size] = old
            setattr(self, name, arr)

    def _join(self, candidates) -> np.ndarray:
        """Vehicles seen for the first time become agents when chosen; their indices. With
        ``max_agents`` reached, a chosen vehicle is driven by SUMO and waits: it becomes an
        agent, mid-trip, when an agent place frees (first come, first served)."""
        import libsumo

        v = self._sumo
        pos = {vid: i for i, vid in enumerate(v.ids)}
        cap = self.config.max_agents
        n_active = int(self._active.sum())
        new = []
        waiting = self._waiting
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
            if cap is not None and n_active >= cap:  # SUMO drives it until a place frees
                waiting[vid] = None
                continue
            waiting.pop(vid, None)
            self._decided.add(vid)
            n_active += 1
            k = len(self._names)
            self._grow(k + 1)
            i = pos[vid]
            self._names.append(vid)
            self._index[vid] = k
            self._x[k], self._y[k], self._yaw[k] = v.x[i], v.y[i], v.yaw[i]
            self._speed[k], self._length[k], self._width[k] = v.speed[i], v.length[i], v.width[i]
            last_edge = libsumo.vehicle.getRoute(vid)[-1]
            shape = np.asarray(libsumo.lane.getShape(f"{last_edge}_0"), np.float64)
            self._dest[k] = shape[-1]
            d = shape[-1] - shape[-2]
            self._dest_yaw[k] = np.arctan2(d[1], d[0])
            self._active[k] = True
            new.append(k)
        return np.array(new, np.int64)

    def _world(self, agents: np.ndarray) -> tuple[Boxes, list[str]]:
        """Boxes of the agents (first rows) then every other SUMO vehicle, with their ids."""
        v = self._sumo
        # string ids: a set lookup per vehicle (~30 µs for 400) beats np.isin on object arrays
        # (~2.5 ms, measured)
        ctrl = set(self._names[k] for k in np.flatnonzero(self._active))
        bg = [i for i, vid in enumerate(v.ids) if vid not in ctrl]
        boxes = Boxes(np.concatenate([self._x[agents], v.x[bg]]),
                      np.concatenate([self._y[agents], v.y[bg]]),
                      np.concatenate([self._yaw[agents], v.yaw[bg]]),
                      np.concatenate([self._length[agents], v.length[bg]]),
                      np.concatenate([self._width[agents], v.width[bg]]))
        return boxes, [self._names[k] for k in agents] + [v.ids[i] for i in bg]

    def _next_lights(self, agents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(A,) light code of each agent's next signal and (A,) distance to it (m, inf: none).

        libsumo has no bulk query for this; one ``getNextTLS`` call per agent (~µs each).
        """
        import libsumo

        code = np.zeros(agents.size)
        dist = np.full(agents.size, np.inf)
        for j, k in enumerate(agents):
            try:
                nxt = libsumo.vehicle.getNextTLS(self._names[k])
            except Exception:  # vehicle not (yet) in SUMO
                continue
            if nxt:
                _, _, d, state = nxt[0]
                code[j] = _LIGHT.get(state, 0)
                dist[j] = d
        return code, dist

    def _observe(self, agents: np.ndarray, lanes: LaneQuery | None = None
                 ) -> tuple[dict[str, np.ndarray], tuple[Boxes, list[str]]]:
        """Observations of ``agents``; ``lanes``: their lane query when already computed."""
        clock = time.perf_counter()
        world = self._world(agents)
        light, dist = self._next_lights(agents)
        self._lc[agents], self._ld[agents] = light, dist
        ego = EgoState(np.arange(agents.size), self._speed[agents], self._prev_action[agents],
                       self._dest[agents], self._dest_yaw[agents])
        obs = self.suite.observe(world[0], ego, 0, lanes,
                                 light=np.where(dist < 50.0, light, 0))
        self.sensor_time += time.perf_counter() - clock
        return {self._names[k]: obs[i] for i, k in enumerate(agents)}, world

    def _info(self, k: int, events: dict[str, bool], reason: str | None, other: str = "") -> dict:
        return {"step": self.t, "events": events, "reason": reason, "collided_with": other,
                "nan_actions": int(self._nan[k]), "clipped_actions": int(self._clipped[k]),
                "state": (float(self._x[k]), float(self._y[k]), float(self._yaw[k]),
                          float(self._speed[k]))}

    # ------------------------------------------------------------------ step
    def step(self, actions: dict[str, Any]):
        cfg = self.config
        if self._session is None:
            raise RuntimeError("call reset() before step()")
        act = np.flatnonzero(self._active)
        clean, nonfinite, outside, missing, extra = checked_actions(
            actions, [self._names[k] for k in act])
        self._nan[act] += nonfinite
        self._clipped[act] += outside
        count_actions(self.action_counts, actions, self._index, nonfinite, outside, missing,
                      extra)
        accel, steer = dynamics.denormalise(clean, cfg.limits, cfg.action_layout)
        red_before = self._lc[act] == 3
        dist_before = self._ld[act].copy()
        new = dynamics.step(dynamics.VehicleState(self._x[act], self._y[act], self._yaw[act],
                                                  self._speed[act]),
                            accel, steer, dynamics.WHEELBASE_RATIO * self._length[act], self.dt,
                            cfg.limits)
        moved = np.hypot(new.x - self._x[act], new.y - self._y[act])
        self._x[act], self._y[act], self._yaw[act], self._speed[act] = new.x, new.y, new.yaw, new.speed
        self._prev_action[act] = clean
        sess = self._session
        sess.move([self._names[k] for k in act], self._x[act], self._y[act], self._yaw[act],
                  self._length[act])
        departed, arrived = sess.step()
        self.t += 1
        self._sumo = sess.vehicles()
        arrived_set = set(arrived)
        joiners = self._join(departed)
        observed = np.concatenate([act, joiners])
        clock = time.perf_counter()
        lanes = self.suite.lane_query(self._x[observed], self._y[observed], self._yaw[observed])
        self.sensor_time += time.perf_counter() - clock
        obs, (boxes, ids) = self._observe(observed, lanes)
        other = first_overlap(boxes.x, boxes.y, boxes.yaw, boxes.length, boxes.width,
                              np.arange(act.size))
        flags = {
            "collision": other >= 0,
            "off_road": off_road(lanes.distance[:act.size], cfg.lane_width, cfg.off_road_margin),
            "red_light": red_before & (dist_before < moved),
            "destination": reached(self._x[act], self._y[act], self._dest[act],
                                   cfg.destination_radius),
        }
        gone_in_sumo = np.array([self._names[k] in arrived_set for k in act], bool)
        end = self.t >= cfg.max_steps
        out = StepDicts()
        leaving = out.stepped(
            [self._names[k] for k in act], flags, CITY_EVENTS, cfg.terminate_on,
            gone_in_sumo | end, np.where(gone_in_sumo, "arrived", "end_of_episode").tolist(),
            lambda i, ev, reason: self._info(act[i], ev, reason,
                                             ids[other[i]] if other[i] >= 0 else ""))
        out.joined([self._names[k] for k in joiners], end, "end_of_episode",
                   lambda j, reason: self._info(joiners[j], {}, reason))
        rewards, terms, truncs, infos = out.astuple()
        gone = act[leaving]
        if end:
            gone = np.concatenate([gone, joiners])
        self._active[gone] = False
        for k in gone:
            sess.remove(self._names[k])
        self.agents = [self._names[k] for k in np.flatnonzero(self._active)]
        self._record_fcd()
        return obs, rewards, terms, truncs, infos

    def agent_states(self):
        """Bicycle state of the live agents, in :attr:`agents` order
        (:class:`~magail_sumo.env.driving_env.AgentStates`; ``rows`` are agent indices)."""
        from .driving_env import AgentStates

        k = np.array([self._index[a] for a in self.agents], np.int64)
        return AgentStates(list(self.agents), k,
                           dynamics.VehicleState(self._x[k].copy(), self._y[k].copy(),
                                                 self._yaw[k].copy(), self._speed[k].copy()),
                           dynamics.WHEELBASE_RATIO * self._length[k])

    # ------------------------------------------------------------------ FCD
    def record_fcd(self, recorder=None):
        """Record every vehicle's pose from now on, each step (agents from their bicycle
        state, the others from SUMO), into ``recorder`` (default: a new
        :class:`~magail_sumo.sim.fcd.FcdRecorder`); returns it. Times are episode seconds."""
        from magail_sumo.sim.fcd import FcdRecorder

        self.fcd = recorder if recorder is not None else FcdRecorder(self.dt)
        if self._session is not None:
            self._record_fcd()
        return self.fcd

    def write_fcd(self, path: str | Path, recorder=None):
        """Write the recording as SUMO FCD plus a ``.sumocfg`` replaying it on the scenario's
        network in ``sumo-gui`` (:func:`~magail_sumo.sim.fcd.write_replay`)."""
        from magail_sumo.sim.fcd import write_replay

        rec = recorder if recorder is not None else self.fcd
        if rec is None:
            raise RuntimeError("nothing recorded: call record_fcd() first")
        return write_replay(rec, path, self.net_file)

    def _record_fcd(self) -> None:
        if self.fcd is None or self._session is None:
            return
        agents = np.flatnonzero(self._active)
        boxes, ids = self._world(agents)
        if not ids:
            return
        kind = ["agent"] * agents.size + ["sumo"] * (len(ids) - agents.size)
        ctrl = set(ids[:agents.size])
        v = self._sumo
        speed = np.concatenate([self._speed[agents],
                                [sp for vid, sp in zip(v.ids, v.speed) if vid not in ctrl]])
        self.fcd.add(self.t * self.dt, ids, boxes.x, boxes.y, boxes.yaw, boxes.length,
                     boxes.width, kind, "passenger", speed)
