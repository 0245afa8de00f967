"""The tanh-Gaussian actor-critic policy of PPO / GAIL / behavioural-cloning runs, built from a
run config (spaces from the observation config, sizes from the ``policy`` block), and loaded
from a checkpoint."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from magail_sumo.models.policies import TanhGaussianPolicy
from magail_sumo.models.priors import make_prior
from magail_sumo.sensors.observation import observation_bounds
from magail_sumo.sim.dynamics import ACTION_SIZE

from .checkpoints import CheckpointError, checkpoint_config, load_checkpoint, load_into
from .config import TrainConfig


def spaces_of(cfg: TrainConfig) -> tuple[spaces.Box, spaces.Box]:
    low, high = observation_bounds(cfg.env.observation)
    return (spaces.Box(low, high, dtype=np.float32),
            spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32))


def policy_kwargs(cfg: TrainConfig) -> dict[str, Any]:
    """:class:`TanhGaussianPolicy` arguments of the config's ``policy`` block."""
    p = cfg.policy
    kwargs: dict[str, Any] = {"net_arch": {"pi": list(p.actor_hidden), "vf": list(p.critic_hidden)},
                              "log_std_init": p.log_std_init}
    if p.critic == "transformer":
        kwargs.update(net_arch={"pi": list(p.actor_hidden), "vf": []}, critic="transformer",
                      critic_transformer=p.critic_transformer)
    prior = make_prior(p.action_prior, cfg.env.observation, cfg.env.limits,
                       cfg.env.action_layout, p.prior_params)
    if prior is not None:
        kwargs["action_prior"] = prior
    return kwargs


class NoOptimizer:
    """The optimizer of a policy loaded to act, never trained: SB3 builds one in every policy,
    and building torch's first optimizer in a process imports ``torch._dynamo`` (about 3 s on
    this CPU, more than the rest of an evaluation batch of a small scene)."""

    def __init__(self, params, **kwargs) -> None:
        pass


def make_policy(cfg: TrainConfig, acting: bool = False) -> TanhGaussianPolicy:
    """A fresh policy for the config's spaces (no env needed; a transformer critic has no scene
    layout then, see :meth:`TanhGaussianPolicy.set_scene_layout` — evaluation uses the actor
    only). ``acting``: a policy that only acts (no optimizer, :class:`NoOptimizer`)."""
    obs, act = spaces_of(cfg)
    extra: dict[str, Any] = {"optimizer_class": NoOptimizer} if acting else {}
    return TanhGaussianPolicy(obs, act, lambda _: cfg.ppo.learning_rate,
                              **policy_kwargs(cfg), **extra).to(cfg.device)


def load_policy(path: str | Path, device: str = "cpu") -> tuple[TanhGaussianPolicy, TrainConfig]:
    """The policy of a checkpoint (and the run's config), to act (no optimizer)."""
    state = load_checkpoint(path)
    cfg = replace(checkpoint_config(state, path), device=device)
    if cfg.algorithm in ("sac", "sac_gail"):
        raise CheckpointError(f"{path}: a {cfg.algorithm} checkpoint (command-branched SAC), not "
                              "a PPO / behavioural-cloning policy (evaluate loads both: "
                              "magail_sumo.policies.load_checkpoint_policy)")
    policy = make_policy(cfg, acting=True)
    load_into(policy, state["policy"], "policy", Path(path))
    policy.set_training_mode(False)
    return policy, cfg
