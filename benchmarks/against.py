"""Any benchmark script of this repository, this checkout against an earlier commit, runs
alternated in one session (the machine's speed drifts by 10–15 % over an hour).

    python benchmarks/against.py COMMIT [--repeats 3] -- benchmarks/SCRIPT.py ARGS...

e.g. ``python benchmarks/against.py 301c2b6 -- benchmarks/train_throughput.py --json
--updates 3`` or ``... -- benchmarks/env_throughput.py --json --scenario ingolstadt21``.

The earlier commit is checked out with ``git worktree add`` into a temporary folder (removed at
the end). Each repeat runs the script once in each checkout, alternating which goes first (AB,
BA, AB, ...), each with the working folder and ``PYTHONPATH`` set to its checkout, so each
version runs its own copy of the script and of the package. The script must print its results
as JSON objects, one per line (the benchmarks' ``--json``); the rows of the two versions are
matched by their order. For every numeric field of every row it prints the median of each
version over the repeats, their ratio (this checkout / the earlier commit) and the runs;
``--json`` prints one object per row and field instead.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _rows(tree: Path, script: list[str]) -> list[dict]:
    """The JSON rows one run of ``script`` prints in checkout ``tree`` (raises on failure)."""
    res = subprocess.run([sys.executable, *script], cwd=tree, capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(tree)))
    if res.returncode != 0:
        raise SystemExit(f"{tree}: {' '.join(script)} failed ({res.returncode}):\n"
                         f"{res.stderr[-2000:]}")
    rows = []
    for line in res.stdout.splitlines():
        line = line.strip()
        if line.startswith("{"):
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    if not rows:
        raise SystemExit(f"{tree}: {' '.join(script)} printed no JSON row (give it --json)")
    return rows


def _numeric(row: dict) -> dict[str, float]:
    return {k: float(v) for k, v in row.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--" not in argv:
        raise SystemExit("usage: against.py COMMIT [--repeats N] [--json] -- SCRIPT ARGS...")
    cut = argv.index("--")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("commit")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="one JSON object per row and field")
    args = ap.parse_args(argv[:cut])
    script = argv[cut + 1:]
    if not script:
        raise SystemExit("against.py: no benchmark script after --")
    if args.repeats < 1:
        raise SystemExit("against.py: --repeats must be >= 1")
    runs: dict[str, list[list[dict]]] = {"earlier": [], "this": []}
    with tempfile.TemporaryDirectory(prefix="against_") as tmp:
        old = Path(tmp) / "earlier"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old),
                        args.commit], check=True, capture_output=True)
        try:
            for r in range(args.repeats):
                order = [("this", ROOT), ("earlier", old)]
                for label, tree in (order if r % 2 == 0 else order[::-1]):
                    runs[label].append(_rows(tree, script))
                    print(f"repeat {r + 1}: {label} done", file=sys.stderr, flush=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)],
                           capture_output=True)
    n_rows = min(len(rs) for rs in runs["this"] + runs["earlier"])
    for i in range(n_rows):
        label = {k: v for k, v in runs["this"][0][i].items() if isinstance(v, str)}
        fields = _numeric(runs["this"][0][i])
        for name in fields:
            vals = {k: [_numeric(rs[i]).get(name) for rs in runs[k]] for k in runs}
            if any(v is None for vs in vals.values() for v in vs):
                continue
            med = {k: statistics.median(vs) for k, vs in vals.items()}
            ratio = med["this"] / med["earlier"] if med["earlier"] else float("nan")
            if args.json:
                print(json.dumps({"row": i, **label, "field": name, "commit": args.commit,
                                  "earlier": med["earlier"], "this": med["this"],
                                  "ratio": round(ratio, 3), "runs_earlier": vals["earlier"],
                                  "runs_this": vals["this"]}))
            else:
                print(f"row {i} {label} {name}: {args.commit} {med['earlier']:g}, this "
                      f"{med['this']:g} ({ratio:.2f}x; runs {vals['earlier']} / "
                      f"{vals['this']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
