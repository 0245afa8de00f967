"""The WOSAC closed-loop protocol evaluation runs, and what its modules share.

Protocol: log steps ``0..current_time_index`` are the recorded history; the next
:data:`N_STEPS` (8 s at 0.1 s) are simulated for every object valid at ``current_time_index``
(the official sim-agent set). How each method produces those steps is
:mod:`magail_sumo.evaluation.methods`; the run over scenes, methods and worker processes
:mod:`magail_sumo.evaluation.runner`; the files it writes :mod:`magail_sumo.evaluation.storage`.
"""

from __future__ import annotations

import sys

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import printable
from magail_sumo.scene.types import STEP_LENGTH

N_STEPS = 80  #: simulated steps per rollout (8 s)
DT = STEP_LENGTH  #: s per step
#: seconds one worker job (a batch of rollouts of one method on one scene, a scene's conversion)
#: may run by default
DEFAULT_TIMEOUT_S = 1800.0
#: what every batch's process imports: SUMO, the methods' code, the learned policies' (torch;
#: a policy's processes would import it each, about 2 s of a core) and the converter's (scenes
#: without a bundle are converted in the same kind of process), imported once by the
#: process they are forked from (:func:`magail_sumo.workers.run_jobs`' ``preload``), not once
#: per batch; ``evaluate`` starts that server first
#: (:func:`magail_sumo.workers.start_job_server`), so it imports them while the command reads
#: its scenes and loads the policy
WORKER_IMPORTS = ("libsumo", "torch", "magail_sumo.evaluation.methods",
                  "converters.sumo.baseline", "converters.sumo.batch", "magail_sumo.policies")


class EvaluationError(MagailSumoError):
    """A rollout or evaluation input cannot be used (one line naming the scene / agent)."""


def rollout_seed(seed: int, rollout: int) -> int:
    """Seed of one rollout (SUMO and numpy), from the run seed; < 2**31."""
    return int(np.random.SeedSequence([seed, rollout]).generate_state(1)[0] % (2 ** 31 - 1))


def log(msg: str) -> None:
    """One line of the run log (stderr)."""
    print(msg, file=sys.stderr, flush=True)


def span(rollouts: tuple[int, ...]) -> str:
    """Rollout indices as the run log names them: ``3`` or ``0-7``."""
    return str(rollouts[0]) if len(rollouts) == 1 else f"{rollouts[0]}-{rollouts[-1]}"


class Problems:
    """The one-line problems of a run, in order, each logged (``error: ...``) as it comes."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def __call__(self, msg: str) -> None:
        msg = msg if msg.isprintable() else printable(msg, 2000)  # one line, whatever the ids
        self.lines.append(msg)
        log(f"error: {msg}")
