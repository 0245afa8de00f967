"""The one rollout loop: a policy drives an env episode (Waymax's ``rollout``, PettingZoo API).

:func:`rollout_worlds` is the same loop over a batched env
(:class:`~magail_sumo.env.batched.BatchedSceneEnv`: many rollouts of a scene stepped at once),
the policy acting for every world in one call. Evaluation's policy rollouts, expert recording,
``magail-sumo replay`` and the policy-comparison benchmark all drive their env with
:func:`rollout`; what they keep of each step they read in their ``on_step`` callback from a
:class:`Step`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .base import Policy


@dataclass
class Step:
    """One env step of a rollout.

    :param t: the env's log step before the step (the step of :attr:`observations`).
    :param agents: the live agents the step moved (``env.agents`` before it), in the env's
        order; each has an entry in :attr:`infos`, whose ``"state"`` is its post-step bicycle
        state ``(x, y, yaw, speed)`` (scene frame; m, rad, m/s). :attr:`infos` may also hold
        agents that joined during the step (not moved by it).
    :param observations: what the policy acted on.
    :param actions: the policy's actions, as given to ``env.step``.
    :param next_observations, rewards, terminations, truncations, infos: ``env.step``'s
        returns. ``on_step`` may edit :attr:`next_observations` in place: the next ``act`` (and
        the next :class:`Step`'s :attr:`observations`) sees the edit.
    """

    t: int
    agents: list[str]
    observations: dict[str, np.ndarray]
    actions: dict[str, Any]
    next_observations: dict[str, np.ndarray]
    rewards: dict[str, float]
    terminations: dict[str, bool]
    truncations: dict[str, bool]
    infos: dict[str, dict]


def rollout(env, policy: Policy, on_step: Callable[[Step], None] | None = None, *,
            seed: int | None = None, max_steps: int | None = None, scene=None,
            on_reset: Callable[[dict, dict], None] | None = None,
            until_empty: bool = True, live_only: bool = False) -> int:
    """Reset ``env`` (with ``seed``), tell the policy (its optional ``begin(scene, env)``, with
    ``scene`` defaulting to ``env.scene``), then step until no agent is live or ``max_steps``
    steps are taken: each step ``policy.act(observations)`` -> ``env.step`` ->
    ``on_step(Step)``. Returns the number of steps taken.

    :param on_reset: called with the reset's (observations, infos) before the policy's ``begin``.
    :param until_empty: stop when no agent is live (False: step on to ``max_steps``, which is
        then required, with no actions while nobody is live: a city where agents join later).
    :param live_only: the policy sees only the live agents' observations (not the final ones of
        agents that just ended), so it acts, and draws samples, for live agents only.
    The env is left open (its episode state, e.g. ``action_counts``, stays readable); the
    caller closes it.
    """
    obs, infos = env.reset(seed=seed)
    if on_reset is not None:
        on_reset(obs, infos)
    begin = getattr(policy, "begin", None)
    if callable(begin):  # optional extension (see Policy)
        begin(getattr(env, "scene", None) if scene is None else scene, env)
    if not until_empty and max_steps is None:
        raise ValueError("rollout(until_empty=False) needs max_steps")
    n = 0
    while (env.agents or not until_empty) and (max_steps is None or n < max_steps):
        t, agents = env.t, list(env.agents)
        if live_only:
            actions = policy.act({a: obs[a] for a in agents}) if agents else {}
        else:
            actions = policy.act(obs)
        nxt, rewards, terms, truncs, infos = env.step(actions)
        n += 1
        if on_step is not None:
            on_step(Step(t, agents, obs, actions, nxt, rewards, terms, truncs, infos))
        obs = nxt
    return n


def rollout_worlds(env, policy, seeds, on_step: Callable[[int, np.ndarray, np.ndarray, Any],
                                                     None] | None = None, *,
                   max_steps: int | None = None, scene=None) -> int:
    """:func:`rollout` of a batched env (:class:`~magail_sumo.env.batched.BatchedSceneEnv`)
    through its array API, world ``w`` driven as a rollout with ``seeds[w]``: the env is
    reset with ``seeds[0]`` (the worlds differ only by the policy's draws), the policy
    reseeded per world (``reseed_worlds(seeds)``) and told the scene (its optional
    ``begin(scene, env)``), then each step ``policy.act_batch`` over every world's live
    agents (grouped by world, each world's in sorted-name order, so its draws are those of a
    single-world rollout; their fleet rows as the agents' keys) -> ``env.step_arrays`` ->
    ``on_step(t, rows, actions, step)`` (``t`` the log step before the step, ``rows`` the
    fleet rows it moved, ``actions`` their (n, 2) actions, ``step`` the
    :class:`~magail_sumo.env.outcomes.ArrayStep`; post-step states are in ``env.fleet``),
    until the episode is over (``env.finished``) or ``max_steps`` steps are taken. Returns the
    number of steps taken."""
    if len(seeds) != env.worlds:
        raise ValueError(f"rollout_worlds: {len(seeds)} seeds for {env.worlds} worlds")
    st = env.reset_arrays(seed=int(seeds[0]))
    policy.reseed_worlds(list(seeds))
    begin = getattr(policy, "begin", None)
    if callable(begin):
        begin(getattr(env, "scene", None) if scene is None else scene, env)
    per = max(env.per_world, 1)
    names = np.array(env.world_agents, dtype=str)
    rank = np.argsort(np.argsort(names, kind="stable"), kind="stable")  # sorted-name rank
    actions = np.zeros((len(env.fleet), 2), np.float32)
    n = 0
    while not env.finished and (max_steps is None or n < max_steps):
        rows = np.flatnonzero(st.live)
        rows = rows[np.lexsort((rank[rows % per], rows // per))]
        actions[:] = 0.0
        if rows.size:
            actions[rows] = policy.act_batch(st.observations[rows], rows // per, rows)
        t = env.t
        st = env.step_arrays(actions)
        n += 1
        if on_step is not None:
            on_step(t, rows, actions[rows], st)
    return n
