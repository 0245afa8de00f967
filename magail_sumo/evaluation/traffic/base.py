"""Metric interface (Waymax style): one :class:`TrafficMetric` subclass per metric, a registry and
a factory, all computed from one shared :class:`MetricInput` per scene and method.

:class:`MetricInput` reuses the realism features (:mod:`magail_sumo.evaluation.realism`) for
*every* sim agent (not only the evaluated ones): batch row 0 is the log, rows 1.. the rollouts,
over the 80 simulated steps; per-step features are masked by the log's validity, as in the
WOSAC metric, so log and rollouts are compared on the same object-steps.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from magail_sumo.evaluation.realism import compute_features, joint_trajectories
from magail_sumo.evaluation.realism.kinematic import central_diff, central_valid
from magail_sumo.evaluation.realism.metrics import Features
from magail_sumo.evaluation.realism.trajectories import JointTrajectories
from magail_sumo.evaluation.submission import ScenarioRollouts
from magail_sumo.scene import ObjectType, Scene
from magail_sumo.scene.types import STEP_LENGTH

DT = STEP_LENGTH  #: s per step


@dataclass(frozen=True, eq=False)
class MetricInput:
    """Log and rollouts of one scene as feature arrays (B = 1 + R batch rows, log first).

    :param jt: joint trajectories, all sim agents evaluated (``n_eval`` = A).
    :param feat: realism features ``(B, A, T)`` over the simulated steps.
    :param x: (B, A, T) float32 simulated-step pose x (m; scene frame).
    :param y: (B, A, T) float32 simulated-step pose y (m; scene frame).
    :param heading: (B, A, T) float32 simulated-step heading (rad; scene frame).
    :param valid: (A, T) bool, the log's validity over the simulated steps.
    :param is_vehicle: (A,) bool.
    """

    scene: Scene
    jt: JointTrajectories
    feat: Features
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    valid: np.ndarray
    is_vehicle: np.ndarray

    @classmethod
    def build(cls, scene: Scene, ro: ScenarioRollouts) -> "MetricInput":
        """Features of validated rollouts ``ro`` of ``scene`` (see module doc)."""
        jt = joint_trajectories(scene, ro)
        jt = dataclasses.replace(jt, n_eval=len(jt.object_id))
        feat = compute_features(scene, jt)
        fut = slice(scene.current_time_index + 1, None)
        return cls(scene, jt, feat, jt.x[..., fut], jt.y[..., fut], jt.heading[..., fut],
                   jt.log_valid[:, fut], jt.object_type == int(ObjectType.VEHICLE))

    @property
    def n_rollouts(self) -> int:
        return self.x.shape[0] - 1

    def feature(self, name: str) -> np.ndarray:
        """(B, A, T) per-step feature: a realism feature name, or ``jerk`` (m/s³)."""
        if name == "jerk":
            return central_diff(self.feat.values["linear_acceleration"]) / np.float32(DT)
        return self.feat.values[name]

    def mask(self, name: str) -> np.ndarray:
        """(A, T) object-steps where ``name`` is defined in the log: central differences need
        valid neighbours (speed: 1, acceleration: 2, jerk: 3 levels)."""
        m = self.valid
        depth = {"linear_speed": 1, "angular_speed": 1, "linear_acceleration": 2,
                 "angular_acceleration": 2, "jerk": 3}.get(name, 0)
        for _ in range(depth):
            m = central_valid(m)
        if name == "time_to_collision":
            m = m & self.is_vehicle[:, None]
        return m

    def log_and_sim(self, name: str, vehicles_only: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Finite values of a feature: (log values, all rollouts' values) on the log's mask."""
        v = self.feature(name)
        m = self.mask(name)
        if vehicles_only:
            m = m & self.is_vehicle[:, None]
        log, sim = v[0][m], v[1:][:, m].ravel()
        return log[np.isfinite(log)], sim[np.isfinite(sim)]


class TrafficMetric(ABC):
    """A scalar traffic metric of one scene's rollouts (mean over rollouts)."""

    name: ClassVar[str]
    unit: ClassVar[str]
    description: ClassVar[str]
    lower_is_better: ClassVar[bool] = True

    @abstractmethod
    def compute(self, inp: MetricInput) -> float:
        """Value (in :attr:`unit`); NaN when the scene has nothing to measure."""


METRICS: dict[str, type[TrafficMetric]] = {}


def register(cls: type[TrafficMetric]) -> type[TrafficMetric]:
    METRICS[cls.name] = cls
    return cls


def make_metric(name: str) -> TrafficMetric:
    """The metric registered under ``name``; ``KeyError`` naming the known ones otherwise."""
    try:
        return METRICS[name]()
    except KeyError:
        raise KeyError(f"unknown traffic metric {name!r} (known: {', '.join(METRICS)})") from None


def compute_metrics(inp: MetricInput, names: list[str] | None = None) -> dict[str, float]:
    """Every (or the named) registered metric of one scene."""
    return {n: float(make_metric(n).compute(inp)) for n in (names or list(METRICS))}
