"""The GAIL discriminator objective over per-token logits of scene steps.

``loss = 0.5·(BCE(policy tokens → 0) + BCE(expert tokens → 1))
       + gp_coef · mean_token ||∂ D(x_expert) / ∂ x||²  +  logit_reg · Σ ||W_head||²``

averaged over present tokens only; weight decay is the optimiser's (AdamW). The gradient
penalty is taken with respect to the normalised expert features, per token (for the decomposed
discriminator, whose forwards also take the vehicles' poses, not with respect to the poses).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel


@dataclass(frozen=True)
class DiscriminatorLossConfig:
    gp_coef: float = 0.1
    logit_reg: float = 0.25


@dataclass
class DiscriminatorLoss:
    """The loss and its parts for logging (detached floats except ``total``)."""

    total: torch.Tensor
    bce: float
    gradient_penalty: float
    logit_penalty: float
    expert_accuracy: float
    policy_accuracy: float


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(values.dtype)
    return (values * m).sum() / m.sum().clamp(min=1.0)


def pose_args(model: nn.Module, pos: torch.Tensor | None) -> tuple:
    """The extra forward arguments of ``model``: ``(pos,)`` for a discriminator that
    ``uses_poses`` (ValueError when ``pos`` is None), else none (``pos`` is ignored)."""
    if not getattr(model, "uses_poses", False):
        return ()
    if pos is None:
        raise ValueError(f"{type(model).__name__} needs the vehicles' poses (B, V, 3)")
    return (pos,)


def discriminator_loss(model: nn.Module, expert_x: torch.Tensor, expert_mask: torch.Tensor,
                       policy_x: torch.Tensor, policy_mask: torch.Tensor,
                       config: DiscriminatorLossConfig | None = None, *,
                       expert_pos: torch.Tensor | None = None,
                       policy_pos: torch.Tensor | None = None) -> DiscriminatorLoss:
    """Loss of ``model`` (a discriminator with ``forward_normalized``) on one batch.

    :param expert_x, policy_x: raw features (B, V, F); normalised here with the model's normaliser.
    :param expert_mask, policy_mask: (B, V) present tokens.
    :param expert_pos, policy_pos: (B, V, 3) poses (x, y m, yaw rad, scene frame) at the step
        of s, for a discriminator that ``uses_poses``; ignored by the others.
    """
    cfg = config or DiscriminatorLossConfig()
    xe = model.normalizer(expert_x).detach().requires_grad_(True)
    xp = model.normalizer(policy_x).detach()
    with sdpa_kernel(SDPBackend.MATH):  # fused attention kernels lack double backward
        le, _ = model.forward_normalized(xe, expert_mask, *pose_args(model, expert_pos))
    lp, _ = model.forward_normalized(xp, policy_mask, *pose_args(model, policy_pos))
    bce = 0.5 * (_masked_mean(-F.logsigmoid(-lp), policy_mask)
                 + _masked_mean(-F.logsigmoid(le), expert_mask))
    grad, = torch.autograd.grad((le * expert_mask).sum(), xe, create_graph=True)
    gp = _masked_mean(grad.pow(2).sum(-1), expert_mask)
    reg = sum(w.pow(2).sum() for w in model.head_weights())
    total = bce + cfg.gp_coef * gp + cfg.logit_reg * reg
    with torch.no_grad():
        acc_e = _masked_mean((le > 0).float(), expert_mask)
        acc_p = _masked_mean((lp < 0).float(), policy_mask)
    return DiscriminatorLoss(total, float(bce.detach()), float(gp.detach()), float(reg.detach()),
                             float(acc_e), float(acc_p))
