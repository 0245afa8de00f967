"""Training configuration (``configs/``), loaded strictly by :func:`magail_sumo.config.load_config`.

Every hyperparameter of a run lives here; unknown keys, wrong types and values out of range
(checked in each dataclass's ``__post_init__``) are refused naming the key.
Each algorithm's own block lives with the algorithm (``ppo``: :mod:`.gail.config`, ``sac``:
:mod:`.sac.config`, ``gameformer``: :mod:`.gameformer.config`);
:func:`~magail_sumo.training.preflight.check_train_config` adds the checks that need the machine
or the scene files, before any set-up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from magail_sumo.config import ConfigError, FieldError, check, check_positive, check_sizes, show
from magail_sumo.env.city_env import VEHICLE_CLASSES, CityEnvConfig
from magail_sumo.env.config import SCENE_CACHE, EnvConfig
from magail_sumo.env.tiled import config_problem as tiled_config_problem
from magail_sumo.models.critic import CriticTransformerConfig
from magail_sumo.models.decomposed import DecomposedConfig
from magail_sumo.models.discriminator import SetEncoderConfig, TransformerConfig
from magail_sumo.models.priors import ACTION_PRIORS, make_prior, prior_params
from magail_sumo.sensors.observation import observation_names
from magail_sumo.splits import PARTS, load_split

from .gail.config import PPOConfig
from .gameformer.config import GameFormerConfig
from .sac.config import SACConfig
from .algorithms import REGISTRY as ALGORITHMS  # ``TrainConfig.algorithm`` names (live registry)


@dataclass(frozen=True)
class ScenesConfig:
    """Training scenes: a scene pool (:mod:`magail_sumo.env.scene_pool`).

    In a config file the pool may be taken from a split (:mod:`magail_sumo.splits`):
    ``scenes: {split: FILE, part: train}`` (``FILE`` relative to the config file that names
    it, as ``extends``; ``part`` ``train``, the default, or ``test``) stands for ``files``: the
    part's scene files as the split lists them, after the ``files`` of the same mapping if it
    has any (``{files: [data/sumo/ingolstadt21], split: ..., part: train}``: a city and the
    train scenes). It is resolved when the config is loaded (:meth:`expand_config`): the
    config, and a run's record of it, hold the files.

    :param files: pool entries, any number: scene files (WOMD TFRecord files or shards,
        ScenarioNet pickles; every scene of each), globs, ScenarioNet dataset folders, folders of
        scene files, or folders of converted bundles.
    :param networks: converted bundles ``networks/<id>/`` (missing ones are converted there on
        demand, by the worker that first plays the scene, and reused).
    :param worker_timeout_s: seconds before a silent scene worker is declared hung.
    :param convert_budget_s: time budget of one on-demand conversion (a scene over it is
        skipped); at most 3/4 of ``worker_timeout_s`` is used.
    :param pin_workers: pin each scene worker to one core, balancing the workers' per-step cost
        (:func:`~magail_sumo.env.vec_env.place_workers`); for a machine dedicated to one run —
        concurrent pinned runs would stack their workers on the same cores. Process backend
        only (``workers.backend: process``); ignored by the others.
    """

    files: tuple[str, ...] = ("data/womd/637f20cafde22ff8.tfrecord",)
    networks: str = "networks"
    worker_timeout_s: float = 120.0
    convert_budget_s: float = 90.0
    pin_workers: bool = False

    #: the keys :meth:`expand_config` replaces by ``files`` (not fields)
    EXPAND_KEYS = ("split", "part")

    def __post_init__(self) -> None:
        check(len(self.files) > 0, "files", "needs at least one scene file")
        check_positive(self, "worker_timeout_s", "convert_budget_s")

    @classmethod
    def expand_config(cls, data: dict[str, Any], base: Path) -> dict[str, Any]:
        """The mapping ``data`` of one config file (or override) with ``split`` / ``part``
        replaced by ``files`` (class doc); ``base`` is the folder of that file.
        :class:`FieldError` naming ``split`` or ``part`` when the split cannot be used."""
        if "split" not in data:
            check("part" not in data, "part", "needs split next to it (the split file)")
            return data

        out = dict(data)
        split, part = out.pop("split"), out.pop("part", "train")
        check(isinstance(split, str) and bool(split.strip()), "split",
              f"expected a split file (configs/splits/*.yaml), got {show(split)}")
        check(isinstance(part, str) and part in PARTS, "part",
              f"must be one of {', '.join(PARTS)}, got {show(part)}")
        files = out.get("files", [])
        check(isinstance(files, list), "files",
              f"expected a list (the split's files go after it), got {show(files)}")
        try:
            scene_split = load_split(base / split)
        except ConfigError as exc:
            raise FieldError("split", str(exc)) from None
        out["files"] = [*files, *map(str, scene_split.paths(part))]  # its root checked on load
        return out

    @property
    def effective_convert_budget_s(self) -> float:
        """The budget a worker converts with: at most 3/4 of ``worker_timeout_s``, so that a
        worker converting a scene still answers in time."""
        return min(self.convert_budget_s, 0.75 * self.worker_timeout_s)


@dataclass(frozen=True)
class CityConfig:
    """City scenarios of the pool (plain SUMO scenarios played by
    :class:`~magail_sumo.env.city_env.SumoCityEnv`; observation, limits, event rules, action
    layout and SUMO seed come from ``env``).

    :param max_agents: policy-driven vehicles alive at once per city worker (its slots); the
        rest of the demand is SUMO-driven background traffic.
    :param control_fraction: share of the departing vehicles that may become agents (seeded).
    :param warmup_s: seconds SUMO runs alone before each episode (traffic already flowing).
    :param max_steps: 0.1-s steps per city episode.
    :param agent_classes: SUMO vehicle classes that may become agents (the rest, and every
        vehicle with stops, stay SUMO-driven).
    :param progress_reward: the city env's reward per metre an agent moves along its route
        (the task reward r_task of city training, weighted by ``discriminator.reward_t_coef``
        with the penalties there; 0: none).
    :param agent_tight_turns: vehicles whose route turns tighter than they can become agents
        too (default: SUMO drives them; ``CityEnvConfig.agent_tight_turns``).
    :param unblock_s: SUMO-driven vehicles that have waited this long (s) next to an agent
        standing as long on a junction stop giving way to standing agents (0: never;
        ``CityEnvConfig.unblock_s``).
    :param demand_scale: each city's demand times this (SUMO's ``--scale``;
        ``CityEnvConfig.demand_scale``; 1: as it is).
    """

    max_agents: int = 256
    control_fraction: float = 1.0
    warmup_s: float = 600.0
    max_steps: int = 200
    agent_classes: tuple[str, ...] = ("passenger",)
    progress_reward: float = 0.0
    agent_tight_turns: bool = False
    unblock_s: float = 10.0
    demand_scale: float = 1.0

    def __post_init__(self) -> None:
        check(self.max_agents >= 1, "max_agents", f"must be >= 1, got {self.max_agents}")
        bad = sorted(set(self.agent_classes) - set(VEHICLE_CLASSES))
        check(bool(self.agent_classes) and not bad, "agent_classes",
              f"must be SUMO vehicle classes, got {bad or '[]'}")
        check(0.0 < self.control_fraction <= 1.0, "control_fraction",
              f"must be in (0, 1], got {self.control_fraction}")
        check(self.warmup_s >= 0, "warmup_s", f"must be >= 0, got {self.warmup_s}")
        check(self.max_steps >= 1, "max_steps", f"must be >= 1, got {self.max_steps}")
        check_positive(self, "progress_reward", allow_zero=True)
        check_positive(self, "unblock_s", allow_zero=True)
        check_positive(self, "demand_scale")

    def env_config(self, env: EnvConfig):
        """The :class:`~magail_sumo.env.city_env.CityEnvConfig` of a training run."""
        return CityEnvConfig.from_env(env, max_agents=self.max_agents,
                                      control_fraction=self.control_fraction,
                                      warmup_s=self.warmup_s, max_steps=self.max_steps,
                                      agent_classes=self.agent_classes,
                                      progress_reward=self.progress_reward,
                                      agent_tight_turns=self.agent_tight_turns,
                                      unblock_s=self.unblock_s,
                                      demand_scale=self.demand_scale)


@dataclass(frozen=True)
class RayConfig:
    """Ray backend of the scene workers (:mod:`magail_sumo.env.ray_workers`).

    :param address: None: start a local Ray in the trainer; else a running cluster's
        ``HOST:PORT`` (or ``auto``).
    :param num_cpus: CPUs each scene-worker actor reserves.
    :param node_ip: the IP address (of one of this machine's interfaces) that the trainer's
        Ray gives the cluster to reach it. None: a local Ray (``address`` None) is bound to
        127.0.0.1, so nothing outside this machine can reach or join it; with an ``address``,
        Ray's own choice (the interface that reaches the head). An address: a local Ray is
        started on that interface (its servers then listen on every interface, as Ray's do,
        and other machines can join it); with an ``address``, the trainer's Ray is reached on
        it (name the private network's interface on a machine with several).
    """

    address: str | None = None
    num_cpus: float = 1.0
    node_ip: str | None = None

    def __post_init__(self) -> None:
        import ipaddress

        check_positive(self, "num_cpus")
        check(self.address is None or bool(str(self.address).strip()), "address",
              "must be HOST:PORT, 'auto' or null")
        if self.node_ip is not None:
            try:
                ip = ipaddress.ip_address(str(self.node_ip))
            except ValueError:
                ip = None
            check(ip is not None and not ip.is_unspecified, "node_ip",
                  f"must be an IP address of this machine or null, got {show(self.node_ip)}")


@dataclass(frozen=True)
class WorkersConfig:
    """The scene workers (one SUMO each) that step the pool.

    :param count: number of workers, each owning a shard of the pool (None: the usable cores,
        at most one per scene unless the pool holds a city scenario). More workers than scenes
        run replicas: each worker one scene, with its own seed (:func:`~magail_sumo.env.
        scene_pool.shard_pool`). The resolved number is what the run records and resumes with.
    :param backend: ``process`` (a local process per worker, the default; what
        ``scenes.pin_workers`` pins), ``hosted`` (the workers that run no SUMO — recorded scenes
        with log background and no SUMO mirror — shared out over one local process per core, a
        step's requests to a process in one message; the same rollouts,
        :mod:`magail_sumo.env.hosted_workers`) or ``ray`` (Ray actors on a cluster;
        ``pip install -e ".[ray]"``).
    :param ray: Ray options.
    :param max_restarts: times in a row a worker that dies or hangs is replaced (its episode
        replayed) before the run stops with its last checkpoint.
    :param scene_cache: scene envs each worker keeps built (the most recent; default
        :data:`~magail_sumo.env.config.SCENE_CACHE`).
    :param scenes_per_env: recorded scenes a worker steps at once as one fleet (a tiled env,
        :mod:`magail_sumo.env.tile_pool`: the step's fixed cost paid once for them all; each
        scene keeps its own start window); 1: one scene per episode. Needs log
        background without the SUMO mirror, no city in the pool, and ego-frame observations.
    """

    count: int | None = None
    backend: Literal["process", "hosted", "ray"] = "process"
    ray: RayConfig = field(default_factory=RayConfig)
    max_restarts: int = 3
    scene_cache: int = SCENE_CACHE
    scenes_per_env: int = 1

    def __post_init__(self) -> None:
        check(self.count is None or self.count >= 1, "count",
              f"must be >= 1 or null, got {self.count}")
        check(self.backend in ("process", "hosted", "ray"), "backend",
              f"must be 'process', 'hosted' or 'ray', got {show(self.backend)}")
        check(self.max_restarts >= 0, "max_restarts", f"must be >= 0, got {self.max_restarts}")
        check(self.scene_cache >= 1, "scene_cache", f"must be >= 1, got {self.scene_cache}")
        check(self.scenes_per_env >= 1, "scenes_per_env",
              f"must be >= 1, got {self.scenes_per_env}")


def usable_cores() -> int:
    """CPU cores this process may run on."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class PolicyConfig:
    """Actor-critic (parameters shared by all vehicles; see
    :class:`~magail_sumo.models.policies.TanhGaussianPolicy`).

    :param actor_hidden: hidden sizes of the per-vehicle tanh-Gaussian actor MLP.
    :param critic_hidden: hidden sizes of the MLP critic (unused by the transformer critic).
    :param log_std_init: initial log-std of the Gaussian (before the tanh squash).
    :param critic: ``"mlp"`` (each vehicle's value from its own observation) or
        ``"transformer"`` (each vehicle's value from the normalised observations of all
        vehicles of its scene at the same step;
        :class:`~magail_sumo.models.critic.TransformerCritic`).
    :param critic_transformer: sizes of the transformer critic (used when ``critic`` is
        ``"transformer"``).
    :param action_prior: ``"none"`` or a rule the actor learns a residual to
        (:mod:`magail_sumo.models.priors`): ``"idm"``, the IDM route follower (needs
        ``env.action_layout: accel_offset`` and ``env.observation`` ``leader`` and
        ``light_gap``).
    :param prior_params: the prior rule's settings changed from their defaults: a mapping of
        the fields of its parameter dataclass to numbers (``idm``:
        :class:`~magail_sumo.models.idm.IdmParams`, e.g. ``{a_lat: 4.0, a_clear: 2.0, margin:
        0.5}``); empty: the defaults. Recorded with the run's config in every checkpoint, so
        evaluation rebuilds the same prior (a checkpoint from before the key: the defaults).
    """

    actor_hidden: tuple[int, ...] = (64, 64)
    critic_hidden: tuple[int, ...] = (64, 64)
    log_std_init: float = 0.0
    critic: Literal["mlp", "transformer"] = "mlp"
    critic_transformer: CriticTransformerConfig = field(default_factory=CriticTransformerConfig)
    action_prior: str = "none"
    prior_params: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check(self.critic in ("mlp", "transformer"), "critic",
              f"must be 'mlp' or 'transformer', got {show(self.critic)}")
        check(self.action_prior == "none" or self.action_prior in ACTION_PRIORS,
              "action_prior", f"must be one of none, {', '.join(ACTION_PRIORS)}, got "
              f"{show(self.action_prior)}")
        check(self.action_prior != "none" or not self.prior_params, "prior_params",
              "needs policy.action_prior (no prior to set)")
        if self.action_prior != "none":
            try:
                prior_params(self.action_prior, self.prior_params)
            except ValueError as exc:
                check(False, "prior_params", str(exc))
        check_sizes(self, "actor_hidden", "critic_hidden")


#: ``discriminator.kind`` values (built by :func:`magail_sumo.training.adversarial.
#: make_discriminator`); the decomposed ones take the vehicles' poses
DISCRIMINATOR_KINDS: tuple[str, ...] = ("transformer", "mlp", "decomposed",
                                        "decomposed_transformer")


@dataclass(frozen=True)
class DiscriminatorConfig:
    """GAIL discriminator and reward.

    :param kind: ``"transformer"`` (MAGAIL: all vehicles of a scene step together), ``"mlp"``
        (plain per-vehicle GAIL), ``"decomposed"`` (an ego–map term per vehicle plus
        distance-weighted pairwise terms with its nearest neighbours; needs expert data with
        poses, format ``magail_sumo.expert/2``) or ``"decomposed_transformer"`` (the same
        decomposition with the terms from a transformer over each vehicle's neighbourhood,
        :mod:`magail_sumo.models.decomposed_transformer`).
    :param decomposed: sizes, neighbourhood geometry (m) and social reward of the decomposed
        discriminator (:class:`~magail_sumo.models.decomposed.DecomposedConfig`; used when
        ``kind`` is ``"decomposed"``; its geometry and social reward also for
        ``"decomposed_transformer"``).
    :param decomposed_transformer: sizes of the neighbourhood encoder of
        ``"decomposed_transformer"`` (:class:`~magail_sumo.models.discriminator.
        SetEncoderConfig`).
    :param epochs: gradient steps per PPO update, each on ``batch_size`` expert and
        ``batch_size`` policy scene steps.
    :param reward_t_coef, reward_i_coef: r = c_t·r_task + c_i·(−log(max(1 − sigmoid(D), floor))).
    :param ignore_features: observation feature names (``observation_names``) the
        discriminator does not see, in s nor in s' — e.g. ``[prev_accel, prev_steer]``: the
        previous action carries the policy's exploration noise, which lets a discriminator
        tell policy from expert without judging the driving.
    :param collision_penalty, off_road_penalty, red_light_penalty: the task reward r_task of
        the step at which an agent leaves by a collision / by going off-road / by running a
        red light is minus this (events in ``env.terminate_on`` end the agent; 0 otherwise).
    """

    kind: str = "transformer"
    transformer: TransformerConfig = field(default_factory=TransformerConfig)
    decomposed: DecomposedConfig = field(default_factory=DecomposedConfig)
    decomposed_transformer: SetEncoderConfig = field(default_factory=SetEncoderConfig)
    mlp_hidden: tuple[int, ...] = (256, 256)
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    epochs: int = 50
    batch_size: int = 32
    gp_coef: float = 0.1
    logit_reg: float = 0.25
    reward_t_coef: float = 0.0
    reward_i_coef: float = 1.0
    reward_floor: float = 1e-4
    collision_penalty: float = 0.0
    off_road_penalty: float = 0.0
    red_light_penalty: float = 0.0
    ignore_features: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check(self.kind in DISCRIMINATOR_KINDS, "kind",
              f"must be one of {', '.join(DISCRIMINATOR_KINDS)}, got {show(self.kind)}")
        check_sizes(self, "mlp_hidden")
        check_positive(self, "learning_rate", "batch_size")
        check_positive(self, "weight_decay", "epochs", "gp_coef", "logit_reg",
                       "collision_penalty", "off_road_penalty", "red_light_penalty",
                       allow_zero=True)
        check(0.0 < self.reward_floor < 1.0, "reward_floor",
              f"must be in (0, 1), got {show(self.reward_floor)}")

    @property
    def decomposes(self) -> bool:
        """The kind is a decomposed one (poses needed, ``decomposed.social_coef`` used)."""
        return self.kind.startswith("decomposed")


@dataclass(frozen=True)
class BCConfig:
    """Behavioural cloning (the ``bc`` algorithm, or PPO initialisation when ``epochs`` > 0).

    :param epochs: passes over the expert (s, a) pairs.
    """

    epochs: int = 0
    batch_size: int = 256
    learning_rate: float = 1e-3

    def __post_init__(self) -> None:
        check_positive(self, "epochs", allow_zero=True)
        check_positive(self, "batch_size", "learning_rate")


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    :param algorithm: ``"gail"`` (PPO + discriminator reward; MAGAIL with a transformer
        discriminator), ``"bc"`` (behavioural cloning only), ``"sac"`` (command-branched SAC
        on the task reward ``sac.task_reward``), ``"sac_gail"`` (the same SAC as the
        off-policy generator of adversarial imitation, rewarded by the ``discriminator``;
        both SAC algorithms need ``env.observation.command: true``) or ``"gameformer"``
        (the GameFormer level-k predictor trained on the recorded ``scenes.files``, section
        ``gameformer``).
    :param expert_dir: what ``magail-sumo expert`` wrote for the same observation layout.
    :param updates: PPO updates (rollout + discriminator + PPO epochs) in the run (gameformer:
        gradient steps).
    :param checkpoint_every: updates between checkpoints (the last update always saves).
    :param torch_threads: torch CPU threads of the trainer process (during rollouts, when the
        scene workers need the cores).
    :param torch_threads_update: torch CPU threads for the discriminator fit and the PPO epochs,
        while the scene workers are idle (None: ``torch_threads``).
    """

    algorithm: str = "gail"
    seed: int = 0
    expert_dir: str = "expert"
    out_dir: str = "runs"
    updates: int = 100
    checkpoint_every: int = 10
    device: str = "cpu"
    torch_threads: int = 1
    torch_threads_update: int | None = None
    env: EnvConfig = field(default_factory=EnvConfig)
    scenes: ScenesConfig = field(default_factory=ScenesConfig)
    workers: WorkersConfig = field(default_factory=WorkersConfig)
    city: CityConfig = field(default_factory=CityConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    discriminator: DiscriminatorConfig = field(default_factory=DiscriminatorConfig)
    bc: BCConfig = field(default_factory=BCConfig)
    sac: SACConfig = field(default_factory=SACConfig)
    gameformer: GameFormerConfig = field(default_factory=GameFormerConfig)

    def __post_init__(self) -> None:
        check(self.algorithm in ALGORITHMS, "algorithm",
              f"must be one of {', '.join(ALGORITHMS)}, got {show(self.algorithm)}")
        if self.algorithm in ("sac", "sac_gail"):
            obs = self.env.observation
            check(obs.command, "env.observation.command",
                  f"algorithm {self.algorithm} branches on the route command: must be true")
            check(self.algorithm != "sac" or obs.layout == "ego", "env.observation.layout",
                  "algorithm sac needs the 'ego' layout (its task reward reads dest_distance)")
        check(self.ppo.prior_coef == 0 or self.policy.action_prior != "none", "ppo.prior_coef",
              f"{self.ppo.prior_coef:g} needs policy.action_prior (no prior to pull toward)")
        if self.policy.action_prior != "none":
            check(self.algorithm in ("gail", "bc"), "policy.action_prior",
                  f"only the PPO-family policies take one, not algorithm {self.algorithm}")
            try:
                make_prior(self.policy.action_prior, self.env.observation, self.env.limits,
                           self.env.action_layout, self.policy.prior_params)
            except ValueError as exc:
                check(False, "policy.action_prior", str(exc))
        check(self.updates >= 0, "updates", f"must be >= 0, got {self.updates}")
        check(self.checkpoint_every >= 1, "checkpoint_every",
              f"must be >= 1, got {self.checkpoint_every}")
        check(0 <= self.seed < 1 << 32, "seed", f"must be in [0, 2**32), got {self.seed}")
        check(self.torch_threads >= 1, "torch_threads", f"must be >= 1, got {self.torch_threads}")
        check(self.torch_threads_update is None or self.torch_threads_update >= 1,
              "torch_threads_update", f"must be >= 1, got {self.torch_threads_update}")
        _check_device_name(self.device)
        if self.workers.scenes_per_env > 1:
            check((problem := tiled_config_problem(self.env)) is None,
                  "workers.scenes_per_env", f"{self.workers.scenes_per_env} scenes per env: "
                  f"{problem}")
        if self.discriminator.ignore_features:
            names = observation_names(self.env.observation)
            unknown = [f for f in self.discriminator.ignore_features if f not in names]
            check(not unknown, "discriminator.ignore_features",
                  f"unknown observation feature(s) {show(unknown, 120)} (features are "
                  f"{', '.join(names[:8])}, ...)")


def _check_device_name(device: str) -> None:
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError, TypeError):
        raise FieldError("device", f"not a torch device, got {show(device)} "
                         "(e.g. 'cpu', 'cuda', 'cuda:0')") from None
    check(dev.type in ("cpu", "cuda", "mps"), "device",
          f"must be a cpu, cuda or mps device, got {show(device)}")
