"""Log replay through the env: every live agent follows its recording by inverse dynamics
(:func:`~magail_sumo.env.log_actions.expert_actions`), as expert recording and ``magail-sumo replay``
drive a scene. (Evaluation's ``logreplay`` method needs no env: the recorded future itself,
:func:`~magail_sumo.evaluation.realism.log_replay`.)"""

from __future__ import annotations

import numpy as np

from magail_sumo.env.log_actions import expert_actions


class LogReplayPolicy:
    """The expert's actions for the env's live agents, in the env's action layout and limits
    (use :data:`~magail_sumo.env.log_actions.REPLAY_LIMITS` to follow the recording closely).

    Needs the env (``begin``, called by :func:`~magail_sumo.agents.rollout.rollout`).
    :attr:`states` holds the live agents' bicycle states the last actions were computed from
    (``env.agent_states()`` before the step; the actions' keys follow its ``names``)."""

    def __init__(self) -> None:
        self.env = None
        self.states = None

    def begin(self, scene, env) -> None:
        self.env = env

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self.env is None:
            raise RuntimeError("LogReplayPolicy: call begin(scene, env) before act")
        self.states = self.env.agent_states()
        return expert_actions(self.env, self.states)
