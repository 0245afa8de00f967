"""The adversarial-imitation reward, apart from any generator algorithm (as ``imitation`` keeps
its reward nets apart from its trainers): the discriminator of ``discriminator.kind``
(:func:`make_discriminator`), the env wrapper that rewards the generator with it
(:class:`~magail_sumo.training.reward.DiscriminatorRewardWrapper`) and its trainer
(:class:`~magail_sumo.training.reward.DiscriminatorTrainer`), built from a run config by
:meth:`AdversarialReward.build` and saved / restored as the checkpoint entries
``discriminator`` and ``disc_trainer``. A generator (PPO in :mod:`~magail_sumo.training.gail`,
SAC in :mod:`~magail_sumo.training.sac`, or a new algorithm) steps :attr:`AdversarialReward.env`
instead of the scene env and calls :attr:`AdversarialReward.trainer` on its rollouts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from magail_sumo.config import ConfigError
from magail_sumo.models.decomposed import DecomposedDiscriminator
from magail_sumo.models.decomposed_transformer import DecomposedTransformerDiscriminator
from magail_sumo.models.discriminator import MLPDiscriminator, TransformerDiscriminator
from magail_sumo.sensors.observation import observation_names

from .checkpoints import load_into, plain
from .config import TrainConfig
from .discriminator_loss import DiscriminatorLossConfig
from .discriminator_trainer import DiscriminatorTrainer
from .reward import DiscriminatorRewardWrapper


#: ``discriminator.kind`` → builder from (``discriminator`` config, token width); the names are
#: :data:`~magail_sumo.training.config.DISCRIMINATOR_KINDS`
DISCRIMINATORS = {
    "transformer": lambda d, f: TransformerDiscriminator(f, d.transformer),
    "mlp": lambda d, f: MLPDiscriminator(f, d.mlp_hidden),
    "decomposed": lambda d, f: DecomposedDiscriminator(f, d.decomposed),
    "decomposed_transformer": lambda d, f: DecomposedTransformerDiscriminator(
        f, d.decomposed, d.decomposed_transformer),
}


def make_discriminator(cfg: TrainConfig, feature_dim: int) -> torch.nn.Module:
    """The config's discriminator over tokens concat(s, s') of ``feature_dim`` columns, with
    ``discriminator.ignore_features`` (observation feature names, in s and in s') masked."""
    d = cfg.discriminator
    disc = DISCRIMINATORS[d.kind](d, feature_dim)
    if d.ignore_features:
        names = observation_names(cfg.env.observation)
        unknown = [f for f in d.ignore_features if f not in names]
        if unknown:
            raise ConfigError(f"discriminator.ignore_features: unknown observation feature(s) "
                              f"{', '.join(unknown)} (features are {', '.join(names[:8])}, ...)")
        if 2 * len(names) != feature_dim:
            raise ValueError(f"tokens have {feature_dim} columns, the observation "
                             f"{len(names)} features (expected twice as many)")
        cols = [names.index(f) for f in d.ignore_features]
        disc.ignore_features(cols + [len(names) + c for c in cols])
    return disc.to(cfg.device)


@dataclass
class AdversarialReward:
    """A run's discriminator, the reward wrapper over its scene env, and the discriminator trainer."""

    discriminator: torch.nn.Module
    env: object  #: :class:`~magail_sumo.training.reward.DiscriminatorRewardWrapper`
    trainer: object  #: :class:`~magail_sumo.training.reward.DiscriminatorTrainer`

    @classmethod
    def build(cls, cfg: TrainConfig, venv, expert, deferred: bool = False) -> "AdversarialReward":
        """The config's discriminator over ``venv``'s (s, s') tokens, rewarding through a
        wrapper of ``venv`` (``deferred``: rewards computed when the generator asks for them,
        see the wrapper) and fitted on ``expert`` by the trainer (seeded with the run seed).
        Torch's global RNG draws the discriminator's initial weights here."""
        d = cfg.discriminator
        disc = make_discriminator(cfg, 2 * venv.obs_dim)
        extra = {"deferred": True} if deferred else {}
        env = DiscriminatorRewardWrapper(
            venv, disc, d.reward_t_coef, d.reward_i_coef, d.reward_floor, cfg.device, **extra,
            penalties={"collision": d.collision_penalty, "off_road": d.off_road_penalty,
                       "red_light": d.red_light_penalty},
            social_coef=d.decomposed.social_coef if d.decomposes else 0.0)
        trainer = DiscriminatorTrainer(
            disc, expert, d.epochs, d.batch_size, d.learning_rate, d.weight_decay,
            DiscriminatorLossConfig(d.gp_coef, d.logit_reg), cfg.seed, cfg.device)
        return cls(disc, env, trainer)

    def state_dict(self) -> dict:
        """Checkpoint entries ``discriminator`` and ``disc_trainer`` (tensors and plain data)."""
        dt = dict(self.trainer.state_dict())
        dt["rng"] = plain(dt["rng"])
        return {"discriminator": self.discriminator.state_dict(), "disc_trainer": dt}

    def load_state_dict(self, state: dict, where: Path) -> None:
        """Restore :meth:`state_dict`'s entries of checkpoint ``state`` (a one-line
        :class:`~magail_sumo.training.checkpoints.CheckpointError` naming ``where`` when the
        discriminator does not fit; KeyError / ValueError / TypeError from a malformed trainer
        state, for the caller to word)."""
        load_into(self.discriminator, state["discriminator"], "discriminator", where)
        self.trainer.load_state_dict(state["disc_trainer"])
