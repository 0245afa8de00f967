"""Expert actions: the normalised actions that drive the agents along their recorded tracks."""

from __future__ import annotations

import numpy as np

from magail_sumo.sim import dynamics

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


def expert_actions(env: SumoDrivingEnv) -> dict[str, np.ndarray]:
    """Per live agent, the (2,) float32 action in [-1, 1]² (accel, steer) that moves it from its
    current bicycle state to its recorded position at the next log step
    (:func:`magail_sumo.sim.dynamics.inverse`, then clipped to the env's limits)."""
    st = env.agent_states()
    if not st.names:
        return {}
    x, y, yaw = log_targets(env, st.rows, min(env.t + 1, env.scene.num_steps - 1))
    accel, steer = dynamics.inverse(st.state, x, y, st.wheelbase, env.dt, yaw_next=yaw)
    act = dynamics.normalise(accel, steer, env.config.limits,
                             env.config.action_layout).astype(np.float32)
    return dict(zip(st.names, act))
