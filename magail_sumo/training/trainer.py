"""Training runs: build env, expert data, discriminator, PPO from a :class:`TrainConfig`; run
updates with checkpoints; resume exactly.

A checkpoint (``RUN/checkpoints/update_NNNNNN.pt`` and ``latest.pt``, written atomically) holds
the policy (with its observation normaliser and its critic, MLP or transformer), the PPO optimiser and current learning rate, the
discriminator (with its normaliser) and its optimiser, the discriminator sampler's RNG, the PPO
behavioural-cloning regulariser's expert sampler RNG and update count, the
torch / numpy / python RNG states, SB3's counters and last observation, and the env state as
per-scene (episode, actions since reset) — replayed in fresh workers on resume, so a resumed run
continues exactly as if uninterrupted. (A transformer critic's slot→scene layout is not state:
:class:`~magail_sumo.training.ppo.MaskedPPO` takes it from the env it is built on.)

Checkpoints hold only tensors and plain data (dicts, lists, tuples, str, numbers, None) and are
read with ``torch.load(weights_only=True)``: a file cannot run code when loaded. Numpy state
(SB3's last observation and episode starts, the env's replayed actions, numpy RNG states) is
stored as tensors / lists (format ``magail_sumo.checkpoint/2``) and converted back on load,
bit for bit. Format-1 checkpoints (pickled numpy objects) are refused; a trusted one can be
converted with :func:`upgrade_checkpoint`.
"""

from __future__ import annotations

import random
import re
import time
import zipfile
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from gymnasium import spaces

from magail_sumo.config import ConfigError, from_dict, record_run, to_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import atomic_path, claim_output_dir, one_line, printable, read_marker
from magail_sumo.expert import ExpertDataset
from magail_sumo.models.decomposed import DecomposedDiscriminator
from magail_sumo.models.discriminator import MLPDiscriminator, TransformerDiscriminator
from magail_sumo.models.policies import TanhGaussianPolicy
from magail_sumo.sensors.observation import observation_bounds, observation_names
from magail_sumo.sim.dynamics import ACTION_SIZE

from .config import TrainConfig, check_train_config

CHECKPOINT_FORMAT = "magail_sumo.checkpoint/2"
#: formats written by earlier versions (pickled numpy objects: unsafe to load)
OLD_CHECKPOINT_FORMATS = ("magail_sumo.checkpoint/1",)
#: config keys (dotted for nested ones) that may differ between a run and its resumption:
#: they change neither the results nor the state
#: what ``train`` writes into a run directory (recorded in its marker: ``--overwrite`` removes
#: only these)
RUN_OUTPUTS = ("config.yaml", "environment.json", "checkpoints", "tb", "skipped_scenes.tsv")
#: second entropy word of the seed of the PPO behavioural-cloning regulariser's expert sampler
#: (a stream apart from the discriminator sampler's, seeded with the run seed alone)
BC_STREAM = 0xBC
RESUMABLE_CHANGES = ("updates", "checkpoint_every", "scenes.worker_timeout_s",
                     "scenes.pin_workers", "workers.backend", "workers.ray.address",
                     "workers.ray.num_cpus", "workers.max_restarts")
#: the run's list of scenes left out of the pool (tab-separated: scene, reason)
SKIPPED_FILE = "skipped_scenes.tsv"


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


class CheckpointError(MagailSumoError):
    """A checkpoint is missing, corrupt, or does not belong to the configured run."""


def spaces_of(cfg: TrainConfig) -> tuple[spaces.Box, spaces.Box]:
    low, high = observation_bounds(cfg.env.observation)
    return (spaces.Box(low, high, dtype=np.float32),
            spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32))


def policy_kwargs(cfg: TrainConfig) -> dict[str, Any]:
    """:class:`TanhGaussianPolicy` arguments of the config's ``policy`` block."""
    p = cfg.policy
    kwargs: dict[str, Any] = {"net_arch": {"pi": list(p.actor_hidden), "vf": list(p.critic_hidden)},
                              "log_std_init": p.log_std_init}
    if p.critic == "transformer":
        kwargs.update(net_arch={"pi": list(p.actor_hidden), "vf": []}, critic="transformer",
                      critic_transformer=p.critic_transformer)
    return kwargs


