"""The Scene: one recorded driving scenario, format-independent."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .base import ArrayDataclass, frozen_array
from .quality import DataQuality, SourceIds
from .roadmap import RoadMap
from .signals import SignalStates
from .tracks import Tracks
from .types import Difficulty


@dataclass(frozen=True, eq=False)
class RequiredPrediction(ArrayDataclass):
    """A track the dataset asks to predict: index into ``Scene.tracks`` and its difficulty."""

    track_index: int
    difficulty: Difficulty = Difficulty.NONE


@dataclass(frozen=True, eq=False)
class Scene(ArrayDataclass):
    """A recorded scene: tracks over T steps, road map and traffic-signal states.

    :param scenario_id: dataset scenario id.
    :param timestamps: (T,) float64 seconds from the first step.
    :param tracks: object tracks (N × T arrays).
    :param roadmap: static map features.
    :param signals: per-step traffic-signal lane states.
    :param sdc_track_index: index of the recording (self-driving) vehicle in ``tracks``; -1 if none.
    :param current_time_index: index of the "current" step (history ends here, 10 in WOMD).
    :param tracks_to_predict: tracks the dataset marks for prediction.
    :param objects_of_interest: ids of tracks with interactive behaviour.
    :param source_ids: original ids of a source with non-integer ids (empty otherwise).
    :param data_quality: what the reader repaired or inferred; not compared (a scene written
        and read back has nothing left to repair).
    """

    scenario_id: str
    timestamps: np.ndarray
    tracks: Tracks
    roadmap: RoadMap = field(default_factory=RoadMap)
    signals: SignalStates = field(default_factory=SignalStates.empty)
    sdc_track_index: int = -1
    current_time_index: int = 0
    tracks_to_predict: tuple[RequiredPrediction, ...] = ()
    objects_of_interest: tuple[int, ...] = ()
    source_ids: SourceIds = field(default_factory=SourceIds)
    data_quality: DataQuality = field(default_factory=DataQuality, compare=False)

    def __post_init__(self) -> None:
        try:
            ts = frozen_array(self.timestamps, np.float64, (self.tracks.num_steps,))
        except ValueError as exc:
            raise ValueError(f"Scene timestamps: {exc} (tracks have {self.tracks.num_steps} steps)") \
                from None
        object.__setattr__(self, "timestamps", ts)

    @property
    def num_steps(self) -> int:
        return self.tracks.num_steps

    @property
    def duration(self) -> float:
        """Seconds from the first to the last step."""
        return float(self.timestamps[-1] - self.timestamps[0]) if self.num_steps else 0.0

    def summary(self) -> dict[str, Any]:
        """Counts describing the scene (the ``magail-sumo inspect --json`` record); with a
        ``data_quality`` record when the reader repaired or inferred anything."""
        out = {
            "scenario_id": self.scenario_id,
            "num_steps": self.num_steps,
            "tracks_by_type": self.tracks.count_by_type(),
            "valid_states": int(self.tracks.valid.sum()),
            "map_features": self.roadmap.count_by_kind(),
            "signal_states": len(self.signals),
            "sdc_track_index": self.sdc_track_index,
            "tracks_to_predict": len(self.tracks_to_predict),
        }
        if not self.data_quality.clean:
            out["data_quality"] = self.data_quality.to_dict()
        return out
