"""Map-match tracks to WOMD lanes with a hidden Markov model (Viterbi over candidate lanes).

Emission: squared distance (m) to the lane centre line and heading difference (rad) to the
lane direction at the closest point. Transition: staying on a lane is free; moving along the
lane graph (exit lanes, same-direction neighbours) costs per hop; a jump off the graph costs
:data:`BREAK_COST`. All positions are box centres in the scene frame.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from magail_sumo.scene import Lane

from .geometry import angle_diff, point_segment, segments, simplify

SIGMA_D = 1.5  #: m
SIGMA_H = 0.35  #: rad
MAX_DIST = 4.0  #: m, candidates farther than this are ignored
MAX_HEADING = np.radians(60.0)
TOP_K = 6
HOP_COST = 1.0
CHANGE_COST = 2.0  #: a lane change to a same-direction neighbour
MAX_GRAPH_COST = 5.0
BREAK_COST = 40.0


@dataclass(frozen=True)
class LaneIndex:
    """Segments of a set of lanes, for vectorised distance queries, plus the lane graph costs."""

    ids: list[int]
    a: np.ndarray  # (S, 2) segment starts
    b: np.ndarray  # (S, 2) segment ends
    owner: np.ndarray  # (S,) index into ids
    heading: np.ndarray  # (S,) rad
    s0: np.ndarray  # (S,) arc length of the segment start on its lane (m)
    graph: dict[int, dict[int, float]]  # lane -> reachable lane -> cost


def build_index(lanes: dict[int, Lane]) -> LaneIndex:
    """Index the lanes ``lanes`` (id -> Lane) for :func:`match_track`."""
    ids = list(lanes)
    polys = [simplify(lanes[i].polyline, 1.0) for i in ids]
    a, b, owner = segments(polys)
    d = b - a
    seglen = np.linalg.norm(d, axis=1)
    s0 = np.zeros(len(a))
    starts = np.concatenate([[0], np.flatnonzero(np.diff(owner)) + 1]) if len(owner) else []
    cum = np.cumsum(seglen) - seglen
    for k, st in enumerate(starts):
        end = starts[k + 1] if k + 1 < len(starts) else len(a)
        s0[st:end] = cum[st:end] - cum[st]
    step: dict[int, list[tuple[int, float]]] = {}
    for i, lane in lanes.items():
        nxt = [(e, HOP_COST) for e in lane.exit_lanes if e in lanes]
        nxt += [(n.feature_id, CHANGE_COST) for n in lane.left_neighbors + lane.right_neighbors
                if n.feature_id in lanes]
        step[i] = nxt
    graph = {}
    for i in lanes:  # Dijkstra bounded by MAX_GRAPH_COST
        dist = {i: 0.0}
        heap = [(0.0, i)]
        while heap:
            c, u = heapq.heappop(heap)
            if c > dist.get(u, np.inf):
                continue
            for v, w in step[u]:
                if c + w <= MAX_GRAPH_COST and c + w < dist.get(v, np.inf):
                    dist[v] = c + w
                    heapq.heappush(heap, (c + w, v))
        graph[i] = dist
    return LaneIndex(ids, a, b, owner, np.arctan2(d[:, 1], d[:, 0]), s0, graph)


@dataclass(frozen=True)
class Match:
    """Per-state match of one track: lane id (-1 = unmatched) and arc position (m) on it."""

    steps: np.ndarray  # (M,) valid step indices
    lane: np.ndarray  # (M,) int64
    pos: np.ndarray  # (M,) float64, arc length along the lane of the closest point
    breaks: int  # number of transitions off the lane graph


def match_track(index: LaneIndex, xy: np.ndarray, heading: np.ndarray, steps: np.ndarray) -> Match:
    """Viterbi-match points ``xy`` (M, 2) with headings (M,) rad at ``steps`` to lanes."""
    m = len(xy)
    lane_out = np.full(m, -1, np.int64)
    pos_out = np.zeros(m)
    if m == 0 or not len(index.a):
        return Match(steps, lane_out, pos_out, 0)
    lo, hi = xy.min(axis=0) - MAX_DIST, xy.max(axis=0) + MAX_DIST
    near = np.flatnonzero(np.all((np.minimum(index.a, index.b) <= hi)
                                 & (np.maximum(index.a, index.b) >= lo), axis=1))
    a, b = index.a[near], index.b[near]
    owner, s0 = index.owner[near], index.s0[near]
    d, t = point_segment(xy, a, b)
    hd = angle_diff(heading[:, None], index.heading[near][None])
    cost = 0.5 * (d / SIGMA_D) ** 2 + 0.5 * (hd / SIGMA_H) ** 2
    cost[(d > MAX_DIST) | (hd > MAX_HEADING)] = np.inf
    seglen = np.linalg.norm(b - a, axis=1)
    cands: list[list[tuple[int, float, float]]] = []  # per state: (lane idx, cost, pos)
    for r in range(m):
        row = cost[r]
        ok = np.flatnonzero(np.isfinite(row))
        if not len(ok):
            cands.append([])
            continue
        order = ok[np.argsort(row[ok])]
        seen: dict[int, tuple[int, float, float]] = {}
        for sidx in order:
            o = int(owner[sidx])
            if o not in seen:
                seen[o] = (o, float(row[sidx]), float(s0[sidx] + t[r, sidx] * seglen[sidx]))
                if len(seen) == TOP_K:
                    break
        cands.append(list(seen.values()))
    rows = [r for r in range(m) if cands[r]]
    if not rows:
        return Match(steps, lane_out, pos_out, 0)
    ids = index.ids
    score = np.array([c[1] for c in cands[rows[0]]])
    back: list[np.ndarray] = []
    for prev, cur in zip(rows[:-1], rows[1:]):
        pc, cc = cands[prev], cands[cur]
        trans = np.empty((len(pc), len(cc)))
        for p, (pl, _, ppos) in enumerate(pc):
            reach = index.graph[ids[pl]]
            for c, (cl, _, cpos) in enumerate(cc):
                if pl == cl:
                    trans[p, c] = 0.0 if cpos >= ppos - 2.0 else BREAK_COST
                else:
                    trans[p, c] = reach.get(ids[cl], BREAK_COST)
        total = score[:, None] + trans
        arg = np.argmin(total, axis=0)
        back.append(arg)
        score = total[arg, np.arange(len(cc))] + np.array([c[1] for c in cc])
    k = int(np.argmin(score))
    path = [k]
    for arg in reversed(back):
        k = int(arg[k])
        path.append(k)
    path.reverse()
    breaks = 0
    prev_lane = None
    for r, k in zip(rows, path):
        li, _, p = cands[r][k]
        lane_out[r] = ids[li]
        pos_out[r] = p
        if prev_lane is not None and prev_lane != ids[li] and ids[li] not in index.graph[prev_lane]:
            breaks += 1
        prev_lane = ids[li]
    return Match(steps, lane_out, pos_out, breaks)
