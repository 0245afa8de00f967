"""The scene-pool vector env of a training run (shared by the algorithms that step scenes)."""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

from converters.sumo.scenario import claim_networks_dir
from magail_sumo.env.scene_pool import ScenePoolError, is_city, resolve_pool
from magail_sumo.env.vec_env import pool_vec_env

from .config import TrainConfig, usable_cores


def make_pool_env(cfg: TrainConfig, log: Callable[[str], None]):
    """The run's scene-pool vector env (:func:`~magail_sumo.env.vec_env.pool_vec_env`) and
    ``cfg`` with ``workers.count`` resolved (None: the usable cores, at most one per scene
    unless the pool holds a city scenario, which replicas play on every core)."""
    skipped: list = []
    refs = resolve_pool(cfg.scenes.files, skipped)
    for s in skipped:
        log(f"scene skipped: {s.what}: {s.reason}")
    if cfg.workers.scenes_per_env > 1 and (city := next((r for r in refs if is_city(r)), None)):
        raise ScenePoolError(f"{city}: a city scenario plays alone, not tiled with other "
                             f"scenes (workers.scenes_per_env: {cfg.workers.scenes_per_env}): "
                             "train cities with scenes_per_env: 1")
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
                                            "num_cpus": w.ray.num_cpus, "node_ip": w.ray.node_ip},
        max_restarts=w.max_restarts, scenes_per_env=w.scenes_per_env)
    venv.skipped[:0] = [(s.what, s.reason) for s in skipped]
    venv.new_skipped[:0] = [(s.what, s.reason) for s in skipped]
    log(f"scene pool: {len(refs)} scene(s) over {len(venv.specs)} "
        f"{w.backend} worker(s), {venv.num_envs} agent slots")
    return cfg, venv


__all__ = ["make_pool_env"]
