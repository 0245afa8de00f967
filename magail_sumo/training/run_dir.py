"""A training run's directory: its default name, the checks before a new run writes into it,
its output-folder marker, and the list of scenes the pool skipped."""

from __future__ import annotations

import os
import time
from pathlib import Path

from magail_sumo.env.scene_pool import PoolSkip, write_skipped
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import claim_output_dir, inside, read_marker

from .config import TrainConfig
from .algorithms import get

#: what ``train`` writes into a run directory (recorded in its marker: ``--overwrite`` removes
#: only these)
RUN_OUTPUTS = ("config.yaml", "environment.json", "checkpoints", "tb", "skipped_scenes.tsv")
#: the run's list of scenes left out of the pool (tab-separated: scene, reason)
SKIPPED_FILE = "skipped_scenes.tsv"


def default_run_dir(cfg: TrainConfig, name: str | None) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")

    kind = f"{cfg.algorithm}-{cfg.discriminator.kind}" if get(cfg.algorithm).adversarial \
        else cfg.algorithm
    return Path(cfg.out_dir) / (name or f"{kind}-seed{cfg.seed}-{stamp}")


def check_run_dir(d: Path) -> Path:
    """Check ``d`` can be the directory of a new run (:func:`claim_run_dir` marks it later).

    Refused when it holds a run (use ``--resume`` or ``--overwrite``), is a non-empty folder
    magail_sumo did not write, or holds a symbolic link out of it in place of one of
    :data:`RUN_OUTPUTS` (:func:`check_run_outputs`). A folder marked by ``train`` that holds none of
    :data:`RUN_OUTPUTS` (an overwritten run next to files of the user's) is reused.
    """
    if d.exists() and not d.is_dir():
        raise MagailSumoError(f"{d}: exists and is not a folder")
    if d.is_dir() and any(d.iterdir()):
        if read_marker(d) is None:
            raise MagailSumoError(f"{d}: run directory exists, is not empty and was not written "
                                  "by magail-sumo train (choose a new or empty folder)")
        check_run_outputs(d)
        if any(os.path.lexists(d / n) for n in RUN_OUTPUTS):
            raise MagailSumoError(f"{d}: run directory holds a run (use --resume, or "
                                  "--overwrite to replace it)")
    return d


def check_run_outputs(d: Path) -> Path:
    """``d``, refused (:class:`~magail_sumo.outputs.OutputError`, one line naming the path)
    when one of :data:`RUN_OUTPUTS` in it leads out of it through a symbolic link (a dangling
    one included): checked before a new or resumed run's set-up, and again through
    :func:`~magail_sumo.outputs.inside` where each is written."""
    for name in RUN_OUTPUTS:
        inside(d, name)
    return d


def claim_run_dir(d: Path, resumed: bool) -> Path:
    """Mark ``d`` as ``train``'s output folder (:func:`~magail_sumo.outputs.claim_output_dir`,
    listing :data:`RUN_OUTPUTS`); a resumed run written before markers existed stays as it is."""
    if resumed and read_marker(d) is None:
        return d
    return claim_output_dir(d, "train", RUN_OUTPUTS)


def note_skipped(venv, run_dir: Path) -> None:
    """Append the scenes the pool skipped since the last call to the run's
    :data:`SKIPPED_FILE` (:class:`~magail_sumo.outputs.OutputError` when it is a symbolic link
    out of ``run_dir``: nothing is appended through it)."""
    new, venv.new_skipped = venv.new_skipped, []
    path = inside(run_dir, SKIPPED_FILE)
    write_skipped(path, [PoolSkip(w, r) for w, r in new])
