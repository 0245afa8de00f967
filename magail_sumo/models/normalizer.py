"""Running mean / standard deviation normaliser (Welford), saved with the model's state dict."""

from __future__ import annotations

import torch
from torch import nn


class RunningNormalizer(nn.Module):
    """Normalise features by a running mean and std; output clipped to ``±clip``.

    Statistics are buffers (so they travel in ``state_dict`` and checkpoints) and are updated
    only by :meth:`update`, never by ``forward``; merging batches uses the parallel Welford
    (Chan et al.) update, exact for any batch sizes.

    :param dim: feature dimension.
    :param clip: bound on normalised values.
    :param eps: added to the variance.
    """

    def __init__(self, dim: int, clip: float = 10.0, eps: float = 1e-8) -> None:
        super().__init__()
        self.clip = clip
        self.eps = eps
        self.register_buffer("mean", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(dim, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Fold a batch (..., dim) of raw features into the statistics."""
        x = x.reshape(-1, x.shape[-1]).to(torch.float64)
        n = x.shape[0]
        if n == 0:
            return
        b_mean = x.mean(0)
        d = x - b_mean
        b_m2 = d.mul_(d).sum(0)  # squared in place: the same sum, one (n, dim) buffer fewer
        total = self.count + n
        delta = b_mean - self.mean
        self.mean += delta * (n / total)
        self.m2 += b_m2 + delta**2 * (self.count * n / total)
        self.count.copy_(total)

    @property
    def std(self) -> torch.Tensor:
        var = self.m2 / torch.clamp(self.count, min=1.0)
        return torch.sqrt(var + self.eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = self.mean.to(x.dtype)
        std = self.std.to(x.dtype)
        return torch.clamp((x - mean) / std, -self.clip, self.clip)
