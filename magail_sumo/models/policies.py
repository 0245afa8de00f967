"""Policies: the seed's tanh-squashed diagonal Gaussian actor-critic as an SB3 policy.

:class:`TanhGaussianPolicy` is an SB3 :class:`~stable_baselines3.common.policies.ActorCriticPolicy`
whose action distribution is SB3's :class:`SquashedDiagGaussianDistribution` (a diagonal
Gaussian with a state-independent log-std parameter, squashed by tanh into [-1, 1]²) and whose
shared features extractor is :class:`NormalizedObservation` — a
:class:`~magail_sumo.models.normalizer.RunningNormalizer` (fitted on the expert observations,
stored in the policy's state dict). The actor is an MLP (64-64 tanh by default) applied to each
vehicle alone, shared by all vehicles; with an action prior (:mod:`magail_sumo.models.priors`)
its mean is a residual added to the prior's pre-tanh action. Two critics:

* ``critic="mlp"`` (default): SB3's per-vehicle value MLP (64-64 tanh by default). In a
  rollout forward over a whole vector-env observation (the slot layout and mask
  :meth:`TanhGaussianPolicy.set_scene_layout` was given), only the occupied slots are evaluated;
  a free slot gets action, value and log-probability 0, never used.
* ``critic="transformer"``: a :class:`~magail_sumo.models.critic.TransformerCritic` — the value
  of a vehicle is computed from the normalised observations (each in its own ego frame, as the
  actor sees them) of *all* vehicles of the same scene at the same step. The policy must then
  know which rows of a batch belong together (:meth:`TanhGaussianPolicy.critic_groups`):

  - training minibatches carry their grouping on the observation tensor
    (:func:`with_scene_groups`; :class:`~magail_sumo.training.gail.ppo.MaskedRolloutBuffer` does it);
    :meth:`~TanhGaussianPolicy.evaluate_actions` refuses a batch without one;
  - a batch of one vector-env observation (as many rows as the env has slots, at rollout time)
    is grouped by :meth:`~TanhGaussianPolicy.set_scene_layout`'s slot→scene layout and the
    env's current slot mask (:class:`~magail_sumo.training.gail.ppo.MaskedPPO` wires both from the
    :class:`~magail_sumo.env.vec_env.MultiSceneVecEnv`): the active slots of a scene form one
    group; a free slot is not evaluated and gets value 0 (never used: the masked buffer drops
    free slot-steps and GAE never bootstraps across a slot re-assignment);
  - any other batch — e.g. the single terminal observation that SB3's ``collect_rollouts``
    bootstraps a truncated agent from — has every row evaluated as a one-vehicle scene (so does
    every batch of an env with a single slot, where the two cases cannot be told apart).
"""

from __future__ import annotations

from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.policies import ActorCriticPolicy, BaseModel
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from .critic import CriticTransformerConfig, TransformerCritic, scene_groups
from .normalizer import RunningNormalizer
from .priors import prior_mean

#: attribute of an observation tensor holding its rows' (N,) int64 scene-step group ids
SCENE_GROUPS_ATTR = "scene_groups"
CRITICS = ("mlp", "transformer")


