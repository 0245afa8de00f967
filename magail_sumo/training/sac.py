"""Command-branched Soft Actor-Critic: a task-reward driving agent (``algorithm: sac``) and the
off-policy generator of adversarial imitation (``algorithm: sac_gail``).

Agent (the seed's SAC driving agent, :class:`~magail_sumo.models.branched.BranchedSAC`): a
tanh-Gaussian actor, twin Q networks, a value network and its soft-updated target (rate
``tau``), all with output heads branched on the route command (left / straight / right, the
``command`` observation feature); one Adam optimiser per network with a StepLR schedule
(``lr_step`` gradient steps, factor ``lr_gamma``) and the entropy temperature learnt towards
``target_entropy`` (``auto_alpha``). Losses per gradient step (SAC with a value network):
``V(s) ← min Q(s, ã) − α log π(ã|s)``, ``Q_i(s, a) ← r + γ (1 − done) V_target(s')``,
actor ``α log π(ã|s) − min Q(s, ã)`` (``ã ~ π(·|s)`` reparametrised). Parameters are shared by
all vehicles: every live agent of every scene is one transition per env step.

Replay: a main buffer and a buffer of collision transitions (the step at which an agent
collided); each batch takes exactly ``int(collision_share · batch_size)`` transitions from the
collision buffer once it holds that many (else all from the main buffer). Only slots that held
an agent at the step enter a buffer (free slots of
:class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` are no transitions). The loop is ours, not
SB3's ``SAC.learn`` (SB3's off-policy loop has no notion of free slots, absorbing states, or
branched heads); SB3's ``polyak_update`` does the soft update.

Rewards. ``sac``: :func:`task_reward` (weights ``sac.task_reward``). ``sac_gail``: the
discriminator's imitation reward (any ``discriminator.kind``, through
:class:`~magail_sumo.training.reward.DiscriminatorRewardWrapper`, the discriminator fitted by
:class:`~magail_sumo.training.reward.DiscriminatorTrainer` on the steps of each update), labelled
when the transition is collected (the transformer and decomposed discriminators judge a vehicle
in the context of its scene step, which a replayed sample does not carry; so rewards are not
relabelled by later discriminators).

Ends of agents. A truncated agent (end of its track or of the scene) bootstraps from its
terminal observation. ``sac``: a terminated agent (an event of ``env.terminate_on``) has
``done = 1``. ``sac_gail`` (absorbing states, as in Discriminator-Actor-Critic): a terminated
agent's transition leads to the absorbing state (zero observation, absorbing flag 1) with
``done = 0``, and the absorbing state's self-transition (zero action, reward
``sac.absorbing_reward``) is stored with it, so the value of leaving is learnt rather than
fixed at 0 (which would bias an always-positive imitation reward towards long lives).

Updates: one update = ``train_freq`` env steps, (``sac_gail``) a discriminator fit on them,
then ``gradient_steps`` gradient steps once ``learning_starts`` transitions are stored (before
that, actions are uniform in [-1, 1]² and the observation normaliser is fitted; it is frozen
from the first gradient step on).

Checkpoints (``RUN/checkpoints/*.pt``, read with ``torch.load(weights_only=True)``): config,
networks (``policy``: the whole :class:`BranchedSAC` with its normaliser), optimisers,
schedulers, the batch sampler's RNG, the torch / numpy / python RNGs, the env state (replayed on
resume), the last observation, the discriminator and its trainer (``sac_gail``) and, with
``sac.save_buffers`` (default), both replay buffers as tensors: a resumed run then continues
bit for bit as if uninterrupted. Without the buffers a resumed run starts with empty buffers
(approximate resume; it waits ``learning_starts`` transitions again).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import nn

from magail_sumo.config import record_run, to_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.models.branched import BranchedSAC
from magail_sumo.outputs import printable
from magail_sumo.sensors.observation import COMMAND_NAMES, ObservationConfig, observation_names

from .config import SACConfig, TaskRewardConfig, TrainConfig
from .adversarial import AdversarialReward
from .checkpoints import (CHECKPOINT_FORMAT, CheckpointError, decode_env_state, encode_env_state,
                          load_into, plain, save_checkpoint, tensor_field)
from .gail import make_pool_env
from .rng import decode_rng, encode_rng, rng_state, set_rng_state
from .run_dir import claim_run_dir, note_skipped
from .algorithms import load_expert

#: second entropy word of the seed of the replay sampler (apart from the other streams)
SAC_STREAM = 0x5AC
ACT_DIM = 2
#: events whose transition is stored with the reason's flag (task reward)
TASK_EVENTS = ("collision", "off_road", "red_light", "destination")


# ----------------------------------------------------------------------------- replay buffer
class ReplayBuffer:
    """A ring buffer of transitions as CPU tensors (oldest overwritten first).

    Rows: ``obs`` and ``next_obs`` (obs_dim + 1: the absorbing flag last), ``action``,
    ``reward``, ``done`` (1: no bootstrap).
    """

    FIELDS = ("obs", "action", "reward", "next_obs", "done")

    def __init__(self, capacity: int, width: int, act_dim: int = ACT_DIM) -> None:
        self.capacity, self.width, self.act_dim = int(capacity), int(width), int(act_dim)
        shapes = {"obs": (width,), "action": (act_dim,), "reward": (), "next_obs": (width,),
                  "done": ()}
        self.data = {k: torch.empty((self.capacity, *shapes[k]), dtype=torch.float32)
                     for k in self.FIELDS}
        self.pos = 0
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(self, **rows: np.ndarray) -> None:
        """Append N transitions (each field an (N, ...) array)."""
        n = len(rows["reward"])
        if n == 0:
            return
        if n > self.capacity:  # only the newest fit
            rows = {k: v[-self.capacity:] for k, v in rows.items()}
            n = self.capacity
        idx = (self.pos + np.arange(n)) % self.capacity
        t = torch.from_numpy(idx)
        for k in self.FIELDS:
            self.data[k][t] = torch.as_tensor(np.asarray(rows[k], np.float32))
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.size + n, self.capacity)

    def get(self, idx: np.ndarray) -> dict[str, torch.Tensor]:
        t = torch.from_numpy(np.asarray(idx, np.int64))
        return {k: v[t] for k, v in self.data.items()}

    def state_dict(self) -> dict:
        """The stored rows (tensors) and the ring position."""
        return {"pos": self.pos, "size": self.size,
                **{k: v[:self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        size, pos = state["size"], state["pos"]
        if not (type(size) is int and type(pos) is int and 0 <= size <= self.capacity
                and 0 <= pos < max(self.capacity, 1) and (size == self.capacity or pos == size)):
            raise ValueError("replay buffer size / position do not fit its capacity")
        for k in self.FIELDS:
            v = tensor_field(state[k], f"replay buffer {k}")
            want = (size, *self.data[k].shape[1:])
            if v.dtype != torch.float32 or tuple(v.shape) != want:
                raise ValueError(f"replay buffer {k} is not float32 {want}")
            self.data[k][:size] = v
        self.size, self.pos = size, pos


def collision_count(batch_size: int, share: float, collisions: int) -> int:
    """Transitions of a batch drawn from the collision buffer: ``int(share · batch_size)`` when
    the collision buffer holds at least that many (and it is > 0), else 0."""
    n = int(share * batch_size)
    return n if 0 < n <= collisions else 0


def sample_batch(main: ReplayBuffer, collision: ReplayBuffer, batch_size: int, share: float,
                 rng: np.random.Generator) -> dict[str, torch.Tensor]:
    """A batch of ``batch_size`` transitions (uniform with replacement), the first
    :func:`collision_count` of them from ``collision``, the rest from ``main``."""
    n_col = collision_count(batch_size, share, len(collision))
    parts = []
    if n_col:
        parts.append(collision.get(rng.integers(0, len(collision), n_col)))
    parts.append(main.get(rng.integers(0, len(main), batch_size - n_col)))
    return {k: torch.cat([p[k] for p in parts]) for k in ReplayBuffer.FIELDS}


# ----------------------------------------------------------------------------- rewards
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


# ----------------------------------------------------------------------------- transitions
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


# ----------------------------------------------------------------------------- agent
def command_columns(obs: ObservationConfig) -> tuple[int, ...]:
    """Columns of the command one-hot in the observation (ValueError without the feature)."""
    names = observation_names(obs)
    if not obs.command:
        raise ValueError("the observation has no route command (env.observation.command)")
    return tuple(names.index(n) for n in COMMAND_NAMES)


def make_sac_model(cfg: TrainConfig) -> BranchedSAC:
    """A fresh :class:`BranchedSAC` for the config's observation."""
    obs = cfg.env.observation
    return BranchedSAC(len(observation_names(obs)), command_columns(obs), ACT_DIM,
                       cfg.sac.hidden, cfg.sac.alpha).to(cfg.device)


