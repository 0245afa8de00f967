"""One env step as named stages, shared by both envs (recorded scenes and SUMO cities).

:class:`FleetEnv` is the PettingZoo ``ParallelEnv`` base of
:class:`~magail_sumo.env.driving_env.SumoDrivingEnv` and
:class:`~magail_sumo.env.city_env.SumoCityEnv`. Its :meth:`~FleetEnv.step` runs, in order
(as sumo-rl's env step does):

1. **clean actions** — the action dict to a clean (A, 2) array over the live agents
   (:func:`~magail_sumo.env.actions.checked_actions`), counting what was fixed;
2. **guard** — with ``guard.kind: gap`` (or ``path``), accelerations that would leave an
   agent unable to stop behind its leader are lowered (:mod:`~magail_sumo.env.guard`; hook
   ``_world``: the road users at the step's start);
3. **dynamics** — the live agents move one step by the bicycle model
   (:meth:`~magail_sumo.env.fleet.Fleet.drive`; in the ``accel_offset`` layout steered along
   their reference paths, :mod:`magail_sumo.sim.tracking`);
4. **push to SUMO** — the env places its SUMO vehicles for the next step (hook ``_push``);
5. **SUMO step** — SUMO advances one step (hook ``_sumo_step``: the env's bookkeeping of who
   entered and left SUMO);
6. **joins** — new agents (hook ``_join``: from the log, or from SUMO's departures);
7. **observe** — observations of the stepped agents and joiners (hook ``_observe``), with one
   lane query shared by the sensors and the off-road rule;
8. **events** — collision (oriented-box overlap with any other road user), off-road,
   red-light (hook ``_red_light``), destination, plus env-specific ones (hook ``_more_events``);
9. **outcomes** — rewards (0, or with a progress reward (hook ``_progress_reward``) that many
   per metre the agent moved along its reference path), terminations, truncations and infos
   (:class:`~magail_sumo.env.outcomes.StepDicts`; hook ``_time_up``: who is out of time and
   why); agents that left are taken out of SUMO.

The envs differ only in the hooks: where agents and background come from (the log vs SUMO's
routes) and their extra events.

**Info contract (both envs)**: ``infos[agent]`` has ``step`` (the env's step counter after the
step), ``events`` (event name -> bool, the env's event order; empty for joiners), ``reason``
(str or None: the first event of the env's order that ended the agent, else its truncation
reason, :data:`END_OF_EPISODE` when the episode's time is up), ``collided_with`` (str: the name
of the road user the agent's box overlapped first — a recorded track id as a decimal string,
as agent names are, or a SUMO vehicle id; ``""`` when none), ``nan_actions`` and
``clipped_actions`` (int: the agent's running counts) and ``state`` (the agent's bicycle state
``(x, y, yaw, speed)`` after the step, floats: scene frame, m, rad, m/s).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from pettingzoo import ParallelEnv

from magail_sumo.sensors.base import PathAhead
from magail_sumo.sensors.units.leader import nearest_ahead
from magail_sumo.sensors.units.path_leader import along_path
from magail_sumo.sim.fcd import FcdRecorder, ReplayFiles
from magail_sumo.sim.paths import Paths

from .actions import checked_actions, count_actions
from .collision import first_overlap
from .events import off_road, reached
from .fleet import AgentStates, Fleet
from .guard import guarded
from .outcomes import StepDicts

#: truncation reason of an agent still live when the episode's time is up (both envs)
END_OF_EPISODE = "end_of_episode"
#: ``infos[agent]["collided_with"]`` of an agent that overlapped nobody
NO_ONE = ""


@dataclass
class Stages:
    """What stages 2 to 8 of one step produced (:meth:`FleetEnv._stages`).

    :param agents: (A',) sorted fleet rows observed: the stepped agents and the joiners.
    :param joiners: fleet rows that joined. :param obs: their observations (the observe
        hook's form). :param flags: event name -> (A,) bool of the stepped rows.
    :param other: (A,) world row each stepped row's box overlaps first (-1: none).
    :param ids: the world boxes' ids. :param arrived: SUMO ids that arrived.
    :param reward: (A,) progress rewards of the stepped rows (None: 0).
    """

    agents: np.ndarray
    joiners: np.ndarray
    obs: Any
    flags: dict[str, np.ndarray]
    other: np.ndarray
    ids: Any
    arrived: Sequence[str]
    reward: np.ndarray | None


class FleetEnv(ParallelEnv):
    """Base of both envs: the :class:`Fleet` state and the step of named stages (module doc).

    A subclass sets, in ``reset``: :attr:`fleet`, ``_session`` (the running
    :class:`~magail_sumo.sim.session.SumoSession`), ``t`` and ``_end`` (the last step of the
    episode: it ends when ``t >= _end``), ``action_counts``, ``guarded``, ``sensor_time``;
    and it implements the hooks ``_push``, ``_sumo_step``, ``_join``, ``_observe``,
    ``_red_light``, ``_time_up``, ``_road_user``, ``_world`` (and, when it has some,
    ``_before_move``, ``_off_road``, ``_more_events``, ``_after_step``, ``_agent_rows``).
    """

    #: event names in the order the first one found becomes the reason
    events: tuple[str, ...] = ()
    #: events that are a reason even outside ``terminate_on``
    always_reasons: tuple[str, ...] = ()
    fleet: Fleet
    #: the agents' reference paths (fleet column ``path``): set by an env with the
    #: ``accel_offset`` action layout (route-relative control) or a route look-ahead
    paths: Paths | None = None

    # ------------------------------------------------------------------ the step
    def step(self, actions: dict[str, Any]):
        if self._session is None:
            raise RuntimeError("call reset() before step()")
        act = self.fleet.live()
        clean = self._clean_actions(actions, act)
        st = self._stages(act, clean, self._observe)
        out = self._outcomes(act, st.joiners, st.flags, st.other, st.ids, st.arrived,
                             st.reward)
        self._after_step(st.obs, out)
        self.agents = self.fleet.names_of(self.fleet.live())
        self._record_fcd()
        return (st.obs, *out.astuple())

    def _stages(self, act: np.ndarray, clean: np.ndarray, observe) -> "Stages":
        """Stages 2 to 8 for the live rows ``act`` under their clean actions; ``observe``:
        the observe hook (:meth:`_observe`, or an env's array form of it)."""
        p0 = self.fleet.position(act)
        s0 = self._route_progress(act) if self._progress_reward() else None
        ctx = self._before_move(act)
        clean = self._guard(act, clean)
        self._dynamics(act, clean)
        self._push()
        departed, arrived = self._sumo_step()
        joiners = self._join(departed)
        agents = np.sort(np.concatenate([act, joiners]), kind="stable")
        lanes = self._lane_query(agents)
        obs, (boxes, ids) = observe(agents, lanes)
        stepped = np.searchsorted(agents, act)
        flags, other = self._events(act, stepped, p0, boxes, lanes, ctx)
        reward = None if s0 is None else \
            self._progress_reward() * (self._route_progress(act) - s0)
        return Stages(agents, joiners, obs, flags, other, ids, arrived, reward)

    # ------------------------------------------------------------------ stages
    def _clean_actions(self, actions: dict[str, Any], act: np.ndarray) -> np.ndarray:
        """Stage 1: (A, 2) clean actions of rows ``act``; counts the fixed ones."""
        f = self.fleet
        clean, nonfinite, outside, missing, extra = checked_actions(actions, f.names_of(act))
        f.count_fixes(act, nonfinite, outside)
        count_actions(self.action_counts, actions, f.index, nonfinite, outside, missing, extra)
        return clean

    def _guard(self, act: np.ndarray, clean: np.ndarray) -> np.ndarray:
        """Stage 2: ``clean`` with the gap guard's caps (unchanged when it is off); counts the
        lowered accelerations in ``guarded``."""
        cfg, f = self.config, self.fleet
        g = cfg.guard
        if not g.on or act.size == 0:
            return clean
        boxes, _ = self._world(act)
        if g.kind == "path" and self.paths is not None:  # along the reference paths
            s = self._route_progress(act)
            gap, along, found = along_path(boxes, np.arange(act.size),
                                           PathAhead(self.paths, f.path[act], f.hint[act], s),
                                           g.range)
        else:
            gap, along, found = nearest_ahead(boxes, np.arange(act.size), f.x[act], f.y[act],
                                              f.yaw[act], g.range, oriented=True)
        out, lowered = guarded(clean, f.speed[act], gap, along, found, g, cfg.limits,
                               cfg.action_layout, self.dt)
        self.guarded += int(lowered.sum())
        return out

    def _dynamics(self, act: np.ndarray, clean: np.ndarray) -> None:
        """Stage 3: the bicycle model moves rows ``act`` (steered along their reference paths
        in the ``accel_offset`` layout)."""
        cfg = self.config
        self.fleet.drive(act, clean, cfg.limits, cfg.action_layout, self.dt, self.paths)

    def _lane_query(self, agents: np.ndarray):
        """Lane query of rows ``agents`` (sensors and off-road share it; timed as sensors)."""
        f = self.fleet
        clock = time.perf_counter()
        lanes = self.suite.lane_query(f.x[agents], f.y[agents], f.yaw[agents])
        self.sensor_time += time.perf_counter() - clock
        return lanes

    def _events(self, act: np.ndarray, stepped: np.ndarray, p0: np.ndarray, boxes, lanes,
                ctx) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Stage 8: event name -> (A,) bool of the stepped rows ``act`` (at world rows
        ``stepped``), and (A,) world row of the first box each overlaps (-1: none)."""
        cfg, f = self.config, self.fleet
        other = first_overlap(boxes.x, boxes.y, boxes.yaw, boxes.length, boxes.width, stepped,
                              boxes.groups)
        flags = {
            "collision": other >= 0,
            "off_road": self._off_road(act, stepped, lanes),
            "red_light": self._red_light(act, p0, ctx),
            "destination": reached(f.x[act], f.y[act], f.dest[act], cfg.destination_radius),
        }
        flags.update(self._more_events(act))
        return flags, other

    def _outcomes(self, act: np.ndarray, joiners: np.ndarray, flags: dict[str, np.ndarray],
                  other: np.ndarray, ids, arrived: Sequence[str],
                  reward: np.ndarray | None = None) -> StepDicts:
        """Stage 9: the step's dicts (``reward``: (A,) of the stepped agents, None: 0);
        agents that left become inactive and leave SUMO."""
        cfg, f = self.config, self.fleet
        end = self.t >= self._end
        time_up, why = self._time_up(act, flags, end, arrived)
        out = StepDicts()
        info, hit = self._infos_of(act), other.tolist()
        leaving = out.stepped(
            f.names_of(act), flags, self.events, cfg.terminate_on, time_up, why,
            lambda i, ev, reason: info(
                i, ev, reason, self._road_user(ids, hit[i]) if hit[i] >= 0 else NO_ONE),
            always_reasons=self.always_reasons, rewards=reward)
        joined = self._infos_of(joiners)
        out.joined(f.names_of(joiners), end, END_OF_EPISODE,
                   lambda j, reason: joined(j, {}, reason))
        self._leave(act[leaving], joiners, end)
        return out

    def _progress_reward(self) -> float:
        """Reward per metre an agent moves along its reference path in a step (0: rewards
        are 0); an env with paths and a progress reward overrides it."""
        return 0.0

    def _route_progress(self, rows: np.ndarray) -> np.ndarray:
        """(A,) arc length (m) of fleet rows' positions on their reference paths (their
        progress hints follow)."""
        f = self.fleet
        at, s = self.paths.project(f.path[rows], f.x[rows], f.y[rows], f.hint[rows])
        f.hint[rows] = at
        return s

    def _leave(self, gone: np.ndarray, joiners: np.ndarray, end: bool) -> None:
        """Rows ``gone`` (stepped agents that ended), and at the episode's ``end`` the step's
        ``joiners`` too, stop being agents; their vehicles leave SUMO."""
        if end:
            gone = np.concatenate([gone, joiners])
        f = self.fleet
        f.active[gone] = False
        for k in gone:
            if f.in_sumo[k]:
                self._session.remove(f.names[k])
                f.in_sumo[k] = False

    def _infos_of(self, rows: np.ndarray):
        """``info(i, events, reason, other="")``: the ``infos`` (module doc) of fleet row
        ``rows[i]``, now; the rows' counts and states are read once, as Python numbers."""
        f, t = self.fleet, self.t
        nan, clip = f.nan_actions[rows].tolist(), f.clipped_actions[rows].tolist()
        state = np.stack([f.x[rows], f.y[rows], f.yaw[rows], f.speed[rows]], axis=1).tolist()

        def info(i: int, events: dict[str, bool], reason: str | None, other: str = NO_ONE):
            return {"step": t, "events": events, "reason": reason, "collided_with": other,
                    "nan_actions": nan[i], "clipped_actions": clip[i], "state": tuple(state[i])}
        return info

    # ------------------------------------------------------------------ hooks each env implements
    def _push(self) -> None:
        """Stage 4: place the env's SUMO vehicles (live agents first) for the next step."""
        raise NotImplementedError

    def _sumo_step(self) -> tuple[list[str], list[str]]:
        """Stage 5: step SUMO (and ``t``); (departed ids, arrived ids) of that step."""
        raise NotImplementedError

    def _join(self, departed: list[str]) -> np.ndarray:
        """Stage 6: rows that become agents now (sorted, joined and active)."""
        raise NotImplementedError

    def _observe(self, agents: np.ndarray, lanes=None) -> tuple[dict, tuple[Any, Any]]:
        """Stage 7: observations of rows ``agents`` (sorted) by name, and the world:
        (boxes of the agents, in order, then every other road user; the boxes' ids)."""
        raise NotImplementedError

    def _red_light(self, act: np.ndarray, p0: np.ndarray, ctx: Any) -> np.ndarray:
        """(A,) bool: the stepped rows ``act`` (at ``p0`` before the step) ran a red light."""
        raise NotImplementedError

    def _time_up(self, act: np.ndarray, flags: dict[str, np.ndarray], end: bool,
                 arrived: list[str]) -> tuple[np.ndarray, list[str]]:
        """(A,) bool: stepped rows out of time (truncated unless terminated), and (A,) the
        truncation reason no event explains (``end``: the episode's last step)."""
        raise NotImplementedError

    def _road_user(self, ids: Any, j: int) -> str:
        """The name of world box ``j`` (``collided_with``)."""
        raise NotImplementedError

    def _world(self, agents: np.ndarray) -> tuple[Any, Any]:
        """Boxes (:class:`~magail_sumo.sensors.base.Boxes`, with speeds) of rows ``agents``
        (first, in order) and of every other road user at the current step, and their ids."""
        raise NotImplementedError

    def _fcd_frame(self, recorder: FcdRecorder) -> None:
        """Add the current step's road users to ``recorder`` (the env's FCD recording)."""
        raise NotImplementedError

    def _fcd_replay(self, recorder: FcdRecorder, path: Path) -> ReplayFiles:
        """Write ``recorder`` with the ``.sumocfg`` replaying it on the env's network."""
        raise NotImplementedError

    # ------------------------------------------------------------------ FCD
    @property
    def fcd(self) -> FcdRecorder | None:
        """The FCD recorder in use (None: not recording; :class:`~magail_sumo.env.fcd.
        EpisodeFcd`)."""
        return self._fcd.recorder

    def record_fcd(self, recorder: FcdRecorder | None = None) -> FcdRecorder:
        """Record every road user's pose from now on, each step, into ``recorder`` (a new
        :class:`~magail_sumo.sim.fcd.FcdRecorder` when None); returns it. Write it with
        :meth:`write_fcd`. Recording starts with the current step when an episode is running.
        Times are episode seconds."""
        return self._fcd.record(recorder, running=self._session is not None)

    def write_fcd(self, path: str | Path, recorder: FcdRecorder | None = None) -> ReplayFiles:
        """Write ``recorder`` (default: :attr:`fcd`) as SUMO FCD plus a ``.sumocfg`` replaying
        it in ``sumo-gui`` on the env's network (:func:`~magail_sumo.sim.fcd.write_replay`);
        returns the :class:`~magail_sumo.sim.fcd.ReplayFiles`."""
        return self._fcd.write(path, recorder)

    def _record_fcd(self) -> None:
        """Add the step's poses to the env's FCD recording, if any (and a session runs)."""
        if self._session is not None:
            self._fcd.add_step()

    # ------------------------------------------------------------------ optional hooks
    def _before_move(self, act: np.ndarray) -> Any:
        """What the events need from before the step besides the positions (none here)."""
        return None

    def _off_road(self, act: np.ndarray, stepped: np.ndarray, lanes) -> np.ndarray:
        """(A,) bool: the stepped rows ``act`` are off-road (here: the lane rule)."""
        cfg = self.config
        return off_road(lanes.distance[stepped], cfg.lane_width, cfg.off_road_margin)

    def _more_events(self, act: np.ndarray) -> dict[str, np.ndarray]:
        """Env-specific events of the stepped rows ``act`` (none here)."""
        return {}

    def _after_step(self, obs: dict, out: StepDicts) -> None:
        """Runs after the outcomes, before the live agents are listed (nothing here)."""

    def _agent_rows(self, k: np.ndarray) -> np.ndarray:
        """What :meth:`agent_states` reports as the rows of fleet rows ``k`` (here: ``k``)."""
        return k

    # ------------------------------------------------------------------ accessors
    def agent_states(self) -> AgentStates:
        """Bicycle state of the live agents, in :attr:`agents` order (for
        :func:`~magail_sumo.env.log_actions.expert_actions` and policies that need poses)."""
        k = self.fleet.rows_of(self.agents)
        return self.fleet.agent_states(k, self._agent_rows(k))
