"""Expert demonstrations: recorded scenes replayed through the env's sensors, stored as Parquet,
and sampled as discriminator scene-steps or behavioural-cloning (s, a) pairs."""

from .dataset import ExpertDataError, ExpertDataset, SceneSteps, check_observation
from .record import EXPERT_FORMAT, observation_hash, record_expert, record_scene

__all__ = ["EXPERT_FORMAT", "ExpertDataError", "ExpertDataset", "SceneSteps", "check_observation",
           "observation_hash", "record_expert", "record_scene"]