@dataclass
class SacStats:
    value_loss: float
    q_loss: float
    policy_loss: float
    alpha: float
    entropy: float


class SacAgent:
    """The networks, optimisers, StepLR schedules and the gradient step (module doc)."""

    NETS = ("actor", "q1", "q2", "value")

    def __init__(self, model: BranchedSAC, config: SACConfig) -> None:
        self.model, self.config = model, config
        c = config
        self.optimizers = {n: torch.optim.Adam(getattr(model, n).parameters(), lr=c.learning_rate)
                           for n in self.NETS}
        self.optimizers["alpha"] = torch.optim.Adam([model.log_alpha], lr=c.learning_rate)
        self.schedulers = {n: torch.optim.lr_scheduler.StepLR(self.optimizers[n], c.lr_step,
                                                              gamma=c.lr_gamma)
                           for n in self.NETS}
        self.target_entropy = float(-ACT_DIM if c.target_entropy is None else c.target_entropy)
        self.gradient_steps = 0

    def state_dict(self) -> dict:
        return {"optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
                "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
                "gradient_steps": self.gradient_steps}

    def load_state_dict(self, state: dict, where: Path) -> None:
        for k, o in self.optimizers.items():
            load_into(o, state["optimizers"][k], f"optimizer {k}", where)
        for k, s in self.schedulers.items():
            load_into(s, state["schedulers"][k], f"scheduler {k}", where)
        steps = state["gradient_steps"]
        if type(steps) is not int or steps < 0:
            raise ValueError("gradient_steps is not a count")
        self.gradient_steps = steps

    def learning_rate(self) -> float:
        return float(self.optimizers["actor"].param_groups[0]["lr"])

    def train_step(self, batch: dict[str, torch.Tensor]) -> SacStats:
        """One gradient step of every network on a batch (module doc), then the soft target
        update and the StepLR steps."""
        from stable_baselines3.common.utils import polyak_update

        m, c = self.model, self.config
        dev = m.log_alpha.device
        s, a, r = batch["obs"].to(dev), batch["action"].to(dev), batch["reward"].to(dev)
        s2, done = batch["next_obs"].to(dev), batch["done"].to(dev)
        alpha = m.log_alpha.exp().detach()
        a_new, logp = m.sample(s)
        q_new = torch.min(*m.q(s, a_new))
        policy_loss = (alpha * logp - q_new).mean()
        self._step("actor", policy_loss)
        value_loss = nn.functional.mse_loss(m.v(s), (q_new - alpha * logp).detach())
        self._step("value", value_loss)
        with torch.no_grad():
            target = r + c.gamma * (1.0 - done) * m.v(s2, target=True)
        q1, q2 = m.q(s, a)
        q_loss = nn.functional.mse_loss(q1, target) + nn.functional.mse_loss(q2, target)
        for n in ("q1", "q2"):
            self.optimizers[n].zero_grad(set_to_none=True)
        q_loss.backward()
        self.optimizers["q1"].step()
        self.optimizers["q2"].step()
        if c.auto_alpha:
            alpha_loss = -(m.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self._step("alpha", alpha_loss)
        polyak_update(m.value.parameters(), m.value_target.parameters(), c.tau)
        for sch in self.schedulers.values():
            sch.step()
        self.gradient_steps += 1
        return SacStats(*(float(v.detach()) for v in (value_loss, q_loss, policy_loss,
                                                       m.log_alpha.exp(), -logp.mean())))

    def _step(self, name: str, loss: torch.Tensor) -> None:
        opt = self.optimizers[name]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


# ----------------------------------------------------------------------------- run
class SacRun:
    """The objects of a SAC run: env (with the discriminator reward for ``sac_gail``), replay
    buffers, agent, discriminator and its trainer.

    :param cfg: run config (``workers.count`` None is resolved). :param expert: expert
        demonstrations (``sac_gail``; None for ``sac``). :param log: one-line messages.
    """

    def __init__(self, cfg: TrainConfig, expert=None,
                 log: Callable[[str], None] | None = None) -> None:
        self.log = log or (lambda msg: None)
        self.gail = cfg.algorithm == "sac_gail"
        if self.gail and expert is None:
            raise ValueError("sac_gail needs expert data")
        d = cfg.discriminator
        if self.gail and d.kind == "decomposed":
            expert.require_poses("discriminator.kind 'decomposed'")
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
        """One update (module doc); totals of the update's env steps."""
        c = self.cfg.sac
        tot = {"reward": 0.0, "task": 0.0, "n": 0, "collisions": 0, "speed": 0.0}
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

    def close(self) -> None:
        self.venv.close()


def train_sac(cfg: TrainConfig, run_dir: Path, ckpt: dict | None,
              log: Callable[[str], None], progress: Callable[[str, int, int], None]) -> Path:
    """Run (or resume, from ``ckpt``) a ``sac`` / ``sac_gail`` run in ``run_dir``."""
    from stable_baselines3.common.logger import configure

    expert = load_expert(cfg) if cfg.algorithm == "sac_gail" else None
    run = SacRun(cfg, expert, log=log)
    cfg = run.cfg
    try:
        if ckpt is not None:
            run.load_state_dict(ckpt, run_dir / "checkpoints" / "latest.pt")
            log(f"resumed {run_dir} at update {run.update}")
        else:
            if expert is not None:
                run.model.normalizer.update(torch.as_tensor(expert.s))
            run.start()
        claim_run_dir(run_dir, resumed=ckpt is not None)
        record_run(run_dir, cfg)
        note_skipped(run.venv, run_dir)
        logger = configure(str(run_dir / "tb"), ["tensorboard"])
        while run.update < cfg.updates:
            t0 = time.perf_counter()
            steps0 = run.venv.agent_steps
            tot = run.run_update()
            dt = time.perf_counter() - t0
            n = max(tot["n"], 1)
            st, ds = run.last_stats, run.last_disc
            logger.record("sac/reward_per_agent_step", tot["reward"] / n)
            logger.record("sac/task_reward_per_agent_step", tot["task"] / n)
            logger.record("sac/collisions", tot["collisions"])
            logger.record("sac/buffer", len(run.buffer))
            logger.record("sac/collision_buffer", len(run.collisions))
            logger.record("env/agent_steps_total", run.venv.agent_steps)
            if "speed" in run.names:  # as PPO's DiscriminatorCallback logs it
                logger.record("diag/speed_policy", tot["speed"] / n)
            if st is not None:
                for k, v in vars(st).items():
                    logger.record(f"sac/{k}", v)
                logger.record("sac/learning_rate", run.agent.learning_rate())
            if ds is not None:
                for k, v in vars(ds).items():
                    logger.record(f"discriminator/{k}", v)
            logger.dump(run.venv.agent_steps)
            log(f"update {run.update}/{cfg.updates}: {run.venv.agent_steps - steps0} agent-steps "
                f"in {dt:.1f} s, reward {tot['reward'] / n:.3f}/agent-step (task "
                f"{tot['task'] / n:.3f}), buffer {len(run.buffer)} + {len(run.collisions)} "
                "collisions"
                + (f", Q loss {st.q_loss:.3f} alpha {st.alpha:.3f} lr "
                   f"{run.agent.learning_rate():.2e}" if st else "")
                + (f", D loss {ds.loss:.3f} acc expert {ds.expert_accuracy:.2f} policy "
                   f"{ds.policy_accuracy:.2f}" if ds else ""))
            note_skipped(run.venv, run_dir)
            progress("sac_updates", run.update, cfg.updates)
            if run.update % cfg.checkpoint_every == 0 or run.update == cfg.updates:
                run.save(run_dir)
    finally:
        run.close()
    return run_dir


__all__ = ["ReplayBuffer", "SacAgent", "SacRun", "Transitions",
           "buffer_rows", "collision_count", "sample_batch",
           "step_transitions", "task_reward", "train_sac"]
