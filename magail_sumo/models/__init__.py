"""Neural networks: discriminators (reward networks), the transformer critic, their input
normaliser, and the action priors a policy learns a residual to (the IDM rule)."""

from .critic import CriticTransformerConfig, TransformerCritic
from .decomposed import DecomposedConfig, DecomposedDiscriminator
from .decomposed_transformer import DecomposedTransformerDiscriminator
from .discriminator import (
    MLPDiscriminator, SetEncoderConfig, TransformerConfig, TransformerDiscriminator,
    imitation_reward,
)
from .idm import IdmParams, IdmRule
from .normalizer import RunningNormalizer
from .priors import ACTION_PRIORS, make_prior

__all__ = ["ACTION_PRIORS", "CriticTransformerConfig", "DecomposedConfig",
           "DecomposedDiscriminator", "DecomposedTransformerDiscriminator", "IdmParams",
           "IdmRule", "MLPDiscriminator", "SetEncoderConfig", "RunningNormalizer",
           "TransformerConfig", "TransformerCritic", "TransformerDiscriminator",
           "imitation_reward", "make_prior"]
