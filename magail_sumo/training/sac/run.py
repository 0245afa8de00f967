"""A ``sac`` / ``sac_gail`` run: env, replay buffers, agent, discriminator, one update of
``train_freq`` env steps and ``gradient_steps`` gradient steps, checkpoints and exact resume
(:mod:`magail_sumo.training.sac`); run by :func:`~magail_sumo.training.loop.run_loop`."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch
from stable_baselines3.common.logger import Logger

from magail_sumo.config import to_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import printable
from magail_sumo.sensors.observation import observation_names

from ..adversarial import AdversarialReward
from ..algorithms import load_expert
from ..checkpoints import (CHECKPOINT_FORMAT, CheckpointError, decode_env_state, encode_env_state,
                           load_into, plain, save_checkpoint, tensor_field)
from ..config import TrainConfig
from ..envs import make_pool_env
from ..loop import Progress, run_loop
from ..rng import decode_rng, encode_rng, rng_state, set_rng_state
from .agent import SacAgent, SacStats, make_sac_model
from .buffer import ACT_DIM, ReplayBuffer, sample_batch
from .transitions import buffer_rows, step_transitions, task_reward

#: second entropy word of the seed of the replay sampler (apart from the other streams)
SAC_STREAM = 0x5AC

class SacRun:
    """The objects of a SAC run: env (with the discriminator reward for ``sac_gail``), replay
    buffers, agent, discriminator and its trainer.

    :param cfg: run config (``workers.count`` None is resolved). :param expert: expert
        demonstrations (``sac_gail``; None for ``sac``). :param log: one-line messages.
    """

    def __init__(self, cfg: TrainConfig, expert=None,
                 log: Callable[[str], None] | None = None) -> None:
        self.log = log or (lambda msg: None)
        self.expert = expert
        self.gail = cfg.algorithm == "sac_gail"
        if self.gail and expert is None:
            raise ValueError("sac_gail needs expert data")
        d = cfg.discriminator
        if self.gail and d.decomposes:
            expert.require_poses(f"discriminator.kind {d.kind!r}")
        cfg, self.venv = make_pool_env(cfg, self.log)
        self.cfg = cfg
        try:
            self.names = observation_names(cfg.env.observation)
            self.model = make_sac_model(cfg)
            self.agent = SacAgent(self.model, cfg.sac)
            width = len(self.names) + 1
            self.buffer = ReplayBuffer(cfg.sac.buffer_size, width)
            self.collisions = ReplayBuffer(cfg.sac.buffer_size, width)
            self.rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, SAC_STREAM]))
            self.env = self.venv
            self.discriminator = self.disc_trainer = self.reward = None
            if self.gail:
                self.reward = AdversarialReward.build(cfg, self.venv, expert)
                self.discriminator, self.env = self.reward.discriminator, self.reward.env
                self.disc_trainer = self.reward.trainer
        except BaseException:
            self.venv.close()
            raise
        self.last_obs: np.ndarray | None = None
        self.update = 0
        self.transitions = 0  # stored (non-absorbing) transitions so far
        self.last_stats: SacStats | None = None
        self.last_disc = None
        self.last_totals: dict[str, float] = {}

    progress_phase = "sac_updates"

    @property
    def steps_per_update(self) -> int:
        """Vector env steps of one update (``sac.train_freq``)."""
        return self.cfg.sac.train_freq

    def start(self) -> None:
        """Reset the env (a new run)."""
        self.last_obs = self.env.reset()

    def actions(self) -> np.ndarray:
        """(num_envs, 2) actions of every slot (free slots' are ignored by the env)."""
        n = self.venv.num_envs
        if self.transitions < self.cfg.sac.learning_starts:
            return self.rng.uniform(-1.0, 1.0, (n, ACT_DIM)).astype(np.float32)
        x = np.concatenate([self.last_obs, np.zeros((n, 1), np.float32)], axis=1)
        with torch.no_grad():
            a = self.model.act(torch.as_tensor(x, device=self.model.log_alpha.device))
        return a.cpu().numpy().astype(np.float32)

    def env_step(self) -> dict[str, float]:
        """One env step: act, store the step's transitions; reward statistics."""
        c = self.cfg.sac
        actions = self.actions()
        obs, rew, dones, infos = self.env.step(actions)
        tr = step_transitions(self.last_obs, actions, obs, dones, infos,
                              self.venv.prev_slot_active)
        task = task_reward(tr.obs, tr.action, tr.next_obs, tr.events, c.task_reward, self.names) \
            if self.cfg.env.observation.layout == "ego" else np.zeros(len(tr.slots), np.float32)
        reward = np.asarray(rew, np.float32)[tr.slots] if self.gail else task
        if self.transitions < c.learning_starts and len(tr.slots):
            self.model.normalizer.update(torch.as_tensor(tr.obs))
        main, col = buffer_rows(tr, reward, self.gail, c.absorbing_reward)
        self.buffer.add(**main)
        self.collisions.add(**col)
        self.transitions += len(tr.slots)
        self.last_obs = obs
        speed = float(tr.obs[:, self.names.index("speed")].sum()) if "speed" in self.names \
            else 0.0
        return {"reward": float(reward.sum()), "task": float(task.sum()), "n": len(tr.slots),
                "collisions": int(tr.events["collision"].sum()), "speed": speed}

    def run_update(self) -> dict[str, float]:
        """One update (module doc); totals of the update's env steps (also kept as
        :attr:`last_totals`)."""
        c = self.cfg.sac
        tot = {"reward": 0.0, "task": 0.0, "n": 0, "collisions": 0, "speed": 0.0}
        self.last_totals = tot
        for _ in range(c.train_freq):
            for k, v in self.env_step().items():
                tot[k] += v
        if self.gail:
            steps = self.env.pop_rollout()
            if steps is not None:
                self.last_disc = self.disc_trainer.train(steps)
        if self.transitions >= c.learning_starts and len(self.buffer):
            self.model.train()
            for _ in range(c.gradient_steps):
                batch = sample_batch(self.buffer, self.collisions, c.batch_size,
                                     c.collision_share, self.rng)
                self.last_stats = self.agent.train_step(batch)
        self.update += 1
        return tot

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """The run's state as a checkpoint (tensors and plain data only)."""
        state = {
            "format": CHECKPOINT_FORMAT, "update": self.update, "config": to_dict(self.cfg),
            "policy": self.model.state_dict(), "sac": self.agent.state_dict(),
            "transitions": self.transitions,
            "sampler_rng": plain(self.rng.bit_generator.state),
            "last_obs": torch.from_numpy(np.array(self.last_obs)),
            "env_state": encode_env_state(self.venv.get_state()),
            "env_counters": [int(self.venv.agent_steps), int(self.venv.episodes)],
            "buffers": {"main": self.buffer.state_dict(),
                        "collision": self.collisions.state_dict()}
            if self.cfg.sac.save_buffers else None,
            "rng": encode_rng(rng_state())}
        if self.gail:
            state.update(self.reward.state_dict())
        return state

    def load_state_dict(self, state: dict, where: Path) -> None:
        """Restore :meth:`state_dict`'s state (replaying the env); :class:`CheckpointError`
        (one line, naming ``where``) when it does not fit this run."""
        try:
            rng = decode_rng(state["rng"])
            last_obs = tensor_field(state["last_obs"], "last_obs").numpy()
            env_state = decode_env_state(self.venv, state["env_state"])
            agent_steps, episodes = (int(v) for v in state["env_counters"])
            transitions, update = state["transitions"], state["update"]
            if type(transitions) is not int or transitions < 0:
                raise ValueError("transitions is not a count")
            if last_obs.shape != (self.venv.num_envs, self.venv.obs_dim):
                raise ValueError(f"last_obs has shape {tuple(last_obs.shape)}, the env "
                                 f"{(self.venv.num_envs, self.venv.obs_dim)}")
            load_into(self.model, state["policy"], "policy", where)
            self.agent.load_state_dict(state["sac"], where)
            buffers = state["buffers"]
            if buffers is not None:
                self.buffer.load_state_dict(buffers["main"])
                self.collisions.load_state_dict(buffers["collision"])
            self.rng.bit_generator.state = state["sampler_rng"]
            if self.gail:
                self.reward.load_state_dict(state, where)
        except KeyError as exc:
            raise CheckpointError(f"{where}: checkpoint lacks {printable(str(exc.args[0]), 60)}"
                                  ) from None
        except (RuntimeError, ValueError, TypeError, AttributeError) as exc:
            raise CheckpointError(f"{where}: checkpoint does not fit this run "
                                  f"({type(exc).__name__}: {printable(str(exc), 200)})") from None
        if buffers is None:
            self.log(f"{where}: no replay buffers in the checkpoint: the resumed run starts "
                     "with empty buffers (approximate resume)")
            transitions = 0
        try:
            obs = self.env.set_state(env_state) if self.gail else self.venv.set_state(env_state)
        except MagailSumoError as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CheckpointError(f"{where}: replaying the env state failed "
                                  f"({printable(first, 200)})") from None
        if not np.array_equal(obs, last_obs):
            raise CheckpointError(f"{where}: replaying the env state did not reproduce the saved "
                                  "observation (scene files or SUMO changed?)")
        self.venv.agent_steps, self.venv.episodes = agent_steps, episodes
        self.last_obs, self.transitions, self.update = obs, transitions, update
        set_rng_state(rng)

    def save(self, run_dir: Path) -> Path:
        return save_checkpoint(run_dir, self.state_dict(), self.update)

    def begin(self, progress: Progress) -> None:
        """A new run: the observation normaliser from the expert states (``sac_gail``), then
        the first reset."""
        if self.expert is not None:
            self.model.normalizer.update(torch.as_tensor(self.expert.s))
        self.start()

    def attach_logger(self, logger: Logger) -> None:
        self.logger = logger

    def summarise(self, logger: Logger) -> str:
        """Records the update's rewards, buffers, SAC and discriminator statistics; the update
        line's tail."""
        tot = self.last_totals
        n = max(tot["n"], 1)
        st, ds = self.last_stats, self.last_disc
        logger.record("sac/reward_per_agent_step", tot["reward"] / n)
        logger.record("sac/task_reward_per_agent_step", tot["task"] / n)
        logger.record("sac/collisions", tot["collisions"])
        logger.record("sac/buffer", len(self.buffer))
        logger.record("sac/collision_buffer", len(self.collisions))
        logger.record("env/agent_steps_total", self.venv.agent_steps)
        if "speed" in self.names:  # as PPO's DiscriminatorCallback logs it
            logger.record("diag/speed_policy", tot["speed"] / n)
        if st is not None:
            for k, v in vars(st).items():
                logger.record(f"sac/{k}", v)
            logger.record("sac/learning_rate", self.agent.learning_rate())
        if ds is not None:
            for k, v in vars(ds).items():
                logger.record(f"discriminator/{k}", v)
        return (f", reward {tot['reward'] / n:.3f}/agent-step (task "
                f"{tot['task'] / n:.3f}), buffer {len(self.buffer)} + {len(self.collisions)} "
                "collisions"
                + (f", Q loss {st.q_loss:.3f} alpha {st.alpha:.3f} lr "
                   f"{self.agent.learning_rate():.2e}" if st else "")
                + (f", D loss {ds.loss:.3f} acc expert {ds.expert_accuracy:.2f} policy "
                   f"{ds.policy_accuracy:.2f}" if ds else ""))

    def log_step(self) -> int:
        return self.venv.agent_steps

    def close(self) -> None:
        self.venv.close()


def train_sac(cfg: TrainConfig, run_dir: Path, ckpt: dict | None,
              log: Callable[[str], None], progress: Progress) -> Path:
    """Run (or resume, from ``ckpt``) a ``sac`` / ``sac_gail`` run in ``run_dir``
    (:func:`~magail_sumo.training.loop.run_loop`)."""
    expert = load_expert(cfg) if cfg.algorithm == "sac_gail" else None
    return run_loop(SacRun(cfg, expert, log=log), run_dir, ckpt, log, progress)


__all__ = ["ReplayBuffer", "SacAgent", "SacRun", "Transitions",
           "buffer_rows", "collision_count", "sample_batch",
           "step_transitions", "task_reward", "train_sac"]
