"""The ``sac`` block of a ``sac`` / ``sac_gail`` run's config, with its task reward's weights."""

from __future__ import annotations

from dataclasses import dataclass, field

from magail_sumo.config import check, check_positive, check_sizes, show


@dataclass(frozen=True)
class TaskRewardConfig:
    """Task reward of the ``sac`` algorithm per agent-step (:func:`~magail_sumo.training.sac.
    task_reward`): ``progress·(d(s) − d(s')) + destination·[reached] − collision·[collided]
    − off_road·[off road] − red_light·[ran a red light] − comfort·|a − a_prev|²``, with ``d``
    the distance to the destination (m, the ``dest_distance`` feature), the events those that
    ended the agent at that step (``env.terminate_on``) and ``a_prev`` the previous normalised
    action (the ``prev_accel``, ``prev_steer`` features of s). All weights >= 0.
    """

    progress: float = 0.1
    destination: float = 1.0
    collision: float = 10.0
    off_road: float = 5.0
    red_light: float = 5.0
    comfort: float = 0.05

    def __post_init__(self) -> None:
        check_positive(self, "progress", "destination", "collision", "off_road", "red_light",
                       "comfort", allow_zero=True)


@dataclass(frozen=True)
class SACConfig:
    """Soft Actor-Critic with command-branched heads (``algorithm: sac`` / ``sac_gail``;
    :mod:`magail_sumo.training.sac`).

    One update = ``train_freq`` env steps (every slot of every scene) then
    ``gradient_steps`` gradient steps (after ``learning_starts`` transitions are stored).

    :param hidden: hidden sizes of the shared trunks of the actor, twin Q and value networks
        (each has one output head per command: left / straight / right).
    :param buffer_size: transitions kept in the main replay buffer (and as many in the
        collision buffer), oldest first out.
    :param batch_size: transitions per gradient step.
    :param collision_share: share of each batch drawn from the collision buffer (transitions
        at which an agent collided), ``int(collision_share·batch_size)`` exactly once that
        buffer holds as many; 0: off.
    :param gamma: discount. :param tau: soft target update rate of the value network.
    :param learning_rate: Adam learning rate of all networks (and of the temperature).
    :param lr_step, lr_gamma: StepLR: every ``lr_step`` gradient steps the learning rates are
        multiplied by ``lr_gamma``.
    :param learning_starts: stored transitions before the first gradient step (actions are
        uniform random until then).
    :param train_freq: env steps per update. :param gradient_steps: gradient steps per update.
    :param alpha: entropy temperature (initial one with ``auto_alpha``).
    :param auto_alpha: learn the temperature towards ``target_entropy``.
    :param target_entropy: entropy target (None: −action dimension, −2).
    :param absorbing_reward: ``sac_gail``: reward of the absorbing state's self-transition
        (the discriminators do not judge absorbing states; default log 2, the imitation
        reward of a discriminator at chance).
    :param save_buffers: store the replay buffers in checkpoints (resume is then exact; without
        them a resumed run starts with empty buffers: approximate).
    :param task_reward: weights of the ``sac`` task reward.
    """

    hidden: tuple[int, ...] = (256, 256)
    buffer_size: int = 200_000
    batch_size: int = 256
    collision_share: float = 0.2
    gamma: float = 0.99
    tau: float = 0.005
    learning_rate: float = 3e-4
    lr_step: int = 10_000
    lr_gamma: float = 0.9
    learning_starts: int = 1000
    train_freq: int = 16
    gradient_steps: int = 16
    alpha: float = 0.2
    auto_alpha: bool = True
    target_entropy: float | None = None
    absorbing_reward: float = 0.6931471805599453
    save_buffers: bool = True
    task_reward: TaskRewardConfig = field(default_factory=TaskRewardConfig)

    def __post_init__(self) -> None:
        check_sizes(self, "hidden")
        for name in ("buffer_size", "batch_size", "lr_step", "train_freq", "gradient_steps"):
            check(getattr(self, name) >= 1, name, f"must be >= 1, got {getattr(self, name)}")
        check(self.learning_starts >= 0, "learning_starts",
              f"must be >= 0, got {self.learning_starts}")
        check(self.batch_size <= self.buffer_size, "batch_size",
              f"must be <= buffer_size ({self.buffer_size}), got {self.batch_size}")
        check(0.0 <= self.collision_share < 1.0, "collision_share",
              f"must be in [0, 1), got {show(self.collision_share)}")
        check(0.0 <= self.gamma < 1.0, "gamma", f"must be in [0, 1), got {show(self.gamma)}")
        check(0.0 < self.tau <= 1.0, "tau", f"must be in (0, 1], got {show(self.tau)}")
        check(0.0 < self.lr_gamma <= 1.0, "lr_gamma",
              f"must be in (0, 1], got {show(self.lr_gamma)}")
        check_positive(self, "learning_rate", "alpha")
        check(self.target_entropy is None or abs(self.target_entropy) < 1e3, "target_entropy",
              f"must be a number in (-1000, 1000) or null, got {show(self.target_entropy)}")
        check(abs(self.absorbing_reward) < 1e3, "absorbing_reward",
              f"must be in (-1000, 1000), got {show(self.absorbing_reward)}")
