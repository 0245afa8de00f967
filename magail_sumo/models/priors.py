"""Action priors: a rule whose actions a learned policy's Gaussian is centred on (residual
policy learning, Silver et al. 2018; Johannink et al. 2019).

A prior maps observation rows (A, D) to normalised actions (A, 2) in [-1, 1]. With one, the
policy's pre-tanh mean is ``atanh(prior(obs)) + action_net(latent)``
(:class:`~magail_sumo.models.policies.TanhGaussianPolicy`): an untrained actor (its last
layer starts near 0) drives like the rule, and training learns the residual, so what the rule
already does well (following a route through a city, stopping at a red light's stop line)
need not be discovered from the imitation reward. The prior has no learned parameters and no
gradient; its rule's settings may be changed from their defaults (``policy.prior_params``: a
mapping of the rule's parameter fields, :class:`~magail_sumo.models.idm.IdmParams` for
``idm``, to numbers), and a checkpoint's config carries them, so evaluation rebuilds the same
prior.

Registered priors (``policy.action_prior``): ``idm``
(:class:`~magail_sumo.models.idm.IdmRule`, route-relative ``accel_offset`` control; the
observation needs ``leader`` and ``light_gap``). A new prior is one class taking
``(observation, limits, params)`` with an ``action_layout``, a ``params_type`` (the frozen
dataclass of its settings) and ``__call__(obs) -> actions``, plus one entry in
:data:`ACTION_PRIORS`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Mapping

import numpy as np

from magail_sumo.sensors.observation import ObservationConfig
from magail_sumo.sim.dynamics import BicycleLimits

from .idm import IdmRule

#: prior name -> class (``policy.action_prior``; ``"none"``: no prior)
ACTION_PRIORS: dict[str, type] = {"idm": IdmRule}
#: the prior's actions are clipped to this before ``atanh`` (a saturated rule, e.g. full
#: braking, stays within reach of the residual: atanh(0.99) ≈ 2.65)
PRIOR_CLIP = 0.99


def prior_class(name: str) -> type:
    """The class of the registered prior ``name``; ValueError naming the known ones."""
    try:
        return ACTION_PRIORS[name]
    except KeyError:
        raise ValueError(f"unknown action prior {name!r} (known: none, "
                         f"{', '.join(ACTION_PRIORS)})") from None


def prior_params(name: str, overrides: Mapping[str, float] | None = None) -> object:
    """The settings of prior ``name``: its ``params_type`` defaults with ``overrides`` (field
    -> number) replaced.

    :raises ValueError: an unknown prior, an override naming no field of the settings (the
        message names it and the known ones), or a value that is not a finite number >= 0.
    """
    params_type = prior_class(name).params_type
    known = [f.name for f in dataclasses.fields(params_type)]
    for key, value in (overrides or {}).items():
        if key not in known:
            raise ValueError(f"unknown {name} prior parameter {key!r} (known: {', '.join(known)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} prior parameter {key!r} must be a finite number >= 0, "
                             f"got {value!r}")
    return dataclasses.replace(params_type(), **{k: float(v) for k, v in
                                                (overrides or {}).items()})


def make_prior(name: str, observation: ObservationConfig, limits: BicycleLimits,
               action_layout: str, params: Mapping[str, float] | None = None
               ) -> Callable[[np.ndarray], np.ndarray] | None:
    """The prior ``name`` for a policy with this observation, limits and action layout (None
    for ``"none"``), its settings the defaults with ``params`` (field -> number,
    ``policy.prior_params``) replaced.

    :raises ValueError: an unknown name, a prior of another action layout, an unknown or
        invalid parameter (:func:`prior_params`), parameters for ``"none"``, or an observation
        the prior cannot read (the prior's message).
    """
    if name == "none":
        if params:
            raise ValueError(f"prior parameters {', '.join(map(repr, params))} given with no "
                             "action prior")
        return None
    cls = prior_class(name)
    if cls.action_layout != action_layout:
        raise ValueError(f"action prior {name!r} gives {cls.action_layout} actions; the env's "
                         f"action_layout is {action_layout}")
    return cls(observation, limits, prior_params(name, params))


def prior_mean(prior: Callable[[np.ndarray], np.ndarray], obs: np.ndarray) -> np.ndarray:
    """(A, 2) pre-tanh mean of the prior's actions for observation rows ``obs``."""
    return np.arctanh(np.clip(prior(obs), -PRIOR_CLIP, PRIOR_CLIP))
