"""A GameFormer checkpoint as a closed-loop sim agent (``magail-sumo evaluate --policy
RUN/checkpoints/latest.pt`` with a ``gameformer`` run; :mod:`magail_sumo.policies.registry`
dispatches on the checkpoint's algorithm).

The agent uses the optional ``begin(scene, env)`` hook of the evaluation rollout
(:func:`magail_sumo.evaluation.methods.policy_rollout`): told the scene and the env after
reset, it keeps the last ``history_steps`` world-frame states of every object — the simulated
state (``env.agent_states()``) of the live agents, the recorded one of every other object — and
every ``replan_every`` steps (and when an agent first appears) predicts every live agent in its
own sample (:func:`~magail_sumo.models.gameformer_features.build_sample`) from that *simulated*
history. Each agent follows one mode of the last level (K): per rollout each agent draws one
u ~ U(0, 1) (from the rollout seed, agents in sorted-name order) and at every replan takes the
first mode whose cumulative softmax score exceeds u (``deterministic``: the highest-scoring
mode). The plan is tracked through the bicycle model (:meth:`GameFormerPolicy._track`: its
speed profile by a proportional speed controller, its path by pure pursuit of a look-ahead
point; steering angle from the bicycle curvature ``tan(steer) / wheelbase``) and returned as a
normalised ``[accel, steer]`` (:func:`magail_sumo.sim.dynamics.normalise`) in the env's limits
and action layout.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from magail_sumo.models.gameformer_features import (Frame, History, build_sample, collate,
                                                   log_history, map_chunks)
from magail_sumo.sim import dynamics
from magail_sumo.training.gameformer.run import load_gameformer


class GameFormerPolicy:
    """Closed-loop GameFormer agent (module doc).

    :param model: the network (eval mode). :param cfg: its run config (TrainConfig).
    :param seed: the rollout seed. :param deterministic: follow the highest-scoring mode.
    """

    def __init__(self, model, cfg, name: str = "", seed: int = 0,
                 deterministic: bool = False) -> None:
        self.model, self.cfg, self.name = model, cfg, name
        self.g = cfg.gameformer
        self.deterministic = bool(deterministic)
        self.rng = np.random.default_rng(int(seed))
        self.env = None

    def reseed(self, seed: int) -> None:
        """Be the policy built with ``seed`` (the next rollout): its mode draws restart from
        ``seed``; the rollout's ``begin`` resets the rest."""
        self.rng = np.random.default_rng(int(seed))
        self.env = None

    def begin(self, scene, env) -> None:
        """Start of a rollout: the scene, the env (just reset)."""
        self.scene, self.env = scene, env
        self.chunks = map_chunks(scene, self.g.map_points, self.g.map_spacing)
        h = log_history(scene, env.t, self.g.history_steps)
        self.hist = {k: np.array(getattr(h, k)) for k in
                     ("x", "y", "heading", "vx", "vy", "valid", "length", "width", "type")}
        self.t = env.t
        self.row_of = {str(int(i)): k for k, i in enumerate(scene.tracks.id.tolist())}
        self.u: dict[str, float] = {}
        self.plans: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}
        self.plan_start: dict[str, tuple[float, float]] = {}
        self.last_plan = None

    def _record(self, st) -> None:
        """Shift the history to step ``env.t`` (recorded states) and put the live agents'
        simulated states into its last column."""
        h, tr, t = self.hist, self.scene.tracks, self.env.t
        if t != self.t:
            for _ in range(t - self.t):
                for k in ("x", "y", "heading", "vx", "vy", "valid"):
                    h[k][:, :-1] = h[k][:, 1:]
                nxt = min(self.t + 1, tr.num_steps - 1)
                ok = tr.valid[:, nxt] & (self.t + 1 < tr.num_steps)
                h["valid"][:, -1] = ok
                for k, src in (("x", tr.x), ("y", tr.y), ("heading", tr.heading),
                               ("vx", tr.vx), ("vy", tr.vy)):
                    h[k][:, -1] = np.where(ok, src[:, nxt], 0.0)
                self.t += 1
        if st.names:
            r = st.rows
            s = st.state
            h["x"][r, -1], h["y"][r, -1], h["heading"][r, -1] = s.x, s.y, s.yaw
            h["vx"][r, -1], h["vy"][r, -1] = s.speed * np.cos(s.yaw), s.speed * np.sin(s.yaw)
            h["valid"][r, -1] = True

    @torch.no_grad()
    def _replan(self, names: list[str], rows: np.ndarray) -> None:
        g = self.g
        hist = History(**self.hist)
        samples = [build_sample(hist, int(r), self.chunks, g.max_agents, g.map_elements)
                   for r in rows]
        b = collate(samples)
        dev = self.cfg.device
        traj, score = self.model(b["agents"].to(dev), b["agent_mask"].to(dev),
                                 b["map"].to(dev), b["map_mask"].to(dev))[-1]
        traj = traj[:, 0, :, :, :2].double().cpu().numpy()  # (A, M, T, 2)
        prob = torch.softmax(score[:, 0].double(), -1).cpu().numpy()  # (A, M)
        for n in sorted(names):  # one draw order per rollout
            if n not in self.u:
                self.u[n] = float(self.rng.random())
        for k, n in enumerate(names):
            if self.deterministic:
                m = int(prob[k].argmax())
            else:
                m = int(min(np.searchsorted(np.cumsum(prob[k]), self.u[n], side="right"),
                            prob.shape[1] - 1))
            fr = Frame(*samples[k]["frame"])
            wx, wy = fr.to_world(traj[k, m, :, 0], traj[k, m, :, 1])
            self.plans[n] = (self.env.t, wx, wy)
            self.plan_start[n] = (fr.x, fr.y)

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self.env is None:
            raise RuntimeError("GameFormerPolicy needs begin(scene, env) before act "
                               "(evaluation's policy rollout calls it)")
        env = self.env
        st = env.agent_states()
        self._record(st)
        if not st.names:
            return {}
        due = self.last_plan is None or env.t - self.last_plan >= self.g.replan_every
        new = [k for k, n in enumerate(st.names) if n not in self.plans]
        if due or new:
            pick = list(range(len(st.names))) if due else new
            self._replan([st.names[k] for k in pick], st.rows[pick])
            if due:
                self.last_plan = env.t
        accel, steer = self._track(st)
        lim = env.config.limits
        a = dynamics.normalise(np.clip(accel, -lim.max_brake, lim.max_accel),
                               np.clip(steer, -lim.max_steer, lim.max_steer), lim,
                               env.config.action_layout).astype(np.float32)
        return dict(zip(st.names, a))

    def _track(self, st) -> tuple[np.ndarray, np.ndarray]:
        """(accel m/s², steer rad) following each agent's plan: the speed of the plan over the
        next :data:`SPEED_WINDOW` steps reached with time constant :data:`SPEED_TAU`, and
        pure pursuit of the first plan point at least ``max(LOOKAHEAD_M, speed·LOOKAHEAD_S)``
        ahead (curvature ``2 sin(α) / d`` to it; straight on where the plan stays closer)."""
        f = self.g.model.future_steps
        s = st.state
        accel, steer = np.zeros(len(st.names)), np.zeros(len(st.names))
        for k, n in enumerate(st.names):  # one plan per agent, 80 points
            t0, wx, wy = self.plans[n]
            j = min(max(self.env.t - t0, 0), f - 1)
            j2 = min(j + SPEED_WINDOW, f - 1)
            px = np.concatenate([[self.plan_start[n][0]], wx])
            py = np.concatenate([[self.plan_start[n][1]], wy])
            v_target = np.hypot(px[j2 + 1] - px[j], py[j2 + 1] - py[j]) / (
                (j2 + 1 - j) * self.env.dt)
            accel[k] = (v_target - s.speed[k]) / SPEED_TAU
            ahead = np.hypot(wx[j:] - s.x[k], wy[j:] - s.y[k])
            far = np.flatnonzero(ahead >= max(LOOKAHEAD_M, abs(s.speed[k]) * LOOKAHEAD_S))
            if far.size:
                i = j + far[0]
                alpha = np.arctan2(wy[i] - s.y[k], wx[i] - s.x[k]) - s.yaw[k]
                curv = 2.0 * np.sin(alpha) / ahead[far[0]]
                steer[k] = np.arctan(curv * st.wheelbase[k])
        return accel, steer


#: plan steps over which the target speed is measured
SPEED_WINDOW = 5
#: s, time constant of the speed control
SPEED_TAU = 0.5
#: pure-pursuit look-ahead: at least this many metres, and this many seconds at the speed
LOOKAHEAD_M, LOOKAHEAD_S = 3.0, 0.8


def load_gameformer_policy(path: str | Path, seed: int = 0, deterministic: bool = False
                           ) -> GameFormerPolicy:
    """The closed-loop agent of a gameformer checkpoint (:class:`CheckpointError` when the
    file is not one)."""
    torch.set_num_threads(1)  # evaluation runs several worker processes
    model, cfg = load_gameformer(path, device="cpu")
    return GameFormerPolicy(model, cfg, str(path), seed=seed, deterministic=deterministic)
