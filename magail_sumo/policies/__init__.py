"""Policies by spec: what ``--policy`` names, resolved to an env-driving
:class:`~magail_sumo.agents.base.Policy` (``random``, ``pretrained[:NAME]``, a training
checkpoint, ``package.module:factory``, ``guarded:SPEC``).

This layer sits above :mod:`magail_sumo.training` (a checkpoint's policy is rebuilt by the code
that trained it) and below :mod:`magail_sumo.evaluation` and the CLI:

* :mod:`.registry`: :func:`make_policy`, :func:`method_name` and the checkpoint-loader registries
  (:data:`POLICY_LOADERS` by file suffix, :data:`CHECKPOINT_LOADERS` by training algorithm);
* :mod:`.checkpoint`: PPO / GAIL / behavioural-cloning checkpoints
  (:class:`~.checkpoint.CheckpointPolicy`);
* :mod:`.sac`: SAC checkpoints (:class:`~.sac.SacCheckpointPolicy`);
* :mod:`.gameformer`: GameFormer checkpoints as closed-loop agents
  (:class:`~.gameformer.GameFormerPolicy`).

Add a trained algorithm's policy: a module here with its loader, and one entry in
:data:`CHECKPOINT_LOADERS` (or :func:`register_checkpoint_loader` from outside the package).
"""

from magail_sumo.agents.specs import BASELINES, BUILTIN_POLICIES, GUARDED, unguarded

from .checkpoint import CheckpointPolicy, load_actor_policy, policy_observation
from .gameformer import GameFormerPolicy, load_gameformer_policy
from .registry import (CHECKPOINT_LOADERS, POLICY_LOADERS, card_noise_scale,
                       load_checkpoint_policy, load_training_checkpoint, make_policy, method_name,
                       register_checkpoint_loader)
from .sac import SacCheckpointPolicy, load_sac_checkpoint_policy

__all__ = ["BASELINES", "BUILTIN_POLICIES", "CHECKPOINT_LOADERS", "CheckpointPolicy", "GUARDED",
           "GameFormerPolicy", "POLICY_LOADERS", "SacCheckpointPolicy", "card_noise_scale",
           "load_actor_policy", "load_checkpoint_policy", "load_gameformer_policy",
           "load_sac_checkpoint_policy", "load_training_checkpoint", "make_policy",
           "method_name", "policy_observation", "register_checkpoint_loader", "unguarded"]
