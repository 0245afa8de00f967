"""Several recorded scenes stepped as one fleet: the batched core across scenes.

:class:`TiledScenesEnv` is a :class:`~magail_sumo.env.driving_env.SumoDrivingEnv` over the
scenes joined by :func:`~magail_sumo.scene.tiling.tile_scenes` (each scene translated to a tile
of its own, far enough from the next that no sensor, collision or neighbourhood reaches across):
one fleet holds every scene's agents and every stage of the env step runs once over all of them
(:class:`~magail_sumo.env.step.FleetEnv`). Where :class:`~magail_sumo.env.batched.
BatchedSceneEnv` batches the rollouts of one scene, this batches different scenes: the fixed
cost of a step (a few dozen array calls, about 2 ms whatever the agent count) is paid once for
all the scenes, not once per scene, which is what most of a scene worker's time was in
training with about a dozen agents per scene.

Agents are named by their tiled track ids, ``(k + 1) * stride + id`` for track ``id`` of scene
``k`` (:meth:`~magail_sumo.scene.tiling.Tiling.scene_of_id`; :meth:`TiledScenesEnv.split` turns a
dict over all agents into one per scene keyed by the scene's own track ids, :meth:`merge` back).
Each scene's agents see, follow and hit exactly what they would in the scene's own env with the
same config and actions; observations are equal up to float rounding (a translated position
rounds differently in its last bits), events and outcomes equal
(``tests/test_tiled_env.py``, the real scenes of ``data/``).

The scenes share one clock: an episode starts every scene at the same log step and ends when
every scene's agents have ended (or at ``max_steps``); a scene whose agents all ended waits,
its tile idle, for the others. Same restrictions as the one-scene batched core: log background
without SUMO (``background: log``, ``sumo_mirror: false``), no FCD recording or rendering, and
ego-frame observations (the ``scene_frame`` layout reads the translated map coordinates); the
controlled vehicles ``all``, ``tracks_to_predict`` or ``scored`` (``sdc`` and a nearest-K count
pick around one SDC, not one per scene).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from converters import load_scene
from converters.sumo.bundle import SceneBundle
from magail_sumo.scene import Scene
from magail_sumo.scene.tiling import GAP_M, Tiling, tile_scenes
from magail_sumo.sensors.base import sensor_class, sensor_order

from .config import EnvConfig
from .driving_env import SumoDrivingEnv
from .events import RoadEdgeRule
from .step import FleetEnv

#: the controlled-vehicle choices a tiled env runs (per scene, they mean what they mean alone)
TILED_CONTROLLED = ("all", "tracks_to_predict", "scored")


def config_problem(cfg: EnvConfig) -> str | None:
    """Why a tiled env cannot run ``cfg`` (module doc), in one line; None: it can."""
    if cfg.background != "log" or cfg.sumo_mirror:
        return ("a tiled env runs log background without SUMO (background: log, sumo_mirror: "
                f"false), got background: {cfg.background}, "
                f"sumo_mirror: {str(cfg.sumo_mirror).lower()}")
    if cfg.fcd_dir is not None:
        return "a tiled env records no FCD (fcd_dir): record one scene's env"
    absolute = [n for n in sensor_order(cfg.observation) if sensor_class(n).scene_frame]
    if absolute:
        return (f"a tiled env observes in the ego frame: sensor {absolute[0]} reads map "
                "coordinates, which tiling moves")
    if cfg.controlled not in TILED_CONTROLLED:
        return (f"a tiled env controls {', '.join(TILED_CONTROLLED)} of every scene, got "
                f"controlled: {cfg.controlled!r} (it picks around one SDC)")
    return None


def tiled_bundle(tiled: Scene, tiling: Tiling, bundles: Sequence[SceneBundle]) -> SceneBundle:
    """One :class:`SceneBundle` over the tiled scene: each bundle's route vehicles with their
    rows and ids moved to the tiled scene's. Its folder and SUMO files are the first scene's
    (a tiled env runs no SUMO: nothing reads them)."""
    rows, ids, parked, spaces, unconverted = [], [], set(), set(), []
    for k, b in enumerate(bundles):
        tid = {v: str((k + 1) * tiling.track_stride + int(v)) for v in b.sumo_ids}
        rows.append(np.asarray(b.sumo_rows, np.int64) + tiling.row_start[k])
        ids += [tid[v] for v in b.sumo_ids]
        parked |= {tid.get(v, v) for v in b.parked}
        spaces |= {tid.get(v, v) for v in b.spaces}
        unconverted += list(b.unconverted)
    first = bundles[0]
    return SceneBundle(tiled, first.folder, first.sumocfg,
                       np.concatenate(rows) if rows else np.zeros(0, np.int64), tuple(ids),
                       tuple(unconverted), frozenset(parked), None, frozenset(spaces))


class TiledScenesEnv(SumoDrivingEnv):
    """The scenes ``scenes`` (with their bundles) as one env (module doc); the PettingZoo
    ``ParallelEnv`` API and the array API of :class:`SumoDrivingEnv`.

    :param scenes: recorded scenes or scene files, one tile each, in order.
    :param bundles: each scene's bundle folder (or read :class:`SceneBundle`).
    :param gap: space between two tiles (m).
    :raises ValueError: a config the tiled core does not run (module doc), no scene, or as many
        bundles as scenes not given.
    """

    def __init__(self, scenes: Sequence[Scene | str | Path],
                 bundles: Sequence[str | Path | SceneBundle],
                 config: EnvConfig | None = None, gap: float = GAP_M) -> None:
        cfg = config or EnvConfig(sumo_mirror=False)
        if (problem := config_problem(cfg)) is not None:
            raise ValueError(problem)
        scenes = [s if isinstance(s, Scene) else load_scene(s) for s in scenes]
        if len(bundles) != len(scenes):
            raise ValueError(f"a tiled env needs one bundle per scene: {len(scenes)} scenes, "
                             f"{len(bundles)} bundles")
        read = [b if isinstance(b, SceneBundle) else SceneBundle.load(s, b)
                for s, b in zip(scenes, bundles)]
        tiled, self.tiling = tile_scenes(scenes, gap)
        self._tile_scenes = scenes
        super().__init__(tiled, tiled_bundle(tiled, self.tiling, read), cfg)

    def _sdc_rows(self) -> tuple[int, ...]:
        return tuple(int(r) for r in self.tiling.sdc_rows if r >= 0)

    def _edge_rule(self) -> list[RoadEdgeRule | None] | None:
        """One road-edge rule per tile, in the scene's own frame (None: the tile has no road
        edge and keeps the lane rule, as its own env does); None when no tile has one.

        Per tile, not one over the tiled map: the rule's edges are float32 (as WOSAC's), which a
        translation would round differently, and which rings close depends on the longest
        edge of the map (:func:`~magail_sumo.sensors.road_edge.road_edge_segments`)."""
        t, cfg = self.tiling, self.config
        rules = []
        for k, scene in enumerate(self._tile_scenes):
            rows = slice(t.row_start[k], t.row_start[k + 1])
            rules.append(RoadEdgeRule.build(scene, cfg.off_road_edge_margin, self._length[rows],
                                            self._width[rows]))
        return rules if any(r is not None for r in rules) else None

    def _off_road(self, act: np.ndarray, stepped: np.ndarray, lanes) -> np.ndarray:
        """Each tile's own rule (:meth:`_edge_rule`): its road edges, else the lanes; the
        poses moved back into the scene's frame (whole metres: exact)."""
        if self._edges is None:
            return FleetEnv._off_road(self, act, stepped, lanes)
        t, f = self.tiling, self.fleet
        out = FleetEnv._off_road(self, act, stepped, lanes)
        rows = self._ctrl[act]
        tile = t.scene_of_rows(rows)
        for k in np.unique(tile).tolist():  # a handful of tiles, each one array call
            rule = self._edges[k]
            if rule is None:
                continue
            m = tile == k
            a = act[m]
            dx, dy = t.offsets[k]
            out[m] = rule.off_road(rows[m] - t.row_start[k], self.t, f.x[a] - dx, f.y[a] - dy,
                                   f.yaw[a], f.length[a], f.width[a])
        return out

    # ------------------------------------------------------------------ scenes
    def scene_of(self, agents: Sequence[str]) -> np.ndarray:
        """(A,) scene index of agents named ``agents``."""
        stride = self.tiling.track_stride
        return np.array([int(a) // stride - 1 for a in agents], np.int64)

    def split(self, values: dict) -> list[dict]:
        """A dict over all agents as one dict per scene keyed by the scene's own track ids."""
        out: list[dict] = [{} for _ in range(self.tiling.num_scenes)]
        for name, v in values.items():
            k, tid = self.tiling.scene_of_id(int(name))
            out[k][str(tid)] = v
        return out

    def merge(self, per_scene: list[dict]) -> dict:
        """One dict per scene keyed by its own track ids as one dict over all agents."""
        stride = self.tiling.track_stride
        return {str((k + 1) * stride + int(a)): v for k, d in enumerate(per_scene)
                for a, v in d.items()}

    # ------------------------------------------------------------------ not per scene
    def record_fcd(self, recorder=None):
        raise NotImplementedError("a tiled env records no FCD: record one scene's env")

    def render(self):
        raise NotImplementedError("a tiled env does not render: render one scene's env")
