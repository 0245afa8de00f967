"""What a policy under test is: the :class:`Policy` protocol and :class:`PolicyError`."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from magail_sumo.errors import MagailSumoError


class PolicyError(MagailSumoError):
    """A policy spec cannot be used: unknown name, no loader for the file, a factory or
    loader that fails (one line naming the spec)."""


class Policy(Protocol):
    """What a policy under test provides: normalised actions in [-1, 1]² per agent (in the
    env's ``action_layout``, ``[accel, steer]`` by default) from the env's observations
    (agents named by their WOMD track id).

    Optional extensions, each read with ``getattr`` (policies without them are driven exactly
    as before):

    * ``begin(scene, env)``: told the scene and the env of each rollout right after the env's
      reset, before its first ``act`` (:func:`~magail_sumo.agents.rollout.rollout`); during
      ``act`` it may read the env (``env.t``, ``env.agent_states()`` for the live agents'
      simulated states, ``env.scene`` for the recorded ones of the others) but must not step
      or reset it.
    * ``observation``: an :class:`~magail_sumo.sensors.observation.ObservationConfig` the env
      must observe with (e.g. a SAC policy's route command).
    * ``action_layout``: the order of its actions (:data:`~magail_sumo.sim.dynamics.
      ACTION_LAYOUTS`) when not the default ``"accel_steer"`` (a checkpoint trained with the
      seed's ``"steer_throttle"``); the env is built with it.
    * ``guard``: a :class:`~magail_sumo.env.guard.GuardConfig` the env drives its actions
      through (a checkpoint trained behind the gap guard).
    * ``limits``: the :class:`~magail_sumo.sim.dynamics.BicycleLimits` the env moves it with (a
      checkpoint trained with a steering rate limit).
    * ``reseed(seed)``: put the policy in the state building it with ``seed`` gives (it then
      draws the same random numbers as a fresh one): evaluation reuses one policy for all the
      rollouts of a batch, reseeded per rollout, and builds a policy without it anew.
    * ``reseed_worlds(seeds)`` and ``act_batch(observations, worlds, agents)``: batched
      rollouts (:func:`~magail_sumo.agents.rollout.rollout_worlds` over a
      :class:`~magail_sumo.env.batched.BatchedSceneEnv`): ``act_batch`` takes (n, D)
      observations of every world's live agents, grouped by ``worlds`` (n,) ascending and each
      world's in sorted-name order, and ``agents`` (n,), integer keys that stay each agent's
      for the rollout (its fleet row; for a policy with memory), and returns (n, 2) actions,
      world ``w`` acting as ``act`` of the policy reseeded with ``seeds[w]`` would;
      evaluation runs all rollouts of a scene at once with a policy that has both
      (:func:`batched`).
    """

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...


def batched(policy) -> bool:
    """Whether ``policy`` acts for many worlds at once (``reseed_worlds`` and
    ``act_batch``, :class:`Policy`)."""
    return callable(getattr(policy, "reseed_worlds", None)) and \
        callable(getattr(policy, "act_batch", None))


#: the optional :class:`Policy` attributes that are env settings (``EnvConfig`` fields)
ENV_SETTINGS = ("observation", "action_layout", "guard", "limits")


def env_settings(policy) -> dict:
    """The ``EnvConfig`` fields ``policy`` names (:data:`ENV_SETTINGS` it has): evaluation
    builds the policy's env with them."""
    return {k: getattr(policy, k) for k in ENV_SETTINGS if hasattr(policy, k)}


def check_noise_scale(scale: float, what: str = "noise scale") -> float:
    """``scale`` as a float, refused (:class:`PolicyError`) unless finite and >= 0."""
    try:
        value = float(scale)
    except (TypeError, ValueError):
        value = float("nan")
    if not math.isfinite(value) or value < 0:
        raise PolicyError(f"{what} must be a finite number >= 0, got {scale!r}")
    return value