def make_policy(cfg: TrainConfig) -> TanhGaussianPolicy:
    """A fresh policy for the config's spaces (no env needed; a transformer critic has no scene
    layout then, see :meth:`TanhGaussianPolicy.set_scene_layout` — evaluation uses the actor
    only)."""
    obs, act = spaces_of(cfg)
    return TanhGaussianPolicy(obs, act, lambda _: cfg.ppo.learning_rate,
                              **policy_kwargs(cfg)).to(cfg.device)


def make_discriminator(cfg: TrainConfig, feature_dim: int) -> torch.nn.Module:
    """The config's discriminator over tokens concat(s, s') of ``feature_dim`` columns, with
    ``discriminator.ignore_features`` (observation feature names, in s and in s') masked."""
    d = cfg.discriminator
    if d.kind == "transformer":
        disc = TransformerDiscriminator(feature_dim, d.transformer)
    elif d.kind == "decomposed":
        disc = DecomposedDiscriminator(feature_dim, d.decomposed)
    else:
        disc = MLPDiscriminator(feature_dim, d.mlp_hidden)
    if d.ignore_features:
        names = observation_names(cfg.env.observation)
        unknown = [f for f in d.ignore_features if f not in names]
        if unknown:
            raise ConfigError(f"discriminator.ignore_features: unknown observation feature(s) "
                              f"{', '.join(unknown)} (features are {', '.join(names[:8])}, ...)")
        if 2 * len(names) != feature_dim:
            raise ValueError(f"tokens have {feature_dim} columns, the observation "
                             f"{len(names)} features (expected twice as many)")
        cols = [names.index(f) for f in d.ignore_features]
        disc.ignore_features(cols + [len(names) + c for c in cols])
    return disc.to(cfg.device)


