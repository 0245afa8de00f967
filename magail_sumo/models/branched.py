"""Command-branched networks of the SAC driving agent (:mod:`magail_sumo.training.sac`).

Every network is a shared ReLU trunk with one linear output head per high-level command
(left / straight / right, :mod:`magail_sumo.sensors.command`): all heads are computed, and each
row keeps the output of its own command's head (a gather), so a head's parameters get gradient
only from the samples of its command (exactly zero from the others).

Inputs: the raw observation (``obs_dim`` values, the command one-hot among them, normalised by
the model's :class:`~magail_sumo.models.normalizer.RunningNormalizer`) followed by one
*absorbing* flag (1 for the absorbing state of an agent that left, Discriminator-Actor-Critic
style; always 0 for a live agent), i.e. ``obs_dim + 1`` columns. The command of a row is the
argmax of its command columns (``command_cols``).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .normalizer import RunningNormalizer

#: number of commands (left, straight, right)
BRANCHES = 3
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class BranchedMLP(nn.Module):
    """ReLU MLP trunk + ``branches`` linear heads; ``forward(x, command)`` -> (N, out_dim), the
    head of each row's command (module doc).

    Weights as in the seed: He-normal trunk layers, Xavier-uniform heads, zero biases.
    """

    def __init__(self, in_dim: int, out_dim: int, hidden: tuple[int, ...] = (256, 256),
                 branches: int = BRANCHES) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        d = in_dim
        for h in hidden:
            lin = nn.Linear(d, h)
            nn.init.kaiming_normal_(lin.weight)
            nn.init.zeros_(lin.bias)
            layers += [lin, nn.ReLU()]
            d = h
        self.trunk = nn.Sequential(*layers)
        bound = math.sqrt(6.0 / (d + out_dim))  # xavier uniform of each (d -> out_dim) head
        self.head_weight = nn.Parameter(torch.empty(branches, d, out_dim).uniform_(-bound, bound))
        self.head_bias = nn.Parameter(torch.zeros(branches, out_dim))

    def heads(self, x: torch.Tensor) -> torch.Tensor:
        """(N, branches, out_dim): every head's output."""
        h = self.trunk(x)
        return torch.einsum("nh,bho->nbo", h, self.head_weight) + self.head_bias

    def forward(self, x: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        all_heads = self.heads(x)
        return all_heads[torch.arange(x.shape[0], device=x.device), command]


class BranchedSAC(nn.Module):
    """Actor, twin Q, value and target value networks of the SAC agent, all branched on the
    command, with one observation normaliser and the log entropy temperature.

    :param obs_dim: observation size (without the absorbing flag).
    :param command_cols: the observation columns of the command one-hot (left, straight,
        right).
    :param act_dim: action size (2: accel, steer, tanh-squashed into [-1, 1]).
    :param hidden: trunk sizes of every network. :param alpha: initial temperature.
    """

    def __init__(self, obs_dim: int, command_cols: tuple[int, ...], act_dim: int = 2,
                 hidden: tuple[int, ...] = (256, 256), alpha: float = 0.2) -> None:
        super().__init__()
        if len(command_cols) != BRANCHES:
            raise ValueError(f"{len(command_cols)} command columns, expected {BRANCHES}")
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.register_buffer("command_cols", torch.as_tensor(command_cols, dtype=torch.long))
        self.normalizer = RunningNormalizer(obs_dim)
        inp = obs_dim + 1
        self.actor = BranchedMLP(inp, 2 * act_dim, hidden)
        self.q1 = BranchedMLP(inp + act_dim, 1, hidden)
        self.q2 = BranchedMLP(inp + act_dim, 1, hidden)
        self.value = BranchedMLP(inp, 1, hidden)
        self.value_target = BranchedMLP(inp, 1, hidden)
        self.value_target.load_state_dict(self.value.state_dict())
        self.value_target.requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(alpha)))

    def command(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) command index of rows ``x`` (N, obs_dim [+ 1])."""
        return x[:, self.command_cols].argmax(dim=1)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Network input of rows ``x`` (N, obs_dim + 1): normalised observation + flag."""
        return torch.cat([self.normalizer(x[:, :self.obs_dim]), x[:, self.obs_dim:]], dim=1)

    def dist(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std) of the pre-tanh Gaussian of rows ``x`` (N, obs_dim + 1)."""
        out = self.actor(self.features(x), self.command(x))
        mu, log_std = out[:, :self.act_dim], out[:, self.act_dim:]
        return mu, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).exp()

    def _pre_tanh(self, x: torch.Tensor, generator: torch.Generator | None,
                  noise_scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(mean, std, ``u = mean + noise_scale·std·eps``) of rows ``x``, eps ~ N(0, I) drawn
        from ``generator``."""
        mu, std = self.dist(x)
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        return mu, std, mu + noise_scale * std * eps

    def sample(self, x: torch.Tensor, generator: torch.Generator | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparametrised tanh-Gaussian action (N, act_dim) and its log-density (N,)."""
        mu, std, u = self._pre_tanh(x, generator)
        a = torch.tanh(u)
        logp = torch.distributions.Normal(mu, std).log_prob(u)
        # tanh change of variables, numerically stable: log(1 - tanh(u)^2)
        logp = logp - 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
        return a, logp.sum(dim=1)

    def act(self, x: torch.Tensor, deterministic: bool = False,
            generator: torch.Generator | None = None, noise_scale: float = 1.0
            ) -> torch.Tensor:
        """Actions (N, act_dim) in [-1, 1] of rows ``x``: sampled (the draws of
        :meth:`sample`, the noise times ``noise_scale``), or tanh of the mean."""
        if deterministic:
            return torch.tanh(self.dist(x)[0])
        return torch.tanh(self._pre_tanh(x, generator, noise_scale)[2])

    def q(self, x: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) twin Q values of rows ``x`` and actions ``a``."""
        f, c = torch.cat([self.features(x), a], dim=1), self.command(x)
        return self.q1(f, c)[:, 0], self.q2(f, c)[:, 0]

    def v(self, x: torch.Tensor, target: bool = False) -> torch.Tensor:
        """(N,) value (or target value) of rows ``x``."""
        net = self.value_target if target else self.value
        return net(self.features(x), self.command(x))[:, 0]
