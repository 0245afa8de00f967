"""Training checkpoints as evaluation policies (``magail-sumo evaluate --policy RUN/checkpoints/latest.pt``).

:func:`load_actor_policy` is registered for ``gail`` / ``bc`` checkpoints in
:data:`magail_sumo.policies.registry.CHECKPOINT_LOADERS`, which evaluation reaches through
``.pt`` in :data:`~magail_sumo.policies.registry.POLICY_LOADERS`
(:func:`~magail_sumo.policies.registry.load_checkpoint_policy` picks by the checkpoint's
algorithm). The policy is the checkpoint's SB3 actor
(with its observation normaliser, stored in the policy's state dict), each vehicle acting from its
own observation with normalised ``[accel, steer]`` in [-1, 1]²: by default a sample of the
policy, ``a = tanh(mu(o) + k·sigma ⊙ eps)`` with ``eps ~ N(0, I)`` drawn from the policy's own
``torch.Generator`` seeded with the rollout seed (agents served in sorted-name order, so a
rollout is reproducible whatever order the env lists them in) and ``k`` the policy's
``noise_scale`` (1 by default; ``magail-sumo evaluate --noise-scale``: a sampling temperature
on the Gaussian's standard deviation; ``eps`` is white unless the policy's ``noise_shape``, from a
pretrained card, weights it per action and correlates it from step to step,
:mod:`magail_sumo.agents.noise`); deterministically
(``magail-sumo evaluate --deterministic``) the tanh of the Gaussian mean, ``a = tanh(mu(o))``. Any checkpoint ``magail-sumo train`` writes works (GAIL / MAGAIL updates and
behavioural cloning, with an MLP or a transformer critic: the critic is loaded with the policy
but never evaluated).

A ``gameformer`` checkpoint is a closed-loop GameFormer agent instead
(:class:`~magail_sumo.policies.gameformer.GameFormerPolicy`: it replans from the simulated
history of all objects through the rollout's ``begin(scene, env)`` hook).

Evaluation drives the env with the default observation layout and bicycle limits; a checkpoint
trained with other ones is refused with a one-line error naming the difference (its actions and
observations would mean something else there). The action layout and the optional
observation features (route command, route look-ahead, leader: ``observation.command``,
``command_lookahead``, ``route_points``, ``leader``, ``leader_range``) are the checkpoint's:
the policy's ``action_layout`` and ``observation`` attributes make evaluation build its env
with them.

SAC checkpoints (``algorithm: sac`` / ``sac_gail``; the checkpoint's recorded algorithm picks
the loader) load as :class:`~magail_sumo.policies.sac.SacCheckpointPolicy`: the command-branched
actor, with the route command appended to the default observation (the policy's
``observation`` attribute tells the evaluation env to compute it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from magail_sumo.agents.noise import NoiseProcess, NoiseShape
from magail_sumo.config import to_dict
from magail_sumo.env.config import EnvConfig
from magail_sumo.sensors.config import ObservationConfig

from magail_sumo.sensors.observation import observation_bounds
from magail_sumo.sim.dynamics import BicycleLimits
from magail_sumo.training.checkpoints import CheckpointError
from magail_sumo.training.policies import load_policy


class CheckpointPolicy:
    """Actions of a trained :class:`~magail_sumo.models.policies.TanhGaussianPolicy` (module doc).

    :param policy: the SB3 policy (eval mode). :param obs_dim: observation size it expects.
    :param seed: seed of the sampling generator (the rollout seed).
    :param deterministic: act with ``tanh(mu(o))`` instead of sampling.
    :param noise_scale: ``k`` of the module doc: the scale of the sampling noise.
    :param action_layout: the order of its actions (the env config it trained in); evaluation
        builds its env with it.
    """

    def __init__(self, policy, obs_dim: int, name: str = "", seed: int = 0,
                 deterministic: bool = False, action_layout: str = "accel_steer",
                 noise_scale: float = 1.0) -> None:
        self.policy = policy
        self.noise_scale = float(noise_scale)
        self.action_layout = action_layout
        self.obs_dim = obs_dim
        self.name = name
        self.deterministic = bool(deterministic)
        self.generator = torch.Generator(device=policy.device).manual_seed(int(seed))
        self.noise = NoiseProcess(NoiseShape())

    @property
    def noise_shape(self) -> NoiseShape:
        """Per-action weights and step-to-step correlation of the sampling noise
        (:mod:`magail_sumo.agents.noise`; default: white noise, as trained)."""
        return self.noise.shape

    @noise_shape.setter
    def noise_shape(self, shape: NoiseShape) -> None:
        self.noise = NoiseProcess(shape)

    def reseed(self, seed: int) -> None:
        """Sample from here on as the policy built with ``seed`` does (the next rollout)."""
        self.generator.manual_seed(int(seed))
        self.noise.reset()

    def reseed_worlds(self, seeds) -> None:
        """Batched rollouts: world ``w`` samples from here on as the policy built with
        ``seeds[w]`` does (:meth:`act_batch`)."""
        dev = self.policy.device
        self.noise.reset()
        self.world_generators = [torch.Generator(device=dev).manual_seed(int(s)) for s in seeds]

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        """(n, D) observations as the policy's input, refused unless D is its size."""
        if x.shape[1] != self.obs_dim:
            raise CheckpointError(f"{self.name}: observations have {x.shape[1]} values, the "
                                  f"policy expects {self.obs_dim}")
        return torch.as_tensor(x, device=self.policy.device)

    def _means(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The actor Gaussian's pre-tanh mean and std for ``obs`` (n, D) (the policy's
        ``actor_gaussian`` where it has one: the same values without distribution objects)."""
        fast = getattr(self.policy, "actor_gaussian", None)
        if fast is not None:
            return fast(obs)
        gauss = self.policy.get_distribution(obs)
        return gauss.distribution.mean, gauss.distribution.stddev

    def _actions(self, obs: torch.Tensor, generator: torch.Generator | None,
                 keys: np.ndarray | None) -> np.ndarray:
        """(n, 2) actions of one world's agents (module doc): sampled with ``generator``'s
        draws, in row order, shaped by :attr:`noise_shape` for the agents ``keys``, or the tanh
        of the mean when deterministic."""
        if self.deterministic:
            a = self.policy._predict(obs, deterministic=True)
            return np.clip(a.cpu().numpy().astype(np.float32), -1.0, 1.0)
        mean, std = self._means(obs)
        eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
        return self._squash(mean, std, self._shaped(eps, keys))

    def _shaped(self, eps: torch.Tensor, keys: np.ndarray | None) -> torch.Tensor:
        """The draws ``eps`` (n, 2) shaped by :attr:`noise_shape` for the agents ``keys``
        (element-wise: one call may cover several worlds' rows)."""
        if self.noise.shape.plain:  # the policy's own noise keeps the draws' bits
            return eps
        return torch.as_tensor(self.noise(eps.cpu().numpy(), keys), dtype=eps.dtype,
                               device=eps.device)

    def _squash(self, mean: torch.Tensor, std: torch.Tensor, eps: torch.Tensor) -> np.ndarray:
        """``tanh(mean + k * std * eps)`` as float32 actions in [-1, 1]."""
        a = torch.tanh(mean + self.noise_scale * std * eps)
        return np.clip(a.cpu().numpy().astype(np.float32), -1.0, 1.0)

    @torch.no_grad()
    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not observations:
            return {}
        # sampling: one draw order for a rollout, whatever the env's
        names = list(observations) if self.deterministic else sorted(observations)
        x = np.stack([np.asarray(observations[n], np.float32).reshape(-1) for n in names])
        keys = None if self.noise.shape.white else self.noise.key(names)
        return dict(zip(names, self._actions(self._tensor(x), self.generator, keys)))

    @torch.no_grad()
    def act_batch(self, observations: np.ndarray, worlds: np.ndarray,
                  agents: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) actions of the agents of every world of a batched env
        (:func:`~magail_sumo.agents.rollout_worlds`): ``observations`` (n, D) grouped by
        ``worlds`` (ascending), each world's agents in sorted-name order; world ``w`` acts
        exactly as :meth:`act` of a policy reseeded with ``seeds[w]`` of
        :meth:`reseed_worlds` (its noise from its own generator, drawn in that order;
        ``agents`` (n,), integers that stay each agent's for the rollout, e.g. fleet rows,
        carry correlated noise from step to step and are needed only for it). The
        forward pass runs per world: one pass over every world's agents would round the last
        float bits otherwise (matrix products' rounding depends on their row count), and a
        rollout would then depend on which rollouts shared its batch."""
        x = np.asarray(observations, np.float32)
        if x.shape[0] == 0:
            return np.zeros((0, 2), np.float32)
        gens = getattr(self, "world_generators", None)
        if gens is None and not self.deterministic:
            raise ValueError(f"{self.name}: call reseed_worlds before act_batch")
        obs = self._tensor(x)
        worlds = np.asarray(worlds, np.int64)
        bounds = np.flatnonzero(np.diff(worlds)) + 1
        if agents is None and not (self.deterministic or self.noise.shape.white):
            raise ValueError(f"{self.name}: correlated sampling noise needs act_batch's agents")
        spans = list(zip(np.r_[0, bounds].tolist(), np.r_[bounds, worlds.size].tolist()))
        if self.deterministic:
            return np.concatenate([self._actions(obs[lo:hi], None, None) for lo, hi in spans])
        # per world: its forward pass, its generator's draws and the tanh (its rows alone, as
        # act gives them); the noise's shaping is element-wise and runs once over all rows
        parts = [self._means(obs[lo:hi]) for lo, hi in spans]
        eps = torch.cat([torch.randn(m.shape, generator=gens[int(worlds[lo])], dtype=m.dtype,
                                     device=m.device) for (m, _), (lo, _) in zip(parts, spans)])
        eps = self._shaped(eps, None if agents is None else np.asarray(agents))
        return np.concatenate([self._squash(m, s, eps[lo:hi])
                               for (m, s), (lo, hi) in zip(parts, spans)])


def check_env_compatible(path: str | Path, trained: EnvConfig, target: EnvConfig) -> None:
    """Refuse a checkpoint whose observation layout, limits or action layout differ from the
    env it is to drive (:class:`CheckpointError` naming the first difference)."""
    for key in ("observation", "limits", "action_layout"):
        a, b = getattr(trained, key), getattr(target, key)
        da = to_dict(a) if hasattr(a, "__dataclass_fields__") else a
        db = to_dict(b) if hasattr(b, "__dataclass_fields__") else b
        if da != db:
            if isinstance(da, dict):
                k = next(k for k in sorted(set(da) | set(db)) if da.get(k) != db.get(k))
                what = f"env.{key}.{k}: trained {da.get(k)!r}, evaluation {db.get(k)!r}"
            else:
                what = f"env.{key}: trained {da!r}, evaluation {db!r}"
            raise CheckpointError(f"{path}: policy trained with another env than evaluation "
                                  f"uses ({what})")


def policy_observation(trained: EnvConfig) -> ObservationConfig:
    """Evaluation's observation for a policy trained in ``trained``: the default one with the
    policy's optional features (route command, route look-ahead, leader, stop-line
    distance, give-way conflict and how it is read, path leader, speed limits, the route's
    standing end, the desired-speed factor)."""
    ob = trained.observation
    return ObservationConfig(command=ob.command, command_lookahead=ob.command_lookahead,
                             route_points=ob.route_points, leader=ob.leader,
                             leader_range=ob.leader_range, light_gap=ob.light_gap,
                             give_way=ob.give_way, give_way_conflicts=ob.give_way_conflicts,
                             path_leader=ob.path_leader, speed_limit=ob.speed_limit,
                             route_stop=ob.route_stop, speed_factor=ob.speed_factor)


def target_env(trained: EnvConfig, target: EnvConfig | None) -> EnvConfig:
    """The env a checkpoint trained in ``trained`` drives: ``target``, or evaluation's (the
    defaults) with the policy's action layout, optional features, gap guard and steering rate
    limit (the policy's ``action_layout``, ``observation``, ``guard`` and ``limits`` attributes
    make evaluation build its env so)."""
    return target or EnvConfig(action_layout=trained.action_layout,
                               observation=policy_observation(trained), guard=trained.guard,
                               limits=BicycleLimits(
                                   max_steer_rate=trained.limits.max_steer_rate))


def load_actor_policy(path: str | Path, seed: int = 0, deterministic: bool = False,
                      target: EnvConfig | None = None) -> CheckpointPolicy:
    """The :class:`CheckpointPolicy` of a PPO / behavioural-cloning checkpoint (``gail``,
    ``bc``), registered in :data:`~magail_sumo.policies.registry.CHECKPOINT_LOADERS`; parameters as
    :func:`~magail_sumo.policies.registry.load_checkpoint_policy`."""
    torch.set_num_threads(1)  # small MLP; evaluation runs several worker processes
    policy, cfg = load_policy(path, device="cpu")
    check_env_compatible(path, cfg.env, target_env(cfg.env, target))
    low, _ = observation_bounds(cfg.env.observation)
    pol = CheckpointPolicy(policy, int(low.shape[0]), str(path), seed=seed,
                           deterministic=deterministic, action_layout=cfg.env.action_layout)
    pol.observation = policy_observation(cfg.env)
    if cfg.env.guard.on:
        pol.guard = cfg.env.guard  # trained behind the gap guard: evaluation keeps it
    if cfg.env.limits.max_steer_rate > 0:  # trained with a steering rate limit: kept too
        pol.limits = target_env(cfg.env, None).limits
    return pol
