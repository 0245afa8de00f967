"""Exceptions raised on bad input; messages are one line naming the file, record and problem."""

from __future__ import annotations

from os import PathLike


class MagailSumoError(Exception):
    """Base class of the errors magail_sumo raises on bad input or configuration."""


class SceneFormatError(MagailSumoError):
    """A recorded-scene file or one of its records cannot be read.

    :param path: the file.
    :param record: index of the record within the file (None when the whole file is bad).
    :param problem: what is wrong.
    :param fatal_for_file: True when nothing after this point of the file can be read.
    """

    def __init__(self, path: str | PathLike, record: int | None, problem: str,
                 fatal_for_file: bool = False) -> None:
        self.path = str(path)
        self.record = record
        self.problem = problem
        self.fatal_for_file = fatal_for_file
        self.reason = problem.split(":")[0].split(" (")[0]  # short category for summaries
        where = self.path if record is None else f"{self.path}: record {record}"
        super().__init__(f"{where}: {problem}")
