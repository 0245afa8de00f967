"""Training runs of the ``gameformer`` algorithm (:class:`~magail_sumo.training.config.GameFormerConfig`).

The GameFormer predictor (:mod:`magail_sumo.models.gameformer`) learns from the recorded scenes
of ``scenes.files`` (every scene of each file; globs allowed) through the seeded
:class:`~magail_sumo.training.gameformer.data.StreamingDataset`; no simulation, no expert
folder. Update ``u`` (0-based) is one AdamW step on batch ``u`` of the stream (the sum over the
levels of :func:`~magail_sumo.models.gameformer.level_loss`, gradients clipped to
``max_grad_norm``).

Checkpoints (``RUN/checkpoints/update_NNNNNN.pt`` and ``latest.pt``, atomic, format
``magail_sumo.checkpoint/2``, read with ``torch.load(weights_only=True)``) hold the config, the
network (under ``policy``), the optimiser, the update count and the torch / numpy / python RNG
states; the batch stream is a function of (seed, update), so a resumed run continues bit for
bit as if uninterrupted.
"""

from __future__ import annotations

import glob
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch

from converters.scene_files import list_records
from magail_sumo.config import record_run, to_dict
from magail_sumo.models.gameformer import GameFormer, gameformer_loss

from ..checkpoints import (CHECKPOINT_FORMAT, CheckpointError, checkpoint_config, encode_state,
                           load_checkpoint, load_into, save_checkpoint)
from ..config import TrainConfig
from ..rng import decode_rng, rng_state, set_rng_state
from ..run_dir import claim_run_dir
from .data import StreamingDataset

ALGORITHM = "gameformer"


def scene_records(files: tuple[str, ...]) -> list:
    """The scene records of ``files`` (globs expanded, sorted), in order."""
    refs = []
    for f in files:
        paths = sorted(glob.glob(f)) if set("*?[") & set(f) else [f]
        for p in paths:
            refs.extend(list_records(p))
    return refs


def make_model(cfg: TrainConfig) -> GameFormer:
    return GameFormer(cfg.gameformer.model).to(cfg.device)


def make_optimizer(cfg: TrainConfig, model: GameFormer) -> torch.optim.Optimizer:
    g = cfg.gameformer
    return torch.optim.AdamW(model.parameters(), lr=g.learning_rate, weight_decay=g.weight_decay)


def batch_loss(model: GameFormer, batch: dict[str, torch.Tensor], cfg: TrainConfig):
    """(total loss, per-level :class:`~magail_sumo.models.gameformer.LevelLoss`) of a batch."""
    g = cfg.gameformer
    dev = cfg.device
    b = {k: v.to(dev) for k, v in batch.items()}
    outs = model(b["agents"], b["agent_mask"], b["map"], b["map_mask"])
    return gameformer_loss(outs, b["future"], b["future_mask"], b["agent_mask"],
                           g.interaction_weight, g.safety_distance)


def train_gameformer(cfg: TrainConfig, run_dir: Path, ckpt: dict | None,
                     log: Callable[[str], None], progress: Callable[[str, int, int], None]
                     ) -> Path:
    """Run (or resume from ``ckpt``) a gameformer training run into ``run_dir``."""
    g = cfg.gameformer
    where = run_dir / "checkpoints" / "latest.pt"
    refs = scene_records(cfg.scenes.files)
    data = StreamingDataset(refs, g, cfg.seed)
    model = make_model(cfg)
    opt = make_optimizer(cfg, model)
    update = 0
    if ckpt is not None:
        try:
            rng = decode_rng(ckpt["rng"])
            update = int(ckpt["update"])
        except KeyError as exc:
            raise CheckpointError(f"{where}: checkpoint lacks {exc.args[0]}") from None
        except (ValueError, TypeError) as exc:
            raise CheckpointError(f"{where}: checkpoint rng does not fit ({exc})") from None
        load_into(model, ckpt["policy"], "policy", where)
        load_into(opt, ckpt.get("optimizer"), "optimizer", where)
        set_rng_state(rng)
        log(f"resumed {run_dir} at update {update}")
    claim_run_dir(run_dir, resumed=ckpt is not None)
    record_run(run_dir, cfg)
    log(f"gameformer: {data.num_samples} samples from {len(refs)} scene(s), "
        f"{data.batches_per_epoch} batches per epoch")

    def save() -> None:
        save_checkpoint(run_dir, encode_state({
            "format": CHECKPOINT_FORMAT, "update": update, "config": to_dict(cfg),
            "policy": model.state_dict(), "optimizer": opt.state_dict(), "rng": rng_state()}),
            update)

    model.train()
    t0, every = time.perf_counter(), max(1, min(50, cfg.checkpoint_every))
    while update < cfg.updates:
        loss, levels = batch_loss(model, data.batch(update), cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), g.max_grad_norm)
        opt.step()
        update += 1
        if update % every == 0 or update == cfg.updates:
            log(f"update {update}/{cfg.updates}: loss {loss.item():.3f} nll "
                + " ".join(f"{lv.nll.item():.2f}" for lv in levels)
                + f" ce {levels[-1].score.item():.3f} inter {levels[-1].interaction.item():.4f}"
                f" ({time.perf_counter() - t0:.0f} s)")
        progress("gameformer updates", update, cfg.updates)
        if update % cfg.checkpoint_every == 0 or update == cfg.updates:
            save()
    if update == 0 and ckpt is None:
        save()
    return run_dir


def load_gameformer(path: str | Path, device: str = "cpu") -> tuple[GameFormer, TrainConfig]:
    """The network of a gameformer checkpoint (eval mode) and its run config;
    :class:`CheckpointError` when the file is not one."""
    state = load_checkpoint(path)
    cfg = replace(checkpoint_config(state, path), device=device)
    if cfg.algorithm != ALGORITHM:
        raise CheckpointError(f"{path}: not a gameformer checkpoint (algorithm "
                              f"{cfg.algorithm!r})")
    model = make_model(cfg)
    load_into(model, state["policy"], "policy", Path(path))
    model.eval()
    return model, cfg
