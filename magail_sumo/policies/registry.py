"""Policies by spec: :func:`make_policy`, :func:`method_name` and the checkpoint-loader
registries.

Two registries, each holding a callable or a ``"package.module:function"`` entry point (a user's
loader, imported when first used, as gymnasium registers envs):

* :data:`POLICY_LOADERS`, by file suffix: ``loader(path, seed) -> Policy``; a loader with a
  ``deterministic`` keyword also gets the caller's choice (sample the policy with ``seed``, or
  act deterministically). ``.pt`` is a training checkpoint (:func:`load_training_checkpoint`).
* :data:`CHECKPOINT_LOADERS`, by the algorithm a training checkpoint records
  (``config.algorithm``): ``loader(path, seed, deterministic=False, **options) -> Policy``.
  A new algorithm registers its loader here (:func:`register_checkpoint_loader`).
"""

from __future__ import annotations

import importlib
import inspect
import warnings
from pathlib import Path
from typing import Callable, Union

import torch

from magail_sumo.agents.base import Policy, PolicyError, check_noise_scale
from magail_sumo.agents.noise import NoiseShape
from magail_sumo.agents.random_policy import RandomPolicy
from magail_sumo.agents.idm import IdmPolicy
from magail_sumo.agents.specs import BASELINES, BUILTIN_POLICIES, GUARDED
from magail_sumo.env.config import EnvConfig
from magail_sumo.env.guard import GuardConfig
from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import regular_file
from magail_sumo.outputs import one_line
from magail_sumo.pretrained import (PretrainedError, is_pretrained_spec, name_of,
                                    resolve as resolve_pretrained)

from .checkpoint import load_actor_policy
from .gameformer import load_gameformer_policy
from .sac import load_sac_checkpoint_policy

Loader = Union[Callable[..., Policy], str]


#: algorithm whose loader reads a checkpoint that records none, or an algorithm without a
#: loader (it names what is wrong with the file)
DEFAULT_ALGORITHM = "gail"
#: training-checkpoint loaders by ``config.algorithm``; see the module doc
CHECKPOINT_LOADERS: dict[str, Loader] = {
    "gail": load_actor_policy,
    "bc": load_actor_policy,
    "sac": load_sac_checkpoint_policy,
    "sac_gail": load_sac_checkpoint_policy,
    "gameformer": load_gameformer_policy,
}


def register_checkpoint_loader(algorithm: str, loader: Loader) -> None:
    """Make ``loader`` (a callable or ``"module:function"``) load checkpoints of ``algorithm``."""
    CHECKPOINT_LOADERS[algorithm] = loader


def resolve(loader: Loader) -> Callable[..., Policy]:
    """The callable of a registry entry (a ``"module:function"`` string is imported)."""
    if callable(loader):
        return loader
    mod, _, attr = loader.partition(":")
    return getattr(importlib.import_module(mod), attr)


def checkpoint_algorithm(path: str | Path) -> str | None:
    """The algorithm a training checkpoint records (``config.algorithm``), None when the file
    cannot be read as one or records none (read with ``torch.load(weights_only=True)``)."""
    try:
        regular_file(path, "a checkpoint")  # not a FIFO (torch.load would block) or device
        with warnings.catch_warnings():  # the checkpoint loader reports what is wrong
            warnings.simplefilter("ignore")
            state = torch.load(Path(path), map_location="cpu", weights_only=True)
        algorithm = state["config"].get("algorithm")
    except Exception:  # noqa: BLE001 - the default loader names what is wrong with the file
        return None
    return algorithm if isinstance(algorithm, str) else None


def load_training_checkpoint(path: str | Path, seed: int = 0, deterministic: bool = False,
                             **options) -> Policy:
    """The policy of a ``magail-sumo train`` checkpoint, by the loader registered for its
    algorithm (:data:`CHECKPOINT_LOADERS`; :data:`DEFAULT_ALGORITHM`'s for a file that records
    none or an unregistered one: it reports the problem). ``options`` (e.g. ``target``, the env
    config the policy is to drive) go to the loader."""
    algorithm = checkpoint_algorithm(path)
    loader = resolve(CHECKPOINT_LOADERS.get(algorithm or "",
                                            CHECKPOINT_LOADERS[DEFAULT_ALGORITHM]))
    # an option the loader has no keyword for is not its concern (a gameformer agent adapts
    # to any env: it takes no ``target``)
    return loader(path, seed, deterministic=deterministic,
                  **{k: v for k, v in options.items() if _takes(loader, k)})


#: checkpoint loaders by file suffix (``".pt"``); see the module doc
POLICY_LOADERS: dict[str, Loader] = {".pt": load_training_checkpoint}


