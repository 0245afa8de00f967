"""PPO over agent slots: a masked rollout buffer, parameter sharing, KL-adaptive learning rate.

All slots of :class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` share one policy (SB3 treats
them as vector envs). Free slot-steps (no agent in the slot) are recorded by SB3's rollout loop
like any step, but :class:`MaskedRolloutBuffer` remembers which were real and its :meth:`get`
only yields those, so they never reach the PPO loss nor the advantage normalisation. The env
marks a slot re-assignment as an episode start, so GAE never bootstraps from one agent into
another (and the free steps in between carry no weight).

Transformer critic (``policy.critic: transformer``): a vehicle's value depends on all vehicles
of its scene step, so PPO minibatches must hold whole scene steps. :class:`MaskedPPO` then gives
the buffer the env's slot→scene layout (:attr:`MaskedRolloutBuffer.slot_scene`) and the policy
the same layout plus the env's current slot mask (for the rollout-time forward passes, see
:mod:`magail_sumo.models.policies`); the buffer samples random *time steps* and yields all
active slot-steps of the chosen steps, with each row's group (= its step and its slot's scene)
attached to the observation tensor, from which the critic rebuilds padded
(groups, max vehicles, obs_dim) tensors with a mask. A minibatch ends at the step where the
running count of active slot-steps passes the next multiple of ``batch_size``, so minibatches
hold ``batch_size`` agent-steps give or take one step's agents, and there are as many as with
independent agent-steps. Free slot-steps still never reach the losses.

The rollout loop (:meth:`MaskedPPO.collect_rollouts`) is SB3's with one reordering: as soon as
a step's observations arrive, the next actions are computed and sent (``env.step_async``), and
the step is booked afterwards (episode bookkeeping, timeout bootstrapping, buffer row) while
the scene workers step. The same draws happen in the same order, so the rollout is SB3's bit
for bit (tested); only the workers wait less.

The PPO update (:meth:`MaskedPPO.train`) is our own, the algorithm SB3's PPO runs (and bit for
bit its result without the regulariser below): for ``n_epochs`` passes over the rollout in
minibatches, with ratio ``rho = exp(log pi(a|s) − log pi_old(a|s))`` and advantages A
(normalised per minibatch when ``normalize_advantage``: ``(A − mean) / (std + 1e-8)``),

    L = −mean min(rho·A, clip(rho, 1 − eps, 1 + eps)·A)      (clipped surrogate)
        + c_ent · (−mean H)                                  (entropy; H estimated as −log pi,
                                                              the tanh-Gaussian has no closed form)
        + c_vf · mean (R − V')²,  V' = V or V_old + clip(V − V_old, ±eps_vf)   (value)
        + c_bc,u · (−mean log pi(a_E | s_E))                  (behavioural cloning)
        + k · mean ½‖μ_θ(s) − μ_prior(s)‖²                    (pull toward the action prior)

then one optimiser (Adam) step on L with the gradient norm clipped to ``max_grad_norm``. A pass
stops early (no step on that minibatch, no further pass) when the approximate KL
``mean((rho − 1) − log rho)`` of a minibatch exceeds ``1.5 · target_kl`` (if set). The
behavioural-cloning term (``ppo.bc_coef`` c > 0) draws ``bc_batch_size`` expert (s, a) pairs per
minibatch from the run's :class:`~magail_sumo.expert.ExpertDataset` with its own seeded numpy
generator (saved in checkpoints), ``c_bc,u = c · bc_decay**u`` at PPO update u = 0, 1, ...
The prior term (``ppo.prior_coef`` k > 0, a policy with an action prior) penalises the actor's
residual, its pre-tanh mean's departure from the prior rule's, on the minibatch's own states:
training moves away from the rule only where the rewards pay for it.
"""

from __future__ import annotations

from typing import Any, Callable, Generator

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import RolloutBufferSamples
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from magail_sumo.models.policies import with_scene_groups

from ..bc import expert_actions, expert_nll


