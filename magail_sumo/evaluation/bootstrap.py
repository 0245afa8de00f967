"""Bootstrap 95 % confidence intervals over scenes and training seeds, and paired comparisons.

The data of one method is a matrix ``M`` (R, N): one row per training seed (a single row for a
baseline or one trained policy), one column per scored scene, each cell the scene's figure
averaged over evaluation seeds and rollouts; NaN where a row did not score a scene. Its figure is
``mean(M)`` = the mean over rows of each row's mean over its scored scenes.

Interval (:func:`bootstrap_ci`): ``reps`` replicates, each drawing N columns (scenes) with
replacement and R rows (training seeds) with replacement, both uniformly — a two-stage
(hierarchical) bootstrap: the scenes are a sample of the scenes one could score on, the training
seeds a sample of the runs the recipe could give. The interval is the 2.5 and 97.5 percentiles of
the replicates' figures. With one row only the scenes are resampled; with one column only the rows.

Comparison (:func:`paired_difference`): ``A − B`` of two methods scored on the same scenes. Each
replicate draws one set of columns for both (the scenes are paired: a hard scene is hard for
both) and rows for each method apart (seed k of A has nothing to do with seed k of B). ``A``
beats ``B`` only where the interval of the difference lies above 0 (:func:`verdict`).

Everything is vectorised over the replicates; the random draws come from ``numpy``'s generator
seeded with ``seed``, so a figure is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: replicates of every interval
REPS = 10_000
#: percentiles of the 95 % interval
LEVEL = (2.5, 97.5)


@dataclass(frozen=True)
class Interval:
    """A figure and its 95 % bootstrap interval (``lo``, ``hi``; NaN when it cannot be drawn:
    no finite value)."""

    mean: float
    lo: float
    hi: float

    def as_dict(self) -> dict[str, float]:
        return {"mean": self.mean, "lo": self.lo, "hi": self.hi}


def _as_matrix(values) -> np.ndarray:
    """``values`` as a float (R, N) matrix (a 1-D array is one row)."""
    m = np.asarray(values, dtype=np.float64)
    if m.ndim == 1:
        m = m[None, :]
    if m.ndim != 2:
        raise ValueError(f"expected (training seeds, scenes) values, got shape {m.shape}")
    return m


def _matrix(values) -> np.ndarray:
    """:func:`_as_matrix` without the scenes no row scored (they tell nothing) and the rows
    that scored none."""
    m = _as_matrix(values)
    m = m[:, np.isfinite(m).any(0)]
    return m[np.isfinite(m).any(1)]


def _finite_mean(x: np.ndarray) -> np.ndarray:
    """The mean of the finite entries along the last axis; NaN where there are none."""
    ok = np.isfinite(x)
    n = ok.sum(-1)
    return np.where(n > 0, np.where(ok, x, 0.0).sum(-1) / np.maximum(n, 1), np.nan)


def figure(values) -> float:
    """The mean over rows of each row's mean over its finite scenes (NaN: none)."""
    m = _matrix(values)
    return float(_finite_mean(_finite_mean(m))) if m.size else float("nan")


def _replicates(m: np.ndarray, cols: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The figure of ``m`` under each replicate's columns ``cols`` (reps, N) and freshly drawn
    rows."""
    reps = cols.shape[0]
    rows = rng.integers(0, m.shape[0], size=(reps, m.shape[0])) if m.shape[0] > 1 \
        else np.zeros((reps, 1), dtype=np.int64)
    picked = m[rows[:, :, None], cols[:, None, :]]  # (reps, R, N)
    return _finite_mean(_finite_mean(picked))


def _columns(n: int, reps: int, rng: np.random.Generator) -> np.ndarray:
    return rng.integers(0, n, size=(reps, n)) if n > 1 else np.zeros((reps, 1), dtype=np.int64)


def _interval(mean: float, rep: np.ndarray) -> Interval:
    """``mean`` with the percentile interval of the finite replicates ``rep``."""
    rep = rep[np.isfinite(rep)]
    lo, hi = np.percentile(rep, LEVEL) if rep.size else (np.nan, np.nan)
    return Interval(mean, float(lo), float(hi))


_NONE = Interval(float("nan"), float("nan"), float("nan"))


def bootstrap_ci(values, reps: int = REPS, seed: int = 0) -> Interval:
    """:class:`Interval` of the figure of ``values`` (R, N) or (N,) (module doc)."""
    m = _matrix(values)
    if m.size == 0:
        return _NONE
    rng = np.random.default_rng(seed)
    return _interval(figure(m), _replicates(m, _columns(m.shape[1], reps, rng), rng))


def paired_difference(a, b, reps: int = REPS, seed: int = 0) -> Interval:
    """:class:`Interval` of ``figure(a) − figure(b)`` for two methods' (R_a, N) and (R_b, N)
    values over the same N scenes (column k is the same scene in both; module doc). Only the
    scenes both scored are used."""
    ma, mb = _as_matrix(a), _as_matrix(b)
    if ma.shape[1] != mb.shape[1]:
        raise ValueError(f"the two methods' values cover {ma.shape[1]} and {mb.shape[1]} scenes")
    both = np.isfinite(ma).any(0) & np.isfinite(mb).any(0)
    ma, mb = _matrix(ma[:, both]), _matrix(mb[:, both])  # every kept column stays: aligned
    if ma.size == 0 or mb.size == 0:
        return _NONE
    rng = np.random.default_rng(seed)
    cols = _columns(ma.shape[1], reps, rng)
    rep = _replicates(ma, cols, rng) - _replicates(mb, cols, rng)
    return _interval(figure(ma) - figure(mb), rep)


def verdict(diff: Interval, a: str, b: str, higher_is_better: bool = True) -> str:
    """``"A better than B"`` / ``"B better than A"`` where the interval of ``A − B`` excludes 0,
    else ``"no difference shown"``."""
    if not (np.isfinite(diff.lo) and np.isfinite(diff.hi)):
        return "no difference shown"
    if diff.lo > 0:
        return f"{a} better than {b}" if higher_is_better else f"{b} better than {a}"
    if diff.hi < 0:
        return f"{b} better than {a}" if higher_is_better else f"{a} better than {b}"
    return "no difference shown"