def _takes(loader: Callable, keyword: str) -> bool:
    """Whether ``loader`` accepts the keyword argument ``keyword``."""
    try:
        params = inspect.signature(loader).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin)
        return False
    return any(p.name == keyword and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
               or p.kind == p.VAR_KEYWORD for p in params)


def make_policy(spec: str, seed: int, deterministic: bool = False,
                noise_scale: float | None = None) -> Policy:
    """The policy named by ``spec``: ``random``, ``idm`` (the IDM route follower,
    :mod:`magail_sumo.agents.idm`), ``pretrained`` / ``pretrained:NAME`` (a
    shipped checkpoint, :mod:`magail_sumo.pretrained`; ``$MAGAIL_SUMO_PRETRAINED_DIR`` selects
    another registry folder), a checkpoint file with a registered loader
    (:data:`POLICY_LOADERS`), or ``package.module:factory`` (``factory(seed) -> Policy``);
    ``guarded:SPEC`` is the policy of ``SPEC`` with a ``guard`` (the gap guard's defaults,
    :class:`~magail_sumo.env.guard.GuardConfig`), so evaluation drives it through the guard
    whatever it was trained with.

    :param seed: the policy's seed (evaluation passes its rollout seed).
    :param deterministic: passed to a checkpoint loader that takes it (a training checkpoint
        then acts with the tanh of its Gaussian mean instead of sampling); ``random`` and
        factories ignore it.
    :param noise_scale: the scale of a sampling policy's Gaussian noise (its ``noise_scale``
        attribute: a checkpoint policy samples ``tanh(mu + noise_scale * sigma * eps)``);
        None: the policy's own (1, or the ``sampling.noise_scale`` a pretrained policy's card
        gives). A policy without one is refused unless the scale is 1.
    :raises PolicyError: an unusable spec, or a loader / factory that fails (one line).
    """
    if noise_scale is not None:
        check_noise_scale(noise_scale)
        return _scaled(spec, make_policy(spec, seed, deterministic), noise_scale)
    if spec.startswith(GUARDED):
        inner = make_policy(spec[len(GUARDED):], seed, deterministic)
        try:
            inner.guard = GuardConfig(kind="gap")
        except AttributeError:
            raise PolicyError(f"{spec}: the policy takes no attributes, so it cannot be "
                              "guarded") from None
        return inner
    if spec == "random":
        return RandomPolicy(seed)
    if spec == "idm":
        return IdmPolicy(seed)
    if is_pretrained_spec(spec):
        entry = resolve_pretrained(spec)
        loader = POLICY_LOADERS.get(entry.checkpoint.suffix)
        if loader is None:  # only if a caller unregistered ".pt"
            raise PolicyError(f"{spec}: no policy loader for '.pt' checkpoints")
        policy = _checkpoint_policy(spec, loader, entry.checkpoint, seed, deterministic)
        scale = card_noise_scale(entry)
        policy = policy if scale is None else _scaled(spec, policy, scale)
        return _shaped(spec, policy, card_noise_shape(entry))
    path = Path(spec)
    if path.is_file():
        loader = POLICY_LOADERS.get(path.suffix)
        if loader is None:
            raise PolicyError(f"{spec}: no policy loader for '{path.suffix}' checkpoints "
                              "(register one in magail_sumo.policies.POLICY_LOADERS)")
        return _checkpoint_policy(spec, loader, path, seed, deterministic)
    if ":" in spec:
        mod, _, attr = spec.partition(":")
        try:
            factory = getattr(importlib.import_module(mod), attr)
        except Exception as exc:  # noqa: BLE001 - any import failure of a user module
            raise PolicyError(f"{spec}: cannot import policy factory "
                              f"({type(exc).__name__}: {one_line(exc)})") from None
        return _built(spec, factory, seed)
    raise PolicyError(f"{spec}: not a method ({', '.join(BASELINES + BUILTIN_POLICIES)}), "
                      "pretrained[:NAME], a checkpoint file or a module:factory spec")


def card_noise_scale(entry) -> float | None:
    """The noise scale a pretrained policy's card asks evaluation to sample with
    (``"sampling": {"noise_scale": k}``), None when it gives none."""
    sampling = entry.card.get("sampling")
    if sampling is None:
        return None
    if not isinstance(sampling, dict) or "noise_scale" not in sampling:
        raise PolicyError(f"pretrained:{entry.name}: card's \"sampling\" must be an object "
                          "with \"noise_scale\"")
    return check_noise_scale(sampling["noise_scale"],
                             f"pretrained:{entry.name}: card's sampling.noise_scale")


