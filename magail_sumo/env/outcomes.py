"""One step's per-agent outcome as PettingZoo dicts: who terminates, who is truncated, and why.

Both envs (recorded scenes, :mod:`~magail_sumo.env.driving_env`, and cities,
:mod:`~magail_sumo.env.city_env`) detect a step's events as (A,) bool arrays over the stepped
agents. An agent *terminates* when an event of ``terminate_on`` occurred; otherwise it is
*truncated* when the env says its time is up. Its ``infos[agent]["reason"]`` is, when it
leaves, the first event in the env's event order that ended it (or that always ends an agent,
e.g. ``end_of_life``), else the env's truncation reason. Rewards are 0 (the trainer computes
rewards). The dict building is a loop over agents: PettingZoo's interface is per-agent dicts.
The array API of the recorded-scene envs (``step_arrays``) reports the same outcome as
:class:`ArrayStep` arrays over the fleet rows, with no per-agent loop (:func:`leaving` decides
for both).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

#: builds ``infos[agent]`` from (stepped-agent position, its events, its reason or None)
InfoFn = Callable[[int, dict, "str | None"], dict]


@dataclass
class StepDicts:
    """The PettingZoo per-agent dicts of one step (observations are built by the env)."""

    rewards: dict[str, float] = field(default_factory=dict)
    terms: dict[str, bool] = field(default_factory=dict)
    truncs: dict[str, bool] = field(default_factory=dict)
    infos: dict[str, dict] = field(default_factory=dict)

    def stepped(self, names: Sequence[str], flags: dict[str, np.ndarray],
                events: Sequence[str], terminate_on: Sequence[str], time_up: np.ndarray,
                truncation_reason: Sequence[str], info: InfoFn,
                always_reasons: Sequence[str] = (), rewards: np.ndarray | None = None
                ) -> np.ndarray:
        """Add the stepped agents; their (A,) bool "leaves now" mask.

        :param names: (A,) agent names. :param flags: event name -> (A,) bool.
        :param events: event order (the first one found is the reason).
        :param terminate_on: events that terminate an agent.
        :param time_up: (A,) the agent is truncated unless it terminated.
        :param truncation_reason: (A,) reason of a truncation no event explains.
        :param info: ``info(i, events_of_i, reason)`` builds the agent's infos.
        :param always_reasons: events that are a reason even outside ``terminate_on``.
        :param rewards: (A,) the agents' rewards (None: 0).
        """
        a = len(names)
        term, trunc = leaving(flags, terminate_on, time_up)
        gone = term | trunc
        reasons = set(terminate_on) | set(always_reasons)
        # Python lists: indexing numpy arrays per agent costs several times more
        columns = [np.asarray(flags[e], bool).tolist() for e in events]
        ends = [e in reasons for e in events]
        reward = [0.0] * a if rewards is None else np.asarray(rewards, np.float64).tolist()
        for i, (name, te, tr, lv) in enumerate(zip(names, term.tolist(), trunc.tolist(),
                                                   gone.tolist())):
            ev = {e: col[i] for e, col in zip(events, columns)}
            reason = next((e for e, col, end in zip(events, columns, ends) if end and col[i]),
                          None)
            if reason is None and tr:
                reason = truncation_reason[i]
            self.rewards[name], self.terms[name], self.truncs[name] = reward[i], te, tr
            self.infos[name] = info(i, ev, reason if lv else None)
        return gone

    def joined(self, names: Sequence[str], end: bool, end_reason: str,
               info: Callable[[int, "str | None"], dict]) -> None:
        """Add agents that joined during the step (no events yet): truncated only when the
        episode ends at this step. :param info: ``info(j, reason)`` for the j-th joiner."""
        for j, name in enumerate(names):
            self.rewards[name], self.terms[name], self.truncs[name] = 0.0, False, bool(end)
            self.infos[name] = info(j, end_reason if end else None)

    def astuple(self) -> tuple[dict, dict, dict, dict]:
        return self.rewards, self.terms, self.truncs, self.infos


@dataclass
class ArrayStep:
    """One step of an env's array API over its fleet rows (``N`` rows, every world's agents
    of a batched env): the same outcome as the dicts, as arrays.

    :param observations: (N, D) float32; rows in :attr:`observed` hold this step's
        observations (the stepped agents and the joiners), the others their last ones. The
        env's own buffer: read or copy it before the next step.
    :param observed: (N,) bool rows observed this step.
    :param live: (N,) bool rows live after the step (they act next).
    :param rewards: (N,) float64 (0 where not stepped). :param terminated, truncated: (N,)
        bool, as the dicts' terminations and truncations (joiners are truncated when the
        episode ends at this step). :param events: event name -> (N,) bool of the stepped rows.
    """

    observations: np.ndarray
    observed: np.ndarray
    live: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    events: dict[str, np.ndarray]


def leaving(flags: dict[str, np.ndarray], terminate_on: Sequence[str], time_up: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """(A,) terminated (an event of ``terminate_on``) and truncated (time up and not
    terminated) masks of the stepped agents, as :meth:`StepDicts.stepped` decides them."""
    term = np.zeros(np.asarray(time_up).shape[0], bool)
    for name in terminate_on:
        term |= flags[name]
    return term, ~term & np.asarray(time_up, bool)
