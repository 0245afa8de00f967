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

Each scene starts its episode at a log step of its own (a random window per scene, drawn from
its own log, as its own env would: :meth:`TiledScenesEnv.window_options`); the tiles are
delayed in time (:func:`~magail_sumo.scene.tiling.shift_tiles`) so that they all start at the
env's first step and run on one clock. A scene's episode ends after ``max_steps`` steps of its
own or with its log; the env's, when every scene's has (a scene whose agents all ended waits,
its tile idle, for the others). ``infos[agent]["step"]`` is the env's clock. Same restrictions as the one-scene batched core: log background
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
from magail_sumo.scene.tiling import GAP_M, Tiling, shift_tiles, tile_scenes
from magail_sumo.sensors.command import RouteCommands
from magail_sumo.sensors.traffic_lights import LightTable
from magail_sumo.sensors.base import sensor_class, sensor_order

from .config import EnvConfig, draw_start, window_starts
from .driving_env import SumoDrivingEnv
from .events import RoadEdgeRule, StopLines
from .scene_pool import most_alive
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
        parked |= {tid[v] for v in b.parked}  # both are route vehicles (SceneBundle.load)
        spaces |= {tid[v] for v in b.spaces}
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
        self._base = tiled
        self._base_maps = (self.suite.lights, self.stop_lines, self._commands)
        k = self.tiling.num_scenes
        #: tile k's log step u is this episode's step u + shift[k] (:meth:`reset`)
        self.shift = np.zeros(k, np.int64)
        self._tile_of_row = self.tiling.scene_of_rows(np.arange(tiled.tracks.num_tracks))
        self._tile_end = np.zeros(k, np.int64)

    # ------------------------------------------------------------------ episodes
    def window_options(self, rng: np.random.Generator) -> dict:
        """Each tile's start window drawn from ``rng`` over its own log, in tile order."""
        return {"start_steps": [draw_start(self.config, int(n), rng)
                                for n in self.tiling.num_steps]}

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start an episode of every tile. ``options={"start_steps": [s_0, ...]}`` starts tile
        ``k`` at its own log step ``s_k`` (:meth:`window_options` draws them); with
        ``{"start_step": s}``, or a fixed window, every tile starts at ``s``; with random
        windows and neither, each tile's start is drawn from its own log (seeded by ``seed``).
        The tiles are delayed in time (:func:`~magail_sumo.scene.tiling.shift_tiles`) so that
        they all start at the env's step ``max(s_k)``; each tile's episode ends after
        ``max_steps`` steps of its own or with its log, the env's when the last one does."""
        opts = dict(options or {})
        starts = opts.pop("start_steps", None)
        lengths = self.tiling.num_steps
        k = self.tiling.num_scenes
        if starts is None and "start_step" in opts:  # one start for all (within each log)
            starts = np.minimum(int(opts["start_step"]), np.maximum(lengths - 2, 0))
        elif starts is None and self.config.start_window == "random":
            rng = np.random.default_rng(None if seed is None else seed % (1 << 64))
            starts = self.window_options(rng)["start_steps"]
        elif starts is None:
            starts = [window_starts(self.config, int(n))[0] for n in lengths]
        starts = np.asarray(starts, np.int64)
        if starts.shape != (k,):
            raise ValueError(f"reset options start_steps: one start per tile ({k}), got "
                             f"{starts.shape[0] if starts.ndim else starts}")
        self._delay(int(starts.max()) - starts)
        opts["start_step"] = int(starts.max())
        own_end = np.minimum(self.tiling.num_steps - 1, starts + self.config.max_steps) \
            if self.config.max_steps is not None else self.tiling.num_steps - 1
        self._tile_end = own_end + self.shift
        return super().reset(seed, opts)

    def _delay(self, shift: np.ndarray) -> None:
        """Tile ``k`` delayed by ``shift[k]`` steps: the log, lights, stop lines and route
        commands this episode reads (rebuilt only when the delays change)."""
        if np.array_equal(shift, self.shift):
            return
        self.shift = shift
        if not shift.any():
            self.scene = self._base
            lights, self.stop_lines, self._commands = self._base_maps
        else:
            self.scene = shift_tiles(self._base, self.tiling, shift)
            lights = LightTable.build(self.scene)
            self.stop_lines = StopLines.build(self.scene)
            if self._commands is not None:
                self._commands = RouteCommands.build(self.scene.tracks,
                                                     self.config.observation.command_lookahead)
        self.suite.lights = self.suite.maps.lights = lights
        self._track_span()
        self._prev_table = None

    def max_concurrent_agents(self) -> int:
        """Most agents alive at once over every episode the config allows: each tile's own
        most (:func:`~magail_sumo.env.scene_pool.most_alive`), summed (tiles start at steps
        of their own, so their busiest steps may meet)."""
        tr, t = self._base.tracks, self.tiling
        rows = self._ctrl
        tile = self._tile_of_row[rows]
        return max(1, sum(most_alive(tr.valid[rows[tile == k], :int(t.num_steps[k])],
                                     self.config) for k in range(t.num_scenes)
                          if (tile == k).any()))

    def _may_join(self) -> np.ndarray:
        """Agents join while their tile's episode runs, up to its last step (where a scene's
        own env truncates them at once, as the env's last step does here; at an earlier tile's
        last step they are truncated one step later)."""
        return self.t <= self._tile_end[self._tile_of_row[self._ctrl]]

    def _time_up(self, act: np.ndarray, flags: dict[str, np.ndarray], end: bool,
                 arrived: list[str]):
        """Out of time also at the end of the agent's tile's episode."""
        time_up, why = super()._time_up(act, flags, end, arrived)
        return time_up | (self.t >= self._tile_end[self._tile_of_row[self._ctrl[act]]]), why

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
            out[m] = rule.off_road(rows[m] - t.row_start[k], self.t - int(self.shift[k]),
                                   f.x[a] - dx, f.y[a] - dy, f.yaw[a], f.length[a], f.width[a])
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
