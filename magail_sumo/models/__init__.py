"""Neural networks: discriminators (reward networks) and their input normaliser."""

from .discriminator import (
    MLPDiscriminator, TransformerConfig, TransformerDiscriminator, imitation_reward,
)
from .normalizer import RunningNormalizer

__all__ = ["MLPDiscriminator", "RunningNormalizer", "TransformerConfig",
           "TransformerDiscriminator", "imitation_reward"]
