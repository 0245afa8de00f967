"""Agents: what drives the road users of a scene (Waymax's ``agents/``).

* :class:`~.base.Policy`, the protocol of an env-driving policy (optional ``begin(scene, env)``,
  ``observation`` and ``action_layout``), and :class:`~.base.PolicyError`;
* :class:`~.random_policy.RandomPolicy`; constant velocity (:mod:`.constant_velocity`: the
  ``constvel`` trajectory model and :class:`~.constant_velocity.ConstantVelocityPolicy`); log
  replay through the env (:class:`~.log_replay.LogReplayPolicy`); SUMO's car-following baseline
  (:mod:`.sumo_baseline`);
* the one rollout loop, :func:`~.rollout.rollout` (and :func:`~.rollout.rollout_worlds`, the
  same over a batched env's worlds).

This package sits below :mod:`magail_sumo.training` (expert recording drives the log replay);
policies named by a spec (``--policy``: checkpoints, ``pretrained``) are resolved above
training, in :mod:`magail_sumo.policies`.

Add an agent: a module here with a class that has ``act(observations)``; a trained one adds its
checkpoint loader in :mod:`magail_sumo.policies`.
"""

from .base import Policy, PolicyError, batched, check_noise_scale, env_settings
from .constant_velocity import ConstantVelocityPolicy
from .log_replay import LogReplayPolicy
from .random_policy import RandomPolicy
from .rollout import Step, rollout, rollout_worlds

__all__ = ["ConstantVelocityPolicy", "LogReplayPolicy", "Policy", "PolicyError", "RandomPolicy",
           "Step", "batched", "check_noise_scale", "env_settings", "rollout", "rollout_worlds"]
