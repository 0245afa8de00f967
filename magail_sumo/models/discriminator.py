"""GAIL discriminators over the set of vehicles of one scene step.

Input: a batch of B scene steps, each a set of up to V vehicle tokens with F features
(``concat(s, s')`` of one vehicle), and a (B, V) boolean mask of present tokens. Output:
per-token logits (B, V) — each vehicle judged in the context of the others — and a pooled
scene logit (B,). Convention: expert logits > 0, policy logits < 0.

* :class:`TransformerDiscriminator` ("BERT"): linear token embedding, post-LN transformer
  encoder with a key-padding mask, no positional embedding (vehicle order carries no meaning,
  so the output is permutation-equivariant), a linear head per token, and mean pooling over
  present tokens or a learned CLS token for the scene logit.
* :class:`MLPDiscriminator`: each vehicle judged alone (plain per-vehicle GAIL), the ablation.
* :class:`~magail_sumo.models.decomposed.DecomposedDiscriminator` (own module): an ego–map
  term per vehicle plus distance-weighted pairwise terms with its nearest neighbours; its
  forwards also take the vehicles' poses (``uses_poses``).

Both normalise inputs with a :class:`RunningNormalizer` stored in their state dict.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from magail_sumo.config import FieldError
from magail_sumo.models.normalizer import RunningNormalizer


@dataclass(frozen=True)
class TransformerConfig:
    """Sizes of :class:`TransformerDiscriminator` (defaults from the seed design)."""

    embed_dim: int = 128
    num_layers: int = 4
    num_heads: int = 4
    ff_dim: int = 512
    dropout: float = 0.1
    pooling: str = "mean"  # "mean" over present tokens, or "cls"

    def __post_init__(self) -> None:
        check_set_encoder_sizes(self)
        if self.pooling not in ("mean", "cls"):
            raise FieldError("pooling", f"must be 'mean' or 'cls', got {self.pooling!r}"[:120])


def check_set_encoder_sizes(cfg) -> None:
    """Range rules of the sizes :func:`set_encoder` takes (``embed_dim``, ``num_layers``,
    ``num_heads``, ``ff_dim``, ``dropout`` of a config dataclass), raised as
    :class:`~magail_sumo.config.FieldError` naming the field."""
    for name in ("embed_dim", "num_layers", "num_heads", "ff_dim"):
        if getattr(cfg, name) < 1:
            raise FieldError(name, f"must be >= 1, got {getattr(cfg, name)}")
    if cfg.embed_dim % cfg.num_heads:
        raise FieldError("num_heads", f"must divide embed_dim ({cfg.embed_dim}), "
                         f"got {cfg.num_heads}")
    if not 0.0 <= cfg.dropout < 1.0:
        raise FieldError("dropout", f"must be in [0, 1), got {cfg.dropout}")


@dataclass(frozen=True)
class SetEncoderConfig:
    """Sizes of a :func:`set_encoder` (the transformer critic's, ``policy.critic_transformer``;
    the decomposed transformer discriminator's, ``discriminator.decomposed_transformer``).

    :param embed_dim: token width (a multiple of ``num_heads``).
    :param num_layers: encoder layers. :param num_heads: attention heads.
    :param ff_dim: hidden width of each layer's feed-forward block.
    :param dropout: dropout of the encoder layers, in [0, 1) (active only in training mode).
    """

    embed_dim: int = 64
    num_layers: int = 2
    num_heads: int = 4
    ff_dim: int = 128
    dropout: float = 0.0

    def __post_init__(self) -> None:
        check_set_encoder_sizes(self)


def set_encoder(embed_dim: int, num_heads: int, ff_dim: int, dropout: float, num_layers: int
                ) -> nn.TransformerEncoder:
    """The vehicle-set encoder of the discriminator and the critic: post-LN, GELU, batch first,
    used with a key-padding mask and no positional embedding (vehicle order means nothing)."""
    layer = nn.TransformerEncoderLayer(embed_dim, num_heads, ff_dim, dropout, activation="gelu",
                                       batch_first=True, norm_first=False)
    return nn.TransformerEncoder(layer, num_layers, enable_nested_tensor=False)


class _TokenInput(nn.Module):
    """Input stage shared by the discriminators: the running normaliser and the feature mask.

    ``feature_mask`` (F,) is 1 for features the discriminator judges and 0 for ignored ones
    (e.g. the previous action, which carries the policy's exploration noise rather than its
    driving); ignored features are zeroed after normalisation, so they reach neither the
    logits nor the gradient penalty. Saved in the state dict (all ones when absent, for
    checkpoints written before it existed).
    """

    #: whether the forwards also take the vehicles' poses (B, V, 3) (the decomposed kind)
    uses_poses = False

    def __init__(self, feature_dim: int) -> None:
        super().__init__()
        self.normalizer = RunningNormalizer(feature_dim)
        self.register_buffer("feature_mask", torch.ones(feature_dim))

    def ignore_features(self, columns) -> None:
        """Zero these token columns (indices into concat(s, s')) from now on."""
        self.feature_mask.fill_(1.0)
        self.feature_mask[list(columns)] = 0.0

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        state_dict.setdefault(prefix + "feature_mask", torch.ones_like(self.feature_mask))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits of raw features x (B, V, F) with mask (B, V)."""
        return self.forward_normalized(self.normalizer(x), mask)


class TransformerDiscriminator(_TokenInput):
    """Set transformer discriminator with per-token and pooled logits (see module doc)."""

    def __init__(self, feature_dim: int, config: TransformerConfig | None = None) -> None:
        super().__init__(feature_dim)
        cfg = config or TransformerConfig()
        if cfg.pooling not in ("mean", "cls"):
            raise ValueError(f"pooling must be 'mean' or 'cls', got {cfg.pooling!r}")
        self.config = cfg
        self.embed = nn.Linear(feature_dim, cfg.embed_dim)
        self.encoder = set_encoder(cfg.embed_dim, cfg.num_heads, cfg.ff_dim, cfg.dropout,
                                   cfg.num_layers)
        self.cls = nn.Parameter(torch.zeros(1, 1, cfg.embed_dim)) if cfg.pooling == "cls" else None
        self.token_head = nn.Linear(cfg.embed_dim, 1)
        self.scene_head = nn.Linear(cfg.embed_dim, 1)

    def head_weights(self) -> list[torch.Tensor]:
        """Weights of the output heads (for the logit regulariser)."""
        return [self.token_head.weight, self.scene_head.weight]

    def forward_normalized(self, x: torch.Tensor, mask: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits of already-normalised features: ((B, V) token logits, (B,) scene logits)."""
        h = self.embed(x * self.feature_mask)
        pad = ~mask
        if self.cls is not None:
            h = torch.cat([self.cls.expand(h.shape[0], -1, -1), h], dim=1)
            pad = torch.cat([torch.zeros_like(pad[:, :1]), pad], dim=1)
        h = self.encoder(h, src_key_padding_mask=pad)
        if self.cls is not None:
            pooled, h = h[:, 0], h[:, 1:]
        else:
            m = mask.unsqueeze(-1).to(h.dtype)
            pooled = (h * m).sum(1) / m.sum(1).clamp(min=1.0)
        tokens = self.token_head(h).squeeze(-1).masked_fill(~mask, 0.0)
        return tokens, self.scene_head(pooled).squeeze(-1)


class MLPDiscriminator(_TokenInput):
    """Per-vehicle MLP discriminator (no interaction between tokens); same interface."""

    def __init__(self, feature_dim: int, hidden: tuple[int, ...] = (256, 256)) -> None:
        super().__init__(feature_dim)
        layers: list[nn.Module] = []
        d = feature_dim
        for h in hidden:
            layers += [nn.Linear(d, h), nn.Tanh()]
            d = h
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(d, 1)

    def head_weights(self) -> list[torch.Tensor]:
        return [self.head.weight]

    def forward_normalized(self, x: torch.Tensor, mask: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        tokens = self.head(self.body(x * self.feature_mask)).squeeze(-1).masked_fill(~mask, 0.0)
        m = mask.to(tokens.dtype)
        return tokens, (tokens * m).sum(1) / m.sum(1).clamp(min=1.0)


def imitation_reward(token_logits: torch.Tensor, floor: float = 1e-4) -> torch.Tensor:
    """GAIL reward per token: ``-log(max(1 - sigmoid(D), floor))`` (high when D says expert)."""
    return -torch.log(torch.clamp(1.0 - torch.sigmoid(token_logits), min=floor))
