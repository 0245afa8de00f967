"""PPO over agent slots: a masked rollout buffer, parameter sharing, KL-adaptive learning rate.

All slots of :class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` share one policy (SB3 treats
them as vector envs). Free slot-steps (no agent in the slot) are recorded by SB3's rollout loop
like any step, but :class:`MaskedRolloutBuffer` remembers which were real and its :meth:`get`
only yields those, so they never reach the PPO loss nor the advantage normalisation. The env
marks a slot re-assignment as an episode start, so GAE never bootstraps from one agent into
another (and the free steps in between carry no weight).
"""

from __future__ import annotations

from typing import Any, Callable, Generator

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import RolloutBufferSamples


class MaskedRolloutBuffer(RolloutBuffer):
    """SB3 rollout buffer that drops inactive slot-steps from the minibatches.

    :attr:`mask_source` is called at every :meth:`add` and returns the (n_envs,) bool mask of the
    observation being added (``MultiSceneVecEnv.prev_slot_active``); None: all active.
    """

    mask_source: Callable[[], np.ndarray] | None = None
    #: called once per rollout before the returns are computed; gives (buffer_size, n_envs)
    #: rewards added to those recorded step by step (the deferred imitation rewards)
    reward_source: Callable[[], np.ndarray] | None = None

    def reset(self) -> None:
        super().reset()
        self.active = np.zeros((self.buffer_size, self.n_envs), bool)

    def add(self, *args: Any, **kwargs: Any) -> None:
        self.active[self.pos] = True if self.mask_source is None else self.mask_source()
        super().add(*args, **kwargs)

    def compute_returns_and_advantage(self, last_values, dones) -> None:
        if self.reward_source is not None:
            extra = np.asarray(self.reward_source(), np.float32)
            if extra.shape != self.rewards.shape:
                raise ValueError(f"deferred rewards have shape {extra.shape}, the buffer "
                                 f"{self.rewards.shape}")
            self.rewards += extra
        super().compute_returns_and_advantage(last_values, dones)

    @property
    def num_active(self) -> int:
        return int(self.active.sum())

    def get(self, batch_size: int | None = None) -> Generator[RolloutBufferSamples, None, None]:
        assert self.full, "the rollout buffer is not full"
        if not self.generator_ready:
            for name in ("observations", "actions", "values", "log_probs", "advantages",
                         "returns"):
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
            self.active_flat = self.active.swapaxes(0, 1).reshape(-1)
            self.generator_ready = True
        idx = np.flatnonzero(self.active_flat)
        indices = idx[np.random.permutation(len(idx))]
        if batch_size is None:
            batch_size = len(indices)
        for start in range(0, len(indices), batch_size):
            yield self._get_samples(indices[start:start + batch_size])


class MaskedPPO(PPO):
    """SB3 PPO whose rollout buffer is a :class:`MaskedRolloutBuffer` reading the env's slot mask.

    Same arguments as :class:`~stable_baselines3.PPO`; the env (possibly wrapped) must reach a
    :class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` through ``.unwrapped``.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["rollout_buffer_class"] = MaskedRolloutBuffer
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        base = self.env.unwrapped if self.env is not None else None
        if base is not None and hasattr(base, "prev_slot_active"):
            self.rollout_buffer.mask_source = lambda: base.prev_slot_active
        if getattr(self.env, "deferred", False):
            self.rollout_buffer.reward_source = self.env.flush_rewards

    def set_learning_rate(self, lr: float) -> None:
        """Constant learning rate ``lr`` from the next update on."""
        self.learning_rate = float(lr)
        self._setup_lr_schedule()


def adapt_learning_rate(lr: float, kl: float, desired_kl: float, lr_min: float, lr_max: float
                        ) -> float:
    """The seed's rule: halve when kl > 2·desired, ×1.5 when kl < desired/2, within bounds."""
    if kl > 2.0 * desired_kl:
        lr = max(lr_min, lr / 2.0)
    elif 0.0 < kl < desired_kl / 2.0:
        lr = min(lr_max, lr * 1.5)
    return lr


class KLAdaptiveLR(BaseCallback):
    """Adapt the PPO learning rate to the approximate KL of the last update.

    After every PPO update (read from ``train/approx_kl`` before the next rollout or at the end of
    ``learn``), apply :func:`adapt_learning_rate`; the current lr is logged as ``train/kl_lr``.

    :param desired_kl: KL target. :param lr_min, lr_max: bounds.
    """

    def __init__(self, desired_kl: float, lr_min: float = 1e-5, lr_max: float = 1e-2,
                 verbose: int = 0) -> None:
        super().__init__(verbose)
        self.desired_kl = desired_kl
        self.lr_min, self.lr_max = lr_min, lr_max
        self._seen_updates = -1

    def _maybe_adapt(self) -> None:
        model = self.model
        if model._n_updates == self._seen_updates or model._n_updates == 0:
            return
        self._seen_updates = model._n_updates
        kl = model.logger.name_to_value.get("train/approx_kl")
        if kl is None:
            return
        lr = adapt_learning_rate(float(model.learning_rate), float(kl), self.desired_kl,
                                 self.lr_min, self.lr_max)
        model.set_learning_rate(lr)
        model.logger.record("train/kl_lr", lr)

    def _on_training_start(self) -> None:
        if self._seen_updates < 0:
            self._seen_updates = self.model._n_updates

    def _on_rollout_start(self) -> None:
        self._maybe_adapt()

    def _on_training_end(self) -> None:
        self._maybe_adapt()

    def _on_step(self) -> bool:
        return True
