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

Modules: :mod:`.buffer` (replay), :mod:`.transitions` (transitions, buffer rows, task reward),
:mod:`.agent` (networks and losses), :mod:`.run` (the run), :mod:`.config` (its config block).
(No imports here: :mod:`magail_sumo.training.config` imports :mod:`.config`.)
"""
