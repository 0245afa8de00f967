"""Behavioural cloning of the expert (s, a) pairs into a :class:`TanhGaussianPolicy`.

Maximises ``log pi(a_expert | s)`` of the actor (MLP + state-independent log-std; the critic is
untouched), so the result is also a PPO initialisation. Expert actions are clipped to
``±(1 − 1e-3)`` (tanh cannot reach ±1). :func:`expert_nll` is also PPO's behavioural-cloning
regulariser (``ppo.bc_coef``, :class:`~magail_sumo.training.gail.ppo.MaskedPPO`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from magail_sumo.config import record_run, to_dict
from magail_sumo.expert import ExpertDataset
from magail_sumo.models.policies import TanhGaussianPolicy
from magail_sumo.outputs import inside, inside_dir

from .algorithms import load_expert
from .checkpoints import CHECKPOINT_FORMAT, encode_state, save_state
from .policies import make_policy
from .rng import rng_state
from .run_dir import claim_run_dir

if TYPE_CHECKING:
    from .config import TrainConfig

#: expert actions are clipped to ±this before the tanh is inverted (tanh cannot reach ±1)
ACTION_BOUND = 0.999


def expert_actions(action: np.ndarray, device) -> torch.Tensor:
    """Expert actions (B, 2) in [-1, 1] as a tensor clipped to ±:data:`ACTION_BOUND`."""
    return torch.as_tensor(np.clip(action, -ACTION_BOUND, ACTION_BOUND), device=device)


def expert_nll(policy: TanhGaussianPolicy, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``−mean log pi(a | s)`` of expert pairs under the tanh-Gaussian actor,
    ``log pi(a|s) = Σ_k [log N(atanh a_k; mu_k(s), sigma_k) − log(1 − a_k²)]``
    (``a`` clipped by :func:`expert_actions`)."""
    return -policy.action_log_prob(s, a).mean()


def behavioural_cloning(policy: TanhGaussianPolicy, expert: ExpertDataset, epochs: int,
                        batch_size: int = 256, learning_rate: float = 1e-3, seed: int = 0,
                        log=None) -> list[float]:
    """Fit the actor of ``policy``; the mean negative log-likelihood of each epoch.

    :param epochs: passes over all expert pairs (shuffled with ``seed``).
    :param log: optional callable receiving (epoch, nll).
    """
    params = list(policy.mlp_extractor.policy_net.parameters()) + \
        list(policy.action_net.parameters()) + [policy.log_std]
    opt = torch.optim.Adam(params, lr=learning_rate)
    rng = np.random.default_rng(seed)
    s_all = torch.as_tensor(expert.s, device=policy.device)
    a_all = expert_actions(expert.action, policy.device)
    policy.set_training_mode(True)
    history = []
    for epoch in range(epochs):
        order = torch.as_tensor(rng.permutation(len(expert)), device=policy.device)
        total, n = 0.0, 0
        for start in range(0, len(order), batch_size):
            idx = order[start:start + batch_size]
            nll = expert_nll(policy, s_all[idx], a_all[idx])
            opt.zero_grad(set_to_none=True)
            nll.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            opt.step()
            total += float(nll.detach()) * len(idx)
            n += len(idx)
        history.append(total / max(n, 1))
        if log is not None:
            log(epoch, history[-1])
    policy.set_training_mode(False)
    return history


def train_bc(cfg: TrainConfig, run_dir: Path, ckpt: dict | None, log: Callable[[str], None],
             progress: Callable[[str, int, int], None]) -> Path:
    """The ``bc`` algorithm: behavioural cloning of the run's expert data into a fresh policy,
    saved as ``checkpoints/latest.pt`` (update 0); a run with a checkpoint is complete."""
    expert = load_expert(cfg)
    if ckpt is not None:
        log(f"{run_dir}: behavioural cloning run already complete")
        return run_dir
    claim_run_dir(run_dir, resumed=False)
    record_run(run_dir, cfg)
    policy = make_policy(cfg)
    policy.obs_normalizer.update(torch.as_tensor(expert.s))

    def bc_log(e: int, v: float) -> None:
        log(f"bc epoch {e + 1}: nll {v:.4f}")
        progress("bc", e + 1, cfg.bc.epochs)

    behavioural_cloning(policy, expert, cfg.bc.epochs, cfg.bc.batch_size, cfg.bc.learning_rate,
                        cfg.seed, log=bc_log)
    inside_dir(run_dir, "checkpoints")
    state = encode_state({"format": CHECKPOINT_FORMAT, "update": 0, "config": to_dict(cfg),
                           "policy": policy.state_dict(), "rng": rng_state()})
    save_state(state, inside(run_dir, "checkpoints", "latest.pt"))
    log(f"{run_dir}: policy saved")
    return run_dir
