"""``python -m magail_sumo.pretrained list | export``: show or add registry entries.

    python -m magail_sumo.pretrained list [--dir DIR]
    python -m magail_sumo.pretrained export RUN/checkpoints/latest.pt --name NAME
        [--description TEXT] [--split configs/splits/womd14.yaml] [--figures FILE.json]
        [--default] [--noise-scale K [--noise-note TEXT]] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import sys

from magail_sumo.errors import MagailSumoError

from . import available, default_name, export, registry_dir


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m magail_sumo.pretrained",
                                 description="list or add pretrained policies")
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
    for p in (ls, ex):
        p.add_argument("--dir", help="registry folder (default: $MAGAIL_SUMO_PRETRAINED_DIR or "
                                     "the package's folder)")
    args = ap.parse_args(argv)
    try:
        if args.command == "list":
            print(f"folder: {registry_dir(args.dir)}")
            print(f"default: {default_name(args.dir)}")
            for name in available(args.dir):
                print(name)
            return 0
        figures = None
        if args.figures:
            with open(args.figures, encoding="utf-8") as fh:
                figures = json.load(fh)
        entry = export(args.checkpoint, args.name, args.dir, description=args.description,
                       split=args.split, figures=figures, make_default=args.default,
                       noise_scale=args.noise_scale, noise_note=args.noise_note)
        print(f"{entry.checkpoint} (+ {entry.checkpoint.with_suffix('.json').name})")
        return 0
    except (MagailSumoError, OSError, ValueError) as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
