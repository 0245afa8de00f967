"""A report's page in headless Chromium at common widths: overflow, overlapping text, images.

    python benchmarks/report_layout.py EVAL_DIR [EVAL_DIR ...] [--widths 1280 1920]

For each evaluation folder (``magail-sumo evaluate`` then ``magail-sumo report``), loads
``EVAL_DIR/report/report.html`` in headless Chromium at each width
(:func:`magail_sumo.evaluation.report.layout.check_layout`) and prints the page width, its
scroll width, the elements wider than the page, the overlapping text boxes and the images that
did not load, plus the scenes and methods the report covers. Exit status 1 when any is found.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magail_sumo.evaluation.report.layout import check_layout  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="evaluation folders with report/")
    ap.add_argument("--widths", nargs="+", type=int, default=[1280, 1920])
    args = ap.parse_args()
    bad = 0
    for d in args.dirs:
        manifest = json.loads((d / "manifest.json").read_text())
        scenes = manifest.get("scenes") or []
        methods = manifest.get("methods") or []
        print(f"{d}: {len(scenes)} scenes x {len(methods)} methods "
              f"({', '.join(map(str, methods))})")
        for w in args.widths:
            got = check_layout(d / "report" / "report.html", w)
            fails = got["wide"] or got["overlaps"] or got["broken"] or got["page"] > got["width"]
            bad += bool(fails)
            print(f"  {w} px: page {got['width']} px, scroll width {got['page']} px, "
                  f"too wide {len(got['wide'])}, overlapping text {len(got['overlaps'])}, "
                  f"images not loaded {len(got['broken'])}"
                  + (f": {got['wide'][:3]} {got['overlaps'][:3]} {got['broken'][:3]}"
                     if fails else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
