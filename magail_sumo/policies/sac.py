"""SAC checkpoints as evaluation policies (``magail-sumo evaluate --policy RUN/checkpoints/latest.pt``
of a ``sac`` / ``sac_gail`` run): the command-branched actor of
:class:`~magail_sumo.models.branched.BranchedSAC`, built as :mod:`magail_sumo.training.sac`
trains it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from magail_sumo.env.config import EnvConfig
from magail_sumo.models.branched import BranchedSAC
from magail_sumo.sensors.config import ObservationConfig
from magail_sumo.training.checkpoints import (CheckpointError, checkpoint_config, load_checkpoint,
                                              load_into)
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.sac.agent import make_sac_model

from .checkpoint import check_env_compatible, target_env


class SacCheckpointPolicy:
    """Evaluation policy of a SAC checkpoint (``magail-sumo evaluate --policy CKPT``): each
    vehicle acts from its own observation (with the route command: :attr:`observation` is the
    observation config the evaluation env must use), sampled from the branched tanh-Gaussian
    with the policy's own generator seeded with the rollout seed (agents in sorted-name order),
    ``tanh(mu + noise_scale * sigma * eps)``, or ``tanh`` of its mean when deterministic."""

    def __init__(self, model: BranchedSAC, observation: ObservationConfig, name: str = "",
                 seed: int = 0, deterministic: bool = False, noise_scale: float = 1.0) -> None:
        self.model = model.eval()
        self.observation = observation
        self.name = name
        self.deterministic = bool(deterministic)
        #: the sampling noise's scale (``magail-sumo evaluate --noise-scale``; 1: the policy's)
        self.noise_scale = float(noise_scale)
        self.generator = torch.Generator().manual_seed(int(seed))

    def reseed(self, seed: int) -> None:
        """Sample from here on as the policy built with ``seed`` does (the next rollout)."""
        self.generator.manual_seed(int(seed))

    @torch.no_grad()
    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not observations:
            return {}
        names = sorted(observations)
        x = np.stack([np.asarray(observations[n], np.float32).reshape(-1) for n in names])
        if x.shape[1] != self.model.obs_dim:
            raise CheckpointError(f"{self.name}: observations have {x.shape[1]} values, the "
                                  f"policy expects {self.model.obs_dim}")
        x = torch.as_tensor(np.concatenate([x, np.zeros((len(names), 1), np.float32)], axis=1))
        a = self.model.act(x, self.deterministic, self.generator, self.noise_scale)
        return dict(zip(names, np.clip(a.numpy().astype(np.float32), -1.0, 1.0)))


def load_sac_policy(path: str | Path, state: dict, cfg: TrainConfig, seed: int = 0,
                    deterministic: bool = False) -> SacCheckpointPolicy:
    """The :class:`SacCheckpointPolicy` of a loaded SAC checkpoint ``state`` (config ``cfg``)."""
    model = make_sac_model(cfg)
    load_into(model, state["policy"], "policy", Path(path))
    return SacCheckpointPolicy(model, cfg.env.observation, str(path), seed, deterministic)


def load_sac_checkpoint_policy(path: str | Path, seed: int = 0, deterministic: bool = False,
                               target: EnvConfig | None = None):
    """The :class:`SacCheckpointPolicy` of a ``sac`` / ``sac_gail``
    checkpoint, registered in :data:`~magail_sumo.policies.registry.CHECKPOINT_LOADERS`; parameters as
    :func:`~magail_sumo.policies.registry.load_checkpoint_policy`."""
    torch.set_num_threads(1)
    state = load_checkpoint(path)
    cfg = checkpoint_config(state, path)
    if cfg.algorithm not in ("sac", "sac_gail"):
        raise CheckpointError(f"{path}: a {cfg.algorithm} checkpoint, not a SAC one")
    env = target_env(cfg.env, target)
    # evaluation drives the env with the policy's route command (SacCheckpointPolicy.observation)
    obs = replace(env.observation, command=cfg.env.observation.command,
                  command_lookahead=cfg.env.observation.command_lookahead)
    check_env_compatible(path, cfg.env, replace(env, observation=obs))
    pol = load_sac_policy(path, state, replace(cfg, device="cpu"), seed, deterministic)
    pol.action_layout = cfg.env.action_layout
    if cfg.env.guard.on:
        pol.guard = cfg.env.guard
    return pol


__all__ = ["SacCheckpointPolicy", "load_sac_checkpoint_policy", "load_sac_policy"]
