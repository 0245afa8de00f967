"""GameFormer samples from recorded scenes, and a seeded streaming dataset of them.

A *sample* is one focal agent at one current step ``c`` of a scene: the focal agent (index 0)
and its ``max_agents − 1`` nearest other objects observed at ``c`` (vehicles, pedestrians,
cyclists, others), in the focal agent's frame at ``c`` (origin at its box centre, +x along its
heading; metres, radians, m/s). Each agent carries ``history_steps`` states ending at ``c``
(``c − history_steps + 1 .. c``; 11 steps = 1 s at 10 Hz) and, for training, its
``future_steps`` recorded positions ``c + 1 .. c + future_steps`` (8 s) with a mask (steps past
the scene's end or unobserved are masked: shorter futures count for what they have). Each agent
also carries its ``map_elements`` nearest map elements: every lane centre line, road line, road
edge and crosswalk outline (closed) of the scene resampled every ``map_spacing`` m and cut into
pieces of ``map_points`` points (:func:`map_chunks`), nearest by the smallest point distance to
the agent's position at ``c``. Feature layouts: :data:`~magail_sumo.models.gameformer.AGENT_FEATURES`,
:data:`~magail_sumo.models.gameformer.MAP_FEATURES`. Traffic-signal states are not used.

Every (scene, c, focal) with ``c`` in ``history_steps − 1, + window_stride, …`` (the 20-s
ScenarioNet scenes give many windows, each 9.1-s WOMD scene a few), a focal of a type in
``focal_types`` observed at ``c`` with at least ``min_future_steps`` observed future steps, is a
training sample (:class:`SampleIndex`). :class:`StreamingDataset` serves batches without holding
the dataset: epoch ``e`` visits the scenes in an order drawn from ``(seed, e)``, groups of
``cache_scenes`` scenes at a time, each group's samples shuffled; only the scenes of the group
being served (plus one) are held (LRU). Batch ``b`` of epoch ``e`` is a pure function of
``(seed, e, b)``, so a run resumes exactly from the position ``(e, b)``.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable

import numpy as np
import torch

from magail_sumo.models.gameformer import AGENT_FEATURES, MAP_FEATURES
from magail_sumo.scene import ObjectType, Scene

if TYPE_CHECKING:
    from .config import GameFormerConfig

#: map element kinds (type one-hot order of the map features)
MAP_KINDS = ("lane", "road_line", "road_edge", "crosswalk")
#: stream word of the dataset's epoch orders (apart from other seeded streams of a run)
DATA_STREAM = 0x6F
OBJECT_TYPES = {"vehicle": ObjectType.VEHICLE, "pedestrian": ObjectType.PEDESTRIAN,
                "cyclist": ObjectType.CYCLIST, "other": ObjectType.OTHER}


# ------------------------------------------------------------------------------------ map
@dataclass(frozen=True)
class MapChunks:
    """Map elements of a scene: ``points`` (C, P, 4) x, y, unit direction (scene frame),
    ``mask`` (C, P) point exists, ``kind`` (C,) index into :data:`MAP_KINDS`."""

    points: np.ndarray
    mask: np.ndarray
    kind: np.ndarray


def _resample(xy: np.ndarray, spacing: float) -> np.ndarray:
    """Points every ``spacing`` m along a polyline (its ends kept); (L, 4) with the unit
    direction of travel."""
    seg = np.hypot(*np.diff(xy, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return np.zeros((0, 4))
    n = max(2, int(np.ceil(s[-1] / spacing)) + 1)
    q = np.linspace(0.0, s[-1], n)
    pts = np.stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])], 1)
    d = np.diff(pts, axis=0)
    d = np.concatenate([d, d[-1:]], 0)
    d /= np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)[:, None]
    return np.concatenate([pts, d], 1)


def map_chunks(scene: Scene, points: int, spacing: float) -> MapChunks:
    """Every lane, road line, road edge and crosswalk (closed outline) of ``scene`` resampled
    every ``spacing`` m and cut into pieces of ``points`` points (module doc)."""
    rm = scene.roadmap
    parts: list[np.ndarray] = []
    kinds: list[int] = []
    sources = ((0, [f.polyline for f in rm.lanes]), (1, [f.polyline for f in rm.road_lines]),
               (2, [f.polyline for f in rm.road_edges]),
               (3, [np.concatenate([f.polygon, f.polygon[:1]]) for f in rm.crosswalks
                    if len(f.polygon)]))
    for kind, lines in sources:
        for line in lines:
            if len(line) < 2:
                continue
            r = _resample(np.asarray(line[:, :2], np.float64), spacing)
            for k in range(0, len(r), points):
                parts.append(r[k:k + points])
                kinds.append(kind)
    c = len(parts)
    pts = np.zeros((c, points, 4))
    mask = np.zeros((c, points), bool)
    for i, p in enumerate(parts):
        pts[i, :len(p)] = p
        mask[i, :len(p)] = True
    return MapChunks(pts, mask, np.asarray(kinds, np.int64))


# ------------------------------------------------------------------------------- history
@dataclass(frozen=True)
class History:
    """States of all A objects of a scene over the history steps (scene frame), the last
    column being the current step. ``x, y, heading, vx, vy``, ``valid``: (A, Th);
    ``length, width``: (A,) m; ``type``: (A,) :class:`ObjectType`."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    valid: np.ndarray
    length: np.ndarray
    width: np.ndarray
    type: np.ndarray


