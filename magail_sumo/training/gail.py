"""GAIL / MAGAIL with a PPO generator (``algorithm: gail``): the scene-pool env, the adversarial
reward (:class:`~magail_sumo.training.adversarial.AdversarialReward`), masked PPO
(:class:`~magail_sumo.training.ppo.MaskedPPO`, with the optional behavioural-cloning regulariser)
and their callbacks, run update by update with checkpoints and exact resume.

A checkpoint (:mod:`~magail_sumo.training.checkpoints`) holds the policy (with its observation
normaliser and its critic, MLP or transformer), the PPO optimiser and current learning rate, the
discriminator (with its normaliser) and its optimiser, the discriminator sampler's RNG, the PPO
behavioural-cloning regulariser's expert sampler RNG and update count, the torch / numpy / python
RNG states, SB3's counters and last observation (:data:`SB3_RESUME_STATE`), and the env state as
per-scene (episode, actions since reset) — replayed in fresh workers on resume, so a resumed run
continues exactly as if uninterrupted. (A transformer critic's slot→scene layout is not state:
:class:`~magail_sumo.training.ppo.MaskedPPO` takes it from the env it is built on.)
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from converters.sumo.scenario import claim_networks_dir
from magail_sumo.config import ConfigError, record_run, to_dict
from magail_sumo.env.scene_pool import is_city, resolve_pool
from magail_sumo.env.vec_env import pool_vec_env
from magail_sumo.errors import MagailSumoError
from magail_sumo.expert import ExpertDataset
from magail_sumo.models.policies import TanhGaussianPolicy
from magail_sumo.outputs import printable

from .adversarial import AdversarialReward
from .checkpoints import (CHECKPOINT_FORMAT, CheckpointError, decode_env_state, encode_state,
                          load_into, plain, save_checkpoint, tensor_field)
from .config import TrainConfig, usable_cores
from .policies import policy_kwargs
from .rng import decode_rng, rng_state, set_rng_state
from .run_dir import claim_run_dir, note_skipped
from .algorithms import load_expert
from .bc import behavioural_cloning
from .ppo import KLAdaptiveLR, MaskedPPO
from .reward import DiscriminatorCallback

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


def torch_threads_callback():
    from stable_baselines3.common.callbacks import BaseCallback

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

    return TorchThreads


def make_pool_env(cfg: TrainConfig, log: Callable[[str], None]):
    """The run's scene-pool vector env (:func:`~magail_sumo.env.vec_env.pool_vec_env`) and
    ``cfg`` with ``workers.count`` resolved (None: the usable cores, at most one per scene
    unless the pool holds a city scenario, which replicas play on every core)."""
    skipped: list = []
    refs = resolve_pool(cfg.scenes.files, skipped)
    for s in skipped:
        log(f"scene skipped: {s.what}: {s.reason}")
    cores = usable_cores()
    count = cfg.workers.count or (cores if any(is_city(r) for r in refs)
                                  else min(len(refs), cores))
    cfg = replace(cfg, workers=replace(cfg.workers, count=count))
    w = cfg.workers
    claim_networks_dir(cfg.scenes.networks)
    venv = pool_vec_env(
        refs, cfg.scenes.networks, count, cfg.env, cfg.seed, cache=w.scene_cache,
        city=cfg.city.env_config(cfg.env),
        convert_budget_s=cfg.scenes.effective_convert_budget_s, log=log,
        timeout_s=cfg.scenes.worker_timeout_s, pin_workers=cfg.scenes.pin_workers,
        backend=w.backend, backend_options={"address": w.ray.address,
                                            "num_cpus": w.ray.num_cpus},
        max_restarts=w.max_restarts)
    venv.skipped[:0] = [(s.what, s.reason) for s in skipped]
    venv.new_skipped[:0] = [(s.what, s.reason) for s in skipped]
    log(f"scene pool: {len(refs)} scene(s) over {len(venv.specs)} "
        f"{w.backend} worker(s), {venv.num_envs} agent slots")
    return cfg, venv


class GailRun:
    """The objects of a GAIL / MAGAIL run (env, reward wrapper, discriminator, PPO, callbacks).

    :param cfg: the run config (``workers.count`` None is resolved: :attr:`cfg` holds the
        number used). :param expert: expert demonstrations. :param log: one-line messages
        (scene pool, skipped scenes, replaced workers).
    """

    def __init__(self, cfg: TrainConfig, expert: ExpertDataset,
                 log: Callable[[str], None] | None = None) -> None:
        from stable_baselines3.common.callbacks import CallbackList

        TorchThreads = torch_threads_callback()

        self.cfg = cfg
        d = cfg.discriminator
        if d.kind == "decomposed":  # before any worker starts
            expert.require_poses("discriminator.kind 'decomposed'")
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
                bc_decay=p.bc_decay, bc_batch_size=p.bc_batch_size,
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
        from stable_baselines3.common.logger import Logger

        self.model.set_logger(Logger(None, []))
        self.update = 0

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

    def close(self) -> None:
        self.venv.close()


def train_gail(cfg: TrainConfig, run_dir: Path, ckpt: dict | None,
               log: Callable[[str], None], progress: Callable[[str, int, int], None]) -> Path:
    """Run (or resume, from ``ckpt``) a ``gail`` run in ``run_dir``: optional behavioural-cloning
    warm start, then ``updates`` PPO updates with a checkpoint every ``checkpoint_every``."""
    from stable_baselines3.common.logger import configure

    expert = load_expert(cfg)
    run = GailRun(cfg, expert, log=log)
    cfg = run.cfg  # workers.count resolved

    try:
        if ckpt is not None:
            run.load_state_dict(ckpt, run_dir / "checkpoints" / "latest.pt")
            log(f"resumed {run_dir} at update {run.update}")
        else:
            run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
            if cfg.bc.epochs > 0:
                behavioural_cloning(run.policy, expert, cfg.bc.epochs, cfg.bc.batch_size,
                                    cfg.bc.learning_rate, cfg.seed,
                                    log=lambda e, v: progress("bc", e + 1, cfg.bc.epochs))
        claim_run_dir(run_dir, resumed=ckpt is not None)
        record_run(run_dir, cfg)
        note_skipped(run.venv, run_dir)
        run.model.set_logger(configure(str(run_dir / "tb"), ["tensorboard"]))
        while run.update < cfg.updates:
            t0 = time.perf_counter()
            steps0 = run.venv.agent_steps
            run.run_update()
            dt = time.perf_counter() - t0
            st = run.disc_callback.last_stats
            kl = run.model.logger.name_to_value.get("train/approx_kl", float("nan"))
            log(f"update {run.update}/{cfg.updates}: {run.venv.agent_steps - steps0} agent-steps "
                f"in {dt:.1f} s, lr {run.model.learning_rate:.2e}, kl {kl:.4f}"
                + (f", D loss {st.loss:.3f} acc expert {st.expert_accuracy:.2f} policy "
                   f"{st.policy_accuracy:.2f}" if st else "")
                + (f", speed {sp:.2f} m/s (expert {run.disc_callback.expert_speed:.2f})"
                   if (sp := run.disc_callback.last_speed) is not None else "")
                + _rates_text(run.disc_callback.last_rates, cfg.env.guard.on))
            if run.venv.restarts:
                run.model.logger.record("workers/restarts", run.venv.restarts)
            run.model.logger.dump(run.model.num_timesteps)
            note_skipped(run.venv, run_dir)
            progress("updates", run.update, cfg.updates)
            if run.update % cfg.checkpoint_every == 0 or run.update == cfg.updates:
                run.save(run_dir)
    finally:
        run.close()
    return run_dir


def _rates_text(rates: dict[str, float], guard: bool) -> str:
    """The update line's outcome shares: agent episodes ended by collision / off-road (of the
    rollout's ended ones) and, behind the gap guard, the agent-steps it slowed."""
    text = "".join(f", {k[4:].replace('_', '-')} {rates[k]:.1%}"
                   for k in ("end_collision", "end_off_road") if k in rates)
    if guard and "guarded_frac" in rates:
        text += f", guard slowed {rates['guarded_frac']:.1%} of agent-steps"
    return text
