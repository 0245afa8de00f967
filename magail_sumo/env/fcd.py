"""FCD recording of an env's episodes, one recorder for both envs
(:class:`~magail_sumo.env.driving_env.SumoDrivingEnv`, :class:`~magail_sumo.env.city_env.
SumoCityEnv`).

An :class:`EpisodeFcd` holds the env's :class:`~magail_sumo.sim.fcd.FcdRecorder` while it
records: on demand (:meth:`EpisodeFcd.record`, then :meth:`EpisodeFcd.write`), or automatically,
every ``every``-th episode into a folder (``EnvConfig.fcd_dir`` / ``fcd_every``; the file of an
episode is written when it ends). The env gives it two hooks: ``frame(recorder)`` adds the
current step's road users to a recorder, and ``replay(recorder, path)`` writes a recording
with the ``.sumocfg`` that replays it (:func:`magail_sumo.sim.fcd.write_replay`) on the env's
network.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from magail_sumo.outputs import safe_name
from magail_sumo.sim.fcd import FcdRecorder, ReplayFiles


class EpisodeFcd:
    """An env's FCD recording (module doc).

    :param dt: seconds per step (the recorder's time step).
    :param frame: adds the env's current step to a recorder.
    :param replay: writes a recorder and its replay files at a path.
    :param folder: where automatic recordings go (None: none).
    :param every: record every this many episodes automatically (0: never).
    """

    def __init__(self, dt: float, frame: Callable[[FcdRecorder], None],
                 replay: Callable[[FcdRecorder, Path], ReplayFiles],
                 folder: str | os.PathLike | None = None, every: int = 0) -> None:
        self.dt = dt
        self._frame, self._replay = frame, replay
        self.folder, self.every = folder, every
        #: the recorder in use (None: not recording)
        self.recorder: FcdRecorder | None = None
        self._episode = -1  # episodes begun so far - 1
        self._auto: Path | None = None  # where the running automatic recording goes

    def record(self, recorder: FcdRecorder | None = None, running: bool = False
               ) -> FcdRecorder:
        """Record from now on into ``recorder`` (a new one when None); with ``running`` (an
        episode is under way) the current step is its first frame."""
        self.recorder = recorder if recorder is not None else FcdRecorder(self.dt)
        if running:
            self.add_step()
        return self.recorder

    def add_step(self) -> None:
        """Add the env's current step to the recording, if any."""
        if self.recorder is not None:
            self._frame(self.recorder)

    def write(self, path: str | Path, recorder: FcdRecorder | None = None) -> ReplayFiles:
        """Write ``recorder`` (default: the one in use) with its replay files."""
        rec = recorder if recorder is not None else self.recorder
        if rec is None:
            raise RuntimeError("nothing recorded: call record_fcd() first")
        return self._replay(rec, Path(path))

    def begin_episode(self, name: str) -> None:
        """A new episode (of the scene ``name``): starts its automatic recording when due
        (``folder/<name>-<pid>-ep<episode>.fcd.xml``)."""
        self._episode += 1
        if self.folder is not None and self.every > 0 and self._episode % self.every == 0:
            if self._auto is not None:
                self.end_episode()
            file = f"{safe_name(name)}-{os.getpid()}-ep{self._episode:05d}.fcd.xml"
            self._auto = Path(self.folder) / file
            self.record()

    def end_episode(self) -> None:
        """The episode ended: its automatic recording, if any, is written and stopped."""
        if self._auto is None:
            return
        path, self._auto = self._auto, None
        if self.recorder is not None and len(self.recorder):
            self.write(path)
        self.recorder = None


__all__ = ["EpisodeFcd"]
