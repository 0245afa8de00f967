"""Training configuration (``configs/*.yaml``), loaded strictly by :func:`magail_sumo.config.load_config`.

Every hyperparameter of a run lives here; unknown keys and wrong types are refused naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from magail_sumo.env.config import EnvConfig
from magail_sumo.models.critic import CriticTransformerConfig
from magail_sumo.models.discriminator import TransformerConfig


@dataclass(frozen=True)
class ScenesConfig:
    """Training scenes.

    :param files: scene files (WOMD / ScenarioNet); every scene of each is used.
    :param networks: converted bundles ``networks/<id>/`` (missing ones are converted there).
    :param worker_timeout_s: seconds before a silent scene worker is declared hung.
    :param pin_workers: pin each scene worker to one core, balancing the scenes' per-step cost
        (:func:`~magail_sumo.env.vec_env.place_workers`); for a machine dedicated to one run —
        concurrent pinned runs would stack their workers on the same cores.
    """

    files: tuple[str, ...] = ("data/womd/637f20cafde22ff8.tfrecord",)
    networks: str = "networks"
    worker_timeout_s: float = 120.0
    pin_workers: bool = False


@dataclass(frozen=True)
class PolicyConfig:
    """Actor-critic (parameters shared by all vehicles; see
    :class:`~magail_sumo.models.policies.TanhGaussianPolicy`).

    :param actor_hidden: hidden sizes of the per-vehicle tanh-Gaussian actor MLP.
    :param critic_hidden: hidden sizes of the MLP critic (unused by the transformer critic).
    :param log_std_init: initial log-std of the Gaussian (before the tanh squash).
    :param critic: ``"mlp"`` (each vehicle's value from its own observation) or
        ``"transformer"`` (each vehicle's value from the normalised observations of all
        vehicles of its scene at the same step;
        :class:`~magail_sumo.models.critic.TransformerCritic`).
    :param critic_transformer: sizes of the transformer critic (used when ``critic`` is
        ``"transformer"``).
    """

    actor_hidden: tuple[int, ...] = (64, 64)
    critic_hidden: tuple[int, ...] = (64, 64)
    log_std_init: float = 0.0
    critic: Literal["mlp", "transformer"] = "mlp"
    critic_transformer: CriticTransformerConfig = field(default_factory=CriticTransformerConfig)

    def __post_init__(self) -> None:
        if self.critic not in ("mlp", "transformer"):
            raise ValueError(f"critic must be 'mlp' or 'transformer', got {self.critic!r}")


@dataclass(frozen=True)
class PPOConfig:
    """SB3 PPO plus the seed's KL-adaptive learning rate.

    :param n_steps: env steps per rollout (each step = every slot of every scene).
    :param batch_size: minibatch size in agent-steps.
    :param desired_kl: target approx KL of an update (None: fixed learning rate); the lr is
        halved above 2x, multiplied by 1.5 below half of it, within [lr_min, lr_max].
    """

    n_steps: int = 128
    batch_size: int = 1024
    n_epochs: int = 10
    gamma: float = 0.995
    gae_lambda: float = 0.97
    clip_range: float = 0.2
    learning_rate: float = 1e-3
    ent_coef: float = 0.0
    vf_coef: float = 1.0
    max_grad_norm: float = 1.0
    normalize_advantage: bool = True
    desired_kl: float | None = 0.01
    lr_min: float = 1e-5
    lr_max: float = 1e-2


@dataclass(frozen=True)
class DiscriminatorConfig:
    """GAIL discriminator and reward.

    :param kind: ``"transformer"`` (MAGAIL: all vehicles of a scene step together) or ``"mlp"``
        (plain per-vehicle GAIL).
    :param epochs: gradient steps per PPO update, each on ``batch_size`` expert and
        ``batch_size`` policy scene steps.
    :param reward_t_coef, reward_i_coef: r = c_t·r_task + c_i·(−log(max(1 − sigmoid(D), floor))).
    :param ignore_features: observation feature names (``observation_names``) the
        discriminator does not see, in s nor in s' — e.g. ``[prev_accel, prev_steer]``: the
        previous action carries the policy's exploration noise, which lets a discriminator
        tell policy from expert without judging the driving.
    :param collision_penalty, off_road_penalty: the task reward r_task of the step at which an
        agent leaves by a collision / by going off-road is minus this (events in
        ``env.terminate_on`` end the agent; 0 otherwise).
    """

    kind: str = "transformer"
    transformer: TransformerConfig = field(default_factory=TransformerConfig)
    mlp_hidden: tuple[int, ...] = (256, 256)
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    epochs: int = 50
    batch_size: int = 32
    gp_coef: float = 0.1
    logit_reg: float = 0.25
    reward_t_coef: float = 0.0
    reward_i_coef: float = 1.0
    reward_floor: float = 1e-4
    collision_penalty: float = 0.0
    off_road_penalty: float = 0.0
    ignore_features: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("transformer", "mlp"):
            raise ValueError(f"discriminator kind must be 'transformer' or 'mlp', got {self.kind!r}")


@dataclass(frozen=True)
class BCConfig:
    """Behavioural cloning (the ``bc`` algorithm, or PPO initialisation when ``epochs`` > 0).

    :param epochs: passes over the expert (s, a) pairs.
    """

    epochs: int = 0
    batch_size: int = 256
    learning_rate: float = 1e-3


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    :param algorithm: ``"gail"`` (PPO + discriminator reward; MAGAIL with a transformer
        discriminator) or ``"bc"`` (behavioural cloning only).
    :param expert_dir: what ``magail-sumo expert`` wrote for the same observation layout.
    :param updates: PPO updates (rollout + discriminator + PPO epochs) in the run.
    :param checkpoint_every: updates between checkpoints (the last update always saves).
    :param torch_threads: torch CPU threads of the trainer process (during rollouts, when the
        scene workers need the cores).
    :param torch_threads_update: torch CPU threads for the discriminator fit and the PPO epochs,
        while the scene workers are idle (None: ``torch_threads``).
    """

    algorithm: str = "gail"
    seed: int = 0
    expert_dir: str = "expert"
    out_dir: str = "runs"
    updates: int = 100
    checkpoint_every: int = 10
    device: str = "cpu"
    torch_threads: int = 1
    torch_threads_update: int | None = None
    env: EnvConfig = field(default_factory=EnvConfig)
    scenes: ScenesConfig = field(default_factory=ScenesConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    discriminator: DiscriminatorConfig = field(default_factory=DiscriminatorConfig)
    bc: BCConfig = field(default_factory=BCConfig)

    def __post_init__(self) -> None:
        if self.algorithm not in ("gail", "bc"):
            raise ValueError(f"algorithm must be 'gail' or 'bc', got {self.algorithm!r}")
        if self.updates < 0 or self.checkpoint_every < 1:
            raise ValueError("updates must be >= 0 and checkpoint_every >= 1")
