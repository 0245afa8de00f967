"""The discriminator's training: expert vs policy scene steps (the GAIL loss with gradient and
logit penalties, :mod:`.discriminator_loss`), the half of adversarial imitation apart from the
reward wrapper (:mod:`.reward`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from magail_sumo.expert import ExpertDataset, SceneSteps

from .discriminator_loss import DiscriminatorLossConfig, discriminator_loss


@dataclass
class DiscriminatorStats:
    loss: float
    bce: float
    gradient_penalty: float
    logit_penalty: float
    expert_accuracy: float
    policy_accuracy: float


class DiscriminatorTrainer:
    """Fits the discriminator on expert vs policy scene steps (AdamW, GAIL loss with GP).

    :param discriminator: the reward net (its :class:`RunningNormalizer` is updated with the
        policy and expert tokens of each call before the gradient steps).
    :param expert: expert demonstrations.
    :param steps: gradient steps per call. :param batch_size: scene steps per side and step.
    :param seed: seed of the batch sampling (its state is part of :meth:`state_dict`).
    """

    def __init__(self, discriminator: torch.nn.Module, expert: ExpertDataset, steps: int = 50,
                 batch_size: int = 32, learning_rate: float = 1e-3, weight_decay: float = 1e-4,
                 loss: DiscriminatorLossConfig | None = None, seed: int = 0,
                 device: str = "cpu") -> None:
        self.discriminator = discriminator
        self.expert = expert
        if getattr(discriminator, "uses_poses", False):
            expert.require_poses(f"the {type(discriminator).__name__}")
        self.steps, self.batch_size = steps, batch_size
        self.loss_config = loss or DiscriminatorLossConfig()
        self.optimizer = torch.optim.AdamW(discriminator.parameters(), lr=learning_rate,
                                           weight_decay=weight_decay)
        self.rng = np.random.default_rng(seed)
        self.device = torch.device(device)

    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict(), "rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        self.rng.bit_generator.state = state["rng"]

    def _t(self, a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, device=self.device)

    def train(self, policy: SceneSteps) -> DiscriminatorStats:
        """``steps`` gradient steps on expert batches vs batches of ``policy`` scene steps."""
        disc = self.discriminator
        poses = getattr(disc, "uses_poses", False)
        present = policy.x[policy.mask]
        exp = self.expert.sample_scene_steps(max(1, len(policy.x)), self.rng)
        disc.normalizer.update(self._t(present))
        disc.normalizer.update(self._t(exp.x[exp.mask]))
        disc.train()
        acc = np.zeros(6)
        for _ in range(self.steps):
            e = self.expert.sample_scene_steps(self.batch_size, self.rng)
            idx = self.rng.integers(0, len(policy.x), self.batch_size)
            px, pm = policy.x[idx], policy.mask[idx]
            v = int(pm.any(axis=0).nonzero()[0].max()) + 1
            pos = {}
            if poses:
                pos = {"expert_pos": self._t(e.pos), "policy_pos": self._t(policy.pos[idx, :v])}
            out = discriminator_loss(disc, self._t(e.x), self._t(e.mask), self._t(px[:, :v]),
                                     self._t(pm[:, :v]), self.loss_config, **pos)
            self.optimizer.zero_grad(set_to_none=True)
            out.total.backward()
            self.optimizer.step()
            acc += [float(out.total.detach()), out.bce, out.gradient_penalty, out.logit_penalty,
                    out.expert_accuracy, out.policy_accuracy]
        disc.eval()
        return DiscriminatorStats(*(acc / max(self.steps, 1)).tolist())


__all__ = ["DiscriminatorStats", "DiscriminatorTrainer"]
