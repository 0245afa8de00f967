"""The ``magail-sumo`` command: a thin layer over the library, one module per subcommand."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from magail_sumo import __version__
from magail_sumo.cli import convert, evaluate, inspect, realism, replay, report, expert, train
from magail_sumo.errors import MagailSumoError

SUBCOMMANDS = (inspect, convert, replay, realism, evaluate, report, expert, train)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magail-sumo",
        description="SUMO co-simulation for multi-agent imitation learning of driving.")
    parser.add_argument("--version", action="version", version=f"magail-sumo {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except MagailSumoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
