"""Traffic-light state of each lane at each log step, as a lookup table built once per scene.

Codes: 0 none/unknown, 1 green, 2 yellow, 3 red (:data:`LIGHT_CODES` maps the WOMD
:class:`SignalState` values). WOMD records signals on the lanes that start at a stop line
(usually the lanes inside a junction); a lane without a record of its own takes the states of
its signalled exit lanes, the most permissive one (green > yellow > red), so an agent on the
approach lane sees the light ahead of it.

A *light source* (:class:`LightSource`) is what the sensors read lights from: a
:class:`LightTable` of a recording's signals, or :data:`NO_LIGHTS` for a map without recorded
signals (a SUMO city, whose env passes the live light of each agent to the sensors instead).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from magail_sumo.scene import Lane, Scene, SignalStates, SignalState

NONE, GREEN, YELLOW, RED = 0, 1, 2, 3
#: light code of each :class:`SignalState` value
LIGHT_CODES = np.zeros(len(SignalState), np.int8)
LIGHT_CODES[[SignalState.ARROW_GO, SignalState.GO]] = GREEN
LIGHT_CODES[[SignalState.ARROW_CAUTION, SignalState.CAUTION, SignalState.FLASHING_CAUTION]] = YELLOW
LIGHT_CODES[[SignalState.ARROW_STOP, SignalState.STOP, SignalState.FLASHING_STOP]] = RED
_RANK = np.array([0, 3, 2, 1], np.int8)  # permissiveness of codes none, green, yellow, red


class LightSource(Protocol):
    """Where the sensors read traffic lights from (lane indices: order of ``RoadMap.lanes``)."""

    def lookup(self, step: int, lane: np.ndarray) -> np.ndarray:
        """(A,) light codes of lane indices at a log step (0 for lane -1)."""

    def at_end(self, lane: np.ndarray) -> np.ndarray:
        """(A,) bool: the lane's light stands at its end (an approach lane showing its exits'
        signal; its stop line is where it ends), False for lane -1 and for lanes whose own
        record it is (the stop line at their start, behind an agent on them)."""


@dataclass(frozen=True)
class LightTable:
    """(T, L) light codes per log step and lane index (lane order of ``RoadMap.lanes``), and
    (L,) which lanes take their light from their exits (:meth:`LightSource.at_end`)."""

    codes: np.ndarray
    inherited: np.ndarray | None = None

    @classmethod
    def build(cls, scene: Scene) -> "LightTable":
        """The light table of a recorded scene (its map's lanes and its signal records)."""
        return cls.from_signals(scene.roadmap.lanes, scene.signals, scene.num_steps)

    @classmethod
    def from_signals(cls, lanes: tuple[Lane, ...], sig: SignalStates, t_steps: int
                     ) -> "LightTable":
        """The light table of ``t_steps`` log steps of signal records ``sig`` over ``lanes``
        (module doc: approach lanes take their signalled exits' lights)."""
        index = {l.id: k for k, l in enumerate(lanes)}
        own = np.zeros((t_steps, len(lanes)), np.int8)
        known = np.array([int(l) in index for l in sig.lane], bool) if len(sig) else np.zeros(0, bool)
        if known.any():
            cols = np.array([index[int(l)] for l in sig.lane[known]], np.int64)
            rows = np.clip(sig.step[known].astype(np.int64), 0, t_steps - 1)
            own[rows, cols] = LIGHT_CODES[sig.state[known].astype(np.int64)]
        codes = own.copy()
        signalled = set(np.unique(cols).tolist()) if known.any() else set()
        inherited = np.zeros(len(lanes), bool)
        for k, lane in enumerate(lanes):  # once per scene: approach lanes take their exits' lights
            if k in signalled:
                continue
            exits = [index[e] for e in lane.exit_lanes if e in index and index[e] in signalled]
            if exits:
                sub = own[:, exits]
                best = np.argmax(_RANK[sub], axis=1)
                codes[:, k] = sub[np.arange(t_steps), best]
                inherited[k] = True
        return cls(codes, inherited)

    def lookup(self, step: int, lane: np.ndarray) -> np.ndarray:
        """(A,) light codes of lane indices at a log step (0 for lane -1 or steps past the log)."""
        lane = np.asarray(lane, np.int64)
        if not 0 <= step < self.codes.shape[0] or self.codes.shape[1] == 0:
            return np.zeros(lane.shape, np.int8)
        return np.where(lane >= 0, self.codes[step, np.maximum(lane, 0)], 0).astype(np.int8)

    def at_end(self, lane: np.ndarray) -> np.ndarray:
        lane = np.asarray(lane, np.int64)
        if self.inherited is None or self.inherited.size == 0:
            return np.zeros(lane.shape, bool)
        return (lane >= 0) & self.inherited[np.maximum(lane, 0)]


#: light source of a map without recorded signals: every lane reads 0 (none) at every step
NO_LIGHTS = LightTable(np.zeros((0, 0), np.int8))
