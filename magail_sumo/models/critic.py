"""Transformer critic: the value of every vehicle from all vehicles of its scene step.

Input: N rows of per-vehicle features (the policy's *normalised* observations, ego frame, one
row per vehicle, the same features the actor sees) and an (N,) integer group id per row — the
rows of one group are the vehicles of one scene at one time step; id -1 marks a row that is not
a vehicle (a free slot), which is not evaluated. Output: (N,) values — estimates of each
vehicle's discounted return (reward units, PPO's gamma) — one per row, each computed in the
context of the other rows of its group only (0 for rows with id -1).

The network follows :class:`~magail_sumo.models.discriminator.TransformerDiscriminator`
("BERT" style): a linear token embedding, a post-LN :class:`torch.nn.TransformerEncoder` with a
key-padding mask, **no positional embedding** (vehicle order means nothing, so the values are
permutation-equivariant within a group), and a linear value head per token. Groups are padded
to ``(groups, max vehicles, features)`` with a key-padding mask (in buckets of similar group
size), so padding never reaches a present token and groups never see each other.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .discriminator import SetEncoderConfig, set_encoder


#: sizes of :class:`TransformerCritic` (``policy.critic_transformer`` in the training config):
#: a :class:`~magail_sumo.models.discriminator.SetEncoderConfig`
CriticTransformerConfig = SetEncoderConfig


def group_positions(group: torch.Tensor) -> tuple[torch.Tensor, int, int]:
    """Position of each row inside its group (in row order), number of groups, largest group.

    :param group: (N,) int64 group ids in ``0 .. G-1``, every id used at least once.
    """
    n = group.shape[0]
    if n == 0:
        return group, 0, 0
    n_groups = int(group.max()) + 1
    counts = torch.bincount(group, minlength=n_groups)
    order = torch.argsort(group, stable=True)
    starts = torch.cumsum(counts, 0) - counts
    pos = torch.empty_like(group)
    pos[order] = torch.arange(n, device=group.device) - starts[group[order]]
    return pos, n_groups, int(counts.max())


def scene_groups(slot_scene: np.ndarray, active: np.ndarray | None) -> np.ndarray:
    """Group ids of one vector-env observation: the active slots of each scene form a group
    (ids 0, 1, ... in scene order); free slots get -1 (not evaluated).

    :param slot_scene: (n_slots,) scene index of each slot. :param active: (n_slots,) bool,
        None: all slots active.
    """
    slot_scene = np.asarray(slot_scene, np.int64)
    if active is None:
        active = np.ones(slot_scene.shape, bool)
    active = np.asarray(active, bool)
    group = np.full(slot_scene.shape, -1, np.int64)
    group[active] = np.unique(slot_scene[active], return_inverse=True)[1].reshape(-1)
    return group


def size_buckets(counts: np.ndarray, small: int = 256) -> np.ndarray:
    """Bucket index (0, 1, ...) of each group (of ``counts`` vehicles) for padded evaluation.

    Groups are taken largest first; a group joins the current bucket (padded to the bucket's
    first, largest group) when it has at least 3/4 as many vehicles, or while the padded
    bucket stays within ``small`` tokens (where one more encoder call costs more than the
    padding); otherwise it opens a new bucket.
    """
    order = np.argsort(-np.asarray(counts), kind="stable")
    bucket = np.empty(len(counts), np.int64)
    b, width, groups = -1, 0, 0
    for g in order:
        c = int(counts[g])
        if b < 0 or (4 * c < 3 * width and (groups + 1) * width > small):
            b, width, groups = b + 1, c, 0
        groups += 1
        bucket[g] = b
    return bucket


class TransformerCritic(nn.Module):
    """Per-vehicle values from the set of vehicles of each scene step (module doc).

    :param feature_dim: size of a vehicle's (normalised) observation.
    :param config: sizes (default :class:`CriticTransformerConfig`).
    """

    def __init__(self, feature_dim: int, config: CriticTransformerConfig | None = None) -> None:
        super().__init__()
        cfg = config or CriticTransformerConfig()
        self.config = cfg
        self.embed = nn.Linear(feature_dim, cfg.embed_dim)
        self.encoder = set_encoder(cfg.embed_dim, cfg.num_heads, cfg.ff_dim, cfg.dropout,
                                   cfg.num_layers)
        self.value_head = nn.Linear(cfg.embed_dim, 1)

    def forward_padded(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Values (B, V) of padded groups x (B, V, F) with mask (B, V) of present vehicles
        (every group has at least one); padded positions are 0."""
        h = self.encoder(self.embed(x), src_key_padding_mask=~mask)
        return self.value_head(h).squeeze(-1).masked_fill(~mask, 0.0)

    def forward(self, features: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
        """Values (N,) of rows ``features`` (N, F) grouped by ``group`` (N,) (see module doc).

        Groups are padded in buckets of similar size (:func:`size_buckets`), so that small
        scenes are not padded to the largest one.
        """
        n = features.shape[0]
        group = group.to(device=features.device, dtype=torch.long)
        present = torch.nonzero(group >= 0).squeeze(1)
        if present.numel() == 0:
            return features.new_zeros(n)
        group_p = group[present]
        pos, n_groups, _ = group_positions(group_p)
        counts = torch.bincount(group_p, minlength=n_groups)
        bucket = torch.as_tensor(size_buckets(counts.cpu().numpy()), device=features.device)
        idx, vals = [], []
        for b in range(int(bucket.max()) + 1):
            in_bucket = bucket == b
            local = torch.cumsum(in_bucket.long(), 0) - 1  # group -> index inside the bucket
            sel = torch.nonzero(in_bucket[group_p]).squeeze(1)
            rows = present[sel]
            g, p = local[group_p[sel]], pos[sel]
            padded = features.new_zeros(int(in_bucket.sum()), int(counts[in_bucket].max()),
                                        features.shape[1]).index_put((g, p), features[rows])
            mask = torch.zeros(padded.shape[:2], dtype=torch.bool, device=features.device)
            mask[g, p] = True
            idx.append(rows)
            vals.append(self.forward_padded(padded, mask)[g, p])
        return features.new_zeros(n).index_put((torch.cat(idx),), torch.cat(vals))