def card_noise_shape(entry) -> NoiseShape:
    """The per-action weights and step correlation of the sampling noise a pretrained policy's
    card gives (``sampling.noise_weights`` / ``noise_correlation``,
    :mod:`magail_sumo.agents.noise`); white noise when it gives none."""
    sampling = entry.card.get("sampling")
    if not isinstance(sampling, dict):
        return NoiseShape()
    return NoiseShape.from_card(sampling, f"pretrained:{entry.name}: card's sampling")


def _shaped(spec: str, policy: Policy, shape: NoiseShape) -> Policy:
    """``policy`` sampling with noise of ``shape`` (refused if shaped noise cannot be had)."""
    if hasattr(policy, "noise_shape"):
        policy.noise_shape = shape
    elif not shape.plain:
        raise PolicyError(f"policy {spec}: {type(policy).__name__} has no sampling noise to "
                          f"shape ({shape})")
    return policy


def _scaled(spec: str, policy: Policy, scale: float) -> Policy:
    """``policy`` sampling with noise scale ``scale`` (refused if it has no noise to scale)."""
    if hasattr(policy, "noise_scale"):
        policy.noise_scale = float(scale)
    elif scale != 1.0:
        raise PolicyError(f"policy {spec}: {type(policy).__name__} has no sampling noise to "
                          f"scale (noise scale {scale:g})")
    return policy


def _checkpoint_policy(spec: str, loader: Loader, path: Path, seed: int,
                       deterministic: bool) -> Policy:
    try:
        fn = resolve(loader)
    except Exception as exc:  # noqa: BLE001 - a registered entry point that does not import
        raise PolicyError(f"policy {spec}: its loader {loader!r} cannot be imported "
                          f"({type(exc).__name__}: {one_line(exc)})") from None
    if _takes(fn, "deterministic"):
        return _built(spec, lambda p, s: fn(p, s, deterministic=deterministic), path, seed)
    return _built(spec, fn, path, seed)


def _built(spec: str, factory: Callable, *args) -> Policy:
    """``factory(*args)``; any exception becomes one :class:`PolicyError` naming ``spec``."""
    try:
        policy = factory(*args)
    except MagailSumoError:
        raise
    except Exception as exc:  # noqa: BLE001 - a user factory / loader may raise anything
        raise PolicyError(f"policy {spec}: could not be created: "
                          f"{type(exc).__name__}: {one_line(exc)}") from None
    if not callable(getattr(policy, "act", None)):
        raise PolicyError(f"policy {spec}: the factory returned {type(policy).__name__}, "
                          "which has no act(observations) method")
    return policy


def method_name(spec: str) -> str:
    """Name a method is stored under (``evaluate --name`` overrides it): the spec itself for
    built-ins; for a checkpoint in a run's ``checkpoints/`` folder the run folder's name
    (``runs/magail/checkpoints/latest.pt`` -> ``magail``; another file there -> ``magail-<stem>``,
    e.g. ``magail-update_000020``); another file's stem; a factory's name; for
    ``pretrained:NAME`` the registry name ``NAME`` (``pretrained``: the default's name); for
    ``guarded:SPEC`` SPEC's name with ``-guarded``."""
    if spec in BASELINES + BUILTIN_POLICIES:
        return spec
    if spec.startswith(GUARDED):
        return f"{method_name(spec[len(GUARDED):])}-guarded"
    if is_pretrained_spec(spec):
        try:
            return name_of(spec)
        except PretrainedError:
            return spec.replace(":", "-")
    p = Path(spec)
    if p.is_file():
        run = p.resolve().parent
        if run.name == "checkpoints" and run.parent.name:
            return run.parent.name if p.stem == "latest" else f"{run.parent.name}-{p.stem}"
        return p.stem
    return spec.rpartition(":")[2] or spec


def load_checkpoint_policy(path: str | Path, seed: int = 0,
                           target: EnvConfig | None = None,
                           deterministic: bool = False):
    """The evaluation policy of a training checkpoint, by the loader its algorithm registered
    (:data:`CHECKPOINT_LOADERS`): a :class:`~.checkpoint.CheckpointPolicy` for PPO /
    behavioural cloning, a :class:`~.sac.SacCheckpointPolicy` for SAC, a
    :class:`~.gameformer.GameFormerPolicy` for a gameformer run.

    :param seed: seed of the action samples (evaluation passes the rollout seed).
    :param target: the env config the policy will drive (default: evaluation's, the defaults
        with the policy's action layout; a gameformer agent adapts to any).
    :param deterministic: act with the tanh of the Gaussian mean (no sampling).
    """
    return load_training_checkpoint(path, seed, deterministic=deterministic,
                                    **({} if target is None else {"target": target}))
