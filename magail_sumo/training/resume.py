"""What may change when a run is resumed, and the worker count a resumed run keeps."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from magail_sumo.config import ConfigError, from_dict, to_dict

from .config import TrainConfig

#: config keys (dotted for nested ones) that may differ between a run and its resumption:
#: they change neither the results nor the state
RESUMABLE_CHANGES = ("updates", "checkpoint_every", "scenes.worker_timeout_s",
                     "scenes.pin_workers", "workers.backend", "workers.ray.address",
                     "workers.ray.num_cpus", "workers.max_restarts")


def flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


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


def check_resume_config(cfg: TrainConfig, saved: dict, where: Path) -> None:
    now = to_dict(cfg)
    try:  # keys added since the run was saved compare as their defaults
        saved = to_dict(from_dict(TrainConfig, saved))
    except ConfigError:
        pass
    now, saved = flat(now), flat(saved)
    diff = sorted(k for k in set(now) | set(saved)
                  if k not in RESUMABLE_CHANGES and now.get(k) != saved.get(k))
    if diff:
        raise ConfigError(f"{where}: the config differs from the run's in {', '.join(diff)} "
                          f"(only {', '.join(RESUMABLE_CHANGES)} may change on resume)")
