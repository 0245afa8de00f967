"""The sampling noise of a Gaussian policy at evaluation: its scale per action and its memory.

A checkpoint policy acts with ``a = tanh(mu(o) + k · w ⊙ sigma(o) ⊙ e_t)``
(:mod:`magail_sumo.policies.checkpoint`; numpy here, so that reading a pretrained card
needs no torch), ``k`` the noise scale, ``w`` the per-action weights
(:attr:`NoiseShape.weights`, ``[accel, steer]`` in the default action layout) and ``e_t`` a
standard normal vector per agent and step. With ``rho = 0`` (the default) ``e_t`` is drawn
afresh every step, as PPO trained it. With a correlation ``0 <= rho < 1`` per action,
``e_t`` is a first-order autoregressive process per agent,

    e_0 = xi_0,    e_t = rho ⊙ e_{t-1} + sqrt(1 - rho²) ⊙ xi_t,    xi_t ~ N(0, I),

whose every marginal is still N(0, I) (same spread per step) but whose steps are correlated
with ``corr(e_t, e_{t+j}) = rho^j`` (at 10 Hz, ``rho = 0.7`` forgets in about 0.3 s). White
noise on the steering is white noise on the yaw rate, which gives the WOSAC angular
acceleration a spread no human has; correlated noise keeps the rollouts apart with smoother
kinematics. The draws ``xi_t`` are the policy's own (its generator, in its draw order), so a
rollout stays reproducible and a batched world acts exactly as a single one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from magail_sumo.agents.base import PolicyError
from magail_sumo.sim.dynamics import ACTION_SIZE


@dataclass(frozen=True)
class NoiseShape:
    """Per-action weights ``w`` (>= 0) and step-to-step correlations ``rho`` (in [0, 1)) of
    the sampling noise (module doc); the defaults are white noise of the policy's own scale."""

    weights: tuple[float, ...] = (1.0,) * ACTION_SIZE
    correlation: tuple[float, ...] = (0.0,) * ACTION_SIZE

    def __post_init__(self) -> None:
        for field, lo, hi in (("weights", 0.0, math.inf), ("correlation", 0.0, 1.0)):
            values = getattr(self, field)
            try:
                vals = tuple(float(v) for v in values)
            except (TypeError, ValueError):
                vals = ()
            if len(vals) != ACTION_SIZE or not all(math.isfinite(v) and lo <= v < hi
                                                   for v in vals):
                bound = ">= 0" if hi == math.inf else "in [0, 1)"
                raise PolicyError(f"noise {field} must be {ACTION_SIZE} numbers {bound} (one per "
                                  f"action), got {values!r}")
            object.__setattr__(self, field, vals)

    @property
    def white(self) -> bool:
        """Whether the noise is drawn afresh every step (every correlation 0)."""
        return not any(self.correlation)

    @property
    def plain(self) -> bool:
        """Whether the noise is the policy's own: white, every weight 1."""
        return self.white and all(w == 1.0 for w in self.weights)

    @classmethod
    def from_card(cls, sampling: dict, what: str) -> NoiseShape:
        """The shape a pretrained card's ``sampling`` gives (``noise_weights``,
        ``noise_correlation``; each optional), refused with a line naming ``what``."""
        kwargs = {k: sampling[f"noise_{k}"] for k in ("weights", "correlation")
                  if f"noise_{k}" in sampling}
        try:
            return cls(**kwargs)
        except PolicyError as exc:
            raise PolicyError(f"{what}: {exc}") from None


class NoiseProcess:
    """The per-agent noise ``w ⊙ e_t`` of one rollout (or of every world of a batched one):
    agents are keyed by integers that stay theirs for the rollout (:meth:`key` numbers names
    in first-seen order; batched rollouts give fleet rows); :meth:`reset` starts a rollout."""

    def __init__(self, shape: NoiseShape) -> None:
        self.shape = shape
        self._rho = np.asarray(shape.correlation, np.float64)
        self._keep = np.sqrt(1.0 - self._rho * self._rho)
        self._w = np.asarray(shape.weights, np.float64)
        self.reset()

    def reset(self) -> None:
        self._prev = np.zeros((0, ACTION_SIZE), np.float64)
        self._seen = np.zeros(0, bool)
        self._names: dict[str, int] = {}

    def key(self, names) -> np.ndarray:
        """Integer keys of agent ``names`` (a new name gets the next one)."""
        for n in names:
            self._names.setdefault(n, len(self._names))
        return np.fromiter((self._names[n] for n in names), np.int64, len(names))

    def __call__(self, xi: np.ndarray, keys: np.ndarray | None) -> np.ndarray:
        """``w ⊙ e_t`` (float64) of the agents ``keys`` (n,) from their fresh draws ``xi``
        (n, A); ``keys`` may be None only for white noise (nothing to remember)."""
        xi = np.asarray(xi, np.float64)
        if self.shape.white:
            return xi * self._w
        if keys is None:
            raise ValueError("correlated sampling noise needs the agents' keys")
        idx = np.asarray(keys, np.int64)
        need = int(idx.max()) + 1 if idx.size else 0
        if need > self._seen.size:  # grow the per-agent memory
            grow = need - self._seen.size
            self._prev = np.concatenate([self._prev, np.zeros((grow, ACTION_SIZE))])
            self._seen = np.concatenate([self._seen, np.zeros(grow, bool)])
        e = np.where(self._seen[idx, None], self._rho * self._prev[idx] + self._keep * xi, xi)
        self._prev[idx] = e
        self._seen[idx] = True
        return e * self._w
