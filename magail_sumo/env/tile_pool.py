"""A worker's shard of a scene pool played several scenes at a time, each group one tiled env.

With ``workers.scenes_per_env: K`` (K > 1) a scene worker steps K recorded scenes of its shard
as one fleet (:class:`~magail_sumo.env.tiled.TiledScenesEnv`): the step's fixed cost, most of a
worker's time with a dozen agents per scene, is paid once for K scenes. :class:`TileCursor` is
the :class:`~magail_sumo.env.scene_pool.PoolCursor` interface the
:class:`~magail_sumo.env.slot_worker.SlotWorker` reads (``env_for``, ``scan``, ``close``,
``new_failures``) over groups instead of records:

- **Groups.** Pass ``p`` over the worker's ``n`` records cuts that pass's seeded order
  (:meth:`PoolCursor.order`) into ``ceil(n / K)`` consecutive groups of K (the last one
  smaller); episode ``e`` plays group ``e mod G`` of pass ``e div G``. A group's scenes are
  tiled in record order, so a shard of at most K records plays one env every episode (built
  once), and the schedule stays a pure function of (seed, episode): exact resume holds.
- **Failures.** A record that cannot be read, converted or started is failed once and
  reported, as in a one-scene pool; its group plays without it (a group left empty: the next).
- **Slots.** A single group: the sum of its scenes' most concurrent agents (each scene starts
  its episode at a step of its own, so their busiest steps may meet). Several: the sum of the K
  largest :func:`~magail_sumo.env.scene_pool.agent_bound` of the first
  :data:`~magail_sumo.env.scene_pool.SCAN_RECORDS` records of the order; a later group that
  needs more plays the longest prefix of its scenes that fits (the others play in other
  groups of later passes).
- **Cache.** ``cache // K`` tiled envs are kept (each holds K scenes).
"""

from __future__ import annotations

from converters.sumo.scenario import ensure_bundle
from magail_sumo.errors import MagailSumoError

from .config import EnvConfig
from .scene_pool import (SCAN_RECORDS, EnvCache, PoolCursor, ScenePoolError, agent_bound,
                         playable_scene)
from .tiled import TiledScenesEnv


class TileCursor:
    """Groups of ``per_env`` records of ``pool``'s shard as tiled envs (module doc)."""

    def __init__(self, pool: PoolCursor, per_env: int, config: EnvConfig) -> None:
        if per_env < 2:
            raise ValueError(f"a tile cursor plays >= 2 scenes per env, got {per_env}")
        self.pool = pool
        self.per_env = per_env
        self.config = config
        self.refs = pool.refs
        self.failed = pool.failed
        self.new_failures = pool.new_failures
        self.slots: int | None = None
        self.cache = max(1, pool.cache // per_env)
        self._envs = EnvCache(self.cache)  # by group
        self._bounds: dict[int, int] = {}

    # ------------------------------------------------------------------ schedule
    def groups(self, epoch: int) -> list[tuple[int, ...]]:
        """Pass ``epoch``'s groups of record positions, each in record order."""
        order = self.pool.order(epoch).tolist()
        k = self.per_env
        return [tuple(sorted(order[i:i + k])) for i in range(0, len(order), k)]

    def _scene(self, k: int):
        """Record ``k``'s scene and bundle folder (converted on first use); raises."""
        ref = self.refs[k]
        scene = playable_scene(ref, self.config)
        self._bounds[k] = agent_bound(scene, self.config)
        return scene, ensure_bundle(scene, self.pool.networks, ref, self.pool.convert_budget_s)

    def _env(self, group: tuple[int, ...]) -> TiledScenesEnv | None:
        """The tiled env of the usable records of ``group`` (None: none is usable); kept by
        group (which of its records are usable is a property of the data)."""
        if (env := self._envs.get(group)) is not None:
            return env
        got = [(k, *self._scene_or_fail(k)) for k in group if k not in self.failed]
        got = [g for g in got if g[1] is not None]
        if self.slots is not None:  # the longest prefix that fits the worker's slots
            used, keep = 0, []
            for g in got:
                if used + self._bounds[g[0]] > self.slots and keep:
                    break
                used += self._bounds[g[0]]
                keep.append(g)
            got = keep
        if not got:
            return None
        env = TiledScenesEnv([g[1] for g in got], [g[2] for g in got], self.config)
        self._envs.put(group, env)
        return env

    def _scene_or_fail(self, k: int):
        try:
            return self._scene(k)
        except (MagailSumoError, OSError, ValueError) as exc:
            self.pool._fail(k, exc)
            return None, None

    def env_for(self, episode: int):
        """``(first record position, tiled env)`` of episode ``episode`` (module doc)."""
        n = len(self.refs)
        count = -(-n // self.per_env)
        epoch, j = divmod(episode, count)
        groups = self.groups(epoch)
        for i in range(count):
            env = self._env(groups[(j + i) % count])
            if env is not None:
                return groups[(j + i) % count][0], env
        raise self.pool.all_failed()

    def scan(self) -> int:
        """The worker's slot count (module doc)."""
        if len(self.refs) <= self.per_env:
            _, env = self.env_for(0)
            return env.max_concurrent_agents()
        bounds = []
        for k in sorted(self.pool.order(0)[:SCAN_RECORDS].tolist()):
            try:
                bounds.append(agent_bound(playable_scene(self.refs[k], self.config),
                                          self.config))
            except (MagailSumoError, OSError, ValueError) as exc:
                self.pool._fail(k, exc)
        if not bounds:
            raise ScenePoolError(f"every scanned scene of this worker failed; first: "
                                 f"{self.refs[min(self.failed)]}: {self.failed[min(self.failed)]}")
        self.slots = max(1, sum(sorted(bounds)[-self.per_env:]))
        return self.slots

    def close(self) -> None:
        self._envs.close()
        self.pool.close()
