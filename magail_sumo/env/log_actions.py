"""Log actions: the normalised actions that drive the agents along their recorded tracks (the
expert actions of imitation; expert data are recorded from them by :mod:`magail_sumo.expert`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from magail_sumo.sim import dynamics

if TYPE_CHECKING:
    from .driving_env import SumoDrivingEnv

#: Limits wide enough to replay recorded tracks exactly (use as ``EnvConfig.limits`` for log
#: replay checks): WOMD tracks carry detection noise that asks for |accel| > 100 m/s² and
#: steering near 90° on single steps, far beyond the physical :class:`BicycleLimits` defaults.
REPLAY_LIMITS = dynamics.BicycleLimits(max_accel=1e3, max_brake=1e3, max_steer=1.5707,
                                       max_speed=100.0, max_reverse_speed=100.0)


def log_targets(env: SumoDrivingEnv, rows: np.ndarray, step: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Recorded centre positions (m, scene frame) and headings (rad) of track ``rows`` at
    ``step``; at invalid steps, positions interpolate linearly between the neighbouring valid
    steps (held at the ends) and the heading is the nearer valid step's."""
    tr = env.scene.tracks
    valid = tr.valid[rows]
    t_steps = valid.shape[1]
    steps = np.arange(t_steps)
    prev = np.where(valid[:, : step + 1], steps[None, : step + 1], -1).max(axis=1)
    nxt = np.where(valid[:, step:], steps[None, step:], t_steps).min(axis=1)
    prev_c = np.where(prev >= 0, prev, nxt).clip(0, t_steps - 1)
    nxt_c = np.where(nxt < t_steps, nxt, prev_c).clip(0, t_steps - 1)
    span = np.maximum(nxt_c - prev_c, 1)
    w = np.where(nxt_c > prev_c, (step - prev_c) / span, 0.0)
    x = tr.x[rows, prev_c] * (1 - w) + tr.x[rows, nxt_c] * w
    y = tr.y[rows, prev_c] * (1 - w) + tr.y[rows, nxt_c] * w
    yaw = np.where(w < 0.5, tr.heading[rows, prev_c], tr.heading[rows, nxt_c]).astype(np.float64)
    return x, y, yaw


def replay_actions(env: SumoDrivingEnv, rows: np.ndarray, state: dynamics.VehicleState,
                   wheelbase: np.ndarray, step: int, limits: dynamics.BicycleLimits,
                   layout: str = "accel_steer") -> np.ndarray:
    """(A, 2) float32 normalised actions (``limits``, ``layout``; clipped to [-1, 1]) that move
    vehicles in ``state`` (track ``rows``, ``wheelbase`` m) from log step ``step`` to their
    recorded pose at ``step + 1`` (:func:`log_targets`, :func:`magail_sumo.sim.dynamics.inverse`
    with the recorded heading as ``yaw_next``; in ``layout`` by
    :func:`magail_sumo.sim.dynamics.relayout`: offset 0 in ``accel_offset``)."""
    x, y, yaw = log_targets(env, rows, min(step + 1, env.scene.num_steps - 1))
    accel, steer = dynamics.inverse(state, x, y, wheelbase, env.dt, yaw_next=yaw)
    return dynamics.relayout(dynamics.normalise(accel, steer, limits), layout).astype(np.float32)


def training_actions(actions: np.ndarray, limits: dynamics.BicycleLimits,
                     layout: str = "accel_steer"
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expert actions normalised with :data:`REPLAY_LIMITS` (``accel_steer``) to the training
    scale: (A, 2) float32 normalised with ``limits`` in ``layout`` and clipped to [-1, 1] (the
    action a policy would have to output), plus the physical (A,) accel (m/s²) and steer
    (rad)."""
    accel, steer = dynamics.denormalise(np.asarray(actions, np.float64), REPLAY_LIMITS)
    act = dynamics.relayout(dynamics.normalise(accel, steer, limits), layout)
    return act.astype(np.float32), accel, steer


def expert_actions(env: SumoDrivingEnv, states=None) -> dict[str, np.ndarray]:
    """Per live agent, the (2,) float32 action in [-1, 1]² (accel, steer) that moves it from its
    current bicycle state to its recorded position at the next log step
    (:func:`magail_sumo.sim.dynamics.inverse`, then clipped to the env's limits).

    :param states: ``env.agent_states()`` when the caller already has them (keys follow
        their ``names``)."""
    st = env.agent_states() if states is None else states
    if not st.names:
        return {}
    act = replay_actions(env, st.rows, st.state, st.wheelbase, env.t, env.config.limits,
                         env.config.action_layout)
    return dict(zip(st.names, act))


def log_prev_actions(env: SumoDrivingEnv, until: int | None = None) -> np.ndarray:
    """(N, T, 2) float32: per track row and log step ``t``, the previous action the expert data
    (:mod:`magail_sumo.expert.record`) gives that vehicle at ``t``: the action of its step
    ``t - 1 -> t`` in ``env.config``'s training limits and action layout
    (:func:`training_actions`), 0 where it took none.

    It replays what the recording does, without SUMO (the bicycle states depend on the log
    alone): every route vehicle joins at its first valid step with :meth:`SumoDrivingEnv.
    log_state`, follows :func:`replay_actions` under :data:`REPLAY_LIMITS` (float32 actions,
    as the env receives them) until its last valid step, and moves by
    :func:`magail_sumo.sim.dynamics.step`. Steps after ``until`` (default: the log's end) are
    not computed (0). One loop over steps, arrays over the vehicles of each step.
    """
    tr = env.scene.tracks
    n, t_steps = tr.valid.shape
    out = np.zeros((n, t_steps, 2), np.float32)
    rows = np.sort(env.bundle.sumo_rows)
    first, last = env._first[rows], env._last[rows]
    live = first < t_steps
    rows, first, last = rows[live], first[live], last[live]
    if not rows.size:
        return out
    stop = t_steps - 1 if until is None else min(until, t_steps - 1)
    x, y, yaw, speed = (np.zeros(rows.size) for _ in range(4))
    wheelbase = dynamics.WHEELBASE_RATIO * env._length[rows]
    for s in range(int(first.min()), stop):  # the step s -> s + 1
        new = np.flatnonzero(first == s)
        if new.size:
            st = env.log_state(rows[new], s)
            x[new], y[new], yaw[new], speed[new] = st.x, st.y, st.yaw, st.speed
        # an agent acts from its first valid step until the step reaching its last one
        # (at least once: one valid step joins and leaves after a step)
        k = np.flatnonzero((first <= s) & ((s < last) | (s == first)))
        if not k.size:
            continue
        st = dynamics.VehicleState(x[k], y[k], yaw[k], speed[k])
        act = replay_actions(env, rows[k], st, wheelbase[k], s, REPLAY_LIMITS)
        clean = np.clip(np.nan_to_num(act.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0),
                        -1.0, 1.0)  # as the env takes it (magail_sumo.env.actions)
        accel, steer = dynamics.denormalise(clean, REPLAY_LIMITS)
        nxt = dynamics.step(st, accel, steer, wheelbase[k], env.dt, REPLAY_LIMITS)
        x[k], y[k], yaw[k], speed[k] = nxt.x, nxt.y, nxt.yaw, nxt.speed
        out[rows[k], s + 1] = training_actions(act, env.config.limits,
                                               env.config.action_layout)[0]
    return out