def log_history(scene: Scene, c: int, steps: int) -> History:
    """The recorded history ``c − steps + 1 .. c`` (steps before 0 unobserved); sizes at
    ``c``."""
    tr = scene.tracks
    idx = np.arange(c - steps + 1, c + 1)
    ok = idx >= 0
    j = np.clip(idx, 0, None)
    valid = tr.valid[:, j] & ok[None]

    def take(a: np.ndarray) -> np.ndarray:
        return np.where(valid, a[:, j].astype(np.float64), 0.0)

    return History(take(tr.x), take(tr.y), take(tr.heading), take(tr.vx), take(tr.vy), valid,
                   tr.length[:, c].astype(np.float64), tr.width[:, c].astype(np.float64),
                   tr.type.astype(np.int64))


@dataclass(frozen=True)
class Frame:
    """An agent-centric frame: origin and heading (scene frame)."""

    x: float
    y: float
    heading: float

    def to_local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.heading), np.sin(self.heading)
        dx, dy = x - self.x, y - self.y
        return c * dx + s * dy, -s * dx + c * dy

    def to_world(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = np.cos(self.heading), np.sin(self.heading)
        return self.x + c * x - s * y, self.y + s * x + c * y


def build_sample(hist: History, focal: int, chunks: MapChunks, max_agents: int,
                 map_elements: int) -> dict[str, np.ndarray]:
    """The sample of ``focal`` (a row of ``hist`` observed at the current step), module doc.

    :returns: ``agents`` (N, Th, AGENT_FEATURES) float32, ``agent_mask`` (N,), ``map``
        (N, Nm, P, MAP_FEATURES) float32, ``map_mask`` (N, Nm, P), ``rows`` (N,) int64 rows of
        ``hist`` (−1: padding), ``frame`` (3,) float64 origin x, y, heading.
    """
    th = hist.valid.shape[1]
    cur = hist.valid[:, -1]
    fx, fy, fh = hist.x[focal, -1], hist.y[focal, -1], hist.heading[focal, -1]
    frame = Frame(float(fx), float(fy), float(fh))
    cand = np.flatnonzero(cur)
    cand = cand[cand != focal]
    d = np.hypot(hist.x[cand, -1] - fx, hist.y[cand, -1] - fy)
    near = cand[np.argsort(d, kind="stable")[:max_agents - 1]]
    rows = np.concatenate([[focal], near]).astype(np.int64)
    n = len(rows)
    agents = np.zeros((max_agents, th, AGENT_FEATURES), np.float32)
    v = hist.valid[rows]
    lx, ly = frame.to_local(hist.x[rows], hist.y[rows])
    h = hist.heading[rows] - fh
    c, s = np.cos(fh), np.sin(fh)
    vx = c * hist.vx[rows] + s * hist.vy[rows]
    vy = -s * hist.vx[rows] + c * hist.vy[rows]
    feats = np.stack([lx, ly, np.cos(h), np.sin(h), vx, vy,
                      np.broadcast_to(hist.length[rows, None], lx.shape),
                      np.broadcast_to(hist.width[rows, None], lx.shape),
                      np.ones_like(lx)], -1)
    onehot = np.zeros((n, 3))
    t = hist.type[rows]
    for k, ot in enumerate((ObjectType.VEHICLE, ObjectType.PEDESTRIAN, ObjectType.CYCLIST)):
        onehot[:, k] = t == ot
    feats = np.concatenate([feats, np.broadcast_to(onehot[:, None], (n, th, 3))], -1)
    agents[:n] = np.where(v[..., None], feats, 0.0)
    agent_mask = np.zeros(max_agents, bool)
    agent_mask[:n] = True
    p = chunks.points.shape[1]
    mp = np.zeros((max_agents, map_elements, p, MAP_FEATURES), np.float32)
    mm = np.zeros((max_agents, map_elements, p), bool)
    if len(chunks.kind):
        px, py = chunks.points[..., 0], chunks.points[..., 1]  # (C, P)
        ax, ay = hist.x[rows, -1], hist.y[rows, -1]
        dist = np.hypot(px[None] - ax[:, None, None], py[None] - ay[:, None, None])
        dist = np.where(chunks.mask[None], dist, np.inf).min(-1)  # (n, C)
        k = min(map_elements, dist.shape[1])
        pick = np.argpartition(dist, k - 1, axis=1)[:, :k] if k < dist.shape[1] \
            else np.broadcast_to(np.arange(k), (n, k))
        order = np.take_along_axis(dist, pick, 1).argsort(1, kind="stable")
        pick = np.take_along_axis(pick, order, 1)  # (n, k) nearest first
        sel = chunks.points[pick]  # (n, k, P, 4)
        qx, qy = frame.to_local(sel[..., 0], sel[..., 1])
        ux = c * sel[..., 2] + s * sel[..., 3]
        uy = -s * sel[..., 2] + c * sel[..., 3]
        kind = np.eye(len(MAP_KINDS))[chunks.kind[pick]]  # (n, k, 4)
        f = np.concatenate([np.stack([qx, qy, ux, uy], -1),
                            np.broadcast_to(kind[:, :, None], (n, k, p, len(MAP_KINDS)))], -1)
        m = chunks.mask[pick]
        mp[:n, :k] = np.where(m[..., None], f, 0.0)
        mm[:n, :k] = m
    out_rows = np.full(max_agents, -1, np.int64)
    out_rows[:n] = rows
    return {"agents": agents, "agent_mask": agent_mask, "map": mp, "map_mask": mm,
            "rows": out_rows, "frame": np.array([fx, fy, fh], np.float64)}


def log_future(scene: Scene, c: int, rows: np.ndarray, frame: np.ndarray, steps: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Recorded positions of track ``rows`` (−1: padding) at ``c + 1 .. c + steps`` in the
    sample frame: (N, steps, 2) float32 and the (N, steps) mask."""
    tr = scene.tracks
    idx = np.arange(c + 1, c + steps + 1)
    inside = idx < tr.num_steps
    j = np.minimum(idx, tr.num_steps - 1)
    r = np.maximum(rows, 0)
    mask = tr.valid[r][:, j] & inside[None] & (rows >= 0)[:, None]
    fx, fy = Frame(*frame).to_local(tr.x[r][:, j], tr.y[r][:, j])
    fut = np.where(mask[..., None], np.stack([fx, fy], -1), 0.0).astype(np.float32)
    return fut, mask


def collate(samples: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    """Stack samples into a batch of tensors."""
    return {k: torch.from_numpy(np.stack([s[k] for s in samples])) for k in samples[0]}


# ------------------------------------------------------------------------------- dataset
def focal_types(names: Iterable[str]) -> np.ndarray:
    return np.array([int(OBJECT_TYPES[n]) for n in names], np.int64)


def window_steps(scene: Scene, history_steps: int, stride: int) -> np.ndarray:
    """Current steps of the windows of ``scene``: ``history_steps − 1`` on by ``stride``,
    while a future step is left."""
    return np.arange(history_steps - 1, scene.num_steps - 1, stride)


def scene_samples(scene: Scene, cfg: "GameFormerConfig", stride: int, min_future: int
                  ) -> np.ndarray:
    """(S, 2) (current step, focal row) of the samples of ``scene`` (module doc)."""
    tr = scene.tracks
    types = np.isin(tr.type, focal_types(cfg.focal_types))
    out = []
    f = cfg.model.future_steps
    for c in window_steps(scene, cfg.history_steps, stride):
        fut = tr.valid[:, c + 1:c + f + 1].sum(1)
        rows = np.flatnonzero(types & tr.valid[:, c] & (fut >= min_future))
        out.extend((int(c), int(r)) for r in rows)
    return np.array(out, np.int64).reshape(-1, 2)


@dataclass
class SceneData:
    """A scene with its map elements (what the dataset caches)."""

    scene: Scene
    chunks: MapChunks


def scene_data(scene: Scene, cfg: "GameFormerConfig") -> SceneData:
    return SceneData(scene, map_chunks(scene, cfg.map_points, cfg.map_spacing))


def training_sample(sd: SceneData, c: int, focal: int, cfg: "GameFormerConfig"
                    ) -> dict[str, np.ndarray]:
    """The training sample of ``focal`` at step ``c``: :func:`build_sample` plus ``future``
    (N, T, 2) and ``future_mask`` (N, T)."""
    hist = log_history(sd.scene, c, cfg.history_steps)
    s = build_sample(hist, focal, sd.chunks, cfg.max_agents, cfg.map_elements)
    s["future"], s["future_mask"] = log_future(sd.scene, c, s["rows"], s["frame"],
                                               cfg.model.future_steps)
    return s


class StreamingDataset:
    """Seeded batches of training samples over scene records (module doc).

    :param refs: scene records (:class:`converters.scene_files.RecordRef`).
    :param cfg: the ``gameformer`` config. :param seed: the run seed.
    """

    def __init__(self, refs: list, cfg: "GameFormerConfig", seed: int) -> None:
        from converters.scene_files import read_record

        self.refs, self.cfg, self.seed = list(refs), cfg, int(seed)
        self._read = read_record
        self.index: list[np.ndarray] = []
        for ref in self.refs:  # one pass, nothing kept but the (c, focal) pairs
            self.index.append(scene_samples(read_record(ref), cfg, cfg.window_stride,
                                            cfg.min_future_steps))
        self.num_samples = int(sum(len(i) for i in self.index))
        if self.num_samples == 0:
            raise ValueError("no training sample in the scenes (no focal agent with "
                             f"{cfg.min_future_steps} future steps)")
        self._cache: OrderedDict[int, SceneData] = OrderedDict()
        self._order: tuple[int, np.ndarray] | None = None

    @property
    def batches_per_epoch(self) -> int:
        return -(-self.num_samples // self.cfg.batch_size)

    def epoch_order(self, epoch: int) -> np.ndarray:
        """(num_samples, 3) (scene, c, focal) in the order epoch ``epoch`` serves them."""
        if self._order is not None and self._order[0] == epoch:
            return self._order[1]
        rng = np.random.default_rng([self.seed, DATA_STREAM, epoch])
        scenes = rng.permutation(len(self.refs))
        g = self.cfg.cache_scenes
        parts = []
        for k in range(0, len(scenes), g):
            group = [np.concatenate([np.full((len(self.index[i]), 1), i), self.index[i]], 1)
                     for i in scenes[k:k + g] if len(self.index[i])]
            if group:
                rows = np.concatenate(group)
                parts.append(rows[rng.permutation(len(rows))])
        order = np.concatenate(parts)
        self._order = (epoch, order)
        return order

    def scene(self, i: int) -> SceneData:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        sd = scene_data(self._read(self.refs[i]), self.cfg)
        self._cache[i] = sd
        while len(self._cache) > self.cfg.cache_scenes + 1:
            self._cache.popitem(last=False)
        return sd

    def batch(self, position: int) -> dict[str, torch.Tensor]:
        """Batch number ``position`` of the run (epoch ``position // batches_per_epoch``)."""
        epoch, b = divmod(position, self.batches_per_epoch)
        order = self.epoch_order(epoch)
        bs = self.cfg.batch_size
        return collate([training_sample(self.scene(int(i)), int(c), int(f), self.cfg)
                        for i, c, f in order[b * bs:(b + 1) * bs]])
