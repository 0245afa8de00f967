"""Bootstrap intervals over scenes and training seeds, and paired comparisons
(magail_sumo.evaluation.bootstrap)."""

from __future__ import annotations

import numpy as np
import pytest

from magail_sumo.evaluation.bootstrap import (Interval, bootstrap_ci, figure, paired_difference,
                                              verdict)


def test_constant_values_give_a_point_interval_and_the_figure_is_the_mean_of_row_means():
    iv = bootstrap_ci([0.7] * 12)
    assert iv.mean == iv.lo == iv.hi == pytest.approx(0.7)
    # rows (training seeds) weigh equally, whatever scenes each scored
    m = [[1.0, 1.0, np.nan], [0.0, 0.0, 0.0]]
    assert figure(m) == pytest.approx(0.5)


def test_interval_covers_the_true_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(3)
    hits = 0
    for k in range(300):
        iv = bootstrap_ci(rng.normal(0.6, 0.1, 30), reps=2000, seed=k)
        hits += iv.lo <= 0.6 <= iv.hi
    assert 0.89 <= hits / 300 <= 0.99


def test_training_seeds_widen_the_interval():
    rng = np.random.default_rng(0)
    scenes = rng.normal(0.7, 0.05, 20)
    same = np.stack([scenes, scenes, scenes])
    spread = same + np.array([[-0.05], [0.0], [0.05]])  # seeds disagree
    a, b = bootstrap_ci(same), bootstrap_ci(spread)
    assert a.mean == pytest.approx(b.mean)
    assert (b.hi - b.lo) > 1.3 * (a.hi - a.lo)


def test_paired_difference_removes_the_scene_variance():
    rng = np.random.default_rng(1)
    base = rng.uniform(0.3, 0.9, 25)  # hard and easy scenes
    a, b = base + 0.02 + rng.normal(0, 0.002, 25), base
    d = paired_difference(a, b)
    assert d.mean == pytest.approx(0.02, abs=0.002) and d.lo > 0.015 and d.hi < 0.025
    assert verdict(d, "A", "B") == "A better than B"
    assert verdict(paired_difference(b, a), "B", "A") == "A better than B"
    # unpaired intervals of the two overlap widely: only the pairing shows it
    ia, ib = bootstrap_ci(a), bootstrap_ci(b)
    assert ia.lo < ib.hi
    same = paired_difference(base + rng.normal(0, 0.01, 25), base)
    assert verdict(same, "A", "B") == "no difference shown"


def test_missing_scenes_and_reproducibility():
    m = np.array([[0.5, np.nan, 0.7, np.nan], [0.6, 0.4, np.nan, np.nan]])
    iv1, iv2 = bootstrap_ci(m, seed=4), bootstrap_ci(m, seed=4)
    assert iv1 == iv2 and iv1.lo <= iv1.mean <= iv1.hi
    assert np.isnan(bootstrap_ci([np.nan, np.nan]).mean)
    d = paired_difference([0.5, np.nan, 0.9], [0.4, 0.3, np.nan])  # only scene 0 in both
    assert d.mean == pytest.approx(0.1) and d.lo == pytest.approx(0.1)
    with pytest.raises(ValueError, match="cover 2 and 3 scenes"):
        paired_difference([0.1, 0.2], [0.1, 0.2, 0.3])
    assert verdict(Interval(0.0, float("nan"), float("nan")), "A", "B") == "no difference shown"
    assert verdict(paired_difference([0.1] * 5, [0.3] * 5), "A", "B",
                   higher_is_better=True) == "B better than A"