class MaskedRolloutBuffer(RolloutBuffer):
    """SB3 rollout buffer that drops inactive slot-steps from the minibatches.

    :attr:`mask_source` is called at every :meth:`add` and returns the (n_envs,) bool mask of the
    observation being added (``MultiSceneVecEnv.prev_slot_active``); None: all active.
    With :attr:`slot_scene` set, :meth:`get` yields minibatches of whole scene steps (module doc).
    """

    mask_source: Callable[[], np.ndarray] | None = None
    #: called once per rollout before the returns are computed; gives (buffer_size, n_envs)
    #: rewards added to those recorded step by step (the deferred imitation rewards)
    reward_source: Callable[[], np.ndarray] | None = None
    #: (n_envs,) scene index of each slot: minibatches of whole scene steps, tagged with their
    #: grouping (for a transformer critic); None: independent agent-steps
    slot_scene: np.ndarray | None = None

    #: the flattened rollout fields, as torch tensors sharing the arrays' memory (made once per
    #: rollout by :meth:`get`; minibatches index them instead of copying numpy rows)
    _SAMPLE_FIELDS = ("observations", "actions", "values", "log_probs", "advantages", "returns")

    def reset(self) -> None:
        super().reset()
        self.active = np.zeros((self.buffer_size, self.n_envs), bool)
        self._tensors: dict[str, torch.Tensor] | None = None

    def _get_samples(self, batch_inds: np.ndarray, env: Any = None) -> RolloutBufferSamples:
        """SB3's minibatch of flat rows ``batch_inds`` (the same tensors), gathered in torch
        from the whole rollout converted once (SB3 copies each field's rows through numpy)."""
        t = self._tensors
        if t is None:
            t = self._tensors = {k: torch.as_tensor(self.__dict__[k], device=self.device)
                                 for k in self._SAMPLE_FIELDS}
        i = torch.as_tensor(batch_inds, device=self.device)
        obs, act, val, logp, adv, ret = (t[k].index_select(0, i) for k in self._SAMPLE_FIELDS)
        return RolloutBufferSamples(obs, act, val.flatten(), logp.flatten(), adv.flatten(),
                                    ret.flatten())

    def add(self, *args: Any, **kwargs: Any) -> None:
        self.active[self.pos] = True if self.mask_source is None else self.mask_source()
        super().add(*args, **kwargs)

    def compute_returns_and_advantage(self, last_values, dones) -> None:
        if self.reward_source is not None:
            extra = np.asarray(self.reward_source(), np.float32)
            if extra.shape != self.rewards.shape:
                raise ValueError(f"deferred rewards have shape {extra.shape}, the buffer "
                                 f"{self.rewards.shape}")
            self.rewards += extra
        super().compute_returns_and_advantage(last_values, dones)

    @property
    def num_active(self) -> int:
        return int(self.active.sum())

    def get(self, batch_size: int | None = None) -> Generator[RolloutBufferSamples, None, None]:
        assert self.full, "the rollout buffer is not full"
        if not self.generator_ready:
            for name in self._SAMPLE_FIELDS:
                self.__dict__[name] = self.swap_and_flatten(self.__dict__[name])
            self._tensors = None
            self.active_flat = self.active.swapaxes(0, 1).reshape(-1)
            self.generator_ready = True
        if self.slot_scene is not None:
            yield from self._scene_step_batches(batch_size)
            return
        idx = np.flatnonzero(self.active_flat)
        indices = idx[np.random.permutation(len(idx))]
        if batch_size is None:
            batch_size = len(indices)
        for start in range(0, len(indices), batch_size):
            yield self._get_samples(indices[start:start + batch_size])

    def _scene_step_batches(self, batch_size: int | None
                            ) -> Generator[RolloutBufferSamples, None, None]:
        """Minibatches of whole time steps in random order, about ``batch_size`` active
        slot-steps each (module doc); rows tagged with their (step, scene) group."""
        counts = self.active.sum(axis=1)
        steps = np.random.permutation(self.buffer_size)
        steps = steps[counts[steps] > 0]
        total = int(counts.sum())
        if total == 0:
            return
        batch_size = batch_size or total
        cum = np.cumsum(counts[steps])
        cuts = np.searchsorted(cum, np.arange(batch_size, total, batch_size), side="left") + 1
        scene = np.asarray(self.slot_scene, np.int64)
        n_scenes = int(scene.max()) + 1
        for chunk in np.split(steps, cuts):
            if chunk.size == 0:
                continue
            row, slot = np.nonzero(self.active[chunk])
            step = chunk[row]
            # flat index of (step, slot) after swap_and_flatten: slot-major
            samples = self._get_samples(slot * self.buffer_size + step)
            _, group = np.unique(step * n_scenes + scene[slot], return_inverse=True)
            with_scene_groups(samples.observations,
                              torch.as_tensor(group.reshape(-1), device=self.device))
            yield samples


