"""The ``magail-sumo`` command: a thin layer over the library, one module per subcommand.

Every error ends the command with one line on stderr, ``error: magail-sumo COMMAND: problem``
(an unexpected exception is named by type and prefixed with the command's input when it has a
single one), and exit status 1; the traceback is printed only with ``--debug``. Ctrl-C exits
with 130.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from typing import Sequence

from magail_sumo import __version__
from magail_sumo.cli import convert, evaluate, inspect, realism, replay, report, expert, train
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import printable

SUBCOMMANDS = (inspect, convert, replay, realism, evaluate, report, expert, train)
#: argument names holding a command's input (the first one present names it in errors)
INPUT_ARGS = ("scene", "inputs", "scenes", "files", "folder", "config")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="magail-sumo",
        description="SUMO co-simulation for multi-agent imitation learning of driving.")
    parser.add_argument("--version", action="version", version=f"magail-sumo {__version__}")
    debug_help = "print the traceback of an unexpected error"
    parser.add_argument("--debug", action="store_true", help=debug_help)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(sub)
    for p in sub.choices.values():  # also accepted after the command
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help=debug_help)
    return parser


def _input_of(args: argparse.Namespace) -> str | None:
    """The command's input when it has exactly one (for error lines), else None."""
    for name in INPUT_ARGS:
        value = getattr(args, name, None)
        if value is None:
            continue
        if isinstance(value, (list, tuple)):
            return str(value[0]) if len(value) == 1 else None
        return str(value)
    return None


def error_line(args: argparse.Namespace, exc: BaseException) -> str:
    """``error: magail-sumo COMMAND: [INPUT: ]problem`` on one line (INPUT for an unexpected
    exception; a :class:`MagailSumoError` names what it is about itself)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if not isinstance(exc, MagailSumoError):  # ours name their file / record / spec already
        text = f"{type(exc).__name__}: {text}"
        src = _input_of(args)
        if src is not None and src not in text:
            text = f"{src}: {text}"
    return f"error: magail-sumo {args.command}: {printable(text, 1000)}"


def _worker_tracebacks(exc: BaseException) -> None:
    """Print the tracebacks of worker processes behind ``exc`` (its cause / context chain)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        tb = getattr(exc, "worker_traceback", "")
        if tb:
            print(f"in the worker:\n{tb}", file=sys.stderr)
        exc = exc.__cause__ or exc.__context__


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print(f"magail-sumo {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one top-level handler
        if getattr(args, "debug", False):
            traceback.print_exc()
            _worker_tracebacks(exc)
        print(error_line(args, exc), file=sys.stderr)
        if not isinstance(exc, MagailSumoError) and not getattr(args, "debug", False):
            print("(run with --debug for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
