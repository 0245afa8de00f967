"""The ``ppo`` block of a ``gail`` run's config: PPO's hyperparameters, the adaptive learning
rate, the behavioural-cloning regulariser and the pull toward the action prior."""

from __future__ import annotations

from dataclasses import dataclass

from magail_sumo.config import check, check_positive, show


@dataclass(frozen=True)
class PPOConfig:
    """SB3 PPO plus the seed's KL-adaptive learning rate.

    :param n_steps: env steps per rollout (each step = every slot of every scene).
    :param batch_size: minibatch size in agent-steps.
    :param desired_kl: target approx KL of an update (None: fixed learning rate); the lr is
        halved above 2x, multiplied by 1.5 below half of it, within [lr_min, lr_max].
    :param bc_coef: weight c of the behavioural-cloning regulariser added to every PPO
        minibatch loss, ``c_u · (−mean log pi(a_E | s_E))`` over ``bc_batch_size`` expert
        (s, a) pairs (:class:`~magail_sumo.training.gail.ppo.MaskedPPO`); 0: off (plain PPO).
    :param bc_decay: d in (0, 1], the weight of PPO update u (0-based) is ``c_u = c · d**u``.
    :param bc_batch_size: expert pairs per minibatch.
    :param prior_coef: weight k of the pull toward the action prior (``policy.action_prior``)
        added to every PPO minibatch loss, ``k · mean ½‖μ_θ(s) − μ_prior(s)‖²`` over the
        minibatch's agent-steps: the squared residual of the actor's pre-tanh mean, i.e. the KL
        from the actor's Gaussian to one of the same spread centred on the prior, times σ²
        (a reference-policy regulariser as in human-regularised PPO, with the rule as the
        reference); 0: off.
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
    bc_coef: float = 0.0
    bc_decay: float = 1.0
    bc_batch_size: int = 256
    prior_coef: float = 0.0

    def __post_init__(self) -> None:
        for name in ("n_steps", "batch_size", "n_epochs", "bc_batch_size"):
            check(getattr(self, name) >= 1, name, f"must be >= 1, got {getattr(self, name)}")
        check_positive(self, "learning_rate", "max_grad_norm", "desired_kl", "lr_min", "lr_max")
        check_positive(self, "vf_coef", "bc_coef", "prior_coef", allow_zero=True)
        check(0.0 < self.bc_decay <= 1.0, "bc_decay",
              f"must be in (0, 1], got {show(self.bc_decay)}")
        for name in ("gamma", "gae_lambda"):
            v = getattr(self, name)
            check(0.0 <= v <= 1.0, name, f"must be in [0, 1], got {show(v)}")
        check(0.0 < self.clip_range <= 1.0, "clip_range",
              f"must be in (0, 1], got {show(self.clip_range)}")
        check(self.lr_max >= self.lr_min, "lr_max",
              f"must be >= lr_min ({self.lr_min:g}), got {self.lr_max:g}")