class MaskedPPO(PPO):
    """SB3 PPO whose rollout buffer is a :class:`MaskedRolloutBuffer` reading the env's slot mask,
    with our own update (:meth:`train`, module doc) and its behavioural-cloning regulariser.

    Same arguments as :class:`~stable_baselines3.PPO`; the env (possibly wrapped) must reach a
    :class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` through ``.unwrapped``. With a
    transformer-critic policy it also wires the env's scene layout and slot mask into the
    policy and the buffer (module doc).

    :param bc_expert: expert (s, a) pairs (an :class:`~magail_sumo.expert.ExpertDataset`;
        needed when ``bc_coef`` > 0). :param bc_coef: weight c of the regulariser (0: off).
    :param bc_decay: its factor per PPO update. :param bc_batch_size: expert pairs per minibatch.
    :param bc_seed: seed of the generator drawing the expert pairs (:attr:`bc_rng`).
    :param prior_coef: weight k of the pull toward the policy's action prior (0: off; > 0
        needs a policy with one).
    """

    def __init__(self, *args: Any, bc_expert: Any = None, bc_coef: float = 0.0,
                 bc_decay: float = 1.0, bc_batch_size: int = 256, bc_seed: int = 0,
                 prior_coef: float = 0.0, **kwargs: Any) -> None:
        if bc_coef < 0 or not 0 < bc_decay <= 1 or bc_batch_size < 1:
            raise ValueError(f"bc_coef {bc_coef} must be >= 0, bc_decay {bc_decay} in (0, 1], "
                             f"bc_batch_size {bc_batch_size} >= 1")
        if bc_coef > 0 and bc_expert is None:
            raise ValueError("bc_coef > 0 needs expert data (bc_expert)")
        if prior_coef < 0:
            raise ValueError(f"prior_coef {prior_coef} must be >= 0")
        self.prior_coef = float(prior_coef)
        self.bc_expert = bc_expert
        self.bc_coef, self.bc_decay = float(bc_coef), float(bc_decay)
        self.bc_batch_size = int(bc_batch_size)
        #: draws the expert pairs of the regulariser (state saved in checkpoints)
        self.bc_rng = np.random.default_rng(bc_seed)
        #: PPO updates done (:meth:`train` calls): the exponent of ``bc_decay``
        self.bc_updates = 0
        kwargs["rollout_buffer_class"] = MaskedRolloutBuffer
        super().__init__(*args, **kwargs)
        if self.prior_coef > 0 and getattr(self.policy, "action_prior", None) is None:
            raise ValueError("prior_coef > 0 needs a policy with an action prior")

    def _setup_model(self) -> None:
        super()._setup_model()
        base = self.env.unwrapped if self.env is not None else None
        if base is not None and hasattr(base, "prev_slot_active"):
            self.rollout_buffer.mask_source = lambda: base.prev_slot_active
        if base is not None and hasattr(self.policy, "set_scene_layout"):
            # scene layout of the slots (an env without one: every slot its own scene) and the
            # slot mask: rollout forwards evaluate occupied slots only (and the transformer
            # critic groups them by scene)
            slot_scene = np.asarray(getattr(base, "slot_scene", np.arange(self.n_envs)), np.int64)
            mask = (lambda: base.slot_active) if hasattr(base, "slot_active") else None
            self.policy.set_scene_layout(slot_scene, mask)
            if getattr(self.policy, "critic_kind", "mlp") == "transformer":
                self.rollout_buffer.slot_scene = slot_scene
        if getattr(self.env, "deferred", False):
            self.rollout_buffer.reward_source = self.env.flush_rewards

    def collect_rollouts(self, env: VecEnv, callback: BaseCallback,
                         rollout_buffer: RolloutBuffer, n_rollout_steps: int) -> bool:
        """SB3's rollout loop, sending each step's actions before booking the step before it
        (module doc): same actions, values, rewards and buffer, bit for bit."""
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        n_steps = 0
        rollout_buffer.reset()
        if self.use_sde:
            self.policy.reset_noise(env.num_envs)
        callback.on_rollout_start()
        sent = self._act_and_send(env, self._last_obs, n_steps)
        new_obs = dones = None
        while n_steps < n_rollout_steps:
            actions, values, log_probs = sent
            new_obs, rewards, dones, infos = env.step_wait()
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            n_steps += 1
            if n_steps < n_rollout_steps:  # the workers step while this step is booked
                sent = self._act_and_send(env, new_obs, n_steps)
            self._update_info_buffer(infos, dones)
            # a truncated agent's return is bootstrapped with the value of its last observation
            # (SB3 issue #633); done slots only (SB3 reads every slot)
            for idx in np.flatnonzero(dones).tolist():
                if infos[idx].get("terminal_observation") is not None \
                        and infos[idx].get("TimeLimit.truncated", False):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with torch.no_grad():
                        terminal_value = self.policy.predict_values(terminal_obs)[0]
                    rewards[idx] += self.gamma * terminal_value
            rollout_buffer.add(self._last_obs, actions, rewards, self._last_episode_starts,
                               values, log_probs)
            self._last_obs = new_obs
            self._last_episode_starts = dones
        with torch.no_grad():
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device))
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def _act_and_send(self, env: VecEnv, obs: np.ndarray, n_steps: int
                      ) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
        """The policy's (actions, values, log-probabilities) for ``obs``; the actions, clipped
        to the action space, are sent to ``env`` (``step_async``)."""
        if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
            self.policy.reset_noise(env.num_envs)
        with torch.no_grad():
            actions, values, log_probs = self.policy(obs_as_tensor(obs, self.device))
        actions = actions.cpu().numpy()
        if self.policy.squash_output:
            clipped = self.policy.unscale_action(actions)
        else:
            clipped = np.clip(actions, self.action_space.low, self.action_space.high)
        env.step_async(clipped)
        return actions, values, log_probs

    def _update_info_buffer(self, infos: list[dict[str, Any]],
                            dones: np.ndarray | None = None) -> None:
        """SB3's episode / success bookkeeping, over the slots that are done only: an episode
        summary (a Monitor's ``episode``) and ``is_success`` come with their slot's done, and
        a step has hundreds of slots (SB3 reads every slot's info at every step)."""
        if dones is None:
            return super()._update_info_buffer(infos, dones)
        done = np.flatnonzero(dones)
        super()._update_info_buffer([infos[i] for i in done], np.ones(len(done), bool))

    def set_learning_rate(self, lr: float) -> None:
        """Constant learning rate ``lr`` from the next update on."""
        self.learning_rate = float(lr)
        self._setup_lr_schedule()

    @property
    def bc_weight(self) -> float:
        """Weight of the behavioural-cloning term in the next update, ``c · d**u``."""
        return self.bc_coef * self.bc_decay ** self.bc_updates

    def _bc_loss(self) -> torch.Tensor:
        """``−mean log pi(a_E | s_E)`` over ``bc_batch_size`` expert pairs drawn by
        :attr:`bc_rng`."""
        s, a = self.bc_expert.sample_pairs(self.bc_batch_size, self.bc_rng)
        dev = self.policy.device
        return expert_nll(self.policy, torch.as_tensor(s, device=dev), expert_actions(a, dev))

    def train(self) -> None:
        """One PPO update on the rollout buffer (module doc): ``n_epochs`` passes of clipped
        surrogate + entropy + value (+ behavioural-cloning) minibatch steps, with approx-KL
        early stopping and gradient-norm clipping. Logs SB3's ``train/*`` keys (explained
        variance over the real slot-steps) plus ``train/bc_coef`` and, when on,
        ``train/bc_loss`` and ``train/prior_loss`` (the mean ½‖residual‖²)."""
        policy = self.policy
        policy.set_training_mode(True)
        self._update_learning_rate(policy.optimizer)
        eps = self.clip_range(self._current_progress_remaining)
        eps_vf = (None if self.clip_range_vf is None
                  else self.clip_range_vf(self._current_progress_remaining))
        bc_on = self.bc_coef > 0
        bc_weight = self.bc_weight
        prior_on = self.prior_coef > 0
        log: dict[str, list[float]] = {"pg": [], "value": [], "entropy": [], "clip": [],
                                       "bc": [], "prior": []}
        kls: list[np.ndarray] = []
        loss = torch.zeros(())
        stop = False
        for _ in range(self.n_epochs):
            kls = []
            for batch in self.rollout_buffer.get(self.batch_size):
                values, log_prob, entropy = policy.evaluate_actions(batch.observations,
                                                                    batch.actions)
                values = values.flatten()
                adv = batch.advantages
                if self.normalize_advantage and len(adv) > 1:  # one sample has no spread
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                ratio = torch.exp(log_prob - batch.old_log_prob)
                surrogate = torch.min(adv * ratio, adv * torch.clamp(ratio, 1 - eps, 1 + eps))
                pg_loss = -surrogate.mean()
                if eps_vf is not None:
                    values = batch.old_values + torch.clamp(values - batch.old_values,
                                                            -eps_vf, eps_vf)
                value_loss = torch.nn.functional.mse_loss(batch.returns, values)
                ent_loss = (-torch.mean(-log_prob) if entropy is None
                            else -torch.mean(entropy))
                loss = pg_loss + self.ent_coef * ent_loss + self.vf_coef * value_loss
                if bc_on:
                    bc_loss = self._bc_loss()
                    loss = loss + bc_weight * bc_loss
                    log["bc"].append(bc_loss.item())
                if prior_on:
                    residual = policy.actor_residual(batch.observations)
                    prior_loss = 0.5 * residual.square().sum(-1).mean()
                    loss = loss + self.prior_coef * prior_loss
                    log["prior"].append(prior_loss.item())
                log["pg"].append(pg_loss.item())
                log["value"].append(value_loss.item())
                log["entropy"].append(ent_loss.item())
                log["clip"].append(torch.mean((torch.abs(ratio - 1) > eps).float()).item())
                with torch.no_grad():  # float32, compared as such (as SB3 does)
                    log_ratio = log_prob - batch.old_log_prob
                    kl = torch.mean(torch.exp(log_ratio) - 1 - log_ratio).cpu().numpy()
                kls.append(kl)
                if self.target_kl is not None and kl > 1.5 * self.target_kl:
                    stop = True
                    break
                policy.optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(policy.parameters(), self.max_grad_norm)
                policy.optimizer.step()
            self._n_updates += 1
            if stop:
                break
        self.bc_updates += 1
        buf = self.rollout_buffer
        real = getattr(buf, "active_flat", None)
        pred, ret = buf.values.flatten(), buf.returns.flatten()
        if real is not None and real.shape == pred.shape and real.any():
            pred, ret = pred[real], ret[real]
        rec = self.logger.record
        rec("train/entropy_loss", float(np.mean(log["entropy"])))
        rec("train/policy_gradient_loss", float(np.mean(log["pg"])))
        rec("train/value_loss", float(np.mean(log["value"])))
        rec("train/approx_kl", float(np.mean(kls)))
        rec("train/clip_fraction", float(np.mean(log["clip"])))
        rec("train/loss", loss.item())
        rec("train/explained_variance", float(explained_variance(pred, ret)))
        if hasattr(policy, "log_std"):
            rec("train/std", torch.exp(policy.log_std).mean().item())
        rec("train/n_updates", self._n_updates, exclude="tensorboard")
        rec("train/clip_range", eps)
        if eps_vf is not None:
            rec("train/clip_range_vf", eps_vf)
        rec("train/bc_coef", bc_weight)
        if bc_on:
            rec("train/bc_loss", float(np.mean(log["bc"])))
        if prior_on:
            rec("train/prior_loss", float(np.mean(log["prior"])))


