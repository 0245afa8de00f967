"""PettingZoo ``ParallelEnv`` over a converted scene: policy-driven vehicles in SUMO co-simulation.

One env step = one log step (0.1 s). Controlled vehicles (agents, named by their WOMD track id)
move by the kinematic bicycle model (:mod:`magail_sumo.sim.dynamics`) from normalised actions
``[accel, steer]`` in [-1, 1]² and are placed in SUMO with ``moveToXY``; their bicycle state,
not SUMO's, is their pose. Background route vehicles replay the log (placed in SUMO at their
recorded poses) or are driven by SUMO; objects SUMO does not carry (parked off-network
vehicles, pedestrians, ...) replay the log in the sensor and collision world; with SUMO
driving the background they are also obstacles in SUMO (placed at their recorded poses each
step, :class:`~magail_sumo.sim.session.Obstacles`), so SUMO's drivers brake for them.

Timeline: after ``reset`` the observation is of the episode's start step (``env.start``:
``EnvConfig.start_step``, a random step of the window with ``start_window: random``, or
``reset(options={"start_step": t})``); SUMO time after the step that produced log step ``t`` is
``(t + 1)·0.1`` s (a vehicle departing at ``t·0.1`` s is inserted by that step). The log before
the start is history: SUMO runs those steps (placing the log-replayed vehicles), agents join at
the start at their recorded poses, and one valid at the step before too starts with the log's
previous action (the expert data's, :func:`~magail_sumo.env.log_actions.log_prev_actions`), the
others with 0. An episode ends ``max_steps`` steps after its start (or with the log). An agent
joins at the first log step its track is valid (from the start on) and leaves on an event (see
:mod:`magail_sumo.env.events`; collision = oriented-box overlap with any other road user) or at
the last valid step of its track (``end_of_life``, truncation). Rewards are 0 (imitation learning supplies its own).
``infos[agent]`` follows both envs' contract (:mod:`magail_sumo.env.step`): ``step`` (log
step), ``events`` (name -> bool), ``reason`` (first event of
:data:`~magail_sumo.env.config.EVENTS` that ended the agent — ``end_of_life`` always counts —,
else ``end_of_episode`` when the episode's last step truncates it, else None),
``collided_with`` (the other road user's track id as a decimal string, like agent names; ``""``
when none), ``nan_actions`` and ``clipped_actions`` (this agent's running counts of
non-finite / out-of-range actions; non-finite entries become 0, out-of-range ones are clipped
to [-1, 1], a missing action counts as non-finite) and ``state``: the agent's bicycle state
``(x, y, yaw, speed)`` after this step (scene frame; m, rad, m/s), so no caller re-derives it.
The step runs the stages of :class:`~magail_sumo.env.step.FleetEnv` over the controlled
vehicles' :class:`~magail_sumo.env.fleet.Fleet` state. ``env.action_counts`` counts, per episode,
the agent-steps without an action (``missing``: the agent coasts with action 0), the actions
given for names that are no agent of the scene (``unknown``) or no longer / not yet live
(``departed``), both ignored, and the non-finite and clipped ones
(:func:`~magail_sumo.env.actions.action_summary` words them for a log line).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from converters import load_scene
from converters.sumo.bundle import SceneBundle
from magail_sumo.scene import Scene
from magail_sumo.sensors.command import RouteCommands
from magail_sumo.sensors.observation import (Boxes, EgoState, PathAhead, SensorSuite,
                                             observation_bounds)
from magail_sumo.sim import dynamics
from magail_sumo.sim.fcd import SHAPES, FcdRecorder, ReplayFiles, write_replay
from magail_sumo.sim.paths import Paths
from magail_sumo.sim.session import STEP_LENGTH, Obstacles, SessionConfig, SumoSession

from .actions import ACTION_COUNTS, cleaned
from .config import EVENTS, EnvConfig, draw_start, window_starts
from .events import RoadEdgeRule, StopLines
from .fleet import AgentStates, Fleet
from .outcomes import ArrayStep, StepDicts, leaving
from .fcd import EpisodeFcd
from .log_actions import log_prev_actions
from .render import AGENT, LOG_ONLY, OTHER, TopDownRenderer
from .step import END_OF_EPISODE, FleetEnv

__all__ = ["AgentStates", "SumoDrivingEnv"]


def _median_valid(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    v = np.where(valid, values.astype(np.float64), np.nan)
    with np.errstate(all="ignore"):
        out = np.nanmedian(np.where(valid.any(1)[:, None], v, 0.0), axis=1)
    return np.nan_to_num(out)


class _NoMirror:
    """The session of an episode without the SUMO mirror (``EnvConfig.sumo_mirror: false``):
    SUMO is neither started nor stepped, so no vehicle ever enters or leaves it. Nothing is
    moved (:meth:`SumoDrivingEnv._push` returns at once) and, as no vehicle is in SUMO, nothing
    is removed: stepping and closing are all an episode asks of it."""

    def step(self) -> tuple[list[str], list[str]]:
        return [], []

    def close(self) -> None:
        pass


_NO_MIRROR = _NoMirror()


class SumoDrivingEnv(FleetEnv):
    """Multi-agent driving in a recorded scene co-simulated with SUMO (module doc).

    :param scene: the recorded scene, or a scene file path (WOMD / ScenarioNet).
    :param bundle: folder with the scene's SUMO files (``convert_scene``'s ``DIR/<id>``), or that
        bundle already read (a :class:`~converters.sumo.bundle.SceneBundle`).
    """

    metadata = {"name": "magail_sumo_v0", "render_modes": ["rgb_array"], "render_fps": 10}
    events = EVENTS
    always_reasons = ("end_of_life",)

    def __init__(self, scene: Scene | str | Path, bundle: str | Path | SceneBundle,
                 config: EnvConfig | None = None, render_mode: str | None = None) -> None:
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.scene = scene
        self.bundle = bundle if isinstance(bundle, SceneBundle) else SceneBundle.load(scene, bundle)
        self.config = cfg = config or EnvConfig()
        self.action_counts = dict.fromkeys(ACTION_COUNTS, 0)
        self.guarded = 0  # agent-steps whose acceleration the gap guard lowered
        self.render_mode = render_mode
        self.dt = STEP_LENGTH
        tr = scene.tracks
        n, t_steps = tr.valid.shape
        self._track_span()
        rows = np.arange(n)
        last = np.maximum(self._last, 0)
        self._dest = np.stack([tr.x[rows, last], tr.y[rows, last]], axis=1)
        self._dest_yaw = tr.heading[rows, last].astype(np.float64)
        self._length = _median_valid(tr.length, tr.valid)
        self._width = _median_valid(tr.width, tr.valid)
        self._in_routes = np.zeros(n, bool)
        self._in_routes[self.bundle.sumo_rows] = True
        #: route vehicles that may be agents: all but those parked in a space off the lanes
        #: (scenery SUMO holds where it was recorded) unless the scene names them (the SDC, the
        #: tracks to predict); a vehicle standing on a lane the whole log (waiting in traffic)
        #: may be one
        named = {*self._sdc_rows(), *(p.track_index for p in scene.tracks_to_predict)}
        self._drivers = np.array([r for r, v in zip(self.bundle.sumo_rows.tolist(),
                                                     self.bundle.sumo_ids)
                                  if v not in self.bundle.spaces or r in named], np.int64)
        #: log step the current (or, before any reset, the first) episode starts at
        self.start = window_starts(cfg, t_steps)[0]
        self._set_controlled(self._select_controlled(self.start))
        # the K nearest change with a random start: any route vehicle may be an agent
        self.possible_agents = [str(int(tr.id[r])) for r in np.sort(self._drivers)] \
            if self._ctrl_depends_on_start() and cfg.start_window == "random" \
            else list(self._ctrl_names)
        self._window_rng: np.random.Generator | None = None
        self._prev_table: tuple[int, np.ndarray] | None = None  # (last step, log_prev_actions)
        self._row_of_sumo = dict(zip(self.bundle.sumo_ids, self.bundle.sumo_rows.tolist()))
        self.suite = SensorSuite(scene, cfg.observation)
        #: recorded routes for the route-command and route look-ahead features
        #: (``observation.command``, ``observation.route_points``, ``observation.route_stop``)
        ob = cfg.observation
        self._commands = RouteCommands.build(tr, ob.command_lookahead) \
            if ob.command or ob.route_points or ob.route_stop else None
        self.stop_lines = StopLines.build(scene)
        #: WOSAC's off-road test (``off_road_rule: road_edge`` in a scene with road edges)
        self._edges = self._edge_rule() if cfg.off_road_rule == "road_edge" else None
        low, high = observation_bounds(cfg.observation)
        # one space per agent (each seeded on its own at reset), copied from one built space:
        # building a Box checks its bounds (~80 µs), a batched env has thousands of agents
        obs_space = spaces.Box(low, high, dtype=np.float32)
        self._obs_spaces = {a: copy.copy(obs_space) for a in self.possible_agents}
        act = (dynamics.ACTION_SIZE,)
        act_space = spaces.Box(-1.0, 1.0, act, np.float32)
        self._act_spaces = {a: copy.copy(act_space) for a in self.possible_agents}
        self._session: SumoSession | None = None
        self._obstacles: Obstacles | None = None
        self._renderer: TopDownRenderer | None = None
        self.agents: list[str] = []
        self.t = 0
        self.sensor_time = 0.0  #: s spent in sensors and observations since reset
        #: FCD recording (:meth:`record_fcd`; automatic with ``EnvConfig.fcd_dir`` / ``fcd_every``)
        self._fcd = EpisodeFcd(self.dt, self._fcd_frame, self._fcd_replay, cfg.fcd_dir,
                               cfg.fcd_every)
        self._id_order: np.ndarray | None = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        return self._act_spaces[agent]

    def _track_span(self) -> None:
        """The log's length ``_T`` and each track's first and last recorded step (``_first``:
        ``_T`` when never recorded; ``_last``: -1) from :attr:`scene`'s tracks."""
        valid = self.scene.tracks.valid
        self._T = t_steps = valid.shape[1]
        has = valid.any(axis=1)
        self._first = np.where(has, np.argmax(valid, axis=1), t_steps)
        self._last = np.where(has, t_steps - 1 - np.argmax(valid[:, ::-1], axis=1), -1)

    def window_options(self, rng: np.random.Generator) -> dict:
        """``reset`` options of an episode whose start window is drawn from ``rng``
        (:func:`~magail_sumo.env.config.draw_start`; the scene worker's seeded draw)."""
        return {"start_step": draw_start(self.config, self.scene.num_steps, rng)}

    def _may_join(self) -> np.ndarray | bool:
        """Which controlled vehicles may join at the current step (here: all of them)."""
        return True

    def _sdc_rows(self) -> tuple[int, ...]:
        """Track rows of the scene's self-driving vehicle (a tiled scene has one per tile)."""
        return (self.scene.sdc_track_index,)

    def _edge_rule(self) -> RoadEdgeRule | None:
        """The road-edge off-road rule of the scene (None: no road edge; the lane rule)."""
        return RoadEdgeRule.build(self.scene, self.config.off_road_edge_margin, self._length,
                                  self._width)

    def _ctrl_depends_on_start(self) -> bool:
        return not isinstance(self.config.controlled, str)

    def _select_controlled(self, start: int) -> np.ndarray:
        """Sorted track rows of the controlled vehicles of an episode starting at ``start``."""
        sc, cfg = self.scene, self.config
        routes = self._drivers
        if cfg.controlled == "all":
            return np.sort(routes)
        if cfg.controlled == "sdc":
            return routes[routes == sc.sdc_track_index]
        if cfg.controlled in ("tracks_to_predict", "scored"):
            want = {p.track_index for p in sc.tracks_to_predict}
            if cfg.controlled == "scored":
                want.add(sc.sdc_track_index)
            return np.sort(routes[[r in want for r in routes.tolist()]]).astype(np.int64)
        tr, t = sc.tracks, min(start, self._T - 1)
        sdc = sc.sdc_track_index
        d = np.hypot(tr.x[routes, t] - tr.x[sdc, t], tr.y[routes, t] - tr.y[sdc, t])
        d = np.where(tr.valid[routes, t], d, np.inf)
        d = np.where(routes == sdc, -1.0, d)
        return np.sort(routes[np.argsort(d, kind="stable")[:int(cfg.controlled)]])

    def _set_controlled(self, ctrl: np.ndarray) -> None:
        """Make track rows ``ctrl`` (sorted) the controlled vehicles; the rest background."""
        tr, cfg = self.scene.tracks, self.config
        self._ctrl = ctrl
        self._ctrl_names = [str(int(tr.id[r])) for r in ctrl]
        self._name_index = {a: k for k, a in enumerate(self._ctrl_names)}
        is_ctrl = np.zeros(len(tr.id), bool)
        is_ctrl[ctrl] = True
        self._is_ctrl = is_ctrl
        in_routes = self._in_routes
        self._bg_rows = self.bundle.sumo_rows[~is_ctrl[self.bundle.sumo_rows]]
        self._bg_ids = [str(int(tr.id[r])) for r in self._bg_rows]
        self._log_rows = np.flatnonzero(~is_ctrl & (~in_routes | (cfg.background == "log")))
        #: road users SUMO does not carry (pedestrians, vehicles off the lane network): with SUMO
        #: driving the background they are obstacles its drivers see (:class:`Obstacles`)
        self._obstacle_rows = np.flatnonzero(~is_ctrl & ~in_routes) \
            if cfg.background == "sumo" else np.zeros(0, np.int64)

    def _episode_start(self, seed: int | None, options: dict | None) -> int:
        """The start step of the episode ``reset(seed, options)`` begins (module doc)."""
        cfg = self.config
        if seed is not None:
            self._window_rng = np.random.default_rng(seed % (1 << 64))
        opt = (options or {}).get("start_step")
        if opt is not None:
            top = max(0, self._T - 2)  # a step left to take
            ok = isinstance(opt, (int, np.integer)) and not isinstance(opt, bool) \
                and 0 <= opt <= top
            if not ok:
                raise ValueError(f"reset options start_step: must be an int in [0, {top}]"
                                 f" (scene {self.scene.scenario_id} has {self._T} steps), got "
                                 f"{opt!r}")
            return int(opt)
        if cfg.start_window == "random" and self._window_rng is None:
            self._window_rng = np.random.default_rng()
        return draw_start(cfg, self._T, self._window_rng)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, seed: int | None = None, options: dict | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start an episode (module doc). ``seed`` seeds SUMO (plus ``sumo_seed``), the spaces
        and the draw of a random window's start; ``options={"start_step": t}`` starts this
        episode at log step ``t`` (in [0, T - 2]) whatever ``start_window`` says (other option
        keys are ignored)."""
        cfg = self.config
        start = self._episode_start(seed, options)
        if self._ctrl_depends_on_start() and start != self.start:
            self._set_controlled(self._select_controlled(start))
            new = [a for a in self._ctrl_names if a not in self._obs_spaces]
            if new:  # an overridden start of a fixed window brought other vehicles in
                low, high = observation_bounds(cfg.observation)
                for a in new:
                    self._obs_spaces[a] = spaces.Box(low, high, dtype=np.float32)
                    self._act_spaces[a] = spaces.Box(-1.0, 1.0, (dynamics.ACTION_SIZE,), np.float32)
                self.possible_agents = self.possible_agents + new
        self.start = start
        if seed is not None:
            for k, a in enumerate(self.possible_agents):
                self._act_spaces[a].seed(seed + k)
                self._obs_spaces[a].seed(seed + k)
        self.close()
        self._fcd.begin_episode(self.scene.scenario_id)
        if not cfg.sumo_mirror:  # nothing of a log-background episode reads SUMO
            self._session = _NO_MIRROR
        else:
            self._session = SumoSession(inputs=self.bundle.inputs, config=SessionConfig(
                seed=cfg.sumo_seed + (seed or 0)))
            self._session.start()
        self._obstacles = None if not cfg.sumo_mirror else Obstacles(
            self._session, [str(int(i)) for i in self.scene.tracks.id[self._obstacle_rows]],
            self._length[self._obstacle_rows], self._width[self._obstacle_rows],
            kinds=self.scene.tracks.type[self._obstacle_rows]) \
            if self._obstacle_rows.size else None
        ctrl = self._ctrl
        #: the controlled vehicles' state (row k: ``self._ctrl[k]``, :class:`Fleet`)
        self.fleet = Fleet.roster(self._ctrl_names, self._length[ctrl], self._width[ctrl],
                                  self._dest[ctrl], self._dest_yaw[ctrl])
        if cfg.action_layout == "accel_offset":  # route-relative control: recorded routes
            self.paths = self._recorded_paths(ctrl)
            self.fleet.path[:ctrl.size] = np.arange(ctrl.size)
        #: this episode's fixed-up actions (:data:`~magail_sumo.env.actions.ACTION_COUNTS`)
        self.action_counts = dict.fromkeys(ACTION_COUNTS, 0)
        self.guarded = 0  # agent-steps whose acceleration the gap guard lowered
        self._bg_in_sumo: set[str] = set()  # background vehicles in SUMO
        self._sumo_bg = None
        self.sensor_time = 0.0
        self.t = -1
        self._end = self._T - 1 if cfg.max_steps is None else \
            min(self._T - 1, start + cfg.max_steps)
        self._advance()  # SUMO step producing log step 0
        while self.t < min(start, self._end):
            self._advance()
        joiners = self._join()
        while not joiners.size and self.t < self._end and (~self.fleet.joined).any():
            self._advance()
            joiners = self._join()
        self.agents = self.fleet.names_of(joiners)
        obs, _ = self._observe(joiners)
        info = self._infos_of(joiners)
        infos = {a: info(i, {}, None) for i, a in enumerate(self.agents)}
        self._record_fcd()
        return obs, infos

    def close(self) -> None:
        self._fcd.end_episode()
        if self._session is not None:
            self._session.close()
            self._session = None

    # ------------------------------------------------------------------ internals
    def _recorded_paths(self, rows: np.ndarray) -> Paths:
        """Reference paths of track ``rows`` (route-relative control): each one's recorded
        route, its valid positions from first to last (the route the recorded route
        look-ahead reads, :mod:`magail_sumo.sensors.command`), with the recorded speed limit
        of the lane at each position (the nearest lane running its way; 0: none or not
        recorded)."""
        tr, lanes = self.scene.tracks, self.scene.roadmap.lanes
        limit = np.array([ln.speed_limit for ln in lanes] + [0.0])  # [-1]: no lane
        polylines, limits = [], []
        for r in rows.tolist():
            v = tr.valid[r]
            if not v.any():
                polylines.append(np.zeros((1, 2)))
                limits.append(np.zeros(1))
                continue
            x, y, h = (np.asarray(a[r, v], np.float64) for a in (tr.x, tr.y, tr.heading))
            polylines.append(np.stack([x, y], axis=1))
            limits.append(limit[self.suite.lane_query(x, y, h).lane])
        return Paths.of(polylines, limits=limits)

    def _advance(self) -> None:
        """Place SUMO's controlled and log-replayed vehicles at log step t + 1, step SUMO."""
        self._push()
        self._sumo_step()

    def _push(self) -> None:
        """Step stage 3: place the live agents in SUMO at their poses, the log-replayed
        background and the obstacles at their recorded poses of log step t + 1."""
        if self._session is _NO_MIRROR:
            return
        sess, f = self._session, self.fleet
        nxt = self.t + 1
        ids: list[str] = []
        parts = []
        if self.t >= 0:
            act = f.live()
            k = act[f.in_sumo[act]]
            if k.size:
                ids += f.names_of(k)
                parts.append((f.x[k], f.y[k], f.yaw[k], f.length[k]))
            if self.config.background == "log" and self._bg_rows.size and nxt < self._T:
                tr = self.scene.tracks
                ok = [i for i, v in enumerate(self._bg_ids) if v in self._bg_in_sumo
                      and tr.valid[self._bg_rows[i], nxt]]
                if ok:
                    r = self._bg_rows[ok]
                    ids += [self._bg_ids[i] for i in ok]
                    parts.append((tr.x[r, nxt], tr.y[r, nxt], tr.heading[r, nxt].astype(np.float64),
                                  self._length[r]))
        if ids:
            x, y, yaw, length = (np.concatenate(p) for p in zip(*parts))
            sess.move(ids, x, y, yaw, length)
        if self._obstacles is not None and nxt < self._T:  # their recorded poses (NaN: gone)
            tr, r = self.scene.tracks, self._obstacle_rows
            ok = tr.valid[r, nxt]
            self._obstacles.place(np.where(ok, tr.x[r, nxt], np.nan),
                                  np.where(ok, tr.y[r, nxt], np.nan),
                                  tr.heading[r, nxt].astype(np.float64))

    def _sumo_step(self) -> tuple[list[str], list[str]]:
        """Step stage 4: SUMO steps to log step t + 1; who entered and left SUMO is noted (an
        agent that already left the episode is taken out as it enters)."""
        sess, f = self._session, self.fleet
        departed, arrived = sess.step()
        done = f.left()
        for vid in departed:
            # parked vehicles carry a SUMO stop; SUMO refuses to step one moved off its stop
            # (even after the stop is removed) and fails on removing it: SUMO keeps them parked
            if vid in self.bundle.parked:
                continue
            k = f.index.get(vid)
            if k is None:
                self._bg_in_sumo.add(vid)
            elif done[k]:
                sess.remove(vid)
            else:
                f.in_sumo[k] = True
        for vid in arrived:
            k = f.index.get(vid)
            if k is None:
                self._bg_in_sumo.discard(vid)
            else:
                f.in_sumo[k] = False
        self.t += 1
        self._sumo_bg = None
        return departed, arrived

    def log_state(self, rows: np.ndarray, t: int) -> dynamics.VehicleState:
        """Bicycle state of track ``rows`` at log step ``t`` as an agent joins with it: the
        recorded pose, and the recorded velocity along the heading as speed."""
        tr = self.scene.tracks
        yaw = tr.heading[rows, t].astype(np.float64)
        return dynamics.VehicleState(tr.x[rows, t], tr.y[rows, t], yaw,
                                     tr.vx[rows, t] * np.cos(yaw) + tr.vy[rows, t] * np.sin(yaw))

    def _log_prev_actions(self, t: int) -> np.ndarray:
        """:func:`~magail_sumo.env.log_actions.log_prev_actions` covering step ``t`` (cached)."""
        if self._prev_table is None or self._prev_table[0] < t:
            # the first need computes up to it (evaluation: the current step), a later one
            # further the whole log
            upto = t if self._prev_table is None else self._T - 1
            self._prev_table = (upto, log_prev_actions(self, upto))
        return self._prev_table[1]

    def _join(self, departed: list[str] | None = None) -> np.ndarray:
        """Step stage 5: controlled tracks valid at step t that never joined become agents at
        their recorded state; their fleet rows (``departed`` is not needed: the log says).

        A joiner valid at t - 1 too (only at the episode start: the log before it is history)
        gets the log's previous action (:func:`~magail_sumo.env.log_actions.log_prev_actions`),
        the others 0."""
        tr, t, f = self.scene.tracks, self.t, self.fleet
        new = np.flatnonzero(~f.joined & tr.valid[self._ctrl, t] & self._may_join())
        if new.size:
            r = self._ctrl[new]
            f.set_state(new, self.log_state(r, t))
            f.prev_action[new] = 0.0
            if t > 0:
                hist = tr.valid[r, t - 1]
                if hist.any():
                    f.prev_action[new[hist]] = self._log_prev_actions(t)[r[hist], t]
            f.join(new)
            if self.paths is not None:
                f.hint[new] = self.paths.project(f.path[new], f.x[new], f.y[new])[0]
        return new

    def _world(self, agents: np.ndarray) -> tuple[Boxes, np.ndarray]:
        """Boxes of the agents (first rows, in order) and every other road user at step t,
        plus (N,) track id of each box (-1 unknown)."""
        tr, t, f = self.scene.tracks, self.t, self.fleet
        rows = self._ctrl[agents]
        lr = self._log_rows[tr.valid[self._log_rows, t]]
        xs = [f.x[agents], tr.x[lr, t]]
        ys = [f.y[agents], tr.y[lr, t]]
        yaws = [f.yaw[agents], tr.heading[lr, t].astype(np.float64)]
        ls = [f.length[agents], tr.length[lr, t].astype(np.float64)]
        ws = [f.width[agents], tr.width[lr, t].astype(np.float64)]
        hd = tr.heading[lr, t].astype(np.float64)
        vs = [f.speed[agents], tr.vx[lr, t] * np.cos(hd) + tr.vy[lr, t] * np.sin(hd)]
        ids = [tr.id[rows], tr.id[lr]]
        if self.config.background == "sumo":
            if self._sumo_bg is None:
                v = self._session.vehicles()
                sel = [i for i, vid in enumerate(v.ids) if not self._is_ctrl[self._row_of_sumo[vid]]]
                self._sumo_bg = (v.x[sel], v.y[sel], v.yaw[sel], v.length[sel], v.width[sel],
                                 v.speed[sel], tr.id[[self._row_of_sumo[v.ids[i]] for i in sel]])
            for lst, arr in zip((xs, ys, yaws, ls, ws, vs, ids), self._sumo_bg):
                lst.append(np.asarray(arr))
        cat = lambda p: np.concatenate(p).astype(np.float64)  # noqa: E731
        return Boxes(cat(xs), cat(ys), cat(yaws), cat(ls), cat(ws), cat(vs)), np.concatenate(ids)

    def _observe(self, agents: np.ndarray, lanes=None
                 ) -> tuple[dict[str, np.ndarray], tuple[Boxes, np.ndarray]]:
        """Step stage 6: observations of fleet rows ``agents`` (sorted) by name, and the world
        (:meth:`_world`); ``lanes``: their lane query when already made."""
        obs, world = self._observe_rows(agents, lanes)
        names = self.fleet.names
        return {names[k]: obs[i] for i, k in enumerate(agents.tolist())}, world

    def _observe_rows(self, agents: np.ndarray, lanes=None
                      ) -> tuple[np.ndarray, tuple[Boxes, np.ndarray]]:
        """:meth:`_observe` as an (A, D) float32 array in the order of ``agents``."""
        import time

        clock = time.perf_counter()
        f = self.fleet
        world = self._world(agents)
        rows = self._ctrl[agents]
        ob = self.config.observation
        cmd = route = stop = None
        if ob.command:
            cmd = self._commands.commands(rows, f.x[agents], f.y[agents])
        if ob.route_points:
            route = self._commands.ahead(rows, f.x[agents], f.y[agents], f.yaw[agents],
                                         ob.route_points)
        if ob.route_stop:
            stop = self._commands.stop_ahead(rows, f.x[agents], f.y[agents])
        ahead = None
        if (ob.path_leader or ob.speed_limit) and self.paths is not None:  # route-relative
            s = self._route_progress(agents)
            ahead = PathAhead(self.paths, f.path[agents], f.hint[agents], s)
        ego = EgoState(np.arange(agents.size), f.speed[agents], f.prev_action[agents],
                       f.dest[agents], f.dest_yaw[agents], cmd, route, ahead, stop)
        obs = self.suite.observe(world[0], ego, self.t, lanes)
        self.sensor_time += time.perf_counter() - clock
        return obs, world

    # ------------------------------------------------------------------ array API
    @property
    def finished(self) -> bool:
        """The episode is over: its last step is taken, or nobody is live and nobody is to
        join (the array API's loop condition; the dict API's is ``env.agents``)."""
        f = self.fleet
        return self.t >= self._end or not (f.active.any() or (~f.joined).any())

    def reset_arrays(self, seed: int | None = None, options: dict | None = None) -> ArrayStep:
        """:meth:`reset` for the array API: the observations of the fleet rows (every world's
        agents of a batched env) as an :class:`~magail_sumo.env.outcomes.ArrayStep` (rows
        ``observed``: the agents joining at the start; ``live``: the same)."""
        obs, _ = self.reset(seed=seed, options=options)
        f = self.fleet
        n = len(f)
        self._obs_rows = np.zeros((n, self.suite.size), np.float32)
        rows = f.rows_of(list(obs))
        if rows.size:
            self._obs_rows[rows] = np.stack(list(obs.values()))
        seen = np.zeros(n, bool)
        seen[rows] = True
        return ArrayStep(self._obs_rows, seen, f.active[:n].copy(), np.zeros(n), np.zeros(n, bool),
                         np.zeros(n, bool), {e: np.zeros(n, bool) for e in self.events})

    def step_arrays(self, actions: np.ndarray) -> ArrayStep:
        """One step of the array API: ``actions`` (N, 2) over the fleet rows (rows not live
        are ignored; non-finite entries count and become 0, the rest are clipped to [-1, 1],
        as in :meth:`step`); the same stages and outcome as :meth:`step` without a dict or an
        info per agent (:class:`~magail_sumo.env.outcomes.ArrayStep`). Steps that find no live
        agent run on (the dict API skips ahead to the next joiner): loop while not
        :attr:`finished`."""
        if self._session is None:
            raise RuntimeError("call reset_arrays() before step_arrays()")
        f = self.fleet
        n = len(f)
        actions = np.asarray(actions)
        if actions.shape != (n, dynamics.ACTION_SIZE):
            raise ValueError(f"step_arrays: actions must be ({n}, {dynamics.ACTION_SIZE}) "
                             f"(one row per fleet row), got {actions.shape}")
        act = f.live()
        clean, nonfinite, outside = cleaned(actions[act])
        f.count_fixes(act, nonfinite, outside)
        self.action_counts["nonfinite"] += int(nonfinite.sum())
        self.action_counts["clipped"] += int(outside.sum())
        st = self._stages(act, clean, self._observe_rows)
        end = self.t >= self._end
        time_up, _ = self._time_up(act, st.flags, end, st.arrived)
        term, trunc = leaving(st.flags, self.config.terminate_on, time_up)
        self._leave(act[term | trunc], st.joiners, end)
        self._obs_rows[st.agents] = st.obs
        seen = np.zeros(n, bool)
        seen[st.agents] = True
        rewards, terminated, truncated = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        if st.reward is not None:
            rewards[act] = st.reward
        terminated[act], truncated[act] = term, trunc
        truncated[st.joiners] = end
        events = {}
        for name in self.events:
            ev = np.zeros(n, bool)
            ev[act] = st.flags[name]
            events[name] = ev
        self.agents = f.names_of(f.live())
        self._record_fcd()
        return ArrayStep(self._obs_rows, seen, f.active[:n].copy(), rewards, terminated,
                         truncated, events)

    def run_on_arrays(self) -> np.ndarray:
        """The dict API's skip ahead, for the array API: after a step that left nobody live
        with agents still to come, run the log on until someone joins, exactly as
        :meth:`step` does before it returns (the same steps, joins and observations); the fleet
        rows that joined (sorted; live, their observations in the rows of the last
        :class:`~magail_sumo.env.outcomes.ArrayStep`'s buffer), empty when none joined. A
        single-world caller that wants the dict API's episodes (the scene worker) calls it;
        lockstep callers (batched worlds) step on instead."""
        late = self._run_on()
        if late.size:
            self._obs_rows[late] = self._observe_rows(late)[0]
            self.agents = self.fleet.names_of(self.fleet.live())
        return late

    def array_reasons(self, step: ArrayStep, rows: np.ndarray) -> list[str | None]:
        """``infos[agent]["reason"]`` of fleet rows ``rows`` in the array step ``step``, as
        the dict API words it: the first event of :attr:`events` in ``terminate_on`` or
        :attr:`always_reasons` that the row had, else :data:`~magail_sumo.env.step.
        END_OF_EPISODE` when it was truncated (a recorded scene truncates for no other
        reason, :meth:`_time_up`), else None."""
        reasons = set(self.config.terminate_on) | set(self.always_reasons)
        cols = [(e, step.events[e][rows].tolist()) for e in self.events if e in reasons]
        trunc = step.truncated[rows].tolist()
        out: list[str | None] = []
        for i in range(len(trunc)):
            why = next((e for e, col in cols if col[i]), None)
            out.append(why if why is not None else (END_OF_EPISODE if trunc[i] else None))
        return out

    # ------------------------------------------------------------------ step hooks
    def step(self, actions: dict[str, Any]):
        """One log step (module doc; the stages: :class:`~magail_sumo.env.step.FleetEnv`)."""
        out = super().step(actions)
        if not self.agents:
            self._fcd.end_episode()
        return out

    def _red_light(self, act: np.ndarray, p0: np.ndarray, ctx) -> np.ndarray:
        """Crossed the stop line of a red signal during the step (:class:`StopLines`)."""
        return self.stop_lines.red_crossings(self.t - 1, p0, self.fleet.position(act),
                                             self.config.lane_width)

    def _off_road(self, act: np.ndarray, stepped: np.ndarray, lanes) -> np.ndarray:
        """Off-road by the road edges (``off_road_rule: road_edge``), else by the lanes."""
        if self._edges is None:
            return super()._off_road(act, stepped, lanes)
        f = self.fleet
        return self._edges.off_road(self._ctrl[act], self.t, f.x[act], f.y[act], f.yaw[act],
                                    f.length[act], f.width[act])

    def _more_events(self, act: np.ndarray) -> dict[str, np.ndarray]:
        """``end_of_life``: the agent's track has no later recorded step (never with
        ``config.end_of_life`` off)."""
        if not self.config.end_of_life:
            return {"end_of_life": np.zeros(act.size, bool)}
        return {"end_of_life": self.t >= self._last[self._ctrl[act]]}

    def _time_up(self, act: np.ndarray, flags: dict[str, np.ndarray], end: bool,
                 arrived: list[str]) -> tuple[np.ndarray, list[str]]:
        """Out of time: at the end of the agent's track (reason ``end_of_life``) or of the
        episode (:data:`~magail_sumo.env.step.END_OF_EPISODE`)."""
        return flags["end_of_life"] | end, [END_OF_EPISODE] * act.size

    def _road_user(self, ids: np.ndarray, j: int) -> str:
        """Name of world box ``j``: its track id as a decimal string."""
        return str(int(ids[j]))

    def _after_step(self, obs: dict, out: StepDicts) -> None:
        """Nobody left but agents to come: run the log on until someone joins (they join the
        step's dicts as live agents)."""
        late = self._run_on()
        if late.size:
            f = self.fleet
            rewards, terms, truncs, infos = out.astuple()
            more, _ = self._observe(late)
            info = self._infos_of(late)
            for i, k in enumerate(late):
                name = f.names[k]
                obs[name] = more[name]
                rewards[name], terms[name], truncs[name] = 0.0, False, False
                infos[name] = info(i, {}, None)

    def _run_on(self) -> np.ndarray:
        """While nobody is live, agents are to come and the episode has steps left: run the
        log on one step and let them join; the fleet rows that joined (empty: none)."""
        f = self.fleet
        while not f.active.any() and self.t < self._end and (~f.joined).any():
            self._advance()
            late = self._join()
            if late.size:
                return late
        return np.zeros(0, np.int64)

    def _agent_rows(self, k: np.ndarray) -> np.ndarray:
        """Track rows of fleet rows ``k``."""
        return self._ctrl[k]

    # ------------------------------------------------------------------ FCD
    def _fcd_frame(self, recorder: FcdRecorder) -> None:
        """Add step t's poses of all road users to ``recorder`` (agents, SUMO- and log-driven
        objects; the same world the sensors see)."""

        tr = self.scene.tracks
        agents = self.fleet.live()
        boxes, ids = self._world(agents)
        if not len(ids):
            return
        if self._id_order is None:
            self._id_order = np.argsort(tr.id, kind="stable")
        pos = np.clip(np.searchsorted(tr.id[self._id_order], ids), 0, len(tr.id) - 1)
        rows = self._id_order[pos]
        kind = np.full(len(ids), "log", dtype=object)
        if self.config.background == "sumo":
            kind[np.isin(ids, [int(v) for v in self.bundle.sumo_ids])] = "sumo"
        kind[:agents.size] = "agent"
        shape = [SHAPES.get(int(t), "passenger") for t in tr.type[rows]]
        speed = np.hypot(tr.vx[rows, self.t], tr.vy[rows, self.t]).astype(np.float64)
        speed[:agents.size] = self.fleet.speed[agents]
        if self.config.background == "sumo":
            speed[kind == "sumo"] = np.nan  # derived from the recorded positions
        recorder.add(self.t * self.dt, [str(int(i)) for i in ids], boxes.x, boxes.y, boxes.yaw,
                     boxes.length, boxes.width, list(kind), shape, speed)

    def _fcd_replay(self, recorder: FcdRecorder, path: Path) -> ReplayFiles:
        """The recording replayed on this scene's converted network with its signal
        programs."""
        files = self.bundle.files
        return write_replay(recorder, path, files.net,
                            [files.signals] if files.signals.is_file() else [])

    # ------------------------------------------------------------------ helpers
    def render(self) -> np.ndarray | None:
        """Top-down RGB frame (H, W, 3) uint8 of step t: agents green, SUMO vehicles blue,
        log-only objects grey."""
        if self.render_mode is None:
            return None
        if self._renderer is None:
            tr = self.scene.tracks
            xs, ys = tr.x[tr.valid], tr.y[tr.valid]
            pad = 10.0
            self._renderer = TopDownRenderer(self.scene, (xs.min() - pad, ys.min() - pad,
                                                          xs.max() + pad, ys.max() + pad),
                                             self.config.render_size)
        agents = self.fleet.live()
        boxes, ids = self._world(agents)
        col = np.empty((len(boxes), 3), np.uint8)
        col[:] = LOG_ONLY
        routed = np.isin(ids, [int(v) for v in self.bundle.sumo_ids])
        col[routed] = OTHER
        col[:agents.size] = AGENT
        return self._renderer.frame(boxes.x, boxes.y, boxes.yaw, boxes.length, boxes.width, col)
