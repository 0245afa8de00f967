"""Decomposed GAIL discriminator (after DecompGAIL, arXiv 2510.06913): each vehicle's realism
from an ego–map term plus distance-weighted ego–neighbour pairwise terms.

A discriminator that judges a vehicle together with its whole neighbourhood (the entangled
MAGAIL transformer) penalises a vehicle that drove well for its neighbours' unrealistic
behaviour. Here the logit of vehicle ``i`` is a sum of parts that each look at ``i`` and at
most one other vehicle, weighted by their distance.

Inputs: tokens ``x`` (B, V, F) = ``concat(s, s')`` of each vehicle of a scene step, a (B, V)
mask of present vehicles, and poses ``pos`` (B, V, 3) = (x, y, yaw) of each vehicle at the step
of ``s``: scene frame, metres and rad counter-clockwise from +x (the env's bicycle state,
:meth:`~magail_sumo.env.driving_env.SumoDrivingEnv.agent_states`). ``x̂`` = the token
normalised by the running normaliser with the ignored features zeroed (as the other
discriminators).

What the token holds (observation layout ``"ego"``,
:func:`~magail_sumo.sensors.observation.observation_names`, in ``s`` and in ``s'``):

* ego kinematics: ``speed`` (m/s), ``prev_accel`` / ``prev_steer`` (the normalised action),
  ``length`` / ``width`` (m);
* map context, all in the ego frame: ``lane_lateral`` (m) and ``lane_heading_error`` (rad) to
  the current lane, ``side_*`` (road-edge detector, m), ``lane_line_*`` (painted lane lines,
  m), ``light`` (signal of the current lane), the destination ``dest_x`` / ``dest_y`` /
  ``dest_distance`` (m) and route direction ``route_cos`` / ``route_sin``;
* ``lidar_*`` (m to the other road users' boxes): the vehicle's own view of its surroundings.
  It stays in the ego–map token (it is what the vehicle reacted to); use
  ``discriminator.ignore_features`` to hide it.

So the ego–map head needs no separate map input: the token is already the vehicle's state in
its map context.

Equations (``N(i)``: the at most ``K`` = ``max_neighbors`` nearest present vehicles ``j ≠ i``
with ``d_ij ≤ R`` = ``radius``; ties at equal distance are broken by slot order):

* ego–map term: ``e_i = MLP_e(x̂_i)``;
* distance ``d_ij = ||(x_j − x_i, y_j − y_i)||`` (m, box centres); pose of ``j`` in ``i``'s
  frame: ``dx = cos ψ_i·Δx + sin ψ_i·Δy``, ``dy = −sin ψ_i·Δx + cos ψ_i·Δy`` (m),
  ``Δψ = ψ_j − ψ_i``;
* pairwise term: ``l_ij = MLP_p([x̂_i, x̂_j, dx/R, dy/R, cos Δψ, sin Δψ, d_ij/R])`` (the
  lengths scaled by ``R`` so the head sees values in [−1, 1]);
* weight: ``w_ij = α·exp(−d_ij/β)`` (``normalize_weights``:
  ``w_ij = α·exp(−d_ij/β) / Σ_{k∈N(i)} exp(−d_ik/β)``, so the weights of a vehicle with
  neighbours sum to ``α`` whatever their number); 0 for ``j ∉ N(i)``;
* per-vehicle logit ``D_i = e_i + Σ_{j∈N(i)} w_ij·l_ij``; scene logit = mean of ``D_i`` over
  the present vehicles;
* social reward (:meth:`DecomposedDiscriminator.social_reward`): ``r_i ← r_i + λ·Σ_j w_ij·r_j``.

Absent vehicles neither receive nor give pairwise terms (their logit is 0); a vehicle without
neighbours gets its ego term only. Everything runs on (B, V, K) arrays — no loop over vehicles.
The first layer of ``MLP_p`` is linear in its three input blocks, so its two token blocks are
applied once per present vehicle and gathered per pair, not once per pair (K times fewer rows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from magail_sumo.config import check, check_positive, check_sizes, show

from .discriminator import _TokenInput

#: columns of the pair head's geometry input: dx/R, dy/R, cos Δψ, sin Δψ, d/R
GEOMETRY_DIM = 5


@dataclass(frozen=True)
class DecomposedConfig:
    """Sizes and geometry of :class:`DecomposedDiscriminator` (module doc for the equations).

    :param ego_hidden: hidden sizes of the ego–map MLP (tanh; empty: linear).
    :param pair_hidden: hidden sizes of the ego–neighbour pairwise MLP (tanh; empty: linear).
    :param alpha: weight scale α of the pairwise terms (0: ego–map term only).
    :param beta: decay length β of the weights ``α·exp(−d/β)`` (m).
    :param radius: neighbours farther than this (m, centre to centre) give no pairwise term.
    :param max_neighbors: K, the nearest neighbours within ``radius`` taken per vehicle.
    :param social_coef: λ of the social reward ``r_i + λ·Σ_j w_ij·r_j`` (0: off).
    :param normalize_weights: divide each vehicle's weights by ``Σ_j exp(−d_ij/β)`` (they sum
        to α) instead of the absolute ``α·exp(−d_ij/β)``.
    """

    ego_hidden: tuple[int, ...] = (256, 256)
    pair_hidden: tuple[int, ...] = (128, 128)
    alpha: float = 1.0
    beta: float = 10.0
    radius: float = 30.0
    max_neighbors: int = 8
    social_coef: float = 0.0
    normalize_weights: bool = False

    def __post_init__(self) -> None:
        check_sizes(self, "ego_hidden", "pair_hidden")
        check_positive(self, "beta", "radius")
        check_positive(self, "alpha", "social_coef", allow_zero=True)
        check(self.max_neighbors >= 1, "max_neighbors",
              f"must be >= 1, got {show(self.max_neighbors)}")


@dataclass(frozen=True)
class Neighbours:
    """The neighbours of every vehicle of a batch of scene steps (K = columns kept).

    :param index: (B, V, K) slot of each neighbour (any value where not ``valid``).
    :param valid: (B, V, K) the entry is a neighbour (present, not itself, within the radius,
        among the K nearest).
    :param weight: (B, V, K) ``w_ij`` (0 where not valid).
    :param geometry: (B, V, K, 5) ``dx/R, dy/R, cos Δψ, sin Δψ, d/R`` (0 where not valid).
    :param distance: (B, V, K) ``d_ij`` in m (inf where not valid).
    """

    index: torch.Tensor
    valid: torch.Tensor
    weight: torch.Tensor
    geometry: torch.Tensor
    distance: torch.Tensor


def _tanh_mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers between consecutive ``sizes`` with tanh between them (none after)."""
    layers: list[nn.Module] = []
    for k in range(len(sizes) - 1):
        if k:
            layers.append(nn.Tanh())
        layers.append(nn.Linear(sizes[k], sizes[k + 1]))
    return nn.Sequential(*layers)