def _pickle_mentions(p: Path, text: bytes) -> bool:
    """Whether the pickle inside torch zip file ``p`` contains ``text`` (read, never run)."""
    try:
        with zipfile.ZipFile(p) as z:
            name = next((n for n in z.namelist() if n.endswith("/data.pkl")), None)
            if name is None or z.getinfo(name).file_size > 1 << 26:
                return False
            return text in z.read(name)
    except (OSError, zipfile.BadZipFile, RuntimeError):
        return False


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint; :class:`CheckpointError` when missing, corrupt, unsafe or not one.

    Read with ``torch.load(weights_only=True)``: anything but tensors and plain data is refused
    before it is constructed (a crafted file cannot run code).
    """
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"{p}: checkpoint not found")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means corrupt or unsafe
        if any(_pickle_mentions(p, f.encode()) for f in OLD_CHECKPOINT_FORMATS):
            raise CheckpointError(
                f"{p}: checkpoint written by an older magail_sumo version in an unsafe format "
                "(pickled numpy objects); refused (convert a file you trust with "
                "magail-sumo train --upgrade-checkpoint FILE --trust)") from None
        found = re.search(r"GLOBAL ([\w.]+)|global[:\s]+([\w.]+)", str(exc))
        if found:
            raise CheckpointError(f"{p}: refused: the file holds {printable(found[1] or found[2], 80)}"
                                  ", not only tensors and plain data (not a magail_sumo "
                                  "checkpoint, or a crafted one)") from None
        raise CheckpointError(f"{p}: corrupt or unreadable checkpoint ({type(exc).__name__}: "
                              f"{one_line(exc, 200)})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{p}: not a magail_sumo checkpoint"
                              + (" (format " + printable(str(state.get("format")), 60) + ")"
                                 if isinstance(state, dict) and "format" in state else ""))
    missing = [k for k in ("config", "policy", "update") if k not in state]
    if missing:
        raise CheckpointError(f"{p}: checkpoint lacks {', '.join(missing)}")
    if not isinstance(state["config"], dict):
        raise CheckpointError(f"{p}: checkpoint config is not a mapping")
    if not isinstance(state["update"], int) or isinstance(state["update"], bool) \
            or state["update"] < 0:
        raise CheckpointError(f"{p}: checkpoint update is not a count "
                              f"({printable(repr(state['update']), 60)})")
    return state


def upgrade_checkpoint(path: str | Path, out: str | Path | None = None, *,
                       trust: bool = False) -> Path:
    """Convert a format-1 checkpoint to the current format (``out``, default: in place).

    Loading a format-1 file unpickles arbitrary objects, i.e. can run code the file holds:
    only for a file you trust, and only with ``trust=True``.
    """
    p = Path(path)
    if not trust:
        raise CheckpointError(f"{p}: converting a format-1 checkpoint runs the code it may "
                              "contain; only for a file you trust (--trust)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{p}: corrupt or unreadable checkpoint ({type(exc).__name__}: "
                              f"{one_line(exc, 200)})") from None
    if not isinstance(state, dict) or state.get("format") not in OLD_CHECKPOINT_FORMATS:
        raise CheckpointError(f"{p}: not a format-1 magail_sumo checkpoint")
    try:
        state = _encode_state(dict(state, format=CHECKPOINT_FORMAT))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(f"{p}: cannot convert ({type(exc).__name__}: "
                              f"{printable(str(exc), 200)})") from None
    dest = Path(out) if out is not None else p
    _save(state, dest)
    return dest


def _summarise_load_error(exc: BaseException) -> str:
    """One line for a ``load_state_dict`` error (torch's is a multi-line dump)."""
    text = str(exc)

    def keys(label: str) -> list[str]:
        m = re.search(label + r"[^:]*: ([^\n]*)", text)
        return re.findall(r'"([^"]*)"', m[1]) if m else []

    def some(names: list[str]) -> str:
        shown = ", ".join(printable(n, 60) for n in names[:4])
        return shown + (f" (+{len(names) - 4} more)" if len(names) > 4 else "")

    parts = []
    for label, what in (("Missing key", "missing keys"), ("Unexpected key", "unexpected keys")):
        found = keys(label)
        if found:
            parts.append(f"{what} {some(found)}")
    sizes = re.findall(r"size mismatch for ([^:]+):", text)
    if sizes:
        parts.append(f"size mismatch for {some(sizes)}")
    if parts:
        return "; ".join(parts)
    return f"{type(exc).__name__}: {printable(' '.join(text.split()), 200)}"


def _load_into(obj: Any, state: Any, what: str, where: Path) -> None:
    """``obj.load_state_dict(state)``; a one-line :class:`CheckpointError` naming ``where``."""
    if not isinstance(state, dict):
        raise CheckpointError(f"{where}: checkpoint {what} is not a state dict")
    try:
        obj.load_state_dict(state)
    except Exception as exc:  # noqa: BLE001 - torch raises several kinds on a mismatch
        raise CheckpointError(f"{where}: checkpoint {what} does not fit this run "
                              f"({_summarise_load_error(exc)})") from None


def _save(state: dict, path: Path) -> None:
    """Write a checkpoint atomically (a crash leaves the old file or none)."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def save_checkpoint(run_dir: Path, state: dict, update: int) -> Path:
    """A run's checkpoint at ``update``: ``checkpoints/update_<update>.pt`` and, the same,
    ``checkpoints/latest.pt`` (both atomic); the first path."""
    d = run_dir / "checkpoints"
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"update_{update:06d}.pt"
    _save(state, path)
    _save(state, d / "latest.pt")
    return path


def load_policy(path: str | Path, device: str = "cpu") -> tuple[TanhGaussianPolicy, TrainConfig]:
    """The policy of a checkpoint (and the run's config)."""
    state = load_checkpoint(path)
    cfg = replace(checkpoint_config(state, path), device=device)
    if cfg.algorithm in ("sac", "sac_gail"):
        raise CheckpointError(f"{path}: a {cfg.algorithm} checkpoint (command-branched SAC), not "
                              "a PPO / behavioural-cloning policy (evaluate loads both: "
                              "magail_sumo.training.policy_loader.load_checkpoint_policy)")
    policy = make_policy(cfg)
    _load_into(policy, state["policy"], "policy", Path(path))
    policy.set_training_mode(False)
    return policy, cfg


def checkpoint_config(state: dict, path: str | Path) -> TrainConfig:
    """The run config a checkpoint holds; :class:`CheckpointError` naming ``path`` if invalid."""
    try:
        return from_dict(TrainConfig, state["config"])
    except ConfigError as exc:
        raise CheckpointError(f"{path}: the checkpoint's config is invalid ({exc})") from None


def resume_worker_count(cfg: TrainConfig, ckpt: dict) -> tuple[TrainConfig, dict]:
    """``cfg`` and the checkpoint's config dict with the run's worker count filled in: a
    checkpoint records the count it resolved (``workers.count``); one written before worker
    pools had one worker per scene, as many as its env state has entries. ``cfg`` with
    ``workers.count`` null takes the run's count."""
    saved = dict(ckpt["config"])
    workers = dict(saved.get("workers") or {})
    if workers.get("count") is None:
        workers["count"] = max(1, len(ckpt.get("env_state") or ())) \
            if "workers" not in saved else None
    saved["workers"] = workers
    if cfg.workers.count is None and workers["count"] is not None:
        cfg = replace(cfg, workers=replace(cfg.workers, count=int(workers["count"])))
    return cfg, saved


def _check_resume_config(cfg: TrainConfig, saved: dict, where: Path) -> None:
    now = to_dict(cfg)
    try:  # keys added since the run was saved compare as their defaults
        saved = to_dict(from_dict(TrainConfig, saved))
    except ConfigError:
        pass
    now, saved = _flat(now), _flat(saved)
    diff = sorted(k for k in set(now) | set(saved)
                  if k not in RESUMABLE_CHANGES and now.get(k) != saved.get(k))
    if diff:
        raise ConfigError(f"{where}: the config differs from the run's in {', '.join(diff)} "
                          f"(only {', '.join(RESUMABLE_CHANGES)} may change on resume)")


def _run_dir(cfg: TrainConfig, name: str | None) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    kind = cfg.algorithm if cfg.algorithm in ("bc", "sac", "gameformer") else \
        f"{cfg.algorithm}-{cfg.discriminator.kind}"
    return Path(cfg.out_dir) / (name or f"{kind}-seed{cfg.seed}-{stamp}")


def check_run_dir(d: Path) -> Path:
    """Check ``d`` can be the directory of a new run (:func:`claim_run_dir` marks it later).

    Refused when it holds a run (use ``--resume`` or ``--overwrite``) or is a non-empty folder
    magail_sumo did not write. A folder marked by ``train`` that holds none of
    :data:`RUN_OUTPUTS` (an overwritten run next to files of the user's) is reused.
    """
    if d.exists() and not d.is_dir():
        raise MagailSumoError(f"{d}: exists and is not a folder")
    if d.is_dir() and any(d.iterdir()):
        marker = read_marker(d)
        if marker is not None and any((d / n).exists() for n in RUN_OUTPUTS):
            raise MagailSumoError(f"{d}: run directory holds a run (use --resume, or "
                                  "--overwrite to replace it)")
        if marker is None:
            raise MagailSumoError(f"{d}: run directory exists, is not empty and was not written "
                                  "by magail-sumo train (choose a new or empty folder)")
    return d


def claim_run_dir(d: Path, resumed: bool) -> Path:
    """Mark ``d`` as ``train``'s output folder (:func:`~magail_sumo.outputs.claim_output_dir`,
    listing :data:`RUN_OUTPUTS`); a resumed run written before markers existed stays as it is."""
    if resumed and read_marker(d) is None:
        return d
    return claim_output_dir(d, "train", RUN_OUTPUTS)


def _rng_state() -> dict:
    """The torch / numpy / python global RNG states (numpy's as it gives them)."""
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
            "python": random.getstate()}


def _encode_rng(state: dict) -> dict:
    """:func:`_rng_state` as tensors and plain data."""
    name, keys, pos, has_gauss, cached = state["numpy"]
    version, internal, gauss = state["python"]
    return {"torch": state["torch"],
            "numpy": [str(name), torch.from_numpy(np.asarray(keys, np.uint32).astype(np.int64)),
                      int(pos), int(has_gauss), float(cached)],
            "python": [int(version), [int(v) for v in internal], gauss]}


def _decode_rng(state: Any) -> dict:
    """:func:`_encode_rng`'s form back to :func:`_rng_state`'s (ValueError / TypeError when
    malformed)."""
    if not isinstance(state, dict):
        raise TypeError("rng is not a mapping")
    t = state["torch"]
    if not isinstance(t, torch.Tensor) or t.dtype != torch.uint8 or t.dim() != 1:
        raise TypeError("rng.torch is not a byte tensor")
    name, keys, pos, has_gauss, cached = state["numpy"]
    if not isinstance(keys, torch.Tensor) or keys.shape != (624,):
        raise ValueError("rng.numpy keys are not 624 integers")
    keys = keys.numpy()
    if keys.min() < 0 or keys.max() >= 1 << 32:
        raise ValueError("rng.numpy keys out of range")
    version, internal, gauss = state["python"]
    if not (isinstance(internal, (list, tuple)) and all(type(v) is int for v in internal)):
        raise TypeError("rng.python state is not a list of integers")
    if not (isinstance(pos, int) and isinstance(has_gauss, int)
            and isinstance(cached, (int, float)) and (gauss is None or isinstance(gauss, float))):
        raise TypeError("rng fields have wrong types")
    return {"torch": t, "numpy": (str(name), keys.astype(np.uint32), pos, has_gauss, float(cached)),
            "python": (version, tuple(internal), gauss)}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def _encode_state(state: dict) -> dict:
    """A run's state (numpy in places) as tensors and plain data (``torch.load``-safe)."""
    out = dict(state)
    out["rng"] = _encode_rng(state["rng"])
    if "last_obs" in state:
        out["last_obs"] = torch.from_numpy(np.array(state["last_obs"]))
        out["last_episode_starts"] = torch.from_numpy(np.array(state["last_episode_starts"]))
        out["env_state"] = encode_env_state(state["env_state"])
        out["env_counters"] = [int(v) for v in state["env_counters"]]
        dt = dict(state["disc_trainer"])
        dt["rng"] = _plain(dt["rng"])
        out["disc_trainer"] = dt
    return out


def _plain(v: Any) -> Any:
    """Numpy scalars in nested dicts / lists as python ones (a numpy bit generator's state)."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v.item() if isinstance(v, np.generic) else v


def _tensor(v: Any, name: str) -> torch.Tensor:
    if not isinstance(v, torch.Tensor):
        raise TypeError(f"{name} is not a tensor")
    return v


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train(cfg: TrainConfig, run_dir: str | Path | None = None, resume: str | Path | None = None,
          log: Callable[[str], None] = print,
          progress: Callable[[str, int, int], None] | None = None) -> Path:
    """Run (or resume) training; the run directory.

    :param run_dir: where to write (default ``out_dir/<algorithm>-seed<seed>-<time>``).
    :param resume: a run directory to continue from its ``checkpoints/latest.pt``.
    :param progress: called as ``progress(phase, done, total)`` after every behavioural-cloning
        epoch (phase ``"bc"``), PPO update (phase ``"updates"``) and SAC update (phase
        ``"sac_updates"``), e.g. for a progress bar.
    """
    check_train_config(cfg)
    ckpt = None
    if resume is not None:
        rd = Path(resume)
        where = rd / "checkpoints" / "latest.pt"
        ckpt = load_checkpoint(where)
        checkpoint_config(ckpt, where)  # a valid config, or an error naming the file
        cfg, saved = resume_worker_count(cfg, ckpt)
        _check_resume_config(cfg, saved, where)
        run_dir = rd
    else:
        run_dir = check_run_dir(Path(run_dir) if run_dir is not None else _run_dir(cfg, None))
    torch.set_num_threads(max(1, cfg.torch_threads))
    _seed_everything(cfg.seed)
    progress = progress or (lambda phase, done, total: None)
    if cfg.algorithm in ("sac", "sac_gail"):
        from .sac import train_sac

        expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation)) \
            if cfg.algorithm == "sac_gail" else None
        return train_sac(cfg, Path(run_dir), expert, ckpt, log, progress)
    if cfg.algorithm == "gameformer":
        from .gameformer import train_gameformer

        return train_gameformer(cfg, Path(run_dir), ckpt, log, progress)
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    if cfg.algorithm == "bc":
        return _train_bc(cfg, Path(run_dir), expert, ckpt, log, progress)
    return _train_gail(cfg, Path(run_dir), expert, ckpt, log, progress)


def _train_bc(cfg: TrainConfig, run_dir: Path, expert: ExpertDataset, ckpt: dict | None,
              log: Callable[[str], None], progress: Callable[[str, int, int], None]) -> Path:
    from .bc import behavioural_cloning

    if ckpt is not None:
        log(f"{run_dir}: behavioural cloning run already complete")
        return run_dir
    claim_run_dir(run_dir, resumed=False)
    record_run(run_dir, cfg)
    policy = make_policy(cfg)
    policy.obs_normalizer.update(torch.as_tensor(expert.s))
    def bc_log(e: int, v: float) -> None:
        log(f"bc epoch {e + 1}: nll {v:.4f}")
        progress("bc", e + 1, cfg.bc.epochs)

    behavioural_cloning(policy, expert, cfg.bc.epochs, cfg.bc.batch_size, cfg.bc.learning_rate,
                        cfg.seed, log=bc_log)
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    state = _encode_state({"format": CHECKPOINT_FORMAT, "update": 0, "config": to_dict(cfg),
                           "policy": policy.state_dict(), "rng": _rng_state()})
    _save(state, run_dir / "checkpoints" / "latest.pt")
    log(f"{run_dir}: policy saved")
    return run_dir


def _torch_threads_callback():
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
    ``cfg`` with ``workers.count`` resolved (None: the usable cores, at most one per scene)."""
    from converters.sumo.scenario import claim_networks_dir
    from magail_sumo.env.scene_pool import resolve_pool
    from magail_sumo.env.vec_env import pool_vec_env

    from .config import usable_cores

    skipped: list = []
    refs = resolve_pool(cfg.scenes.files, skipped)
    for s in skipped:
        log(f"scene skipped: {s.what}: {s.reason}")
    count = cfg.workers.count or min(len(refs), usable_cores())
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


def note_skipped(venv, run_dir: Path) -> None:
    """Append the scenes the pool skipped since the last call to the run's
    :data:`SKIPPED_FILE`."""
    from magail_sumo.env.scene_pool import PoolSkip, write_skipped

    new, venv.new_skipped = venv.new_skipped, []
    write_skipped(run_dir / SKIPPED_FILE, [PoolSkip(w, r) for w, r in new])


def encode_env_state(env_state) -> list:
    """:meth:`MultiSceneVecEnv.get_state` as tensors and plain data."""
    return [[int(ep), torch.from_numpy(np.stack(acts).astype(np.float32))
             if len(acts) else torch.zeros((0, 0), dtype=torch.float32)]
            for ep, acts in env_state]


def decode_env_state(venv, saved: Any) -> list[tuple[int, list[np.ndarray]]]:
    """A checkpoint's env state (:func:`encode_env_state`) as
    :meth:`MultiSceneVecEnv.set_state` takes it; ValueError / TypeError when it does not fit
    the env's scenes."""
    if not isinstance(saved, (list, tuple)) or len(saved) != len(venv.slots):
        raise ValueError(f"env_state does not hold {len(venv.slots)} scenes")
    out = []
    for k, (ep, acts) in enumerate(saved):
        acts = _tensor(acts, "env_state actions")
        if not isinstance(ep, int) or not 0 <= ep < 1 << 31:
            raise ValueError(f"env_state scene {k}: bad episode index")
        if acts.numel() and (acts.dtype != torch.float32 or acts.dim() != 3
                             or tuple(acts.shape[1:]) != (venv.slots[k], 2)
                             or not bool(torch.isfinite(acts).all())):
            raise ValueError(f"env_state scene {k}: actions are not finite float32 "
                             f"(steps, {venv.slots[k]}, 2)")
        out.append((ep, list(acts.numpy()) if acts.numel() else []))
    return out


class GailRun:
    """The objects of a GAIL / MAGAIL run (env, reward wrapper, discriminator, PPO, callbacks).

    :param cfg: the run config (``workers.count`` None is resolved: :attr:`cfg` holds the
        number used). :param expert: expert demonstrations. :param log: one-line messages
        (scene pool, skipped scenes, replaced workers).
    """

    def __init__(self, cfg: TrainConfig, expert: ExpertDataset,
                 log: Callable[[str], None] | None = None) -> None:
        from stable_baselines3.common.callbacks import CallbackList

        from .discriminator_loss import DiscriminatorLossConfig
        from .ppo import KLAdaptiveLR, MaskedPPO
        from .reward import DiscriminatorCallback, DiscriminatorRewardWrapper, DiscriminatorTrainer

        TorchThreads = _torch_threads_callback()

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
            self.discriminator = make_discriminator(cfg, 2 * self.venv.obs_dim)
            self.wrapper = DiscriminatorRewardWrapper(self.venv, self.discriminator,
                                                      d.reward_t_coef, d.reward_i_coef,
                                                      d.reward_floor, cfg.device, deferred=True,
                                                      penalties={"collision": d.collision_penalty,
                                                                 "off_road": d.off_road_penalty},
                                                      social_coef=d.decomposed.social_coef
                                                      if d.kind == "decomposed" else 0.0)
            self.disc_trainer = DiscriminatorTrainer(
                self.discriminator, expert, d.epochs, d.batch_size, d.learning_rate,
                d.weight_decay, DiscriminatorLossConfig(d.gp_coef, d.logit_reg), cfg.seed,
                cfg.device)
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
        return _encode_state({
            "format": CHECKPOINT_FORMAT, "update": self.update, "config": to_dict(self.cfg),
            "policy": m.policy.state_dict(), "policy_optimizer": m.policy.optimizer.state_dict(),
            "learning_rate": float(m.learning_rate), "num_timesteps": m.num_timesteps,
            "n_updates": m._n_updates, "last_obs": m._last_obs,
            "last_episode_starts": m._last_episode_starts,
            "discriminator": self.discriminator.state_dict(),
            "disc_trainer": self.disc_trainer.state_dict(),
            "bc_regulariser": {"updates": m.bc_updates,
                               "rng": _plain(m.bc_rng.bit_generator.state)},
            "env_state": self.venv.get_state(),
            "env_counters": (self.venv.agent_steps, self.venv.episodes),
            "rng": _rng_state()})

    def load_state_dict(self, state: dict, where: Path) -> None:
        """Restore :meth:`state_dict`'s state (replaying the env); :class:`CheckpointError`
        (one line, naming ``where``) when it does not fit this run."""
        m = self.model
        try:  # decode and check the plain parts first: cheap, before the env replay
            rng = _decode_rng(state["rng"])
            last_obs = _tensor(state["last_obs"], "last_obs").numpy()
            starts = _tensor(state["last_episode_starts"], "last_episode_starts").numpy()
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
        _load_into(m.policy, state["policy"], "policy", where)
        _load_into(m.policy.optimizer, optim_state, "policy_optimizer", where)
        _load_into(self.discriminator, state["discriminator"], "discriminator", where)
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
            _set_rng_state(rng)
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


def _train_gail(cfg: TrainConfig, run_dir: Path, expert: ExpertDataset, ckpt: dict | None,
                log: Callable[[str], None], progress: Callable[[str, int, int], None]) -> Path:
    from stable_baselines3.common.logger import configure

    run = GailRun(cfg, expert, log=log)
    cfg = run.cfg  # workers.count resolved

    try:
        if ckpt is not None:
            run.load_state_dict(ckpt, run_dir / "checkpoints" / "latest.pt")
            log(f"resumed {run_dir} at update {run.update}")
        else:
            run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
            if cfg.bc.epochs > 0:
                from .bc import behavioural_cloning

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
                   if (sp := run.disc_callback.last_speed) is not None else ""))
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