def with_scene_groups(obs: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
    """Attach (N,) int64 group ids (rows of one scene step share an id, ``0 .. G-1``; -1: not a
    vehicle, value 0) to ``obs`` (N, obs_dim), read by the transformer critic; returns ``obs``
    itself (the attribute lives on this tensor object only, not on tensors derived from it)."""
    if group.shape != obs.shape[:1]:
        raise ValueError(f"{group.shape[0]} group ids for {obs.shape[0]} observations")
    setattr(obs, SCENE_GROUPS_ATTR, group)
    return obs


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

    :param critic: ``"mlp"`` (per-vehicle value MLP ``net_arch["vf"]``) or ``"transformer"``
        (:class:`~magail_sumo.models.critic.TransformerCritic` over the vehicles of a scene
        step; ``net_arch["vf"]`` is then ignored). The state dict holds the critic's weights as
        ``value_net.*`` (MLP head) or ``critic.*`` (transformer).
    :param critic_transformer: sizes of the transformer critic (default
        :class:`~magail_sumo.models.critic.CriticTransformerConfig`).
    :param action_prior: a rule from raw observation rows to normalised actions
        (:mod:`magail_sumo.models.priors`) whose ``atanh`` is added to the actor's mean: the
        actor learns a residual to it. None: no prior.
    """

    def __init__(self, observation_space: gym.spaces.Space, action_space: gym.spaces.Box,
                 lr_schedule: Any, critic: str = "mlp",
                 critic_transformer: CriticTransformerConfig | None = None,
                 action_prior: Callable[[np.ndarray], np.ndarray] | None = None,
                 **kwargs: Any) -> None:
        if critic not in CRITICS:
            raise ValueError(f"critic must be one of {list(CRITICS)}, got {critic!r}")
        kwargs.setdefault("net_arch", {"pi": [64, 64], "vf": [64, 64]})
        kwargs.setdefault("activation_fn", torch.nn.Tanh)
        kwargs.setdefault("features_extractor_class", NormalizedObservation)
        if kwargs.get("use_sde"):
            raise ValueError("TanhGaussianPolicy does not support gSDE")
        if critic == "transformer":
            arch = kwargs["net_arch"]
            pi = list(arch.get("pi", [])) if isinstance(arch, dict) else list(arch)
            kwargs["net_arch"] = {"pi": pi, "vf": []}  # no value MLP: the critic is separate
        # read by _build, which ActorCriticPolicy.__init__ calls
        self.__dict__["critic_kind"] = critic
        self.__dict__["critic_config"] = critic_transformer or CriticTransformerConfig()
        self.__dict__["action_prior"] = action_prior
        #: the prior's pre-tanh mean for the observations being evaluated (:meth:`_set_prior`)
        self.__dict__["_prior_mean"] = None
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        #: slot -> scene index of the vector env's observation, and the env's slot mask source
        self._slot_scene: np.ndarray | None = None
        self._mask_source: Callable[[], np.ndarray] | None = None

    def _build(self, lr_schedule: Any) -> None:
        self.action_dist = SquashedDiagGaussianDistribution(get_action_dim(self.action_space))
        super()._build(lr_schedule)
        if self.critic_kind == "transformer":
            del self.value_net
            self.critic = TransformerCritic(self.features_dim, self.critic_config)
            self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1),
                                                  **self.optimizer_kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(critic=self.critic_kind, critic_transformer=self.critic_config,
                    action_prior=self.action_prior)
        return data

    # ------------------------------------------------------------------ action prior
    def _set_prior(self, obs: torch.Tensor) -> None:
        """Compute the prior's pre-tanh mean for the raw observations ``obs`` (read by
        :meth:`_get_action_dist_from_latent` in the same call); nothing without a prior."""
        if self.action_prior is None:
            return
        mean = prior_mean(self.action_prior, obs.detach().cpu().numpy())
        self._prior_mean = torch.as_tensor(mean, dtype=obs.dtype, device=obs.device)

    def _get_action_dist_from_latent(self, latent_pi: torch.Tensor):
        mean = self.action_net(latent_pi)
        if self.action_prior is not None:
            prior = self._prior_mean
            if prior is None or prior.shape != mean.shape:
                raise RuntimeError("the action prior was not computed for these observations")
            mean = mean + prior
        return self.action_dist.proba_distribution(mean, self.log_std)

    def get_distribution(self, obs: torch.Tensor):
        self._set_prior(obs)
        return super().get_distribution(obs)

    def actor_gaussian(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The pre-tanh mean and standard deviation (each (n, 2)) of the actor's Gaussian for
        ``obs`` (n, D): ``get_distribution(obs).distribution.mean`` and ``.stddev`` bit for
        bit, without building distribution objects (a batched evaluation step builds one per
        world)."""
        self._set_prior(obs)
        features = BaseModel.extract_features(self, obs, self.pi_features_extractor)
        mean = self.action_net(self.mlp_extractor.forward_actor(features))
        if self.action_prior is not None:
            mean = mean + self._prior_mean
        return mean, torch.ones_like(mean) * self.log_std.exp()

    def actor_residual(self, obs: torch.Tensor) -> torch.Tensor:
        """(n, 2) the actor network's part of its pre-tanh mean for ``obs`` (n, D): the mean
        minus the action prior's (the mean itself without a prior)."""
        features = BaseModel.extract_features(self, obs, self.pi_features_extractor)
        return self.action_net(self.mlp_extractor.forward_actor(features))

    @property
    def obs_normalizer(self) -> RunningNormalizer:
        return self.features_extractor.normalizer

    def action_log_prob(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """log pi(actions | obs) (actions in (-1, 1); for behavioural cloning)."""
        return self.get_distribution(obs).log_prob(actions)

    # ------------------------------------------------------------------ slot layout
    def set_scene_layout(self, slot_scene: np.ndarray | None,
                         mask_source: Callable[[], np.ndarray] | None = None) -> None:
        """How rows of a vector-env observation map to slots and scenes: a rollout forward
        evaluates the occupied slots only (:meth:`rollout_rows`), and the transformer critic
        groups them by scene.

        :param slot_scene: (n_slots,) scene index of each slot (``MultiSceneVecEnv.slot_scene``);
            None: no layout (every row is a one-vehicle scene).
        :param mask_source: returns the (n_slots,) bool mask of the observation being evaluated
            (``MultiSceneVecEnv.slot_active``); None: all slots active.
        """
        self._slot_scene = None if slot_scene is None else np.asarray(slot_scene, np.int64)
        self._mask_source = mask_source

    def critic_groups(self, obs: torch.Tensor) -> torch.Tensor:
        """(N,) group ids of the rows of ``obs`` for the transformer critic (module doc): rows
        with the same id are one scene step, -1 marks a free slot."""
        group = getattr(obs, SCENE_GROUPS_ATTR, None)
        if group is None:
            n = obs.shape[0]
            if self._slot_scene is not None and n == len(self._slot_scene) > 1:
                mask = None if self._mask_source is None else self._mask_source()
                group = torch.from_numpy(scene_groups(self._slot_scene, mask))
            else:
                group = torch.arange(n)
        return group.to(obs.device)

    def _features(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.extract_features(obs)
        return (features, features) if self.share_features_extractor else features

    def _values(self, vf_features: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
        return self.critic(vf_features, group).unsqueeze(-1)

    def rollout_rows(self, obs: torch.Tensor) -> np.ndarray | None:
        """The rows of ``obs`` holding an agent when ``obs`` is one whole vector-env
        observation with free slots (the layout and mask :meth:`set_scene_layout` was given);
        None otherwise (every row is evaluated)."""
        if self._slot_scene is None or self._mask_source is None:
            return None
        if not obs.shape[0] == len(self._slot_scene) > 1:
            return None
        active = np.asarray(self._mask_source(), bool)
        return None if active.all() else np.flatnonzero(active)

    def forward(self, obs: torch.Tensor, deterministic: bool = False
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if self.critic_kind == "mlp":
            rows = self.rollout_rows(obs)
            if rows is None:
                self._set_prior(obs)
                return super().forward(obs, deterministic)
            # a rollout step: only the slots holding an agent are evaluated (and draw noise);
            # a free slot gets action, value and log-probability 0, never used (the masked
            # buffer drops free slot-steps, GAE never bootstraps across a re-assignment)
            n, i = obs.shape[0], torch.as_tensor(rows, device=obs.device)
            self._set_prior(obs[i])
            actions, values, log_prob = super().forward(obs[i], deterministic)
            out = (actions.new_zeros((n, *actions.shape[1:])), values.new_zeros((n, 1)),
                   log_prob.new_zeros(n))
            out[0][i], out[1][i], out[2][i] = actions, values, log_prob
            return out
        group = self.critic_groups(obs)
        self._set_prior(obs)
        pi_features, vf_features = self._features(obs)
        dist = self._get_action_dist_from_latent(self.mlp_extractor.forward_actor(pi_features))
        actions = dist.get_actions(deterministic=deterministic)
        log_prob = dist.log_prob(actions)
        actions = actions.reshape((-1, *self.action_space.shape))
        return actions, self._values(vf_features, group), log_prob

    def evaluate_actions(self, obs: torch.Tensor, actions: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        self._set_prior(obs)
        if self.critic_kind == "mlp":
            return super().evaluate_actions(obs, actions)
        if getattr(obs, SCENE_GROUPS_ATTR, None) is None:
            raise ValueError("the transformer critic needs minibatches of whole scene steps "
                             "(observations tagged by with_scene_groups, as MaskedPPO's rollout "
                             "buffer yields them)")
        group = self.critic_groups(obs)
        pi_features, vf_features = self._features(obs)
        dist = self._get_action_dist_from_latent(self.mlp_extractor.forward_actor(pi_features))
        return self._values(vf_features, group), dist.log_prob(actions), dist.entropy()

    def predict_values(self, obs: torch.Tensor) -> torch.Tensor:
        if self.critic_kind == "mlp":
            return super().predict_values(obs)
        group = self.critic_groups(obs)
        return self._values(self._features(obs)[1], group)
