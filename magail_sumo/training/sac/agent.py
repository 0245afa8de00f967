"""The SAC agent: the command-branched networks and their losses, optimisers and schedules
(:mod:`magail_sumo.training.sac`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from magail_sumo.models.branched import BranchedSAC
from magail_sumo.sensors.observation import COMMAND_NAMES, ObservationConfig, observation_names

from ..checkpoints import (load_into)
from ..config import TrainConfig
from .buffer import ACT_DIM
from .config import SACConfig


def command_columns(obs: ObservationConfig) -> tuple[int, ...]:
    """Columns of the command one-hot in the observation (ValueError without the feature)."""
    names = observation_names(obs)
    if not obs.command:
        raise ValueError("the observation has no route command (env.observation.command)")
    return tuple(names.index(n) for n in COMMAND_NAMES)


def make_sac_model(cfg: TrainConfig) -> BranchedSAC:
    """A fresh :class:`BranchedSAC` for the config's observation."""
    obs = cfg.env.observation
    return BranchedSAC(len(observation_names(obs)), command_columns(obs), ACT_DIM,
                       cfg.sac.hidden, cfg.sac.alpha).to(cfg.device)


@dataclass
class SacStats:
    value_loss: float
    q_loss: float
    policy_loss: float
    alpha: float
    entropy: float


class SacAgent:
    """The networks, optimisers, StepLR schedules and the gradient step (module doc)."""

    NETS = ("actor", "q1", "q2", "value")

    def __init__(self, model: BranchedSAC, config: SACConfig) -> None:
        self.model, self.config = model, config
        c = config
        self.optimizers = {n: torch.optim.Adam(getattr(model, n).parameters(), lr=c.learning_rate)
                           for n in self.NETS}
        self.optimizers["alpha"] = torch.optim.Adam([model.log_alpha], lr=c.learning_rate)
        self.schedulers = {n: torch.optim.lr_scheduler.StepLR(self.optimizers[n], c.lr_step,
                                                              gamma=c.lr_gamma)
                           for n in self.NETS}
        self.target_entropy = float(-ACT_DIM if c.target_entropy is None else c.target_entropy)
        self.gradient_steps = 0

    def state_dict(self) -> dict:
        return {"optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
                "gradient_steps": self.gradient_steps}

    def load_state_dict(self, state: dict, where: Path) -> None:
        for k, o in self.optimizers.items():
            load_into(o, state["optimizers"][k], f"optimizer {k}", where)
        for k, s in self.schedulers.items():
            load_into(s, state["schedulers"][k], f"scheduler {k}", where)
        steps = state["gradient_steps"]
        if type(steps) is not int or steps < 0:
            raise ValueError("gradient_steps is not a count")
        self.gradient_steps = steps

    def learning_rate(self) -> float:
        return float(self.optimizers["actor"].param_groups[0]["lr"])

    def train_step(self, batch: dict[str, torch.Tensor]) -> SacStats:
        """One gradient step of every network on a batch (module doc), then the soft target
        update and the StepLR steps."""
        from stable_baselines3.common.utils import polyak_update

        m, c = self.model, self.config
        dev = m.log_alpha.device
        s, a, r = batch["obs"].to(dev), batch["action"].to(dev), batch["reward"].to(dev)
        s2, done = batch["next_obs"].to(dev), batch["done"].to(dev)
        alpha = m.log_alpha.exp().detach()
        a_new, logp = m.sample(s)
        q_new = torch.min(*m.q(s, a_new))
        policy_loss = (alpha * logp - q_new).mean()
        self._step("actor", policy_loss)
        value_loss = nn.functional.mse_loss(m.v(s), (q_new - alpha * logp).detach())
        self._step("value", value_loss)
        with torch.no_grad():
            target = r + c.gamma * (1.0 - done) * m.v(s2, target=True)
        q1, q2 = m.q(s, a)
        q_loss = nn.functional.mse_loss(q1, target) + nn.functional.mse_loss(q2, target)
        for n in ("q1", "q2"):
            self.optimizers[n].zero_grad(set_to_none=True)
        q_loss.backward()
        self.optimizers["q1"].step()
        self.optimizers["q2"].step()
        if c.auto_alpha:
            alpha_loss = -(m.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self._step("alpha", alpha_loss)
        polyak_update(m.value.parameters(), m.value_target.parameters(), c.tau)
        for sch in self.schedulers.values():
            sch.step()
        self.gradient_steps += 1
        return SacStats(*(float(v.detach()) for v in (value_loss, q_loss, policy_loss,
                                                       m.log_alpha.exp(), -logp.mean())))

    def _step(self, name: str, loss: torch.Tensor) -> None:
        opt = self.optimizers[name]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
