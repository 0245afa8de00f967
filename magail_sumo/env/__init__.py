"""Multi-agent driving environment (PettingZoo ``ParallelEnv``) over converted scene bundles."""

from .bundle import BundleError, SceneBundle
from .config import EVENTS, EnvConfig
from .driving_env import AgentStates, SumoDrivingEnv
from .expert import REPLAY_LIMITS, expert_actions

__all__ = ["AgentStates", "BundleError", "EVENTS", "EnvConfig", "REPLAY_LIMITS", "SceneBundle", "SumoDrivingEnv",
           "expert_actions"]
