"""GAIL / MAGAIL with a PPO generator (``algorithm: gail``): the scene-pool env, the adversarial
reward (:class:`~magail_sumo.training.adversarial.AdversarialReward`), masked PPO
(:class:`~magail_sumo.training.gail.ppo.MaskedPPO`, with the optional behavioural-cloning regulariser)
and their callbacks, run update by update with checkpoints and exact resume.

A checkpoint (:mod:`~magail_sumo.training.checkpoints`) holds the policy (with its observation
normaliser and its critic, MLP or transformer), the PPO optimiser and current learning rate, the
discriminator (with its normaliser) and its optimiser, the discriminator sampler's RNG, the PPO
behavioural-cloning regulariser's expert sampler RNG and update count, the torch / numpy / python
RNG states, SB3's counters and last observation (:data:`SB3_RESUME_STATE`), and the env state as
per-scene (episode, actions since reset) — replayed in fresh workers on resume, so a resumed run
continues exactly as if uninterrupted. (A transformer critic's slot→scene layout is not state:
:class:`~magail_sumo.training.gail.ppo.MaskedPPO` takes it from the env it is built on.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import Logger

from magail_sumo.config import ConfigError, to_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.expert import ExpertDataset
from magail_sumo.models.policies import TanhGaussianPolicy
from magail_sumo.outputs import printable

from ..adversarial import AdversarialReward
from ..checkpoints import (CHECKPOINT_FORMAT, CheckpointError, decode_env_state, encode_state,
                           load_into, plain, save_checkpoint, tensor_field)
from ..config import TrainConfig
from ..policies import policy_kwargs
from ..rng import decode_rng, rng_state, set_rng_state
from ..algorithms import load_expert
from ..bc import behavioural_cloning
from ..envs import make_pool_env
from ..loop import Progress, run_loop
from .callbacks import DiscriminatorCallback
from .ppo import KLAdaptiveLR, MaskedPPO

#: second entropy word of the seed of the PPO behavioural-cloning regulariser's expert sampler
#: (a stream apart from the discriminator sampler's, seeded with the run seed alone)
BC_STREAM = 0xBC
#: the private attributes of SB3's ``OnPolicyAlgorithm`` a checkpoint keeps, each because exact
#: resume needs it: ``_n_updates`` (the gradient-step count SB3 logs and schedules by),
#: ``_last_obs`` (the observation the next rollout starts from; checked against the replayed
#: env), ``_last_episode_starts`` (which slots begin an episode: GAE cuts there). Everything
#: else is public API (``num_timesteps``, ``learning_rate``, the policy and its optimiser).
SB3_RESUME_STATE = ("_n_updates", "_last_obs", "_last_episode_starts")
#: the deferred imitation rewards are computed every this many rollout steps, while the scene
#: workers step (between sending the actions and waiting for them), instead of all after the
#: rollout; the same rewards (the discriminator is fixed during a rollout), off the critical path
#: (README "Benchmarks": train_throughput.py)
REWARD_AHEAD_STEPS = 64


class TorchThreads(BaseCallback):
    """Torch CPU threads: ``rollout`` while the scene workers step, ``update`` for the
    discriminator fit and PPO epochs (the workers are idle then)."""

    def __init__(self, rollout: int, update: int) -> None:
        super().__init__(0)
        self.rollout, self.update = max(1, rollout), max(1, update)

    def _on_rollout_start(self) -> None:
        torch.set_num_threads(self.rollout)

    def _on_rollout_end(self) -> None:
        torch.set_num_threads(self.update)

    def _on_training_end(self) -> None:
        torch.set_num_threads(self.rollout)

    def _on_step(self) -> bool:
        return True


class GailRun:
    """The objects of a GAIL / MAGAIL run (env, reward wrapper, discriminator, PPO, callbacks),
    a :class:`~magail_sumo.training.loop.Run`.

    :param cfg: the run config (``workers.count`` None is resolved: :attr:`cfg` holds the
        number used). :param expert: expert demonstrations. :param log: one-line messages
        (scene pool, skipped scenes, replaced workers).
    """

    def __init__(self, cfg: TrainConfig, expert: ExpertDataset,
                 log: Callable[[str], None] | None = None) -> None:
        self.cfg, self.expert = cfg, expert
        d = cfg.discriminator
        if d.decomposes:  # before any worker starts
            expert.require_poses(f"discriminator.kind {d.kind!r}")
        self.log = log or (lambda msg: None)
        cfg, self.venv = make_pool_env(cfg, self.log)
        self.cfg = cfg
        try:
            p = cfg.ppo
            rollout = p.n_steps * self.venv.num_envs
            if p.batch_size > rollout:
                raise ConfigError(f"ppo.batch_size: {p.batch_size} is larger than a rollout "
                                  f"(ppo.n_steps {p.n_steps} x {self.venv.num_envs} agent slots "
                                  f"of the scenes = {rollout} agent-steps)")
            self.reward = AdversarialReward.build(cfg, self.venv, expert, deferred=True)
            self.discriminator = self.reward.discriminator
            self.wrapper, self.disc_trainer = self.reward.env, self.reward.trainer
            # the reward pass runs during the rollout, REWARD_AHEAD_STEPS steps at a time while
            # the workers step; the rest after it, on the update threads
            self.wrapper.ahead_steps = REWARD_AHEAD_STEPS
            self.wrapper.flush_threads = cfg.torch_threads_update or cfg.torch_threads
            self.model = MaskedPPO(
                TanhGaussianPolicy, self.wrapper, learning_rate=p.learning_rate,
                n_steps=p.n_steps, batch_size=p.batch_size, n_epochs=p.n_epochs, gamma=p.gamma,
                gae_lambda=p.gae_lambda, clip_range=p.clip_range,
                normalize_advantage=p.normalize_advantage, ent_coef=p.ent_coef,
                vf_coef=p.vf_coef, max_grad_norm=p.max_grad_norm,
                policy_kwargs=policy_kwargs(cfg), seed=cfg.seed, device=cfg.device, verbose=0,
                bc_expert=expert if p.bc_coef > 0 else None, bc_coef=p.bc_coef,
                bc_decay=p.bc_decay, bc_batch_size=p.bc_batch_size, prior_coef=p.prior_coef,
                bc_seed=np.random.SeedSequence([cfg.seed, BC_STREAM]))
            self.disc_callback = DiscriminatorCallback(self.wrapper, self.disc_trainer)
            cbs = [TorchThreads(cfg.torch_threads, cfg.torch_threads_update or cfg.torch_threads),
                   self.disc_callback]
            if p.desired_kl is not None:
                cbs.append(KLAdaptiveLR(p.desired_kl, p.lr_min, p.lr_max))
            self.callbacks = CallbackList(cbs)
        except BaseException:
            self.venv.close()
            raise
        # no output until a run sets its own (SB3 would otherwise make a /tmp/SB3-<time> folder
        # for every learn() call without a logger)
        self.model.set_logger(Logger(None, []))
        self.update = 0

    progress_phase = "updates"

    @property
    def steps_per_update(self) -> int:
        """Vector env steps of one PPO rollout (``ppo.n_steps``)."""
        return self.cfg.ppo.n_steps

    @property
    def policy(self) -> TanhGaussianPolicy:
        return self.model.policy

    def state_dict(self) -> dict:
        """The run's state as a checkpoint (tensors and plain data only)."""
        m = self.model
        return encode_state({
            "format": CHECKPOINT_FORMAT, "update": self.update, "config": to_dict(self.cfg),
            "policy": m.policy.state_dict(), "policy_optimizer": m.policy.optimizer.state_dict(),
            "learning_rate": float(m.learning_rate), "num_timesteps": m.num_timesteps,
            "n_updates": m._n_updates, "last_obs": m._last_obs,
            "last_episode_starts": m._last_episode_starts,
            **self.reward.state_dict(),
            "bc_regulariser": {"updates": m.bc_updates,
                               "rng": plain(m.bc_rng.bit_generator.state)},
            "env_state": self.venv.get_state(),
            "env_counters": (self.venv.agent_steps, self.venv.episodes),
            "rng": rng_state()})

    def load_state_dict(self, state: dict, where: Path) -> None:
        """Restore :meth:`state_dict`'s state (replaying the env); :class:`CheckpointError`
        (one line, naming ``where``) when it does not fit this run."""
        m = self.model
        try:  # decode and check the plain parts first: cheap, before the env replay
            rng = decode_rng(state["rng"])
            last_obs = tensor_field(state["last_obs"], "last_obs").numpy()
            starts = tensor_field(state["last_episode_starts"], "last_episode_starts").numpy()
            env_state = self._decode_env_state(state["env_state"])
            agent_steps, episodes = (int(v) for v in state["env_counters"])
            lr, timesteps = float(state["learning_rate"]), int(state["num_timesteps"])
            n_updates, update = int(state["n_updates"]), int(state["update"])
            disc_state = state["disc_trainer"]
            optim_state = state["policy_optimizer"]
            # older checkpoints (no regulariser then): its weight follows the update count
            bc_state = state.get("bc_regulariser", {"updates": update, "rng": None})
            if not isinstance(bc_state, dict) or type(bc_state.get("updates")) is not int \
                    or bc_state["updates"] < 0:
                raise ValueError("bc_regulariser does not hold an update count")
            if last_obs.shape != (self.venv.num_envs, self.venv.obs_dim):
                raise ValueError(f"last_obs has shape {tuple(last_obs.shape)}, the env "
                                 f"{(self.venv.num_envs, self.venv.obs_dim)}")
            if starts.shape != (self.venv.num_envs,):
                raise ValueError(f"last_episode_starts has shape {tuple(starts.shape)}")
        except KeyError as exc:
            raise CheckpointError(f"{where}: checkpoint lacks {printable(str(exc.args[0]), 60)}"
                                  ) from None
        except (RuntimeError, ValueError, TypeError, AttributeError) as exc:
            raise CheckpointError(f"{where}: checkpoint does not fit this run "
                                  f"({type(exc).__name__}: {printable(str(exc), 200)})") from None
        load_into(m.policy, state["policy"], "policy", where)
        load_into(m.policy.optimizer, optim_state, "policy_optimizer", where)
        load_into(self.discriminator, state["discriminator"], "discriminator", where)
        try:
            self.disc_trainer.load_state_dict(disc_state)
            m.bc_updates = bc_state["updates"]
            if bc_state["rng"] is not None:
                m.bc_rng.bit_generator.state = bc_state["rng"]
            m.set_learning_rate(lr)
            m.num_timesteps, m._n_updates = timesteps, n_updates
            obs = self.wrapper.set_state(env_state)
            self.venv.agent_steps, self.venv.episodes = agent_steps, episodes
            m._last_episode_starts = starts
            self.update = update
        except MagailSumoError as exc:  # a scene worker failed replaying the actions
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CheckpointError(f"{where}: replaying the env state failed "
                                  f"({printable(first, 200)})") from None
        except KeyError as exc:
            raise CheckpointError(f"{where}: checkpoint lacks {printable(str(exc.args[0]), 60)}"
                                  ) from None
        except (RuntimeError, ValueError, TypeError, AttributeError, IndexError) as exc:
            raise CheckpointError(f"{where}: checkpoint does not fit this run "
                                  f"({type(exc).__name__}: "
                                  f"{printable(str(exc).splitlines()[0] if str(exc) else '', 200)})"
                                  ) from None
        if not np.array_equal(obs, last_obs):
            raise CheckpointError(f"{where}: replaying the env state did not reproduce the saved "
                                  "observation (scene files or SUMO changed?)")
        m._last_obs = obs
        try:
            set_rng_state(rng)
        except (RuntimeError, ValueError, TypeError) as exc:
            raise CheckpointError(f"{where}: checkpoint rng does not fit ({type(exc).__name__}: "
                                  f"{printable(str(exc), 200)})") from None

    def _decode_env_state(self, saved: Any) -> list[tuple[int, list[np.ndarray]]]:
        """:func:`decode_env_state` for this run's env."""
        return decode_env_state(self.venv, saved)

    def save(self, run_dir: Path) -> Path:
        return save_checkpoint(run_dir, self.state_dict(), self.update)

    def run_update(self) -> None:
        """One PPO update: rollout (with imitation rewards), discriminator fit, PPO epochs."""
        m = self.model
        m.learn(total_timesteps=m.n_steps * m.n_envs, callback=self.callbacks,
                reset_num_timesteps=False, progress_bar=False)
        self.update += 1

    def begin(self, progress: Progress) -> None:
        """A new run: the observation normaliser from the expert states, then the optional
        behavioural-cloning warm start (``bc.epochs``)."""
        cfg = self.cfg
        self.policy.obs_normalizer.update(torch.as_tensor(self.expert.s))
        if cfg.bc.epochs > 0:
            behavioural_cloning(self.policy, self.expert, cfg.bc.epochs, cfg.bc.batch_size,
                                cfg.bc.learning_rate, cfg.seed,
                                log=lambda e, v: progress("bc", e + 1, cfg.bc.epochs))

    def attach_logger(self, logger: Logger) -> None:
        self.model.set_logger(logger)

    def summarise(self, logger: Logger) -> str:
        """The update line's tail: learning rate, KL, the discriminator's loss and accuracies,
        the policy's mean speed and the outcome shares; records the worker restarts."""
        st = self.disc_callback.last_stats
        kl = logger.name_to_value.get("train/approx_kl", float("nan"))
        tail = (f", lr {self.model.learning_rate:.2e}, kl {kl:.4f}"
                + (f", D loss {st.loss:.3f} acc expert {st.expert_accuracy:.2f} policy "
                   f"{st.policy_accuracy:.2f}" if st else "")
                + (f", speed {sp:.2f} m/s (expert {self.disc_callback.expert_speed:.2f})"
                   if (sp := self.disc_callback.last_speed) is not None else "")
                + _rates_text(self.disc_callback.last_rates, self.cfg.env.guard.on))
        if self.venv.restarts:
            logger.record("workers/restarts", self.venv.restarts)
        return tail

    def log_step(self) -> int:
        return self.model.num_timesteps

    def close(self) -> None:
        self.venv.close()


def train_gail(cfg: TrainConfig, run_dir: Path, ckpt: dict | None,
               log: Callable[[str], None], progress: Progress) -> Path:
    """Run (or resume, from ``ckpt``) a ``gail`` run in ``run_dir``: optional behavioural-cloning
    warm start, then ``updates`` PPO updates with a checkpoint every ``checkpoint_every``
    (:func:`~magail_sumo.training.loop.run_loop`)."""
    return run_loop(GailRun(cfg, load_expert(cfg), log=log), run_dir, ckpt, log, progress)


def _rates_text(rates: dict[str, float], guard: bool) -> str:
    """The update line's outcome shares: agent episodes ended by collision / off-road (of the
    rollout's ended ones) and, behind the gap guard, the agent-steps it slowed."""
    text = "".join(f", {k[4:].replace('_', '-')} {rates[k]:.1%}"
                   for k in ("end_collision", "end_off_road") if k in rates)
    if guard and "guarded_frac" in rates:
        text += f", guard slowed {rates['guarded_frac']:.1%} of agent-steps"
    return text
