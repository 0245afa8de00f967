"""What a report shows, as data: :class:`Scores` (every figure of an evaluation folder) and
:class:`SceneView` (one scene's drawn trajectories and animation); :mod:`.scoring` fills them,
:mod:`.figures`, :mod:`.animation` and the report draw them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magail_sumo.evaluation.submission import ScenarioRollouts
from magail_sumo.scene import Scene


@dataclass
class Scores:
    """Everything a report shows.

    :param rows: one dict per (scenario_id, method): traffic metrics and realism fields.
    :param counts: per (scenario_id, method), per :data:`FIGURE_FEATURES` feature, the log's
        and the rollouts' histogram counts on the feature's bins (for the distribution figure).
    :param rollouts: the rollouts per (scenario_id, method).
    :param errors: one-line problems (scene / method / agent named).
    :param agent_rows: one dict per (scenario_id, method, evaluated agent): see
        :func:`.scoring.agent_metrics`.
    :param valid: per (scenario_id, method), (R, A, T) bool: the states the method marked
        valid (absent: all valid).
    :param views: per scenario_id, its trajectory figure and animation drawn by a scoring
        worker (see :class:`SceneView`); the report draws the scenes without one itself.
    """

    manifest: dict
    scenes: dict[str, Scene]
    methods: list[str]
    rows: list[dict] = field(default_factory=list)
    counts: dict[tuple[str, str], dict[str, tuple[np.ndarray, np.ndarray]]] = \
        field(default_factory=dict)
    rollouts: dict[tuple[str, str], ScenarioRollouts] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    agent_rows: list[dict] = field(default_factory=list)
    valid: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    views: dict[str, "SceneView"] = field(default_factory=dict)


@dataclass(frozen=True)
class SceneView:
    """A scene's trajectory figure (PNG bytes, :func:`.figures.trajectories`) and animation
    (HTML, :func:`.animation.scene_animation`), drawn where the scene was scored from the
    methods ``methods`` (in report order); valid for a report whose methods with rollouts for
    this scene are exactly these."""

    methods: tuple[str, ...]
    trajectories_png: bytes
    animation_html: str
