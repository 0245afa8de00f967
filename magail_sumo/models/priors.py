"""Action priors: a rule whose actions a learned policy's Gaussian is centred on (residual
policy learning, Silver et al. 2018; Johannink et al. 2019).

A prior maps observation rows (A, D) to normalised actions (A, 2) in [-1, 1]. With one, the
policy's pre-tanh mean is ``atanh(prior(obs)) + action_net(latent)``
(:class:`~magail_sumo.models.policies.TanhGaussianPolicy`): an untrained actor (its last
layer starts near 0) drives like the rule, and training learns the residual, so what the rule
already does well (following a route through a city, stopping at a red light's stop line)
need not be discovered from the imitation reward. The prior has no parameters and no gradient.

Registered priors (``policy.action_prior``): ``idm``
(:class:`~magail_sumo.models.idm.IdmRule`, route-relative ``accel_offset`` control; the
observation needs ``leader`` and ``light_gap``). A new prior is one class taking
``(observation, limits)`` with an ``action_layout`` and ``__call__(obs) -> actions``, plus
one entry in :data:`ACTION_PRIORS`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from magail_sumo.sensors.observation import ObservationConfig
from magail_sumo.sim.dynamics import BicycleLimits

from .idm import IdmRule

#: prior name -> class (``policy.action_prior``; ``"none"``: no prior)
ACTION_PRIORS: dict[str, type] = {"idm": IdmRule}
#: the prior's actions are clipped to this before ``atanh`` (a saturated rule, e.g. full
#: braking, stays within reach of the residual: atanh(0.99) ≈ 2.65)
PRIOR_CLIP = 0.99


def make_prior(name: str, observation: ObservationConfig, limits: BicycleLimits,
               action_layout: str) -> Callable[[np.ndarray], np.ndarray] | None:
    """The prior ``name`` for a policy with this observation, limits and action layout (None
    for ``"none"``).

    :raises ValueError: an unknown name, a prior of another action layout, or an observation
        the prior cannot read (the prior's message).
    """
    if name == "none":
        return None
    try:
        cls = ACTION_PRIORS[name]
    except KeyError:
        raise ValueError(f"unknown action prior {name!r} (known: none, "
                         f"{', '.join(ACTION_PRIORS)})") from None
    if cls.action_layout != action_layout:
        raise ValueError(f"action prior {name!r} gives {cls.action_layout} actions; the env's "
                         f"action_layout is {action_layout}")
    return cls(observation, limits)


def prior_mean(prior: Callable[[np.ndarray], np.ndarray], obs: np.ndarray) -> np.ndarray:
    """(A, 2) pre-tanh mean of the prior's actions for observation rows ``obs``."""
    return np.arctanh(np.clip(prior(obs), -PRIOR_CLIP, PRIOR_CLIP))
