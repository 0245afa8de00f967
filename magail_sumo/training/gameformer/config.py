"""The ``gameformer`` block of a ``gameformer`` run's config."""

from __future__ import annotations

from dataclasses import dataclass, field

from magail_sumo.config import check, check_positive, show
from magail_sumo.models.gameformer import GameFormerModelConfig


@dataclass(frozen=True)
class GameFormerConfig:
    """The ``gameformer`` algorithm: level-k interactive trajectory prediction trained on the
    recorded scenes ``scenes.files`` (no simulation; :mod:`magail_sumo.training.gameformer`,
    samples as in :mod:`magail_sumo.training.gameformer.data`), driving as a sim agent in
    evaluation. ``updates`` of the run are gradient steps, one batch each.

    :param model: network sizes (:class:`~magail_sumo.models.gameformer.GameFormerModelConfig`).
    :param history_steps: 0.1-s history steps per agent, the current one included.
    :param max_agents: agents per sample (the focal one and its nearest others).
    :param map_elements: map elements per agent. :param map_points: points per element.
    :param map_spacing: m between the points of an element.
    :param window_stride: steps between the current steps of the training windows.
    :param min_future_steps: observed future steps a focal agent needs to be a sample.
    :param focal_types: object types that are focal agents (``vehicle``, ``pedestrian``,
        ``cyclist``, ``other``).
    :param interaction_weight: weight of the repulsion term; :param safety_distance: m below
        which it acts.
    :param cache_scenes: scenes the dataset holds at once (and groups when shuffling).
    :param replan_every: steps between replans of the closed-loop agent.
    :param eval_stride: steps between the current steps of the open-loop evaluation windows.
    """

    model: GameFormerModelConfig = field(default_factory=GameFormerModelConfig)
    history_steps: int = 11
    max_agents: int = 8
    map_elements: int = 16
    map_points: int = 10
    map_spacing: float = 2.0
    window_stride: int = 5
    min_future_steps: int = 10
    focal_types: tuple[str, ...] = ("vehicle", "cyclist")
    batch_size: int = 32
    learning_rate: float = 5e-4
    weight_decay: float = 0.0
    max_grad_norm: float = 1.0
    interaction_weight: float = 0.1
    safety_distance: float = 3.0
    cache_scenes: int = 4
    replan_every: int = 10
    eval_stride: int = 10

    def __post_init__(self) -> None:
        for name in ("history_steps", "max_agents", "map_elements", "map_points",
                     "window_stride", "min_future_steps", "batch_size", "cache_scenes",
                     "replan_every", "eval_stride"):
            v = getattr(self, name)
            check(v >= 1, name, f"must be >= 1, got {show(v)}")
        check(self.min_future_steps <= self.model.future_steps, "min_future_steps",
              f"must be <= model.future_steps ({self.model.future_steps}), "
              f"got {self.min_future_steps}")
        check_positive(self, "map_spacing", "learning_rate", "max_grad_norm", "safety_distance")
        check_positive(self, "weight_decay", "interaction_weight", allow_zero=True)
        known = ("vehicle", "pedestrian", "cyclist", "other")
        bad = [t for t in self.focal_types if t not in known]
        check(bool(self.focal_types) and not bad, "focal_types",
              f"must be a non-empty list of {', '.join(known)}, got {show(self.focal_types)}")
