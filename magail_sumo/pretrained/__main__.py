"""``python -m magail_sumo.pretrained list | export``: show or add registry entries.

    python -m magail_sumo.pretrained [--debug] list [--dir DIR]
    python -m magail_sumo.pretrained [--debug] export RUN/checkpoints/latest.pt --name NAME
        [--description TEXT] [--split configs/splits/womd14.yaml] [--figures FILE.json]
        [--default] [--noise-scale K [--noise-note TEXT]] [--dir DIR]
"""

from __future__ import annotations

import argparse
import sys
import traceback

from magail_sumo.agents.noise import NoiseShape
from magail_sumo.errors import MagailSumoError
from magail_sumo.sim.dynamics import ACTION_SIZE
from magail_sumo.outputs import os_error, printable

from . import available, default_name, export, read_figures, registry_dir


def _error_line(args: argparse.Namespace, exc: Exception) -> str:
    """``error: problem`` on one line: ours (and an ``OSError``) name their file; another
    exception is named by type and prefixed with the file the user gave (the checkpoint for
    ``export``, the registry folder for ``list``)."""
    if isinstance(exc, OSError):
        exc = os_error(exc, args.checkpoint if args.command == "export" else
                       registry_dir(args.dir))
    text = " ".join(str(exc).split()) or type(exc).__name__
    if not isinstance(exc, MagailSumoError):
        src = str(args.checkpoint if args.command == "export" else registry_dir(args.dir))
        text = f"{src}: {type(exc).__name__}: {text}"
    return f"error: {printable(text, 1000)}"


def main(argv: list[str] | None = None) -> int:
    """Every error is one line on stderr (``--debug``: its traceback first) and exit status 1."""
    ap = argparse.ArgumentParser(prog="python -m magail_sumo.pretrained",
                                 description="list or add pretrained policies")
    ap.add_argument("--debug", action="store_true", help="print the traceback of an error")
    sub = ap.add_subparsers(dest="command", required=True)
    ls = sub.add_parser("list", help="the available names and the default")
    ex = sub.add_parser("export", help="add a training checkpoint as NAME.pt + NAME.json")
    ex.add_argument("checkpoint")
    ex.add_argument("--name", required=True)
    ex.add_argument("--description", default="")
    ex.add_argument("--split", help="the split file it was trained on (its test scenes are "
                                    "checked against the training config)")
    ex.add_argument("--figures", help="a JSON file of figures for the card (e.g. "
                                      "benchmarks/quality.py --json output)")
    ex.add_argument("--default", action="store_true", help="make it the default (index.json)")
    ex.add_argument("--noise-scale", type=float, help="the noise scale evaluation samples it "
                                                      "with (card's sampling; default 1)")
    ex.add_argument("--noise-note", default="", help="how that noise scale was chosen")
    ex.add_argument("--noise-weights", type=float, nargs=ACTION_SIZE, metavar="W",
                    help="the noise's weight per action (default 1 each)")
    ex.add_argument("--noise-correlation", type=float, nargs=ACTION_SIZE, metavar="RHO",
                    help="the noise's step-to-step correlation per action, in [0, 1) "
                         "(default 0: white; magail_sumo.agents.noise)")
    for p in (ls, ex):
        p.add_argument("--dir", help="registry folder (default: $MAGAIL_SUMO_PRETRAINED_DIR or "
                                     "the package's folder)")
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="print the traceback of an error")
    args = ap.parse_args(argv)
    try:
        if args.command == "list":
            print(f"folder: {registry_dir(args.dir)}")
            print(f"default: {default_name(args.dir)}")
            for name in available(args.dir):
                print(name)
            return 0
        figures = read_figures(args.figures) if args.figures else None
        entry = export(args.checkpoint, args.name, args.dir, description=args.description,
                       split=args.split, figures=figures, make_default=args.default,
                       noise_scale=args.noise_scale, noise_note=args.noise_note,
                       noise_shape=NoiseShape(
                           weights=args.noise_weights or NoiseShape().weights,
                           correlation=args.noise_correlation or NoiseShape().correlation))
        print(f"{entry.checkpoint} (+ {entry.checkpoint.with_suffix('.json').name})")
        return 0
    except KeyboardInterrupt:
        print("python -m magail_sumo.pretrained: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one top-level handler
        if args.debug:
            traceback.print_exc()
        print(_error_line(args, exc), file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
