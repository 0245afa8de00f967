"""The one training run loop, shared by every update-based algorithm (SB3's
``BaseAlgorithm.learn`` plays this part there): resume or start, claim the run folder, record the
run, log each update, checkpoint on cadence, always close.

An algorithm provides a :class:`Run` (its objects and one update) and its run function is
``run_loop(TheRun(cfg, ...), run_dir, ckpt, log, progress)``. The loop, per update ``k`` of
``cfg.updates``:

1. ``run.run_update()`` (the update: rollout, learning);
2. ``run.summarise(logger)`` records the update's scalars into the TensorBoard logger and
   returns the tail of the console line ``update k/N: A agent-steps in T s<tail>``;
3. ``logger.dump(run.log_step())``, the skipped scenes noted, ``progress(run.progress_phase, k,
   N)``;
4. a checkpoint (``run.save``) every ``cfg.checkpoint_every`` updates and after the last.

A run resumed from a checkpoint (``ckpt``) restores its state (:meth:`Run.load_state_dict`)
instead of :meth:`Run.begin`, and continues exactly as if uninterrupted.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Protocol

from stable_baselines3.common.logger import Logger, configure

from magail_sumo.config import record_run
from magail_sumo.outputs import inside_dir

from .config import TrainConfig
from .run_dir import claim_run_dir, note_skipped

from magail_sumo.workers import Progress  # noqa: F401 - the loop's progress protocol


class Run(Protocol):
    """What the loop needs of an algorithm's run.

    :ivar cfg: the run config (``workers.count`` resolved).
    :ivar update: updates done so far.
    :ivar venv: the scene-pool vector env (``agent_steps``, ``skipped``; closed by :meth:`close`).
    :ivar progress_phase: the progress phase its updates are reported under.
    :ivar steps_per_update: vector env steps of one update (0: not reported), reported as
        progress phase ``"steps"`` while the update collects them.
    """

    cfg: TrainConfig
    update: int
    venv: Any
    progress_phase: str
    steps_per_update: int

    def begin(self, progress: Progress) -> None:
        """Start a new run (warm starts, normalisers, the first reset)."""

    def load_state_dict(self, state: dict, where: Path) -> None:
        """Restore a checkpoint's state (``where`` names it in errors)."""

    def attach_logger(self, logger: Logger) -> None:
        """Log into ``logger`` from now on."""

    def run_update(self) -> None:
        """One update; ``update`` counts it."""

    def summarise(self, logger: Logger) -> str:
        """Record the last update's scalars; the tail of its console line."""

    def log_step(self) -> int:
        """The x value the update's scalars are dumped at."""

    def save(self, run_dir: Path) -> Path:
        """Write a checkpoint of the current state; its path."""

    def close(self) -> None:
        """Release the env (worker processes)."""


def tb_logger(run_dir: Path) -> Logger:
    """The run's TensorBoard logger, writing into ``run_dir/tb``
    (:func:`~magail_sumo.outputs.inside_dir`: refused when ``tb`` is a symbolic link out of
    ``run_dir``)."""
    return configure(str(inside_dir(run_dir, "tb")), ["tensorboard"])


def run_loop(run: Run, run_dir: Path, ckpt: dict | None, log: Callable[[str], None],
             progress: Progress) -> Path:
    """Run (or resume, from ``ckpt``) ``run`` in ``run_dir`` until ``cfg.updates`` (module doc);
    the run is closed whatever happens."""
    cfg = run.cfg
    try:
        if ckpt is not None:
            run.load_state_dict(ckpt, run_dir / "checkpoints" / "latest.pt")
            log(f"resumed {run_dir} at update {run.update}")
        else:
            run.begin(progress)
        claim_run_dir(run_dir, resumed=ckpt is not None)
        record_run(run_dir, cfg)
        note_skipped(run.venv, run_dir)
        logger = tb_logger(run_dir)
        run.attach_logger(logger)
        per = getattr(run, "steps_per_update", 0)
        first = run.venv.steps
        if per:
            run.venv.on_step = lambda n: progress("steps", min(n - first, per), per)
        while run.update < cfg.updates:
            first = run.venv.steps
            t0 = time.perf_counter()
            steps0 = run.venv.agent_steps
            run.run_update()
            dt = time.perf_counter() - t0
            tail = run.summarise(logger)
            log(f"update {run.update}/{cfg.updates}: {run.venv.agent_steps - steps0} agent-steps "
                f"in {dt:.1f} s{tail}")
            logger.dump(run.log_step())
            note_skipped(run.venv, run_dir)
            progress(run.progress_phase, run.update, cfg.updates)
            if run.update % cfg.checkpoint_every == 0 or run.update == cfg.updates:
                run.save(run_dir)
    finally:
        run.close()
    return run_dir


__all__ = ["Progress", "Run", "run_loop", "tb_logger"]
