"""Per-agent episode events other than collisions: off-road, red-light violation, destination.

Rules (scene frame, metres):

* **off-road** (``EnvConfig.off_road_rule``): ``"lane"``: the box centre lies farther than
  ``lane_width / 2 + margin`` from every lane centre line of the scene map (WOMD lanes carry no
  width, so one nominal width is used); ``"road_edge"`` (:class:`RoadEdgeRule`): a corner of
  the box lies more than ``off_road_edge_margin`` beyond the road edges, WOSAC's off-road test
  (the signed distance of :mod:`magail_sumo.sensors.road_edge`, positive
  off-road), while the agent's recorded pose at that step does not (parked off the road in
  the log is not off-road), in scenes whose map has road edges (the lane rule elsewhere);
* **red-light violation**: during the step the box centre crosses a signalled stop line — the
  line through a signal record's stop point, normal to the start direction of its lane, within
  ``lane_width / 2`` of the stop point — and every signal record at that stop line is red at the
  step's start (a vehicle going straight on green past a red turn arrow is not flagged);
* **destination reached**: the box centre is within ``radius`` of the last recorded position
  of the agent's track.
"""

from __future__ import annotations

import warnings

from dataclasses import dataclass

import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.sensors.road_edge import distance_to_road_edge, has_road_edges, road_edge_segments
from magail_sumo.sensors.traffic_lights import LIGHT_CODES, RED


def off_road(lane_distance: np.ndarray, lane_width: float, margin: float) -> np.ndarray:
    """(A,) bool: lane-centre distance (m) beyond half the lane width plus the margin."""
    return np.asarray(lane_distance) > 0.5 * lane_width + margin


@dataclass(frozen=True)
class RoadEdgeRule:
    """WOSAC's off-road test for the env (module doc), built once per scene.

    An agent is off-road when a corner of its box lies beyond the road edges by more than the
    margin **while its recorded pose at that step does not** (a vehicle parked off the road in
    the log is not flagged for staying there: WOSAC scores an agent's off-road indication
    against its log's). At steps its track is not recorded, its nearest earlier recorded step
    stands in (else its first).

    :param segments: the scene's road-edge segments
        (:func:`~magail_sumo.sensors.road_edge.road_edge_segments`).
    :param z: (N,) each track's median recorded box bottom (z less half the height, m):
        the env is 2-D, and z only picks the road level where edges overlap.
    :param log_off: (N, T) the recorded pose of track n at step t is off-road (filled as
        above).
    :param margin: tolerance (m) beyond the edge before a corner counts as off-road.
    """

    segments: object
    z: np.ndarray
    log_off: np.ndarray
    margin: float

    @classmethod
    def build(cls, scene: Scene, margin: float, length: np.ndarray, width: np.ndarray
              ) -> "RoadEdgeRule | None":
        """The rule of ``scene`` (``length, width``: (N,) each track's box size, m); None
        when its map has no road edge (nuScenes pickles)."""
        if not has_road_edges(scene):
            return None
        tr = scene.tracks
        n, t_steps = tr.valid.shape
        z = np.where(tr.valid, tr.z - tr.height / 2, np.nan)  # the box's bottom, as WOSAC
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a track never valid: NaN, then 0
            med = np.nanmedian(z, axis=1) if t_steps else np.zeros(n)
        rule = cls(road_edge_segments(scene), np.nan_to_num(med).astype(np.float32),
                   np.zeros((n, t_steps), bool), margin)
        r, t = np.nonzero(tr.valid)
        off = rule.corners_off(r, tr.x[r, t], tr.y[r, t], tr.heading[r, t], length[r],
                               width[r])
        # forward fill over unrecorded steps (back fill before the first recorded one)
        idx = np.where(tr.valid, np.arange(t_steps)[None, :], -1)
        last = np.maximum.accumulate(idx, axis=1)
        first = np.argmax(tr.valid, axis=1)[:, None]
        src = np.where(last >= 0, last, first)
        rec = np.zeros((n, t_steps), bool)
        rec[r, t] = off
        rule.log_off[:] = np.take_along_axis(rec, src, axis=1)
        return rule

    def corners_off(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                    length: np.ndarray, width: np.ndarray) -> np.ndarray:
        """(A,) bool: a box corner of track rows ``rows`` at the given poses lies beyond the
        road edge by more than the margin (whatever the log did)."""
        if len(rows) == 0:
            return np.zeros(0, bool)
        # the metric's (batch, object, step) layout: one batch, one step; z is already the
        # box's bottom, so height 0
        pose = [np.asarray(v, np.float64)[None, :, None] for v in (x, y, self.z[rows], yaw)]
        size = [np.asarray(v, np.float64)[:, None] for v in (length, width)]
        d = distance_to_road_edge(*pose[:3], pose[3], *size, np.zeros_like(size[0]),
                                  np.ones(pose[0].shape, bool), self.segments)
        return d[0, :, 0] > self.margin

    def off_road(self, rows: np.ndarray, t: int, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                 length: np.ndarray, width: np.ndarray) -> np.ndarray:
        """(A,) bool: track rows ``rows`` at the given poses at step ``t`` are off-road where
        their log is not (class doc)."""
        return self.corners_off(rows, x, y, yaw, length, width) & ~self.log_off[rows, t]


