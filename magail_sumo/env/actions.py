"""Agent action dicts (PettingZoo) and action arrays to clean arrays, counting what had to be
fixed."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from magail_sumo.sim.dynamics import ACTION_SIZE

_ABSENT = object()
#: keys of the envs' ``action_counts`` (per episode)
ACTION_COUNTS = ("missing", "unknown", "departed", "nonfinite", "clipped")


def action_array(actions: Mapping[str, Any], names: Sequence[str]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, 2) normalised actions of agents ``names`` in [-1, 1], plus (A,) masks of the entries
    that were non-finite or missing (replaced by 0) and of those outside [-1, 1] (clipped).

    Nothing non-finite or out of range ever reaches the vehicle model or SUMO.
    """
    clean, nonfinite, outside, _, _ = checked_actions(actions, names)
    return clean, nonfinite, outside


def checked_actions(actions: Mapping[str, Any], names: Sequence[str]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """:func:`action_array` plus the (A,) mask of agents without an action (``missing``, part
    of ``nonfinite``) and the number of actions given for names not in ``names`` (unknown or
    departed agents: ignored; :func:`count_actions` tells them apart).

    :raises ValueError: an action that is not two numbers (naming the agent).
    """
    given = _every_action(actions, names)
    if given is not None:  # the usual step: one array per agent, all given
        raw, missing, present = given, np.zeros(len(names), bool), len(names)
    else:
        raw, missing, present = _each_action(actions, names)
    unknown = len(actions) - present
    clean, nonfinite, outside = cleaned(raw)
    return clean, nonfinite, outside, missing, unknown


def cleaned(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, 2) actions as the env takes them: non-finite entries 0, the rest clipped to
    [-1, 1]; plus (A,) masks of the rows that had a non-finite entry and of those outside
    [-1, 1]."""
    raw = np.asarray(raw, np.float64)
    nonfinite = ~np.isfinite(raw).all(axis=1)
    clean = np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
    outside = (np.abs(clean) > 1.0).any(axis=1)
    return np.clip(clean, -1.0, 1.0), nonfinite, outside


def _every_action(actions: Mapping[str, Any], names: Sequence[str]) -> np.ndarray | None:
    """(A, 2) float64 actions of ``names`` in one stack when every agent has a numeric array
    of shape (2,); None otherwise (:func:`_each_action` then looks at each one)."""
    try:
        rows = [actions[n] for n in names]
    except KeyError:
        return None
    if not all(isinstance(v, np.ndarray) and v.shape == (ACTION_SIZE,) and v.dtype.kind in "fiu"
               for v in rows):
        return None
    if not rows:
        return np.zeros((0, ACTION_SIZE))
    return np.stack(rows).astype(np.float64)


def _each_action(actions: Mapping[str, Any], names: Sequence[str]
                 ) -> tuple[np.ndarray, np.ndarray, int]:
    """Agent by agent: (A, 2) actions (NaN where missing), (A,) missing mask, how many given."""
    raw = np.full((len(names), ACTION_SIZE), np.nan)
    missing = np.zeros(len(names), bool)
    present = 0
    for i, name in enumerate(names):  # dict → array: the PettingZoo interface is per agent
        v = actions.get(name, _ABSENT)
        if v is not _ABSENT:
            present += 1
        if v is None or v is _ABSENT:
            missing[i] = True
            continue
        try:
            raw[i] = np.asarray(v, np.float64).reshape(ACTION_SIZE)
        except (TypeError, ValueError):
            raise ValueError(f"action of agent {name}: expected 2 numbers [accel, steer], got "
                             f"{np.shape(v) if hasattr(v, '__len__') else type(v).__name__}"
                             ) from None
    return raw, missing, present


def count_actions(counts: dict[str, int], actions: Mapping[str, Any], known: Mapping,
                  nonfinite: np.ndarray, outside: np.ndarray, missing: np.ndarray,
                  extra: int) -> None:
    """Add one step's :func:`checked_actions` findings to an env's ``counts``
    (:data:`ACTION_COUNTS`); ``known``: every agent name of the episode (an action for a name
    outside it is ``unknown``, for a known one that is not live ``departed``). The per-name
    look-up runs only on steps that had such actions."""
    counts["missing"] += int(missing.sum())
    counts["nonfinite"] += int(nonfinite.sum())
    counts["clipped"] += int(outside.sum())
    if extra:
        unknown = sum(1 for a in actions if a not in known)
        counts["unknown"] += unknown
        counts["departed"] += extra - unknown


def action_summary(counts: Mapping[str, int]) -> str:
    """One line describing the fixed-up actions of ``counts`` (:data:`ACTION_COUNTS`), "" when
    every action was given and valid."""
    parts = []
    if counts.get("missing"):
        parts.append(f"policy gave no action for {counts['missing']} agent-step(s) (those agents "
                     "coasted: zero acceleration and steering)")
    if counts.get("unknown"):
        parts.append(f"{counts['unknown']} action(s) for unknown agents ignored")
    nan = counts.get("nonfinite", 0) - counts.get("missing", 0)
    if nan > 0:
        parts.append(f"{nan} non-finite action(s) replaced by 0")
    if counts.get("clipped"):
        parts.append(f"{counts['clipped']} action(s) outside [-1, 1] clipped")
    return "; ".join(parts)
