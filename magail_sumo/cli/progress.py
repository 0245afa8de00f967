"""Progress bars for the CLI: on stderr, only when stderr is a terminal (quiet in logs and CI).

:func:`progress` wraps an iterable; :class:`PhaseBars` is the
:data:`~magail_sumo.workers.Progress` the long commands (``train``, ``evaluate``, ``expert``,
``report``) are given: one bar per phase, a bar started anew when its count starts over (the
env steps of each training update).
"""

from __future__ import annotations

import sys
from typing import Iterable, Iterator, TypeVar

from tqdm import tqdm

T = TypeVar("T")


def progress(items: Iterable[T], *, desc: str, total: int | None = None, unit: str = "it",
             enabled: bool = True) -> Iterator[T]:
    """Wrap ``items`` in a tqdm bar on stderr; silent when stderr is not a TTY."""
    return iter(tqdm(items, desc=desc, total=total, unit=unit, file=sys.stderr, leave=False,
                     disable=not (enabled and sys.stderr.isatty())))


#: (description, unit) of each phase a command reports
PHASES = {"bc": ("behavioural cloning", "epoch"), "updates": ("PPO updates", "update"),
          "sac_updates": ("SAC updates", "update"), "steps": ("env steps of the update", "step"),
          "gameformer updates": ("GameFormer updates", "update"),
          "rollouts": ("rollouts", "rollout"), "scenes": ("scenes", "scene"),
          "scored": ("scored scene-method pairs", "pair")}


class PhaseBars:
    """One tqdm bar per phase on stderr, shown only when stderr is a terminal (``enabled``);
    :meth:`log` prints a line above the bars. Call as ``bars(phase, done, total)``."""

    def __init__(self, enabled: bool | None = None) -> None:
        self.bars: dict[str, tqdm] = {}
        self.enabled = sys.stderr.isatty() if enabled is None else enabled

    def log(self, line: str) -> None:
        tqdm.write(line, file=sys.stdout)

    def __call__(self, phase: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        bar = self.bars.get(phase)
        if bar is None or done < bar.n or bar.disable:  # new, or counting anew
            if bar is not None:
                bar.close()
            desc, unit = PHASES.get(phase, (phase, "it"))
            bar = self.bars[phase] = tqdm(total=total, initial=max(0, done - 1), desc=desc,
                                          unit=unit, file=sys.stderr, leave=False)
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()
