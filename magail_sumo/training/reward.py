"""GAIL reward over vehicle sets: an SB3 ``VecEnvWrapper``.

Reward nets and the RL algorithm are kept apart (as in ``imitation``):
:class:`DiscriminatorRewardWrapper` turns env steps into rewards with a frozen discriminator and
records the policy's scene steps; :class:`~magail_sumo.training.discriminator_trainer.
DiscriminatorTrainer` fits the discriminator on expert vs policy scene steps;
:class:`~magail_sumo.training.gail.callbacks.DiscriminatorCallback` runs the trainer between PPO
rollouts and logs to SB3's logger (TensorBoard).

Token of a vehicle = ``concat(s, s')`` of one env step (``s'`` = the terminal observation when
the vehicle left). All vehicles of a scene step go through the discriminator together (the
transformer judges each in the context of the others; the MLP judges each alone), and the
reward of slot ``i`` is ``c_t·r_task + c_i·(−log(max(1 − sigmoid(D_i), floor)))``; free slots
get 0. ``r_task`` is the env reward minus the configured penalty of the reason an agent left
(collision, off-road) at that step.

Each scene step also keeps the vehicles' poses at the step of ``s`` ((x, y, yaw), scene frame,
m / rad; :attr:`~magail_sumo.env.vec_env.MultiSceneVecEnv.prev_slot_pos`), which the
decomposed discriminator (``uses_poses``) takes with the tokens, for the rewards and for its
training (the expert's poses come from the same env state); with ``social_coef`` λ > 0 the
imitation reward becomes ``r_i + λ·Σ_j w_ij·r_j`` over the vehicle's neighbours
(:meth:`~magail_sumo.models.decomposed.DecomposedDiscriminator.social_reward`). The other
discriminators ignore the poses.

The discriminator is frozen during a rollout, so with ``deferred=True`` (what training uses) the
imitation part is not computed step by step: the wrapper returns ``c_t·r_task`` and keeps the
scene tokens, and :meth:`DiscriminatorRewardWrapper.flush_rewards` computes the imitation reward
of every step of the rollout in a few large batched forwards (per scene, trimmed to the slots
that were ever occupied), added to the rollout buffer's rewards before the returns are computed
(:class:`~magail_sumo.training.gail.ppo.MaskedRolloutBuffer` ``reward_source``). Same rewards as the
per-step computation, up to float rounding.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
import torch
from stable_baselines3.common.vec_env import VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from magail_sumo.expert import SceneSteps
from magail_sumo.models.discriminator import imitation_reward

from .discriminator_loss import pose_args


class DiscriminatorRewardWrapper(VecEnvWrapper):
    """Replace the env reward by the GAIL reward of all vehicles of each scene (module doc).

    :param venv: a :class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` (or a wrapper of one).
    :param discriminator: module mapping ((B, V, 2F), (B, V) mask) to ((B, V), (B,)) logits.
    :param reward_t_coef, reward_i_coef: weights of the env (task) and imitation rewards.
    :param floor: floor of ``1 − sigmoid(D)`` in the log.
    :param device: torch device of the discriminator.
    :param social_coef: λ of the social reward (a discriminator with ``social_reward`` only;
        0: off).
    """

    def __init__(self, venv, discriminator: torch.nn.Module, reward_t_coef: float = 0.0,
                 reward_i_coef: float = 1.0, floor: float = 1e-4, device: str = "cpu",
                 deferred: bool = False, chunk_tokens: int = 65536,
                 penalties: dict[str, float] | None = None, social_coef: float = 0.0) -> None:
        super().__init__(venv)
        base = venv.unwrapped
        self.base = base
        self.discriminator = discriminator
        self.reward_t_coef, self.reward_i_coef, self.floor = reward_t_coef, reward_i_coef, floor
        self.device = torch.device(device)
        self.num_scenes = len(base.scene_slices)
        self.max_slots = max(base.slots)
        self.pos_in_scene = np.concatenate([np.arange(n) for n in base.slots])
        self._last_obs: np.ndarray | None = None
        self.rollout_x: list[np.ndarray] = []
        self.rollout_mask: list[np.ndarray] = []
        #: (scenes kept, S, 3) float32 poses at the step of s, with rollout_x
        self.rollout_pos: list[np.ndarray] = []
        if social_coef and not hasattr(discriminator, "social_reward"):
            raise ValueError(f"social_coef needs a discriminator with neighbours, not "
                             f"{type(discriminator).__name__}")
        self.social_coef = float(social_coef)
        self.deferred = deferred
        #: task reward −penalty at the step an agent leaves for that reason (e.g. "collision")
        self.penalties = {k: float(v) for k, v in (penalties or {}).items() if v}
        self.chunk_tokens = chunk_tokens
        #: torch CPU threads of :meth:`flush_rewards` (None: the current count)
        self.flush_threads: int | None = None
        #: deferred mode: per step since the last flush, the scenes kept in rollout_x (indices)
        self._pending: list[np.ndarray] = []
        self._pending_first = 0  # index into rollout_x of the first pending step
        #: deferred mode: the last step's (s, s_next, acted, poses) until the next step_async
        #: (or a flush) records its tokens: the workers step meanwhile
        self._raw: tuple | None = None
        #: deferred mode: once this many steps are pending, :meth:`step_async` computes their
        #: rewards while the workers step (None or 0: all at the flush)
        self.ahead_steps: int | None = None
        #: the blocks of pending steps computed ahead, in step order: futures of
        #: (raw rewards, present), on one background thread (torch runs its kernels without the
        #: GIL, so they overlap the rollout loop and the workers)
        self._ahead: list[Future] = []
        self._ahead_pool: ThreadPoolExecutor | None = None
        self.reward_sum = self.reward_sq = 0.0
        self.reward_n = 0

    def reset(self) -> np.ndarray:
        return self._begin(self.venv.reset())

    def set_state(self, state) -> np.ndarray:
        """Restore the env (``MultiSceneVecEnv.set_state``); the observation."""
        return self._begin(self.base.set_state(state))

    def _begin(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` after a reset or a restore: the step left raw is recorded, the pending steps
        and the blocks computed ahead are dropped."""
        self._record_raw()
        self._pop_pending()
        self._ahead = []
        self._last_obs = obs
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        """Send the actions; in deferred mode with :attr:`ahead_steps` pending steps, compute
        their imitation rewards while the workers step (the discriminator does not change
        during a rollout, so they are the rewards :meth:`flush_rewards` would give)."""
        self.venv.step_async(actions)
        self._record_raw()  # the previous step's tokens, while the workers step
        if self.deferred and self.ahead_steps and len(self._pending) >= self.ahead_steps:
            if self._ahead_pool is None:
                self._ahead_pool = ThreadPoolExecutor(1, thread_name_prefix="imitation-reward")
            self._ahead.append(self._ahead_pool.submit(
                self._rewards_of, *self._pop_pending(),
                (self.rollout_x, self.rollout_mask, self.rollout_pos)))

    def _pop_pending(self) -> tuple[list[np.ndarray], int]:
        """The pending steps and the index of their first entry in rollout_x; cleared."""
        steps, first = self._pending, self._pending_first
        self._pending = []
        self._pending_first = len(self.rollout_x)
        return steps, first

    def close(self) -> None:
        if self._ahead_pool is not None:
            self._ahead_pool.shutdown(wait=True, cancel_futures=True)
            self._ahead_pool = None
        self.venv.close()

    def scene_tokens(self, s: np.ndarray, s_next: np.ndarray, acted: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Slot tokens arranged per scene: ((K, S, 2F) float32, (K, S) bool)."""
        x = np.zeros((self.num_scenes, self.max_slots, 2 * s.shape[1]), np.float32)
        mask = np.zeros((self.num_scenes, self.max_slots), bool)
        sc, pos = self.base.slot_scene, self.pos_in_scene
        x[sc, pos] = np.concatenate([s, s_next], axis=1)
        mask[sc, pos] = acted
        return x, mask

    def scene_poses(self, slot_pos: np.ndarray) -> np.ndarray:
        """Slot poses (num_envs, 3) arranged per scene: (K, S, 3) float32 (0 where no slot)."""
        out = np.zeros((self.num_scenes, self.max_slots, 3), np.float32)
        out[self.base.slot_scene, self.pos_in_scene] = slot_pos
        return out

    @torch.no_grad()
    def rewards(self, x: np.ndarray, mask: np.ndarray, pos: np.ndarray | None = None
                ) -> np.ndarray:
        """(K, S) imitation rewards of scene tokens (0 where masked); ``pos`` (K, S, 3): the
        poses at the step of s (used by a discriminator that ``uses_poses``)."""
        disc = self.discriminator
        disc.eval()
        xt = torch.as_tensor(x, device=self.device)
        mt = torch.as_tensor(mask, device=self.device)
        pt = None if pos is None else torch.as_tensor(pos, device=self.device)
        args = pose_args(disc, pt)
        if args and hasattr(disc, "neighbours"):  # one neighbour search for logits and social
            nb = disc.neighbours(pt, mt)
            logits, _ = disc(xt, mt, pt, nb)
        else:
            nb = None
            logits, _ = disc(xt, mt, *args)
        r = imitation_reward(logits, self.floor).masked_fill(~mt, 0.0)
        if self.social_coef:
            r = disc.social_reward(r, pt, mt, self.social_coef, nb)
        return r.cpu().numpy()

    def step_wait(self) -> VecEnvStepReturn:
        obs, task, dones, infos = self.venv.step_wait()
        acted = self.base.prev_slot_active
        s_next = obs.copy()
        for i in np.flatnonzero(dones):
            term = infos[i].get("terminal_observation")
            if term is not None:
                s_next[i] = term
        if self.penalties:
            task = np.array(task, np.float32)
            for i in np.flatnonzero(dones):
                task[i] -= self.penalties.get(infos[i].get("reason"), 0.0)
        raw = (self._last_obs, s_next, acted, self.base.prev_slot_pos)
        if self.deferred:  # tokens recorded by the next step_async, after it sent the actions
            rew = (self.reward_t_coef * task).astype(np.float32)
            self._raw = raw
        else:
            x, mask, pos = self._record(*raw)
            r_i = self.rewards(x, mask, pos)[self.base.slot_scene, self.pos_in_scene]
            rew = (self.reward_t_coef * task + self.reward_i_coef * r_i).astype(np.float32)
            self._add_stats(r_i[acted])
        rew[~acted] = 0.0
        self._last_obs = obs
        return obs, rew, dones, infos

    def _record(self, s: np.ndarray, s_next: np.ndarray, acted: np.ndarray,
                slot_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Append one step's scene tokens and poses to the rollout record (scenes with an
        agent that acted; deferred mode: listed as pending); the step's (x, mask, pos)."""
        x, mask = self.scene_tokens(s, s_next, acted)
        pos = self.scene_poses(slot_pos)
        keep = mask.any(axis=1)
        if self.deferred:
            self._pending.append(np.flatnonzero(keep))
        if keep.any():
            self.rollout_x.append(x[keep])
            self.rollout_mask.append(mask[keep])
            self.rollout_pos.append(pos[keep])
        return x, mask, pos

    def _record_raw(self) -> None:
        """Record the step :meth:`step_wait` left raw (deferred mode), if any."""
        raw, self._raw = self._raw, None
        if raw is not None:
            self._record(*raw)

    def _add_stats(self, ra: np.ndarray) -> None:
        self.reward_sum += float(ra.sum())
        self.reward_sq += float((ra ** 2).sum(dtype=np.float64))
        self.reward_n += int(ra.size)

    def flush_rewards(self) -> np.ndarray:
        """Deferred mode: ``c_i`` × the imitation rewards of the steps since the last flush,
        (steps, num_envs) float32 (0 for free slots): those :meth:`step_async` computed ahead,
        and the rest in batched forwards with :attr:`flush_threads` torch threads (the scene
        workers wait meanwhile); cleared."""
        threads = torch.get_num_threads()
        if self.flush_threads and self.flush_threads != threads:
            torch.set_num_threads(self.flush_threads)
        try:
            return self._flush_rewards()
        finally:
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)

    def _flush_rewards(self) -> np.ndarray:
        self._record_raw()
        ahead, self._ahead = self._ahead, []
        blocks = [f.result() for f in ahead]
        blocks.append(self._rewards_of(*self._pop_pending()))
        out = np.concatenate([b[0] for b in blocks])
        self._add_stats(out[np.concatenate([b[1] for b in blocks])])
        return self.reward_i_coef * out

    def _rewards_of(self, steps: list[np.ndarray], first: int, recorded: tuple | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """The raw imitation rewards (steps, num_envs) float32 of pending ``steps`` (whose
        entries start at ``rollout_x[first]``) and where an agent acted (bool), in batched
        forwards. ``recorded``: the (rollout_x, rollout_mask, rollout_pos) lists to read (None:
        the current ones); only entries already appended are read, and they never change."""
        rx, rm, rp = recorded or (self.rollout_x, self.rollout_mask, self.rollout_pos)
        out = np.zeros((len(steps), self.num_envs), np.float32)
        present = np.zeros(out.shape, bool)
        # rollout_x[first + entry[j]] holds the scenes steps[j] of step j (in that order): one
        # pass lists each scene's (step, row) pairs; each scene's rows are then gathered trimmed
        # to its slots ever occupied (no copy of the whole padded rollout)
        entry = first + np.cumsum([len(k) > 0 for k in steps]) - 1
        rows_of: list[list[tuple[int, int]]] = [[] for _ in range(self.num_scenes)]
        for j, sc in enumerate(steps):
            for i, k in enumerate(sc.tolist()):
                rows_of[k].append((j, i))
        for k, at in enumerate(rows_of):
            if not at:
                continue
            js = np.array([j for j, _ in at])
            m = np.stack([rm[entry[j]][i] for j, i in at])
            v = int(m.any(axis=0).nonzero()[0].max()) + 1
            m = m[:, :v]
            x = np.stack([rx[entry[j]][i, :v] for j, i in at])
            p = np.stack([rp[entry[j]][i, :v] for j, i in at])
            per = max(1, self.chunk_tokens // v)
            r = np.concatenate([self.rewards(x[i:i + per], m[i:i + per], p[i:i + per])
                                for i in range(0, len(at), per)])
            start = self.base.scene_slices[k].start
            out[js, start:start + v] = r
            present[js, start:start + v] = m
        return out, present

    def pop_rollout(self) -> SceneSteps | None:
        """The policy scene steps recorded since the last call (padded, with the poses at the
        step of s), cleared."""
        self._record_raw()
        if not self.rollout_x:
            return None
        x, m = np.concatenate(self.rollout_x), np.concatenate(self.rollout_mask)
        p = np.concatenate(self.rollout_pos)
        self.rollout_x, self.rollout_mask, self.rollout_pos = [], [], []
        self._pending_first = 0
        return SceneSteps(x, m, p)

    def pop_reward_stats(self) -> dict[str, float]:
        """Mean and std of the imitation reward per agent-step since the last call, cleared."""
        n = max(self.reward_n, 1)
        mean = self.reward_sum / n
        std = float(np.sqrt(max(self.reward_sq / n - mean ** 2, 0.0)))
        out = {"imitation_mean": mean, "imitation_std": std, "agent_steps": float(self.reward_n)}
        self.reward_sum = self.reward_sq = 0.0
        self.reward_n = 0
        return out
