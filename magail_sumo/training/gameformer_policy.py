"""A GameFormer checkpoint as a closed-loop sim agent (``magail-sumo evaluate --policy
RUN/checkpoints/latest.pt`` with a ``gameformer`` run; :mod:`magail_sumo.training.policy_loader`
dispatches on the checkpoint's algorithm).

The agent uses the optional ``begin(scene, env)`` hook of the evaluation rollout
(:func:`magail_sumo.evaluation.rollouts._policy_rollout`): told the scene and the env after
reset, it keeps the last ``history_steps`` world-frame states of every object — the simulated
state (``env.agent_states()``) of the live agents, the recorded one of every other object — and
every ``replan_every`` steps (and when an agent first appears) predicts every live agent in its
own sample (:func:`~magail_sumo.training.gameformer_data.build_sample`) from that *simulated*
history. Each agent follows one mode of the last level (K): per rollout each agent draws one
u ~ U(0, 1) (from the rollout seed, agents in sorted-name order) and at every replan takes the
first mode whose cumulative softmax score exceeds u (``deterministic``: the highest-scoring
mode). The plan's next position is tracked through the bicycle model's inverse
(:func:`magail_sumo.sim.dynamics.inverse`, heading target along the planned path) and returned
as a normalised ``[accel, steer]`` in the env's limits and action layout.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from magail_sumo.sim import dynamics

from .gameformer_data import build_sample, collate, log_history, map_chunks, History, Frame


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
        self.plans: dict[str, tuple[int, np.ndarray, np.ndarray, np.ndarray]] = {}
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
            px, py = np.concatenate([[fr.x], wx]), np.concatenate([[fr.y], wy])
            dx, dy = np.diff(px), np.diff(py)
            yaw = np.arctan2(dy, dx)
            still = np.hypot(dx, dy) < 0.05
            yaw = np.where(still, np.nan, yaw)
            for t in range(len(yaw)):  # hold the last heading where the plan does not move
                if np.isnan(yaw[t]):
                    yaw[t] = yaw[t - 1] if t else fr.heading
            self.plans[n] = (self.env.t, wx, wy, yaw)

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
        f = self.g.model.future_steps
        tx, ty, tyaw = (np.empty(len(st.names)) for _ in range(3))
        for k, n in enumerate(st.names):
            t0, wx, wy, yaw = self.plans[n]
            j = min(env.t - t0, f - 1)
            tx[k], ty[k], tyaw[k] = wx[j], wy[j], yaw[j]
        accel, steer = dynamics.inverse(st.state, tx, ty, st.wheelbase, env.dt, yaw_next=tyaw)
        lim = env.config.limits
        a = dynamics.normalise(np.clip(accel, -lim.max_brake, lim.max_accel),
                               np.clip(steer, -lim.max_steer, lim.max_steer), lim,
                               env.config.action_layout).astype(np.float32)
        return dict(zip(st.names, a))


def load_gameformer_policy(path: str | Path, seed: int = 0, deterministic: bool = False
                           ) -> GameFormerPolicy:
    """The closed-loop agent of a gameformer checkpoint (:class:`CheckpointError` when the
    file is not one)."""
    from .gameformer import load_gameformer

    torch.set_num_threads(1)  # evaluation runs several worker processes
    model, cfg = load_gameformer(path, device="cpu")
    return GameFormerPolicy(model, cfg, str(path), seed=seed, deterministic=deterministic)
