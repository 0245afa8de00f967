"""The GAIL run's SB3 callbacks: the discriminator's fit between PPO rollouts, with its logs."""

from __future__ import annotations

from collections import Counter

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback


from ..discriminator_trainer import DiscriminatorStats, DiscriminatorTrainer
from ..reward import DiscriminatorRewardWrapper


class DiscriminatorCallback(BaseCallback):
    """Between PPO rollouts: train the discriminator on the rollout's scene steps and log
    ``discriminator/*`` (loss, BCE, gradient penalty, expert/policy accuracy), ``reward/*``
    (imitation reward mean/std per agent-step), ``env/*`` (agent-steps, scene episodes) and,
    when the observation has a ``speed`` entry, ``diag/speed_policy`` / ``diag/speed_expert``
    (mean speed along the heading at s over the rollout's agent-steps / over every expert
    transition, m/s) and ``diag/speed_gap`` (policy − expert): the speed bias as training sees
    it (the populations differ — rollout windows vs whole logs — so it is a trend, not the
    evaluation's ``speed_bias``).

    :param wrapper: the reward wrapper of the model's env. :param trainer: the fitter.
    """

    def __init__(self, wrapper: DiscriminatorRewardWrapper, trainer: DiscriminatorTrainer,
                 verbose: int = 0) -> None:
        super().__init__(verbose)
        self.wrapper, self.trainer = wrapper, trainer
        self.last_stats: DiscriminatorStats | None = None
        names = list(getattr(trainer.expert, "observation_names", []))
        self._speed_col = names.index("speed") if "speed" in names else None
        self.expert_speed = (float(np.mean(trainer.expert.s[:, self._speed_col]))
                              if self._speed_col is not None and len(trainer.expert) else None)
        #: the last rollout's mean policy speed (m/s), None before the first
        self.last_speed: float | None = None
        #: the vector env's (agent-steps, guarded, end reasons) totals at the last rollout end
        self._seen: tuple[int, int, Counter] = (0, 0, Counter())
        #: the last rollout's ``env/*`` rates (``guarded_frac``, ``end_<reason>``) by name
        self.last_rates: dict[str, float] = {}

    def _on_step(self) -> bool:
        return True

    def _on_training_start(self) -> None:
        base = self.wrapper.base  # a resumed run's env starts from its restored totals
        self._seen = (base.agent_steps, base.guarded, Counter(base.end_reasons))

    def _log_env_rates(self, base) -> None:
        """``env/guarded_frac``: share of the rollout's agent-steps whose acceleration the gap
        guard lowered; ``env/end_<reason>``: share of the rollout's ended agent episodes that
        ended for that reason (collision, off_road, …); from the vector env's running totals."""
        steps = base.agent_steps - self._seen[0]
        guarded, ends = base.guarded, Counter(base.end_reasons)
        rates: dict[str, float] = {}
        if steps > 0:
            rates["guarded_frac"] = (guarded - self._seen[1]) / steps
        new = ends - self._seen[2]
        total = sum(new.values())
        if total:
            for reason in sorted(set(ends) | set(self._seen[2]) | {"collision", "off_road"}):
                rates[f"end_{reason}"] = new.get(reason, 0) / total
        for k, v in rates.items():
            self.logger.record(f"env/{k}", v)
        self.last_rates = rates
        self._seen = (base.agent_steps, guarded, ends)

    def _on_rollout_end(self) -> None:
        for k, v in self.wrapper.pop_reward_stats().items():
            self.logger.record(f"reward/{k}", v)
        base = self.wrapper.base
        self.logger.record("env/agent_steps_total", base.agent_steps)
        self.logger.record("env/scene_episodes_total", base.episodes)
        self._log_env_rates(base)
        data = self.wrapper.pop_rollout()
        if data is not None and self._speed_col is not None and data.mask.any():
            self.last_speed = float(data.x[..., self._speed_col][data.mask].mean())
            self.logger.record("diag/speed_policy", self.last_speed)
            self.logger.record("diag/speed_expert", self.expert_speed)
            self.logger.record("diag/speed_gap", self.last_speed - self.expert_speed)
        if data is None or self.trainer.steps == 0:
            return
        stats = self.trainer.train(data)
        self.last_stats = stats
        for k, v in vars(stats).items():
            self.logger.record(f"discriminator/{k}", v)


__all__ = ["DiscriminatorCallback"]
