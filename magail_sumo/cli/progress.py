"""Progress bars for the CLI: on stderr, only when stderr is a terminal."""

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
