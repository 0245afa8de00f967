"""Policies: the seed's tanh-squashed diagonal Gaussian actor-critic as an SB3 policy.

:class:`TanhGaussianPolicy` is an SB3 :class:`~stable_baselines3.common.policies.ActorCriticPolicy`
whose action distribution is SB3's :class:`SquashedDiagGaussianDistribution` (a diagonal
Gaussian with a state-independent log-std parameter, squashed by tanh into [-1, 1]²) and whose
shared features extractor is :class:`NormalizedObservation` — a
:class:`~magail_sumo.models.normalizer.RunningNormalizer` (fitted on the expert observations,
stored in the policy's state dict). Actor and critic are separate MLPs (64-64 tanh by default).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from .normalizer import RunningNormalizer


class NormalizedObservation(BaseFeaturesExtractor):
    """Features = observation normalised by running statistics (clipped to ±clip).

    :param observation_space: a flat Box. :param clip: bound on normalised values.
    """

    def __init__(self, observation_space: gym.spaces.Box, clip: float = 10.0) -> None:
        dim = int(observation_space.shape[0])
        super().__init__(observation_space, dim)
        self.normalizer = RunningNormalizer(dim, clip=clip)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        x = observations.float()
        n = self.normalizer
        # the normaliser's float32 mean / std, cached until its statistics change (update and
        # load_state_dict write the buffers in place, bumping their versions)
        key = (n.mean._version, n.m2._version, n.count._version, n.mean.data_ptr(),
               n.mean.device)
        cache = self.__dict__.get("_stats")
        if cache is None or cache[0] != key:
            cache = (key, n.mean.to(x.dtype), n.std.to(x.dtype))
            self.__dict__["_stats"] = cache
        return torch.clamp((x - cache[1]) / cache[2], -n.clip, n.clip)


class TanhGaussianPolicy(ActorCriticPolicy):
    """Actor-critic with a tanh-squashed diagonal Gaussian actor (module doc).

    Takes :class:`ActorCriticPolicy`'s arguments; defaults: ``net_arch=dict(pi=[64, 64],
    vf=[64, 64])``, ``activation_fn=nn.Tanh``, :class:`NormalizedObservation` features.
    """

    def __init__(self, observation_space: gym.spaces.Space, action_space: gym.spaces.Box,
                 lr_schedule: Any, **kwargs: Any) -> None:
        kwargs.setdefault("net_arch", {"pi": [64, 64], "vf": [64, 64]})
        kwargs.setdefault("activation_fn", torch.nn.Tanh)
        kwargs.setdefault("features_extractor_class", NormalizedObservation)
        if kwargs.get("use_sde"):
            raise ValueError("TanhGaussianPolicy does not support gSDE")
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def _build(self, lr_schedule: Any) -> None:
        self.action_dist = SquashedDiagGaussianDistribution(get_action_dim(self.action_space))
        super()._build(lr_schedule)

    @property
    def obs_normalizer(self) -> RunningNormalizer:
        return self.features_extractor.normalizer

    def action_log_prob(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """log pi(actions | obs) (actions in (-1, 1); for behavioural cloning)."""
        return self.get_distribution(obs).log_prob(actions)