def adapt_learning_rate(lr: float, kl: float, desired_kl: float, lr_min: float, lr_max: float
                        ) -> float:
    """The seed's rule: halve when kl > 2·desired, ×1.5 when kl < desired/2, within bounds."""
    if kl > 2.0 * desired_kl:
        lr = max(lr_min, lr / 2.0)
    elif 0.0 < kl < desired_kl / 2.0:
        lr = min(lr_max, lr * 1.5)
    return lr


class KLAdaptiveLR(BaseCallback):
    """Adapt the PPO learning rate to the approximate KL of the last update.

    After every PPO update (read from ``train/approx_kl`` before the next rollout or at the end of
    ``learn``), apply :func:`adapt_learning_rate`; the current lr is logged as ``train/kl_lr``.

    :param desired_kl: KL target. :param lr_min, lr_max: bounds.
    """

    def __init__(self, desired_kl: float, lr_min: float = 1e-5, lr_max: float = 1e-2,
                 verbose: int = 0) -> None:
        super().__init__(verbose)
        self.desired_kl = desired_kl
        self.lr_min, self.lr_max = lr_min, lr_max
        self._seen_updates = -1

    def _maybe_adapt(self) -> None:
        model = self.model
        if model._n_updates == self._seen_updates or model._n_updates == 0:
            return
        self._seen_updates = model._n_updates
        kl = model.logger.name_to_value.get("train/approx_kl")
        if kl is None:
            return
        lr = adapt_learning_rate(float(model.learning_rate), float(kl), self.desired_kl,
                                 self.lr_min, self.lr_max)
        model.set_learning_rate(lr)
        model.logger.record("train/kl_lr", lr)

    def _on_training_start(self) -> None:
        if self._seen_updates < 0:
            self._seen_updates = self.model._n_updates

    def _on_rollout_start(self) -> None:
        self._maybe_adapt()

    def _on_training_end(self) -> None:
        self._maybe_adapt()

    def _on_step(self) -> bool:
        return True
