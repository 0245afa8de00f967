"""GameFormer: interactive multi-agent trajectory prediction with level-k reasoning.

After Huang et al., "GameFormer: Game-theoretic Modeling and Learning of Transformer-based
Interactive Prediction and Planning" (ICCV 2023); our own implementation.

Inputs (one sample = N agents and, for each agent, its Nm nearest map elements, all in one
agent-centric frame; :mod:`magail_sumo.models.gameformer_features` builds them):

* ``agents`` (B, N, Th, :data:`AGENT_FEATURES`) history states, zero at unobserved steps;
  ``agent_mask`` (B, N) bool: the agent exists (observed at the current step, the last
  history step). Agent 0 must exist in every sample.
* ``map`` (B, N, Nm, P, :data:`MAP_FEATURES`) polyline points; ``map_mask`` (B, N, Nm, P)
  bool: the point exists (an element with no point is padding).

Architecture: an LSTM encodes each agent's history; an MLP encodes every map point and a
max-pool over the points of an element gives the element's token (PointNet style). For each
agent i a transformer encoder fuses the N agent tokens with agent i's Nm map tokens into its
scene context ``C_i`` ((N + Nm) tokens). Level 0: M learnable modality queries plus agent i's own
token of ``C_i`` cross-attend ``C_i`` and give M Gaussian trajectories (μx, μy, log σx, log σy
per future step, metres in the sample frame; the means are running sums of predicted per-step
displacements) and M mode scores (logits). Level k = 1..K: each
agent's level-(k−1) trajectories are encoded (MLP per step, max-pool over time) to
``A_mf`` (B, N, M, D), averaged over modes with the softmax of the level-(k−1) scores to one
future token per agent, the future tokens attend to each other (self-attention over the agents),
and agent i's queries ``Z_{k−1,i} + A_mf,i`` cross-attend the future tokens of the *other* agents
(its own is masked) followed by ``C_i``. Every level has its own weights.

Loss (:func:`level_loss`, summed over the levels): Gaussian NLL of the best mode (smallest
mean displacement to the ground truth over the valid future steps) + cross-entropy of the mode
scores against the best mode + (levels ≥ 1) ``interaction_weight`` × the repulsion term
``mean_{m,t} max_{j≠i,n} 1/(d + 1)`` over pairs closer than ``safety_distance`` (d: distance
between agent i's level-k mode m and agent j's level-(k−1) mode n at step t; the level-(k−1)
futures are fixed, detached).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from magail_sumo.config import check

#: per-step agent features: x, y, cos h, sin h, vx, vy, length, width, observed, and the
#: type one-hot (vehicle, pedestrian, cyclist)
AGENT_FEATURES = 12
#: per-point map features: x, y, unit direction (dx, dy), type one-hot (lane centre line, road
#: line, road edge, crosswalk)
MAP_FEATURES = 8
#: metres per unit of the network's internal coordinates (inputs divided, outputs multiplied)
POSITION_SCALE = 10.0
#: metres per unit of the trajectory head's per-step displacements (μ is their running sum)
STEP_SCALE = 1.0
#: the future encoder and the repulsion term look at every this many future steps (0.5 s),
#: ending at the last one
FUTURE_STRIDE = 5


@dataclass(frozen=True)
class GameFormerModelConfig:
    """Sizes of the GameFormer network (module doc).

    :param d_model: token width D. :param num_heads: attention heads (divides ``d_model``).
    :param fusion_layers: transformer encoder layers of the scene fusion.
    :param ff_dim: feed-forward width of every transformer block.
    :param modes: M, trajectories per agent. :param levels: K, level-k interaction decoders
        (level 0 plus K levels are predicted). :param future_steps: predicted 0.1-s steps.
    :param log_sigma_min, log_sigma_max: clamp of the predicted log standard deviations (log m).
    """

    d_model: int = 64
    num_heads: int = 4
    fusion_layers: int = 2
    ff_dim: int = 128
    modes: int = 6
    levels: int = 3
    future_steps: int = 80
    log_sigma_min: float = -1.6
    log_sigma_max: float = 3.0

    def __post_init__(self) -> None:
        for name in ("d_model", "num_heads", "fusion_layers", "ff_dim", "modes", "future_steps"):
            check(getattr(self, name) >= 1, name, f"must be >= 1, got {getattr(self, name)}")
        check(self.levels >= 0, "levels", f"must be >= 0, got {self.levels}")
        check(self.d_model % self.num_heads == 0, "num_heads",
              f"must divide d_model ({self.d_model}), got {self.num_heads}")
        check(self.log_sigma_min < self.log_sigma_max, "log_sigma_max",
              f"must be > log_sigma_min ({self.log_sigma_min}), got {self.log_sigma_max}")


def _mlp(i: int, h: int, o: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(i, h), nn.ReLU(), nn.Linear(h, o))


class CrossBlock(nn.Module):
    """Post-norm cross-attention block: ``x = LN(q + MHA(q, kv)); LN(x + FFN(x))``."""

    def __init__(self, d: int, heads: int, ff: int) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(d, heads, dropout=0.0, batch_first=True)
        self.ff = _mlp(d, ff, d)
        self.n1, self.n2 = nn.LayerNorm(d), nn.LayerNorm(d)

    def forward(self, q: torch.Tensor, kv: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
        """:param pad: (B, L) True where the key is absent (at least one key per row kept)."""
        x = self.n1(q + self.attn(q, kv, kv, key_padding_mask=pad, need_weights=False)[0])
        return self.n2(x + self.ff(x))


class GMMHead(nn.Module):
    """Trajectories (B, N, M, T, 4) and scores (B, N, M) from query contents (B, N, M, D); the
    means are the running sums of per-step displacements (a trajectory starts at the agent)."""

    def __init__(self, cfg: GameFormerModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.traj = _mlp(cfg.d_model, cfg.ff_dim, cfg.future_steps * 4)
        self.score = _mlp(cfg.d_model, cfg.ff_dim, 1)

    def forward(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = self.cfg
        g = self.traj(z).unflatten(-1, (c.future_steps, 4))
        mu = torch.cumsum(g[..., :2] * STEP_SCALE, dim=-2)  # starts at the current position
        log_sigma = g[..., 2:].clamp(c.log_sigma_min, c.log_sigma_max)
        return torch.cat([mu, log_sigma], -1), self.score(z).squeeze(-1)


def _strided(traj: torch.Tensor) -> torch.Tensor:
    """Every :data:`FUTURE_STRIDE`-th step of (..., T, C), the last step included."""
    t = traj.shape[-2]
    return traj[..., (t - 1) % FUTURE_STRIDE::FUTURE_STRIDE, :]


class FutureEncoder(nn.Module):
    """(B, N, M, T, 4) trajectories -> (B, N, M, D): MLP over (x, y, dx, dy) at every
    :data:`FUTURE_STRIDE`-th step (scaled positions, displacement since the previous such
    step), max-pool over the steps."""

    def __init__(self, d: int, ff: int) -> None:
        super().__init__()
        self.mlp = _mlp(4, ff, d)

    def forward(self, traj: torch.Tensor) -> torch.Tensor:
        xy = _strided(traj[..., :2]) / POSITION_SCALE
        step = torch.diff(xy, dim=-2, prepend=torch.zeros_like(xy[..., :1, :]))
        return self.mlp(torch.cat([xy, step], -1)).amax(-2)


class InteractionDecoder(nn.Module):
    """One level-k decoder (module doc)."""

    def __init__(self, cfg: GameFormerModelConfig) -> None:
        super().__init__()
        d, h, f = cfg.d_model, cfg.num_heads, cfg.ff_dim
        self.future = FutureEncoder(d, f)
        self.social = nn.TransformerEncoderLayer(d, h, f, dropout=0.0, batch_first=True)
        self.cross = CrossBlock(d, h, f)
        self.head = GMMHead(cfg)

    def future_tokens(self, traj: torch.Tensor, scores: torch.Tensor, agent_mask: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """Level-(k−1) futures -> (per-mode encodings A_mf (B, N, M, D), agent future tokens
        after the agents' self-attention (B, N, D))."""
        a_mf = self.future(traj)
        w = torch.softmax(scores, -1).unsqueeze(-1)
        a_f = (a_mf * w).sum(-2)
        return a_mf, self.social(a_f, src_key_padding_mask=~agent_mask)

    def decode(self, tokens: torch.Tensor, a_mf: torch.Tensor, z_prev: torch.Tensor,
               context: torch.Tensor, context_pad: torch.Tensor, agent_mask: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Agent i's queries attend [future tokens of the others, C_i]; (traj, scores, Z)."""
        b, n, m, d = z_prev.shape
        kv = torch.cat([tokens.unsqueeze(1).expand(b, n, n, d), context], 2)
        own = torch.eye(n, dtype=torch.bool, device=tokens.device)
        fut_pad = (~agent_mask).unsqueeze(1) | own  # (B, N_query, N_key): own future masked
        pad = torch.cat([fut_pad, context_pad], 2)
        z = self.cross((z_prev + a_mf).flatten(0, 1), kv.flatten(0, 1), pad.flatten(0, 1))
        z = z.unflatten(0, (b, n))
        traj, scores = self.head(z)
        return traj, scores, z


class GameFormer(nn.Module):
    """The GameFormer network (module doc); :meth:`forward` returns the levels' outputs."""

    def __init__(self, cfg: GameFormerModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d, h, f = cfg.d_model, cfg.num_heads, cfg.ff_dim
        self.agent_in = nn.Linear(AGENT_FEATURES, d)
        self.lstm = nn.LSTM(d, d, batch_first=True)
        self.map_mlp = _mlp(MAP_FEATURES, d, d)
        layer = nn.TransformerEncoderLayer(d, h, f, dropout=0.0, batch_first=True)
        self.fusion = nn.TransformerEncoder(layer, cfg.fusion_layers,
                                            enable_nested_tensor=False)
        self.modal_query = nn.Parameter(torch.randn(cfg.modes, d) * 0.1)
        self.level0 = CrossBlock(d, h, f)
        self.head0 = GMMHead(cfg)
        self.levels = nn.ModuleList(InteractionDecoder(cfg) for _ in range(cfg.levels))

    def encode(self, agents: torch.Tensor, agent_mask: torch.Tensor, map_points: torch.Tensor,
               map_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Scene contexts C (B, N, N + Nm, D) and their key padding (B, N, N + Nm)."""
        b, n, th, _ = agents.shape
        x = agents.clone()
        x[..., :2] = x[..., :2] / POSITION_SCALE
        x[..., 4:6] = x[..., 4:6] / POSITION_SCALE
        out, _ = self.lstm(self.agent_in(x).flatten(0, 1))
        a = out[:, -1].unflatten(0, (b, n))  # (B, N, D)
        mp = map_points.clone()
        mp[..., :2] = mp[..., :2] / POSITION_SCALE
        pts = self.map_mlp(mp)  # (B, N, Nm, P, D)
        pts = pts.masked_fill(~map_mask.unsqueeze(-1), float("-inf")).amax(-2)
        elem = map_mask.any(-1)  # (B, N, Nm)
        m_tok = torch.where(elem.unsqueeze(-1), pts, torch.zeros_like(pts))
        nm = m_tok.shape[2]
        tokens = torch.cat([a.unsqueeze(1).expand(b, n, n, a.shape[-1]), m_tok], 2)
        pad = torch.cat([(~agent_mask).unsqueeze(1).expand(b, n, n), ~elem], 2)
        c = self.fusion(tokens.flatten(0, 1), src_key_padding_mask=pad.flatten(0, 1))
        return c.unflatten(0, (b, n)), pad

    def decode_level0(self, context: torch.Tensor, pad: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Level 0 from the scene contexts: (traj, scores, query contents Z (B, N, M, D))."""
        b, n = context.shape[:2]
        idx = torch.arange(n, device=context.device)
        own = context[:, idx, idx]  # (B, N, D): agent i's own token in C_i
        q = own.unsqueeze(2) + self.modal_query
        z = self.level0(q.flatten(0, 1), context.flatten(0, 1), pad.flatten(0, 1))
        z = z.unflatten(0, (b, n))
        traj, scores = self.head0(z)
        return traj, scores, z

    def forward(self, agents: torch.Tensor, agent_mask: torch.Tensor, map_points: torch.Tensor,
                map_mask: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """[(trajectories (B, N, M, T, 4), scores (B, N, M)) for level 0..K]."""
        context, pad = self.encode(agents, agent_mask, map_points, map_mask)
        traj, scores, z = self.decode_level0(context, pad)
        outs = [(traj, scores)]
        for dec in self.levels:
            a_mf, tokens = dec.future_tokens(traj, scores, agent_mask)
            traj, scores, z = dec.decode(tokens, a_mf, z, context, pad, agent_mask)
            outs.append((traj, scores))
        return outs


# ------------------------------------------------------------------------------------ loss
@dataclass
class LevelLoss:
    """Terms of one level's loss (scalars); ``total`` is what is minimised."""

    total: torch.Tensor
    nll: torch.Tensor
    score: torch.Tensor
    interaction: torch.Tensor


def best_mode(traj: torch.Tensor, future: torch.Tensor, future_mask: torch.Tensor) -> torch.Tensor:
    """(B, N) index of the mode with the smallest mean displacement over the valid steps."""
    d = torch.linalg.vector_norm(traj[..., :2] - future.unsqueeze(2), dim=-1)  # (B, N, M, T)
    w = future_mask.unsqueeze(2).to(d.dtype)
    return ((d * w).sum(-1) / w.sum(-1).clamp_min(1.0)).argmin(-1)


def gmm_nll(traj: torch.Tensor, future: torch.Tensor, future_mask: torch.Tensor
            ) -> torch.Tensor:
    """(B, N) per-agent NLL of ``traj`` (B, N, T, 4) (one mode): mean over the valid future
    steps of ``log σx + log σy + ½((dx/σx)² + (dy/σy)²)`` (the constant log 2π left out)."""
    ls = traj[..., 2:]
    z = (future - traj[..., :2]) * torch.exp(-ls)
    per = ls.sum(-1) + 0.5 * (z * z).sum(-1)
    w = future_mask.to(per.dtype)
    return (per * w).sum(-1) / w.sum(-1).clamp_min(1.0)


def interaction_term(traj: torch.Tensor, prev: torch.Tensor, agent_mask: torch.Tensor,
                     safety_distance: float) -> torch.Tensor:
    """(B, N) repulsion ``mean_{m,t} max_{j≠i,n} 1/(d+1)`` over pairs with d < safety_distance
    (0 where none), between agent i's modes ``traj`` (B, N, M, T, ≥2) and the other agents'
    modes ``prev`` (B, N, M, T, ≥2), t over every :data:`FUTURE_STRIDE`-th step."""
    traj, prev = _strided(traj[..., :2]), _strided(prev[..., :2])
    b, n, m, t, _ = traj.shape
    a = traj[..., :2].permute(0, 3, 1, 2, 4).reshape(b, t, n * m, 2)
    p = prev[..., :2].permute(0, 3, 1, 2, 4).reshape(b, t, n * m, 2)
    d = torch.cdist(a, p).view(b, t, n, m, n, m)  # [b, t, i, m, j, n]
    other = ~torch.eye(n, dtype=torch.bool, device=traj.device)
    ok = (agent_mask.view(b, 1, n, 1, 1, 1) & agent_mask.view(b, 1, 1, 1, n, 1)
          & other.view(1, 1, n, 1, n, 1) & (d < safety_distance))
    rep = torch.where(ok, 1.0 / (d + 1.0), torch.zeros_like(d))
    return rep.amax(dim=(4, 5)).mean(dim=(1, 3))


def level_loss(traj: torch.Tensor, scores: torch.Tensor, future: torch.Tensor,
               future_mask: torch.Tensor, agent_mask: torch.Tensor,
               prev: torch.Tensor | None = None, interaction_weight: float = 0.0,
               safety_distance: float = 3.0) -> LevelLoss:
    """One level's loss (module doc), averaged over the agents with a valid future step.

    :param traj: (B, N, M, T, 4). :param scores: (B, N, M) logits.
    :param future: (B, N, T, 2) ground truth. :param future_mask: (B, N, T) bool.
    :param prev: the level-(k−1) trajectories (detached here), None at level 0.
    """
    has = agent_mask & future_mask.any(-1)
    w = has.to(traj.dtype)
    count = w.sum().clamp_min(1.0)
    m_star = best_mode(traj.detach(), future, future_mask)
    best = torch.gather(traj, 2, m_star[:, :, None, None, None].expand(
        *m_star.shape, 1, *traj.shape[3:])).squeeze(2)
    nll = (gmm_nll(best, future, future_mask) * w).sum() / count
    ce = nn.functional.cross_entropy(scores.flatten(0, 1), m_star.flatten(), reduction="none")
    ce = (ce.view_as(w) * w).sum() / count
    inter = torch.zeros((), dtype=traj.dtype, device=traj.device)
    if prev is not None and interaction_weight > 0:
        am = agent_mask.to(traj.dtype)
        inter = (interaction_term(traj, prev.detach(), agent_mask, safety_distance) * am).sum() \
            / am.sum().clamp_min(1.0)
    return LevelLoss(nll + ce + interaction_weight * inter, nll, ce, inter)


def gameformer_loss(outputs: list[tuple[torch.Tensor, torch.Tensor]], future: torch.Tensor,
                    future_mask: torch.Tensor, agent_mask: torch.Tensor,
                    interaction_weight: float, safety_distance: float
                    ) -> tuple[torch.Tensor, list[LevelLoss]]:
    """Sum over the levels of :func:`level_loss`; (total, per-level terms)."""
    levels, prev = [], None
    for traj, scores in outputs:
        levels.append(level_loss(traj, scores, future, future_mask, agent_mask, prev,
                                 interaction_weight, safety_distance))
        prev = traj
    return sum(lv.total for lv in levels), levels


def num_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


__all__ = ["AGENT_FEATURES", "FUTURE_STRIDE", "MAP_FEATURES", "POSITION_SCALE", "GameFormer",
           "GameFormerModelConfig", "LevelLoss", "best_mode", "gameformer_loss", "gmm_nll",
           "interaction_term", "level_loss", "num_parameters"]
