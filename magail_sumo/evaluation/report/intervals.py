"""95 % confidence intervals of means over scenes (or seeds), for the report's tables and error
bars.

For ``n`` finite values with sample mean ``m`` and sample standard deviation ``s`` (``ddof=1``),
the interval is ``m ± t(0.975, n - 1) · s / sqrt(n)`` (Student's t: the scenes are a sample of
the scenes one could evaluate on). :func:`t975` gives the quantile: exact to three decimals
from a table for 1–30 degrees of freedom, the Cornish–Fisher expansion around the normal
quantile beyond (error below 1e-4 there). Fewer than two finite values give no interval (NaN).
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np

#: t(0.975, df) for df = 1..30
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
         2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
         2.060, 2.056, 2.052, 2.048, 2.045, 2.042)
_Z975 = 1.959964


def t975(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` >= 1 degrees of freedom."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    if df <= len(_T975):
        return _T975[df - 1]
    z = _Z975
    return z + (z ** 3 + z) / (4 * df) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)


def mean_ci(values: Iterable[float]) -> tuple[float, float]:
    """(mean, half-width of its 95 % interval) of the finite ``values``; NaN half-width for
    fewer than two, (NaN, NaN) for none."""
    v = np.asarray([x for x in values if x is not None], np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan")
    if v.size == 1:
        return float(v[0]), float("nan")
    return float(v.mean()), t975(v.size - 1) * float(v.std(ddof=1)) / math.sqrt(v.size)


def with_ci(mean: float, half: float, digits: int = 4) -> str:
    """A table cell ``"0.6123 ± 0.0310"`` (the mean alone when there is no interval)."""
    if not math.isfinite(mean):
        return "n/a"
    text = f"{mean:.{digits}g}"
    return text if not math.isfinite(half) else f"{text} ± {half:.2g}"
