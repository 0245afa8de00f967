"""Neural networks: discriminators (reward networks), the transformer critic, and their input
normaliser."""

from .critic import CriticTransformerConfig, TransformerCritic
from .decomposed import DecomposedConfig, DecomposedDiscriminator
from .discriminator import (
    MLPDiscriminator, TransformerConfig, TransformerDiscriminator, imitation_reward,
)
from .normalizer import RunningNormalizer

__all__ = ["CriticTransformerConfig", "DecomposedConfig", "DecomposedDiscriminator", "MLPDiscriminator", "RunningNormalizer", "TransformerConfig",
           "TransformerCritic", "TransformerDiscriminator", "imitation_reward"]
