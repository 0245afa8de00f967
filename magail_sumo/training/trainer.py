"""Training runs: ``train(cfg)`` checks the config, claims or resumes the run directory, seeds
everything and runs the config's algorithm (:mod:`~magail_sumo.training.algorithms`).

The shared machinery lives in one module each: checkpoint I/O
(:mod:`~magail_sumo.training.checkpoints`), the RNG states (:mod:`~magail_sumo.training.rng`),
the run directory (:mod:`~magail_sumo.training.run_dir`), what may change on resume
(:mod:`~magail_sumo.training.resume`), the PPO / BC policy (:mod:`~magail_sumo.training.policies`)
and the adversarial reward (:mod:`~magail_sumo.training.adversarial`); each algorithm is its own
module (:mod:`~magail_sumo.training.gail`, :mod:`~magail_sumo.training.bc`,
:mod:`~magail_sumo.training.sac`, :mod:`~magail_sumo.training.gameformer`). The names below that
those modules define are re-exported here for callers of this module.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch

from . import algorithms
from .adversarial import AdversarialReward, make_discriminator
from .checkpoints import (CHECKPOINT_FORMAT, OLD_CHECKPOINT_FORMATS, CheckpointError,
                          checkpoint_config, decode_env_state, encode_env_state, encode_state,
                          load_checkpoint, load_into, save_checkpoint, save_state,
                          upgrade_checkpoint)
from .config import TrainConfig
from .envs import make_pool_env
from .gail.run import BC_STREAM, SB3_RESUME_STATE, GailRun
from .preflight import check_train_config
from .policies import load_policy, make_policy, policy_kwargs, spaces_of
from .resume import RESUMABLE_CHANGES, check_resume_config, resume_worker_count
from .rng import rng_state, seed_everything
from .run_dir import (RUN_OUTPUTS, SKIPPED_FILE, check_run_dir, check_run_outputs, claim_run_dir,
                      default_run_dir, note_skipped)

# earlier private names, kept for callers (tests, scripts)
_rng_state, _check_resume_config, _encode_state = rng_state, check_resume_config, encode_state

__all__ = ["AdversarialReward", "BC_STREAM", "CHECKPOINT_FORMAT", "CheckpointError", "GailRun",
           "OLD_CHECKPOINT_FORMATS", "RESUMABLE_CHANGES", "RUN_OUTPUTS", "SB3_RESUME_STATE",
           "SKIPPED_FILE", "check_run_dir", "check_run_outputs", "checkpoint_config",
           "claim_run_dir", "decode_env_state", "encode_env_state", "load_checkpoint", "load_into",
           "load_policy", "make_discriminator", "make_policy", "make_pool_env", "note_skipped",
           "policy_kwargs", "resume_worker_count", "save_checkpoint", "save_state", "spaces_of",
           "train", "upgrade_checkpoint"]


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
        rd = check_run_outputs(Path(resume))
        where = rd / "checkpoints" / "latest.pt"
        ckpt = load_checkpoint(where)
        checkpoint_config(ckpt, where)  # a valid config, or an error naming the file
        cfg, saved = resume_worker_count(cfg, ckpt)
        check_resume_config(cfg, saved, where)
        run_dir = rd
    else:
        run_dir = check_run_dir(Path(run_dir) if run_dir is not None
                                else default_run_dir(cfg, None))
    torch.set_num_threads(max(1, cfg.torch_threads))
    seed_everything(cfg.seed)
    progress = progress or (lambda phase, done, total: None)
    run = algorithms.get(cfg.algorithm).run_function()
    return run(cfg, Path(run_dir), ckpt, log, progress)
