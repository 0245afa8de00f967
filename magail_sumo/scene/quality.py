"""What a reader had to repair or infer, and the ids a source used before we numbered them.

Neither is part of the recorded scene itself: :class:`DataQuality` is kept on the Scene but
excluded from equality (a scene written and read back has nothing left to repair), while
:class:`SourceIds` is compared (the writer writes the original ids back).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .base import ArrayDataclass


@dataclass(frozen=True, eq=False)
class DroppedReference(ArrayDataclass):
    """A reference of a map feature to an id that is not in the map; the reader dropped it.

    :param feature_id: id of the feature holding the reference (our integer id).
    :param field: the source field (``entry_lanes``, ``right_neighbor``, ``left_boundaries``,
        ``lane`` of a stop sign, ``dynamic_map_states`` for a signal's lane, ...).
    :param missing_id: the referenced id as written in the source.
    """

    feature_id: int
    field: str
    missing_id: str

    def to_dict(self) -> dict[str, Any]:
        return {"feature_id": self.feature_id, "field": self.field, "missing_id": self.missing_id}


@dataclass(frozen=True, eq=False)
class DataQuality(ArrayDataclass):
    """Repairs and inferences made while reading a scene (empty for a clean source).

    :param dropped_references: references to ids not in the map, dropped (the scene is kept).
    :param inferred_successors: lane successor links (exit/entry pairs) inferred from geometry
        because the source has no lane connectivity at all.
    :param inferred_neighbors: lane neighbour links (left or right) inferred from geometry.
    :param notes: other one-line remarks (e.g. a source layout that records few signal steps).
    """

    dropped_references: tuple[DroppedReference, ...] = ()
    inferred_successors: int = 0
    inferred_neighbors: int = 0
    notes: tuple[str, ...] = ()

    @property
    def clean(self) -> bool:
        return not (self.dropped_references or self.inferred_successors
                    or self.inferred_neighbors or self.notes)

    def to_dict(self) -> dict[str, Any]:
        """The ``data_quality`` record of ``inspect --json`` and ``conversion.json``."""
        return {
            "dropped_references": [r.to_dict() for r in self.dropped_references],
            "inferred_connectivity": {"successors": self.inferred_successors,
                                      "neighbors": self.inferred_neighbors},
            "notes": list(self.notes),
        }


@dataclass(frozen=True, eq=False)
class SourceIds(ArrayDataclass):
    """Original ids of a source whose track or map-feature ids are not integers.

    Such a source (nuScenes, nuPlan, Argoverse in ScenarioNet: ``"ego"``, UUIDs) is numbered
    0..N-1 in recorded order; these pairs map our integer id back to the original string.
    Empty when the source's ids are the integers themselves.

    :param tracks: ``(track id, original id)`` pairs.
    :param map_features: ``(feature id, original id)`` pairs.
    """

    tracks: tuple[tuple[int, str], ...] = ()
    map_features: tuple[tuple[int, str], ...] = ()

    def track_names(self) -> dict[int, str]:
        return dict(self.tracks)

    def feature_names(self) -> dict[int, str]:
        return dict(self.map_features)
