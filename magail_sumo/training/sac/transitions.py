"""The transitions of SAC's env steps (rows = slots that held an agent), their buffer rows with
absorbing states, and the task reward (:mod:`magail_sumo.training.sac`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


from .buffer import ACT_DIM
from .config import TaskRewardConfig

#: events whose transition is stored with the reason's flag (task reward)
TASK_EVENTS = ("collision", "off_road", "red_light", "destination")

def task_reward(s: np.ndarray, a: np.ndarray, s_next: np.ndarray,
                events: dict[str, np.ndarray], weights: TaskRewardConfig,
                names: list[str]) -> np.ndarray:
    """(N,) task reward of N transitions (:class:`~magail_sumo.training.config.TaskRewardConfig`).

    :param s, s_next: (N, F) observations (``names`` layout, ``"ego"``), s_next the terminal
        observation of an agent that left. :param a: (N, 2) normalised actions.
    :param events: (N,) bool per event of :data:`TASK_EVENTS` that ended the agent at this step
        (missing: none).
    """
    d, pa, ps = (names.index(n) for n in ("dest_distance", "prev_accel", "prev_steer"))
    w = weights
    r = w.progress * (s[:, d] - s_next[:, d]).astype(np.float64)
    r -= w.comfort * ((a[:, 0] - s[:, pa]) ** 2 + (a[:, 1] - s[:, ps]) ** 2)
    zero = np.zeros(len(s), bool)
    r += w.destination * events.get("destination", zero)
    r -= w.collision * events.get("collision", zero)
    r -= w.off_road * events.get("off_road", zero)
    r -= w.red_light * events.get("red_light", zero)
    return r.astype(np.float32)




@dataclass
class Transitions:
    """The transitions of one env step (rows = slots that held an agent), with what each
    buffer needs (see module doc).

    :param slots: (N,) slot of each row. :param obs, next_obs: (N, F) raw observations
    (next_obs: the terminal observation of an agent that left).
    :param terminated, truncated: (N,) the agent left by an event / by a time limit.
    :param events: (N,) bool per :data:`TASK_EVENTS` event that ended the agent.
    """

    slots: np.ndarray
    obs: np.ndarray
    action: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    events: dict[str, np.ndarray]


def step_transitions(last_obs: np.ndarray, actions: np.ndarray, obs: np.ndarray,
                     dones: np.ndarray, infos: list[dict], acted: np.ndarray) -> Transitions:
    """The transitions of a vector-env step (``acted``: the slots that held an agent at its
    start; free slots are dropped). Only the few leaving agents are looked at one by one."""
    slots = np.flatnonzero(acted)
    nxt = obs[slots].copy()
    n = slots.size
    terminated, truncated = np.zeros(n, bool), np.zeros(n, bool)
    events = {e: np.zeros(n, bool) for e in TASK_EVENTS}
    row = np.full(len(acted), -1)
    row[slots] = np.arange(n)
    for i in np.flatnonzero(dones & acted):
        info = infos[i]
        term = info.get("terminal_observation")
        if term is None:  # a free slot handed to a new agent: no agent left here
            continue
        j = row[i]
        nxt[j] = term
        if info.get("TimeLimit.truncated", False):
            truncated[j] = True
        else:
            terminated[j] = True
        reason = info.get("reason")
        if reason in events:
            events[reason][j] = True
    return Transitions(slots, last_obs[slots], np.asarray(actions, np.float32)[slots], nxt,
                       terminated, truncated, events)


def buffer_rows(tr: Transitions, reward: np.ndarray, absorbing: bool, absorbing_reward: float
                ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(main-buffer rows, collision-buffer rows) of a step's transitions (module doc): the
    absorbing flag column appended; with ``absorbing`` a terminated agent leads to the
    absorbing state (done 0) whose self-transition is added to the main rows, else it has
    done 1."""
    n, f = tr.obs.shape
    flag0 = np.zeros((n, 1), np.float32)
    obs = np.concatenate([tr.obs, flag0], axis=1)
    nxt = np.concatenate([tr.next_obs, flag0], axis=1)
    done = np.zeros(n, np.float32)
    absorbing_state = np.zeros(f + 1, np.float32)
    absorbing_state[f] = 1.0
    if absorbing:
        nxt[tr.terminated] = absorbing_state
    else:
        done[tr.terminated] = 1.0
    rows = {"obs": obs, "action": tr.action, "reward": np.asarray(reward, np.float32),
            "next_obs": nxt, "done": done}
    col = tr.events["collision"]
    collision = {k: v[col] for k, v in rows.items()}
    main = {k: v[~col] for k, v in rows.items()}
    k = int(tr.terminated.sum()) if absorbing else 0
    if k:
        ab = np.repeat(absorbing_state[None], k, axis=0)
        main = {"obs": np.concatenate([main["obs"], ab]),
                "action": np.concatenate([main["action"], np.zeros((k, ACT_DIM), np.float32)]),
                "reward": np.concatenate([main["reward"],
                                          np.full(k, absorbing_reward, np.float32)]),
                "next_obs": np.concatenate([main["next_obs"], ab]),
                "done": np.concatenate([main["done"], np.zeros(k, np.float32)])}
    return main, collision
