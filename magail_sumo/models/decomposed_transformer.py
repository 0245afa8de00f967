"""Decomposed GAIL discriminator with a transformer ("BERT") over each vehicle's neighbourhood.

The decomposition of :mod:`magail_sumo.models.decomposed` — a vehicle's logit is an ego–map
term plus distance-weighted ego–neighbour terms, ``D_i = e_i + Σ_{j∈N(i)} w_ij·l_ij`` — with the
terms read off the per-token outputs of one encoder instead of two MLPs:

* one sequence per present vehicle ``i``: its ego token ``h_i⁰ = E(x̂_i) + u`` followed by one
  token per neighbour ``j ∈ N(i)``, ``h_ij⁰ = E(x̂_j) + G(g_ij)``, where ``E`` is a linear
  embedding of the normalised token ``concat(s, s')``, ``u`` a learned "ego" embedding and
  ``G`` a linear embedding of the neighbour's pose in ``i``'s frame
  ``g_ij = (dx/R, dy/R, cos Δψ, sin Δψ, d_ij/R)`` (the decomposed module's geometry, m and rad);
* a post-LN encoder (:func:`~magail_sumo.models.discriminator.set_encoder`) over the K + 1
  tokens with the absent neighbours padded out; no positional embedding (the neighbour order
  means nothing: the pose is in the token);
* ``e_i = head_e(h_i)`` on the ego token's output, ``l_ij = head_p(h_ij)`` on each neighbour
  token's output — so ``l_ij`` judges ``j`` as ``i`` sees it, in the context of ``i``'s other
  neighbours;
* weights ``w_ij``, the scene logit (mean of ``D_i``) and the social reward exactly as the MLP
  kind (:class:`~magail_sumo.models.decomposed.DecomposedBase`, ``discriminator.decomposed``:
  α, β, radius, K, λ).

Arrays: N present vehicles give an (N, K + 1, E) batch of sequences; no loop over vehicles.
Config: ``discriminator.kind: decomposed_transformer`` with sizes in
``discriminator.decomposed_transformer`` (a :class:`~magail_sumo.models.discriminator.
SetEncoderConfig`) and the geometry in
``discriminator.decomposed`` (its ``ego_hidden`` / ``pair_hidden`` are not used).
"""

from __future__ import annotations

import torch
from torch import nn

from .decomposed import GEOMETRY_DIM, DecomposedBase, DecomposedConfig, Neighbours
from .discriminator import SetEncoderConfig, set_encoder


class DecomposedTransformerDiscriminator(DecomposedBase):
    """Ego–map and ego–neighbour terms from a transformer over each vehicle's neighbourhood
    (module doc); the interface of :class:`~magail_sumo.models.decomposed.
    DecomposedDiscriminator` (forwards take the poses ``pos`` (B, V, 3))."""

    def __init__(self, feature_dim: int, config: DecomposedConfig | None = None,
                 encoder: SetEncoderConfig | None = None) -> None:
        super().__init__(feature_dim)
        self.config = config or DecomposedConfig()
        enc = encoder or SetEncoderConfig()
        self.encoder_config = enc
        self.embed = nn.Linear(feature_dim, enc.embed_dim)
        self.ego_type = nn.Parameter(torch.zeros(enc.embed_dim))
        self.geometry = nn.Linear(GEOMETRY_DIM, enc.embed_dim, bias=False)
        self.encoder = set_encoder(enc.embed_dim, enc.num_heads, enc.ff_dim, enc.dropout,
                                   enc.num_layers)
        self.ego_head = nn.Linear(enc.embed_dim, 1)
        self.pair_head = nn.Linear(enc.embed_dim, 1)

    def head_weights(self) -> list[torch.Tensor]:
        """Weights of the output heads (for the logit regulariser)."""
        return [self.ego_head.weight, self.pair_head.weight]

    def terms(self, xp: torch.Tensor, bi: torch.Tensor, vi: torch.Tensor, mask: torch.Tensor,
              nb: Neighbours) -> tuple[torch.Tensor, torch.Tensor]:
        n = bi.numel()
        ego = xp.new_zeros(mask.shape)
        pair = xp.new_zeros(nb.valid.shape)
        if n == 0:
            return ego, pair
        h = self.embed(xp)  # (N, E), once per present vehicle
        row = torch.zeros(mask.shape, dtype=torch.long, device=xp.device)
        row[bi, vi] = torch.arange(n, device=xp.device)
        index = nb.index[bi, vi]  # (N, K) slots of the neighbours
        valid = nb.valid[bi, vi]  # (N, K)
        nrow = row[bi[:, None], index]  # (N, K) rows of the neighbours among the present
        neighbours = h[nrow] + self.geometry(nb.geometry[bi, vi].to(xp.dtype))
        seq = torch.cat([(h + self.ego_type)[:, None], neighbours], dim=1)  # (N, K + 1, E)
        pad = torch.cat([torch.zeros_like(valid[:, :1]), ~valid], dim=1)
        out = self.encoder(seq, src_key_padding_mask=pad)
        ego = ego.index_put((bi, vi), self.ego_head(out[:, 0]).squeeze(-1))
        l_ij = self.pair_head(out[:, 1:]).squeeze(-1).masked_fill(~valid, 0.0)
        pair = pair.index_put((bi, vi), l_ij)
        return ego, pair
