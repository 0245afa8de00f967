"""Many rollouts of one recorded scene stepped as one fleet (a batched simulator core).

:class:`BatchedSceneEnv` holds ``W`` independent copies ("worlds") of a recorded scene with
log background and no SUMO (``background: log``, ``sumo_mirror: false``): every world's
controlled vehicles are rows of one :class:`~magail_sumo.env.fleet.Fleet`, world-major (fleet
row ``w·C + c`` is controlled vehicle ``c`` of world ``w``, ``C`` controlled vehicles per
world), and every stage of the env step (:class:`~magail_sumo.env.step.FleetEnv`) runs once
over all worlds' arrays: actions, gap guard, bicycle model, joins, lane query, every sensor,
events and outcomes. The log-replayed road users are the same in every world and are kept once
(shared boxes); an agent sees, follows and hits only its own world's agents and the shared
road users (:class:`~magail_sumo.sensors.worlds.BoxGroups`), so each world evolves exactly as
a :class:`~magail_sumo.env.driving_env.SumoDrivingEnv` of the scene with the same config and
the same actions does (``tests/test_batched_env.py`` checks observations, events, rewards and
states on the real WOMD and ScenarioNet scenes in ``data/``).

Two APIs: the PettingZoo dicts, agents named ``"<w>/<track id>"`` (:func:`world_name`;
:meth:`BatchedSceneEnv.split` turns a dict over all worlds into one dict per world keyed by
track id, :meth:`BatchedSceneEnv.merge` the other way, so a policy written for one world's dicts
serves each), and the array API of every recorded-scene env
(:meth:`~magail_sumo.env.driving_env.SumoDrivingEnv.reset_arrays`, ``step_arrays``: (N, 2)
actions over the fleet rows in, an :class:`~magail_sumo.env.outcomes.ArrayStep` out, no dict or
info per agent), which :func:`~magail_sumo.agents.rollout_worlds` and evaluation use. The worlds
run in lockstep from one ``reset``: the same start step, and the log runs on past steps with no
live agent only when no world has one (a single-world env skips them; the worlds' states are the
same either way, only the step count differs). Not here: SUMO-driven background or a SUMO mirror
(their worlds would differ in SUMO: the per-world env keeps them), FCD recording and rendering
(per world: the single-world env), and random start windows with a start-dependent set of
controlled vehicles.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.sensors.worlds import SHARED, BoxGroups

from .config import EnvConfig
from .driving_env import SumoDrivingEnv


def world_name(world: int, agent: str) -> str:
    """The batched env's name of agent ``agent`` (a track id) of world ``world``."""
    return f"{world}/{agent}"


class BatchedSceneEnv(SumoDrivingEnv):
    """``worlds`` copies of a recorded scene stepped as one fleet (module doc); the
    PettingZoo ``ParallelEnv`` API of :class:`SumoDrivingEnv` with world-prefixed names.

    :raises ValueError: ``worlds`` < 1, or a config the batched core does not run (module
        doc: SUMO background or mirror, FCD, random start windows with a start-dependent set
        of controlled vehicles).
    """

    def __init__(self, scene: Scene | str | Path, bundle: str | Path,
                 config: EnvConfig | None = None, worlds: int = 1) -> None:
        cfg = config or EnvConfig(sumo_mirror=False)
        if not isinstance(worlds, int) or isinstance(worlds, bool) or worlds < 1:
            raise ValueError(f"worlds must be an int >= 1, got {worlds!r}")
        if cfg.background != "log" or cfg.sumo_mirror:
            raise ValueError("a batched env runs log background without SUMO (background: "
                             f"log, sumo_mirror: false), got background: {cfg.background}, "
                             f"sumo_mirror: {str(cfg.sumo_mirror).lower()}")
        if cfg.fcd_dir is not None:
            raise ValueError("a batched env records no FCD (fcd_dir): record a single-world "
                             "env")
        if not isinstance(cfg.controlled, str) and cfg.start_window == "random":
            raise ValueError("a batched env needs the same controlled vehicles in every "
                             "episode: controlled a count or list with start_window: random is "
                             "not supported")
        self.worlds = worlds
        super().__init__(scene, bundle, cfg)

    # ------------------------------------------------------------------ worlds
    def _set_controlled(self, ctrl: np.ndarray) -> None:
        """Track rows ``ctrl`` controlled in every world: fleet rows world-major."""
        super()._set_controlled(ctrl)
        #: controlled vehicles per world
        self.per_world = int(ctrl.size)
        #: the controlled vehicles' track ids (each world's agents, unprefixed)
        self.world_agents = list(self._ctrl_names)
        self._ctrl = np.tile(ctrl, self.worlds)
        self._ctrl_names = [world_name(w, a) for w in range(self.worlds)
                            for a in self.world_agents]
        self._name_index = {a: k for k, a in enumerate(self._ctrl_names)}

    def world_of(self, rows: np.ndarray) -> np.ndarray:
        """(A,) world of fleet rows ``rows``."""
        return np.asarray(rows, np.int64) // max(self.per_world, 1)

    def _world(self, agents: np.ndarray):
        """The single-world env's boxes (agents first, then the log-replayed road users),
        grouped by world: the agents' own, the log-replayed ones shared."""
        boxes, ids = super()._world(agents)
        world = np.full(len(boxes), SHARED, np.int64)
        world[:agents.size] = self.world_of(agents)
        return replace(boxes, groups=BoxGroups.of(world, self.worlds)), ids

    # ------------------------------------------------------------------ dicts by world
    def split(self, values: dict) -> list[dict]:
        """A dict over all worlds' agents as one dict per world keyed by track id."""
        out: list[dict] = [{} for _ in range(self.worlds)]
        for name, v in values.items():
            w, _, agent = name.partition("/")
            out[int(w)][agent] = v
        return out

    def merge(self, per_world: list[dict]) -> dict:
        """One dict per world keyed by track id as one dict over all worlds' agents."""
        return {world_name(w, a): v for w, d in enumerate(per_world) for a, v in d.items()}

    # ------------------------------------------------------------------ not per world
    def record_fcd(self, recorder=None):
        raise NotImplementedError("a batched env records no FCD: record a single-world env")

    def render(self):
        raise NotImplementedError("a batched env does not render: render a single-world env")
