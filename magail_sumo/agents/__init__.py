"""Agents: what drives the road users of a scene (Waymax's ``agents/``).

* :class:`~.base.Policy`, the protocol of an env-driving policy (optional ``begin(scene, env)``,
  ``observation`` and ``action_layout``), and :class:`~.base.PolicyError`;
* :class:`~.random_policy.RandomPolicy`; constant velocity (:mod:`.constant_velocity`: the
  ``constvel`` trajectory model and :class:`~.constant_velocity.ConstantVelocityPolicy`); log
  replay through the env (:class:`~.log_replay.LogReplayPolicy`); SUMO's car-following baseline
  (:mod:`.sumo_baseline`);
* the policy registry (:mod:`.registry`): :func:`make_policy` from a spec, :func:`method_name`,
  checkpoint loaders by file suffix and by training algorithm (lazy ``module:function`` entry
  points: this package imports no training code);
* the one rollout loop, :func:`~.rollout.rollout`.

Add an agent: a module here with a class that has ``act(observations)``; a trained one also
registers its checkpoint loader (:func:`register_checkpoint_loader`).
"""

from .base import Policy, PolicyError, env_settings
from .constant_velocity import ConstantVelocityPolicy
from .log_replay import LogReplayPolicy
from .random_policy import RandomPolicy
from .registry import (BASELINES, BUILTIN_POLICIES, CHECKPOINT_LOADERS, POLICY_LOADERS,
                       load_training_checkpoint, make_policy, method_name,
                       register_checkpoint_loader)
from .rollout import Step, rollout

__all__ = ["env_settings", "BASELINES", "BUILTIN_POLICIES", "CHECKPOINT_LOADERS", "ConstantVelocityPolicy",
           "LogReplayPolicy", "POLICY_LOADERS", "Policy", "PolicyError", "RandomPolicy", "Step",
           "load_training_checkpoint",
           "make_policy", "method_name", "register_checkpoint_loader", "rollout"]
