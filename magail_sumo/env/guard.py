"""Gap guard: an optional car-following safety limit on the agents' acceleration (``EnvConfig.
guard``), the last stage before the bicycle model moves them.

A policy picks its acceleration freely; the guard only lowers it where keeping it would leave
the agent unable to stop behind its leader. The leader is the nearest road user ahead in the
agent's path at the step's start (:func:`magail_sumo.sensors.units.leader.nearest_ahead`: box
centre ahead, boxes overlapping sideways, within ``range`` m; the other box's extents taken
along the agent's axes, so a vehicle crossing the path counts with its length). With
``kind: path`` the leader is read along the agent's reference path instead (route-relative
control; :func:`magail_sumo.sensors.units.path_leader.along_path`: the nearest road user
reaching into the agent's lane corridor ahead, the gap along the path; an env without
reference paths reads straight ahead as with ``gap``): straight ahead, a
guard stops agents for vehicles on crossing and neighbouring lanes that will never be in their
way, and jams a city.

Safe speed (m/s; the stopping-distance form of Gipps' and SUMO's Krauss model): with gap ``g``
(m, bumper to bumper) less the standstill gap ``min_gap``, the leader's speed along the agent's
heading ``v_l >= 0`` (m/s), braking ``b`` (m/s², assumed of both) and reaction time ``tau`` (s),
the agent can stop behind a leader that brakes at ``b`` when its speed is at most

    v_safe = -b·tau + sqrt((b·tau)² + v_l² + 2·b·max(g - min_gap, 0))

(the agent's reaction distance plus braking distance ``v·tau + v²/(2b)`` equals the gap plus
the leader's braking distance ``v_l²/(2b)``). The guard caps the acceleration at
``(max(v_safe, 0) - v) / dt`` (never below ``-max_brake``: the limits still hold); agents
without a leader in range, or already below ``v_safe``, keep their action. Everything is a
pure function of (A,) arrays; the env counts the lowered actions per episode
(``env.guarded``).

The guard is part of the environment a policy was trained in: a checkpoint trained with it
carries it (the policy's ``guard`` attribute, :class:`~magail_sumo.agents.base.Policy`), so
evaluation drives it the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magail_sumo.config import check, check_positive, show
from magail_sumo.sim.dynamics import BicycleLimits, denormalise, normalise

#: ``GuardConfig.kind`` choices
GUARD_KINDS: tuple[str, ...] = ("none", "gap", "path")


@dataclass(frozen=True)
class GuardConfig:
    """The gap guard (module doc).

    :param kind: ``"none"`` (off), ``"gap"`` or ``"path"`` (the leader along the agent's
        reference path, module doc).
    :param decel: braking the guard assumes of the agent and its leader (m/s², > 0; SUMO's
        default passenger car: 4.5).
    :param tau: the agent's reaction time (s, >= 0; SUMO's default: 1.0).
    :param min_gap: gap kept at standstill (m, >= 0; SUMO's default: 2.5).
    :param range: farthest leader considered (m, > 0).
    """

    kind: str = "none"
    decel: float = 4.5
    tau: float = 0.5
    min_gap: float = 1.0
    range: float = 50.0

    def __post_init__(self) -> None:
        # plain keys: from_dict names the dotted path (env.guard.decel)
        check(self.kind in GUARD_KINDS, "kind",
              f"must be one of {list(GUARD_KINDS)}, got {show(self.kind)}")
        for name in ("decel", "tau", "min_gap", "range"):
            v = getattr(self, name)
            check(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
                  name, f"must be a finite number, got {show(v)}")
        check_positive(self, "decel", "range")
        check_positive(self, "tau", "min_gap", allow_zero=True)

    @property
    def on(self) -> bool:
        return self.kind != "none"


def safe_speed(gap: np.ndarray, leader_speed: np.ndarray, cfg: GuardConfig) -> np.ndarray:
    """(A,) largest speed (m/s, >= 0) at which an agent ``gap`` m behind a leader driving at
    ``leader_speed`` m/s along its heading can still stop behind it (module doc)."""
    b, tau = cfg.decel, cfg.tau
    g = np.maximum(np.asarray(gap, np.float64) - cfg.min_gap, 0.0)
    vl = np.maximum(np.asarray(leader_speed, np.float64), 0.0)
    return np.maximum(-b * tau + np.sqrt((b * tau) ** 2 + vl * vl + 2.0 * b * g), 0.0)


def guarded(action: np.ndarray, speed: np.ndarray, gap: np.ndarray, leader_speed: np.ndarray,
            found: np.ndarray, cfg: GuardConfig, limits: BicycleLimits, layout: str, dt: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """Clean normalised (A, 2) ``action`` (in ``layout``) with the acceleration capped by the
    guard, and the (A,) mask of the agents whose acceleration it lowered.

    :param speed: (A,) the agents' speeds (m/s). :param gap, leader_speed, found: (A,) each
        agent's leader gap (m), its speed along the agent's heading (m/s) and whether it has a
        leader in range.
    """
    accel, steer = denormalise(action, limits, layout)
    cap = (safe_speed(gap, leader_speed, cfg) - np.asarray(speed, np.float64)) / dt
    cap = np.maximum(cap, -limits.max_brake)
    lower = np.asarray(found, bool) & (accel > cap)
    if not lower.any():
        return action, lower
    out = normalise(np.where(lower, cap, accel), steer, limits, layout)
    keep = ~lower
    out[keep] = action[keep]  # untouched actions stay bit for bit
    return out, lower
