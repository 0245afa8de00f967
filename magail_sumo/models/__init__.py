"""Neural networks: discriminators (reward networks), the transformer critic, and their input
normaliser."""

from .critic import CriticTransformerConfig, TransformerCritic
from .decomposed import DecomposedConfig, DecomposedDiscriminator
from .decomposed_transformer import DecomposedTransformerDiscriminator
from .discriminator import (
    MLPDiscriminator, SetEncoderConfig, TransformerConfig, TransformerDiscriminator,
    imitation_reward,
)
from .normalizer import RunningNormalizer

__all__ = ["CriticTransformerConfig", "DecomposedConfig", "DecomposedDiscriminator",
           "DecomposedTransformerDiscriminator", "MLPDiscriminator", "SetEncoderConfig",
           "RunningNormalizer", "TransformerConfig", "TransformerCritic",
           "TransformerDiscriminator", "imitation_reward"]