def _gather_slots(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[b, index[b, i, k]]``: (B, V, ...) gathered to (B, V, K, ...)."""
    b = torch.arange(values.shape[0], device=values.device).view(-1, 1, 1)
    return values[b, index]


class DecomposedBase(_TokenInput):
    """What every decomposed discriminator shares (module doc): the neighbour search, the
    weighted sum ``D_i = e_i + Σ_j w_ij·l_ij``, the scene logit and the social reward. A
    subclass gives the terms (:meth:`terms`); its forwards take the poses ``pos`` (B, V, 3)
    too. ``config`` is a :class:`DecomposedConfig` (its geometry fields are used here)."""

    #: forwards take the vehicles' poses (scene frame x, y in m, yaw in rad) as a third argument
    uses_poses = True
    config: DecomposedConfig

    def forward(self, x: torch.Tensor, mask: torch.Tensor, pos: torch.Tensor,
                neighbours: Neighbours | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits of raw tokens x (B, V, F) with mask (B, V) and poses (B, V, 3);
        ``neighbours``: :meth:`neighbours` of ``pos`` and ``mask`` when already computed."""
        bi, vi = mask.nonzero(as_tuple=True)  # normalise the present vehicles' tokens only
        return self._logits(self.normalizer(x[bi, vi]), bi, vi, mask, pos, neighbours)

    @torch.no_grad()
    def neighbours(self, pos: torch.Tensor, mask: torch.Tensor) -> Neighbours:
        """:class:`Neighbours` of every present vehicle from the poses (B, V, 3) (scene frame,
        m, rad) and the mask (B, V). Not differentiable (poses are no features)."""
        cfg = self.config
        b, v, _ = pos.shape
        pos = pos.to(torch.float32)
        x, y, yaw = pos[..., 0], pos[..., 1], pos[..., 2]
        # (B, V_i, V_j) components of p_j − p_i, kept apart: the pairwise tensors are the cost
        # of this search in a city (V = hundreds), so no (B, V, V, 2) tensor and in-place masks
        ddx = x[:, None, :] - x[:, :, None]
        ddy = y[:, None, :] - y[:, :, None]
        d = torch.sqrt(ddx * ddx + ddy * ddy)
        eye = torch.eye(v, dtype=torch.bool, device=pos.device)
        ok = (mask[:, :, None] & mask[:, None, :]).logical_and_(~eye) \
            .logical_and_(d <= cfg.radius)
        d = d.masked_fill_(~ok, math.inf)
        dist, index = torch.topk(d, min(cfg.max_neighbors, v), dim=-1, largest=False,
                                 sorted=True)
        valid = torch.isfinite(dist)
        relx, rely = torch.gather(ddx, 2, index), torch.gather(ddy, 2, index)  # (B, V, K)
        cos_i, sin_i = torch.cos(yaw)[..., None], torch.sin(yaw)[..., None]
        dx = cos_i * relx + sin_i * rely
        dy = -sin_i * relx + cos_i * rely
        dyaw = _gather_slots(yaw, index) - yaw[..., None]
        r = cfg.radius
        geometry = torch.stack([dx / r, dy / r, torch.cos(dyaw), torch.sin(dyaw),
                                torch.where(valid, dist, 0.0) / r], dim=-1)
        geometry = torch.where(valid[..., None], geometry, 0.0)
        if cfg.normalize_weights:
            score = torch.where(valid, -dist / cfg.beta, -math.inf)
            weight = cfg.alpha * torch.softmax(score, dim=-1)
        else:
            weight = cfg.alpha * torch.exp(-dist / cfg.beta)
        weight = torch.where(valid, weight, 0.0)  # also the NaN of all-invalid softmax rows
        return Neighbours(index, valid, weight, geometry, dist)

    def forward_normalized(self, x: torch.Tensor, mask: torch.Tensor, pos: torch.Tensor,
                           neighbours: Neighbours | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits of already-normalised tokens: ((B, V) ``D_i``, (B,) scene logits)."""
        bi, vi = mask.nonzero(as_tuple=True)
        return self._logits(x[bi, vi], bi, vi, mask, pos, neighbours)

    def _logits(self, xp: torch.Tensor, bi: torch.Tensor, vi: torch.Tensor, mask: torch.Tensor,
                pos: torch.Tensor, neighbours: Neighbours | None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward_normalized` from the normalised tokens ``xp`` (N, F) of the present
        vehicles ``(bi, vi)`` (``mask.nonzero()``, in that order)."""
        if pos is None:
            raise ValueError("the decomposed discriminator needs the vehicles' poses")
        nb = self.neighbours(pos, mask) if neighbours is None else neighbours
        ego, pair = self.terms(xp * self.feature_mask, bi, vi, mask, nb)
        tokens = (ego + (nb.weight.to(xp.dtype) * pair).sum(-1)).masked_fill(~mask, 0.0)
        m = mask.to(tokens.dtype)
        return tokens, (tokens * m).sum(1) / m.sum(1).clamp(min=1.0)

    def terms(self, xp: torch.Tensor, bi: torch.Tensor, vi: torch.Tensor, mask: torch.Tensor,
              nb: Neighbours) -> tuple[torch.Tensor, torch.Tensor]:
        """``(e, l)``: (B, V) ego–map terms and (B, V, K) pairwise terms (0 where absent or
        not a neighbour) from the masked normalised tokens ``xp`` (N, F) of the present
        vehicles ``(bi, vi)``."""
        raise NotImplementedError


    @torch.no_grad()
    def social_reward(self, rewards: torch.Tensor, pos: torch.Tensor, mask: torch.Tensor,
                      coef: float, neighbours: Neighbours | None = None) -> torch.Tensor:
        """``r_i + coef·Σ_{j∈N(i)} w_ij·r_j`` for (B, V) rewards (0 stays 0 where absent);
        ``neighbours``: :meth:`neighbours` of ``pos`` and ``mask`` when already computed."""
        if coef == 0.0:
            return rewards
        nb = self.neighbours(pos, mask) if neighbours is None else neighbours
        social = (nb.weight.to(rewards.dtype) * _gather_slots(rewards, nb.index)).sum(-1)
        return (rewards + coef * social).masked_fill(~mask, 0.0)


class DecomposedDiscriminator(DecomposedBase):
    """Ego–map plus distance-weighted ego–neighbour discriminator with MLP heads (module doc);
    same outputs as the other discriminators ((B, V) per-vehicle logits, (B,) scene logits) but
    its forwards also take the poses ``pos`` (B, V, 3)."""

    def __init__(self, feature_dim: int, config: DecomposedConfig | None = None) -> None:
        super().__init__(feature_dim)
        cfg = config or DecomposedConfig()
        self.config = cfg
        self.ego = _tanh_mlp([feature_dim, *cfg.ego_hidden, 1])
        first = cfg.pair_hidden[0] if cfg.pair_hidden else 1
        # first layer of MLP_p over [x̂_i, x̂_j, geometry], split by input block
        self.pair_i = nn.Linear(feature_dim, first)
        self.pair_j = nn.Linear(feature_dim, first, bias=False)
        self.pair_geometry = nn.Linear(GEOMETRY_DIM, first, bias=False)
        # the rest of MLP_p: tanh, the other layers; nothing when MLP_p is linear
        self.pair_rest = nn.Sequential(nn.Tanh(), *_tanh_mlp([*cfg.pair_hidden, 1])) \
            if cfg.pair_hidden else nn.Sequential()

    def head_weights(self) -> list[torch.Tensor]:
        """Weights of the output layers (for the logit regulariser)."""
        if self.config.pair_hidden:
            pair = [self.pair_rest[-1].weight]
        else:
            pair = [self.pair_i.weight, self.pair_j.weight, self.pair_geometry.weight]
        return [self.ego[-1].weight, *pair]

    def terms(self, xp: torch.Tensor, bi: torch.Tensor, vi: torch.Tensor, mask: torch.Tensor,
              nb: Neighbours) -> tuple[torch.Tensor, torch.Tensor]:
        # the heads run on present vehicles and valid pairs only (a padded batch of a large
        # scene is mostly absent slots and missing neighbours); the rest stays 0
        ego = xp.new_zeros(mask.shape).index_put((bi, vi), self.ego(xp).squeeze(-1))
        pb, pv, pk = nb.valid.nonzero(as_tuple=True)
        # row of each vehicle among the present ones; the first layer's token blocks run once
        # per present vehicle and are gathered per pair (about K times fewer rows)
        row = torch.zeros(mask.shape, dtype=torch.long, device=xp.device)
        row[bi, vi] = torch.arange(bi.numel(), device=xp.device)
        pre = (self.pair_i(xp)[row[pb, pv]] + self.pair_j(xp)[row[pb, nb.index[pb, pv, pk]]]
               + self.pair_geometry(nb.geometry[pb, pv, pk].to(xp.dtype)))  # (P, H)
        pair = xp.new_zeros(nb.valid.shape).index_put((pb, pv, pk),
                                                      self.pair_rest(pre).squeeze(-1))
        return ego, pair
