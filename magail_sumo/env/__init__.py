"""Multi-agent driving environments (PettingZoo ``ParallelEnv``): recorded scenes converted to
SUMO (:class:`SumoDrivingEnv`) and plain SUMO city scenarios (:class:`SumoCityEnv`)."""

from .city_env import CITY_EVENTS, CityEnvConfig, SumoCityEnv
from .config import EVENTS, EnvConfig
from .driving_env import AgentStates, SumoDrivingEnv
from .log_actions import REPLAY_LIMITS, expert_actions

__all__ = ["AgentStates", "CITY_EVENTS", "CityEnvConfig", "EVENTS", "EnvConfig",
           "REPLAY_LIMITS", "SumoCityEnv", "SumoDrivingEnv", "expert_actions"]
