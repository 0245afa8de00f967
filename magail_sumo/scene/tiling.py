"""Several recorded scenes as one scene, placed apart in the plane ("tiles").

A batched simulator core steps many scenes as one fleet (Waymax and GPUDrive hold many scenes
as one batched state). :func:`tile_scenes` does it by geometry instead of by a scene axis: scene
``k`` is translated by an integer offset ``(dx_k, dy_k)`` (metres) so that the scenes lie side
by side along x, each at least ``gap`` metres from the next, and everything is joined into one
:class:`~magail_sumo.scene.Scene`. Every spatial query of the env (lane query, ray casts, the
leader, collisions, road edges, stop lines, the discriminator's neighbourhood) then finds only
its own scene's features and road users, as long as ``gap`` exceeds every range (sensors reach
at most 50 m; an agent moves at most 40 m/s): the sensors and events need no notion of a
scene. Observations are ego-frame quantities, unchanged by a translation (layouts reading scene
coordinates, ``scene_frame``, are not).

What is joined, with scene ``k``'s ids moved to ``(k + 1) * stride + id`` (one stride for track
ids, one for map-feature ids: the least power of ten above every id of the scenes) so that they
stay unique and readable (:meth:`Tiling.scene_of_id`):

- **tracks**: rows of scene 0, then scene 1, ... (:attr:`Tiling.row_start`); scenes shorter
  than the longest are padded with invalid steps (the last recorded value repeated);
- **map features** of each kind, with their references (entry / exit lanes, neighbours,
  boundaries, stop signs' lanes) moved with them;
- **signals**: every scene's records, ordered by step, their lanes and stop points moved;
- ``tracks_to_predict`` (rows moved), ``objects_of_interest`` and source ids (ids moved),
  ``sdc_track_index`` of scene 0 (one SDC per scene: :attr:`Tiling.sdc_rows`).

Time is shared: log step ``t`` of the tiled scene is log step ``t`` of every scene (timestamps:
the longest scene's), so an env over it runs all scenes on one clock; :func:`shift_tiles`
delays tiles in time, so that each starts its episode at a log step of its own.
Offsets are whole metres: positions recorded in float32 (WOMD) move exactly in float64.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .base import ArrayDataclass, frozen_array
from .quality import DataQuality, SourceIds
from .roadmap import (FEATURE_KINDS, BoundarySegment, Lane, LaneNeighbor, RoadMap, StopSign)
from .scene import RequiredPrediction, Scene
from .signals import SignalStates
from .tracks import Tracks

#: default space between two tiles (m): far beyond every sensor's range and a step's travel
GAP_M = 2000.0


@dataclass(frozen=True, eq=False)
class Tiling(ArrayDataclass):
    """Where each scene of a tiled scene went (module doc).

    :param scenario_ids: (S,) the scenes' ids, in tile order.
    :param offsets: (S, 2) float64 translation (m) of each scene.
    :param row_start: (S + 1,) int64: scene ``k``'s tracks are rows ``row_start[k]`` to
        ``row_start[k + 1] - 1`` of the tiled scene.
    :param num_steps: (S,) int64 steps each scene recorded (the tiled scene has the most).
    :param sdc_rows: (S,) int64 each scene's SDC row in the tiled scene (-1: none).
    :param track_stride: tiled track id = ``(k + 1) * track_stride + id``.
    :param feature_stride: the same for map-feature ids.
    """

    scenario_ids: tuple[str, ...]
    offsets: np.ndarray
    row_start: np.ndarray
    num_steps: np.ndarray
    sdc_rows: np.ndarray
    track_stride: int
    feature_stride: int

    def __post_init__(self) -> None:
        s = len(self.scenario_ids)
        object.__setattr__(self, "offsets", frozen_array(self.offsets, np.float64, (s, 2)))
        object.__setattr__(self, "row_start", frozen_array(self.row_start, np.int64, (s + 1,)))
        object.__setattr__(self, "num_steps", frozen_array(self.num_steps, np.int64, (s,)))
        object.__setattr__(self, "sdc_rows", frozen_array(self.sdc_rows, np.int64, (s,)))

    @property
    def num_scenes(self) -> int:
        return len(self.scenario_ids)

    def scene_of_rows(self, rows: np.ndarray) -> np.ndarray:
        """(A,) scene index of tiled track rows ``rows``."""
        return np.searchsorted(self.row_start, np.asarray(rows, np.int64), side="right") - 1

    def scene_of_id(self, track_id: int) -> tuple[int, int]:
        """``(scene index, the scene's own track id)`` of a tiled track id."""
        k, tid = divmod(int(track_id), self.track_stride)
        return k - 1, tid


def _stride(ids: Sequence[int]) -> int:
    """The least power of ten above every id (at least 10)."""
    top = max([0, *(abs(int(i)) for i in ids)])
    stride = 10
    while stride <= top:
        stride *= 10
    return stride


def _extent(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(2,) low and high corner of the scene's recorded positions and map (m)."""
    tr = scene.tracks
    pts = [np.stack([tr.x[tr.valid], tr.y[tr.valid]], axis=1)]
    for kind in FEATURE_KINDS:
        for f in scene.roadmap.features(kind):
            geom = f.position[None] if kind == "stop_sign" else \
                f.polyline if hasattr(f, "polyline") else f.polygon
            if geom.size:
                pts.append(geom[:, :2])
    if len(scene.signals):
        pts.append(scene.signals.stop_point[:, :2])
    allp = np.concatenate(pts) if pts else np.zeros((0, 2))
    allp = allp[np.isfinite(allp).all(axis=1)]
    if not allp.size:
        return np.zeros(2), np.zeros(2)
    return allp.min(axis=0), allp.max(axis=0)


def _moved_points(p: np.ndarray, d: np.ndarray) -> np.ndarray:
    out = np.array(p, np.float64)
    out[..., 0] += d[0]
    out[..., 1] += d[1]
    return out


def _moved_map(roadmap: RoadMap, d: np.ndarray, fid) -> dict[str, list]:
    """The map's features of each kind translated by ``d`` with ids mapped by ``fid``."""

    def seg(b: BoundarySegment) -> BoundarySegment:
        return dataclasses.replace(b, boundary_feature_id=fid(b.boundary_feature_id)
                                   if b.boundary_feature_id else 0)

    def nb(n: LaneNeighbor) -> LaneNeighbor:
        return dataclasses.replace(n, feature_id=fid(n.feature_id),
                                   boundaries=tuple(seg(b) for b in n.boundaries))

    out: dict[str, list] = {kind: [] for kind in FEATURE_KINDS}
    for lane in roadmap.lanes:
        out["lane"].append(dataclasses.replace(
            lane, id=fid(lane.id), polyline=_moved_points(lane.polyline, d),
            entry_lanes=tuple(fid(i) for i in lane.entry_lanes),
            exit_lanes=tuple(fid(i) for i in lane.exit_lanes),
            left_neighbors=tuple(nb(n) for n in lane.left_neighbors),
            right_neighbors=tuple(nb(n) for n in lane.right_neighbors),
            left_boundaries=tuple(seg(b) for b in lane.left_boundaries),
            right_boundaries=tuple(seg(b) for b in lane.right_boundaries)))
    for kind in ("road_line", "road_edge"):
        for f in roadmap.features(kind):
            out[kind].append(dataclasses.replace(f, id=fid(f.id),
                                                 polyline=_moved_points(f.polyline, d)))
    for s in roadmap.stop_signs:
        out["stop_sign"].append(StopSign(fid(s.id), tuple(fid(i) for i in s.lanes),
                                         _moved_points(s.position[None], d)))
    for kind in ("crosswalk", "speed_bump", "driveway"):
        for f in roadmap.features(kind):
            out[kind].append(dataclasses.replace(f, id=fid(f.id),
                                                 polygon=_moved_points(f.polygon, d)))
    return out


def _padded(a: np.ndarray, steps: int) -> np.ndarray:
    """(N, T) ``a`` to (N, steps): the last column repeated (invalid steps carry no meaning)."""
    if a.shape[1] == steps:
        return np.asarray(a)
    if a.shape[1] == 0:
        return np.zeros((a.shape[0], steps), a.dtype)
    return np.concatenate([a, np.repeat(a[:, -1:], steps - a.shape[1], axis=1)], axis=1)


def tile_scenes(scenes: Sequence[Scene], gap: float = GAP_M) -> tuple[Scene, Tiling]:
    """The scenes joined into one, each translated to its own tile (module doc); the tiled
    scene and where everything went.

    :raises ValueError: no scene, ``gap`` not positive, or two scenes with the same id.
    """
    scenes = list(scenes)
    if not scenes:
        raise ValueError("tile_scenes: no scene to tile")
    if not gap > 0:
        raise ValueError(f"tile_scenes: gap must be > 0 m, got {gap!r}")
    ids = [s.scenario_id for s in scenes]
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise ValueError(f"tile_scenes: scene {dup!r} given twice (a scene is one tile)")
    tstride = _stride([i for s in scenes for i in s.tracks.id.tolist()])
    fids = [f.id for s in scenes for kind in FEATURE_KINDS for f in s.roadmap.features(kind)]
    fids += [int(i) for s in scenes for i in s.signals.lane.tolist()]
    fstride = _stride(fids)
    steps = max(s.num_steps for s in scenes)
    longest = max(scenes, key=lambda s: s.num_steps)

    offsets, cursor = [], 0.0
    for s in scenes:
        lo, hi = _extent(s)
        # whole metres: the scene's low x at the cursor, its y centred on 0
        d = np.array([np.ceil(cursor - lo[0]), np.round(-(lo[1] + hi[1]) / 2.0)])
        offsets.append(d)
        cursor = hi[0] + d[0] + gap
    offsets = np.array(offsets)

    cols = {f.name: [] for f in dataclasses.fields(Tracks)}
    feats: dict[str, list] = {kind: [] for kind in FEATURE_KINDS}
    sig = {"step": [], "lane": [], "state": [], "stop_point": []}
    predict, interest, names, fnames, notes = [], [], [], [], []
    row_start, sdc_rows, row = [0], [], 0
    for k, (s, d) in enumerate(zip(scenes, offsets)):
        tr = s.tracks
        tid = lambda i, k=k: (k + 1) * tstride + int(i)  # noqa: E731
        fid = lambda i, k=k: (k + 1) * fstride + int(i)  # noqa: E731
        cols["id"].append((k + 1) * tstride + tr.id)
        cols["type"].append(tr.type)
        for name in ("x", "y"):
            cols[name].append(_padded(getattr(tr, name) + d[0 if name == "x" else 1], steps))
        for name in ("z", "length", "width", "height", "heading", "vx", "vy"):
            cols[name].append(_padded(getattr(tr, name), steps))
        cols["valid"].append(np.concatenate(
            [tr.valid, np.zeros((tr.num_tracks, steps - tr.num_steps), bool)], axis=1))
        for kind, lst in _moved_map(s.roadmap, d, fid).items():
            feats[kind] += lst
        sg = s.signals
        sig["step"].append(sg.step)
        sig["lane"].append((k + 1) * fstride + sg.lane)
        sig["state"].append(sg.state)
        sig["stop_point"].append(_moved_points(sg.stop_point, d))
        predict += [RequiredPrediction(p.track_index + row, p.difficulty)
                    for p in s.tracks_to_predict]
        interest += [tid(i) for i in s.objects_of_interest]
        names += [(tid(i), n) for i, n in s.source_ids.tracks]
        fnames += [(fid(i), n) for i, n in s.source_ids.map_features]
        notes.append(f"tile {k}: scene {s.scenario_id} moved by ({d[0]:.0f}, {d[1]:.0f}) m, "
                     f"track rows {row}..{row + tr.num_tracks - 1}")
        sdc_rows.append(s.sdc_track_index + row if s.sdc_track_index >= 0 else -1)
        row += tr.num_tracks
        row_start.append(row)
    order = np.argsort(np.concatenate(sig["step"]), kind="stable")
    signals = SignalStates(*(np.concatenate(sig[n])[order]
                             for n in ("step", "lane", "state", "stop_point")))
    tracks = Tracks(**{n: np.concatenate(v) for n, v in cols.items()})
    roadmap = RoadMap(**{kind + "s": tuple(feats[kind]) for kind in FEATURE_KINDS})
    tiled = Scene(
        scenario_id="tiles-" + "+".join(ids), timestamps=longest.timestamps, tracks=tracks,
        roadmap=roadmap, signals=signals, sdc_track_index=sdc_rows[0],
        current_time_index=scenes[0].current_time_index, tracks_to_predict=tuple(predict),
        objects_of_interest=tuple(interest),
        source_ids=SourceIds(tuple(names), tuple(fnames)),
        data_quality=DataQuality(notes=tuple(notes)))
    tiling = Tiling(tuple(ids), offsets, np.array(row_start), np.array([s.num_steps for s in scenes]),
                    np.array(sdc_rows), tstride, fstride)
    return tiled, tiling


def shift_tiles(tiled: Scene, tiling: Tiling, shifts) -> Scene:
    """``tiled`` with tile ``k`` delayed by ``shifts[k]`` >= 0 steps: its log step ``u`` is
    step ``u + shifts[k]`` of the result (steps before it invalid), its signal records moved
    with it. So tiles can start their episodes at different log steps of their own and still
    run on one clock (:class:`~magail_sumo.env.tiled.TiledScenesEnv`). The result has
    ``max(num_steps[k] + shifts[k])`` steps; timestamps continue at the first step spacing."""
    e = np.asarray(shifts, np.int64)
    if e.shape != (tiling.num_scenes,) or (e < 0).any():
        raise ValueError(f"shift_tiles: one shift >= 0 per tile ({tiling.num_scenes}), got {e}")
    steps = int(max(tiling.num_steps + e))
    tr = tiled.tracks
    cols = {}
    for f in dataclasses.fields(Tracks):
        a = getattr(tr, f.name)
        if a.ndim == 1:
            cols[f.name] = a
            continue
        out = np.zeros((a.shape[0], steps), a.dtype)
        for k in range(tiling.num_scenes):
            r0, r1 = tiling.row_start[k], tiling.row_start[k + 1]
            n, d = int(tiling.num_steps[k]), int(e[k])
            if r1 == r0 or n == 0:
                continue
            block = a[r0:r1, :n]
            out[r0:r1, d:d + n] = block
            if f.name != "valid":  # invalid steps repeat the nearest recorded value
                out[r0:r1, :d] = block[:, :1]
                out[r0:r1, d + n:] = block[:, -1:]
        cols[f.name] = out
    sg = tiled.signals
    tile = sg.lane // tiling.feature_stride - 1
    step = sg.step.astype(np.int64) + e[np.clip(tile, 0, tiling.num_scenes - 1)]
    order = np.argsort(step, kind="stable")
    signals = SignalStates(step[order], sg.lane[order], sg.state[order], sg.stop_point[order])
    ts = tiled.timestamps
    dt = float(ts[1] - ts[0]) if len(ts) > 1 else 0.1
    timestamps = (ts[0] if len(ts) else 0.0) + dt * np.arange(steps)
    return dataclasses.replace(tiled, timestamps=timestamps, tracks=Tracks(**cols),
                               signals=signals)
