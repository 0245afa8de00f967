"""Argument types with bounds for the CLI: a bad value is an argparse error (usage + one line)."""

from __future__ import annotations

import argparse
from typing import Callable


def bounded(kind: type, low: float | None = None, high: float | None = None,
            none: str | None = None) -> Callable[[str], object]:
    """An argparse ``type`` parsing ``kind`` (int or float) within ``[low, high]``; the word
    ``none`` (when given, e.g. ``"none"``) parses to None."""

    def parse(text: str):
        if none is not None and text.strip().lower() == none:
            return None
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a{'n' if kind is int else ''} "
                                             f"{kind.__name__}") from None
        if value != value or (low is not None and value < low) or \
                (high is not None and value > high):
            rng = f"{low if low is not None else '-inf'}..{high if high is not None else 'inf'}"
            raise argparse.ArgumentTypeError(f"{text} is outside {rng}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


#: ``--timeout-s``: seconds per scene (worker job) before it is reported failed; "none": no limit
timeout_s = bounded(float, 0.1, 7 * 24 * 3600.0, none="none")