def reached(x: np.ndarray, y: np.ndarray, destination: np.ndarray, radius: float) -> np.ndarray:
    """(A,) bool: positions within ``radius`` m of (A, 2) destinations."""
    return np.hypot(destination[:, 0] - x, destination[:, 1] - y) <= radius


@dataclass(frozen=True)
class StopLines:
    """Signal records with their stop line geometry, ordered by step (built once per scene).

    :param step: (K,) log step. :param point: (K, 2) stop point (m).
    :param direction: (K, 2) unit start direction of the controlled lane.
    :param red: (K,) the record's state is red.
    :param line: (K,) stop-line group id (records sharing a stop point, rounded to 0.5 m).
    """

    step: np.ndarray
    point: np.ndarray
    direction: np.ndarray
    red: np.ndarray
    line: np.ndarray

    @classmethod
    def build(cls, scene: Scene) -> "StopLines":
        sig = scene.signals
        dirs = {}
        for lane in scene.roadmap.lanes:
            p = lane.polyline[:, :2]
            d = p[1:] - p[:-1] if len(p) > 1 else np.zeros((0, 2))
            d = d[np.hypot(d[:, 0], d[:, 1]) > 1e-6]
            if len(d):
                dirs[lane.id] = d[0] / np.hypot(*d[0])
        keep = np.array([int(l) in dirs for l in sig.lane], bool) if len(sig) else np.zeros(0, bool)
        point = sig.stop_point[keep, :2]
        key = np.round(point / 0.5).astype(np.int64)
        line = np.unique(key, axis=0, return_inverse=True)[1].reshape(-1) if len(key) \
            else np.zeros(0, np.int64)
        return cls(sig.step[keep].astype(np.int64), point,
                   np.array([dirs[int(l)] for l in sig.lane[keep]]).reshape(-1, 2),
                   LIGHT_CODES[sig.state[keep].astype(np.int64)] == RED, line)

    def red_crossings(self, step: int, p0: np.ndarray, p1: np.ndarray, lane_width: float
                      ) -> np.ndarray:
        """(A,) bool: agents moving from (A, 2) ``p0`` to ``p1`` ran a red light at ``step``."""
        lo, hi = np.searchsorted(self.step, [step, step + 1])
        a = p0.shape[0]
        if hi == lo or a == 0:
            return np.zeros(a, bool)
        pt, d = self.point[lo:hi], self.direction[lo:hi]
        r0 = p0[:, None, :] - pt[None]
        r1 = p1[:, None, :] - pt[None]
        s0 = (r0 * d[None]).sum(-1)
        s1 = (r1 * d[None]).sum(-1)
        lat = np.abs(r1[..., 0] * d[None, :, 1] - r1[..., 1] * d[None, :, 0])
        crossed = (s0 < 0) & (s1 >= 0) & (lat <= 0.5 * lane_width)  # (A, K)
        lines = self.line[lo:hi]
        red = self.red[lo:hi]
        # a crossed line is a violation when no record on it is non-red at this step
        nonred_on_line = np.zeros(int(self.line.max()) + 1, bool)
        np.logical_or.at(nonred_on_line, lines, ~red)
        return (crossed & ~nonred_on_line[lines][None]).any(axis=1)
