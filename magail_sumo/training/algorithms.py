"""Training algorithms registered by name (``TrainConfig.algorithm``).

Each algorithm is one module with a run function
``train_<name>(cfg, run_dir, ckpt, log, progress) -> run_dir`` (``ckpt``: the checkpoint to
resume from, or None; ``log``: one-line messages; ``progress(phase, done, total)``), named here by
a ``"module:function"`` entry point resolved only when a run starts (as gymnasium registers envs),
so importing the registry imports no algorithm. Adding an algorithm = its module plus one
:func:`register` line below; :func:`~magail_sumo.training.trainer.train` does the shared part
(config checks, resume checks, threads, seeds) and calls it. Evaluating an algorithm's
checkpoints is registered apart, one layer up (:mod:`magail_sumo.policies`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from magail_sumo.expert import ExpertDataset

if TYPE_CHECKING:
    from magail_sumo.expert import ExpertDataset

    from .config import TrainConfig


@dataclass(frozen=True)
class Algorithm:
    """A registered algorithm.

    :param entry: ``"module:function"`` of its run function.
    :param adversarial: learns from a discriminator reward (``discriminator.*`` applies; its run
        directory name carries the discriminator kind).
    """

    name: str
    entry: str
    adversarial: bool = False
    summary: str = ""

    def run_function(self) -> Callable:
        module, _, func = self.entry.partition(":")
        return getattr(importlib.import_module(module), func)


REGISTRY: dict[str, Algorithm] = {}


def register(algorithm: Algorithm) -> Algorithm:
    """Add ``algorithm`` under its name (a second registration of a name replaces the first)."""
    REGISTRY[algorithm.name] = algorithm
    return algorithm


def get(name: str) -> Algorithm:
    try:
        return REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown algorithm {name!r} (known: {', '.join(REGISTRY)})") from None


def load_expert(cfg: "TrainConfig") -> "ExpertDataset":
    """The run's expert demonstrations (``expert_dir``), columns in the observation's order,
    actions in the env's action layout; data recorded with another observation config (any
    field) is refused."""
    return ExpertDataset(cfg.expert_dir, observation=cfg.env.observation,
                         action_layout=cfg.env.action_layout)


register(Algorithm("gail", "magail_sumo.training.gail.run:train_gail", adversarial=True,
                   summary="GAIL / MAGAIL: PPO generator, discriminator reward"))
register(Algorithm("bc", "magail_sumo.training.bc:train_bc",
                   summary="behavioural cloning of the expert (s, a)"))
register(Algorithm("sac", "magail_sumo.training.sac.run:train_sac",
                   summary="command-branched SAC on a task reward"))
register(Algorithm("sac_gail", "magail_sumo.training.sac.run:train_sac", adversarial=True,
                   summary="command-branched SAC generator, discriminator reward"))
register(Algorithm("gameformer", "magail_sumo.training.gameformer.run:train_gameformer",
                   summary="GameFormer level-k trajectory prediction (supervised)"))
