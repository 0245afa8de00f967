"""GameFormer model inputs from a scene: map elements, agent histories, agent-centric samples.

A *sample* is one focal agent at one current step ``c`` of a scene: the focal agent (index 0)
and its ``max_agents − 1`` nearest other objects observed at ``c`` (vehicles, pedestrians,
cyclists, others), in the focal agent's frame at ``c`` (origin at its box centre, +x along its
heading; metres, radians, m/s). Each agent carries ``history_steps`` states ending at ``c``
(``c − history_steps + 1 .. c``; 11 steps = 1 s at 10 Hz) and, for training and open-loop
scoring, its ``future_steps`` recorded positions ``c + 1 .. c + future_steps`` (8 s) with a mask
(:func:`log_future`; steps past the scene's end or unobserved are masked). Each agent also
carries its ``map_elements`` nearest map elements: every lane centre line, road line, road
edge and crosswalk outline (closed) of the scene resampled every ``map_spacing`` m and cut into
pieces of ``map_points`` points (:func:`map_chunks`), nearest by the smallest point distance to
the agent's position at ``c``. Feature layouts: :data:`~magail_sumo.models.gameformer.AGENT_FEATURES`,
:data:`~magail_sumo.models.gameformer.MAP_FEATURES`. Traffic-signal states are not used.
Training (:mod:`magail_sumo.training.gameformer.data`), open-loop evaluation and the closed-loop
agent build their samples here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np
import torch

from magail_sumo.scene import ObjectType, Scene

from .gameformer import AGENT_FEATURES, MAP_FEATURES

#: map element kinds (type one-hot order of the map features)
MAP_KINDS = ("lane", "road_line", "road_edge", "crosswalk")
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


