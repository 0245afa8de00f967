"""Likelihood estimators: how probable the logged values are under the rollouts' distribution.

Histograms are built per object from all its simulated values (rollouts × steps, no validity
masking, independent time steps); values are clipped to the range and a NaN falls into the last
bin, as in the official tool.
"""

from __future__ import annotations

import numpy as np

from magail_sumo.evaluation.realism.config import Bernoulli, Histogram


def bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin of each value: ``[e_k, e_k+1)`` bins, the maximum and above in the last, below the
    minimum in the first, NaN in the last."""
    nb = len(edges) - 1
    v = np.clip(values, edges[0], edges[-1])
    b = np.searchsorted(edges, v, side="right") - 1  # NaN sorts past the end
    return np.clip(b, 0, nb - 1)


def histogram_log_likelihood(log_values: np.ndarray, sim_values: np.ndarray,
                             est: Histogram) -> np.ndarray:
    """Log-probability of each logged value under its object's rollout histogram.

    :param log_values: (E, T) logged feature values.
    :param sim_values: (R, E, T) simulated values.
    :returns: (E, T) float64 log-likelihoods.
    """
    edges = est.edges
    nb = est.num_bins
    R, E, T = sim_values.shape
    sb = bin_index(sim_values, edges) + np.arange(E)[None, :, None] * nb
    counts = np.bincount(sb.ravel(), minlength=E * nb).reshape(E, nb) + est.pseudocount
    logp = np.log(counts / counts.sum(1, keepdims=True))
    return np.take_along_axis(logp, bin_index(log_values, edges), 1)


def bernoulli_log_likelihood(log_flags: np.ndarray, sim_flags: np.ndarray,
                             est: Bernoulli) -> np.ndarray:
    """Log-probability of each object's logged flag under its rollouts' frequency.

    :param log_flags: (E,) bool; ``sim_flags``: (R, E) bool.
    :returns: (E,) float64.
    """
    R = sim_flags.shape[0]
    k = sim_flags.sum(0).astype(np.float64)
    pc = est.pseudocount
    p_true = (k + pc) / (R + 2 * pc)
    p_false = (R - k + pc) / (R + 2 * pc)
    return np.log(np.where(log_flags, p_true, p_false))


def masked_mean_likelihood(log_lik: np.ndarray, mask: np.ndarray) -> float:
    """``exp`` of the mean log-likelihood over the masked (object, step) pairs; NaN if none."""
    n = mask.sum()
    return float(np.exp(np.where(mask, log_lik, 0.0).sum() / n)) if n else float("nan")
