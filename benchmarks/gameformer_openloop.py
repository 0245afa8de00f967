"""Open-loop prediction quality of a GameFormer checkpoint per level k, on held-out scenes.

Trains nothing. Scores the checkpoint
(``magail-sumo train --config configs/experiments/womd14/gameformer.yaml``) on the test scenes
of a split (``configs/splits/womd14.yaml``; or ``--scenes FILE...``) with
:func:`magail_sumo.evaluation.openloop.evaluate_openloop`: minADE, minFDE, Waymo miss rate at
3 / 5 / 8 s and their mean, overlap rate of the most likely mode, for level 0..K and for the
constant-velocity prediction; then the scenes scored. A scene the checkpoint trained on is
refused (``--allow-trained-scenes`` scores it anyway, marked).

    python benchmarks/gameformer_openloop.py runs/gameformer/checkpoints/latest.pt [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magail_sumo.outputs import finite_json  # noqa: E402

DEFAULT_SPLIT = "configs/splits/womd14.yaml"
LABELS = (("min_ade", "minADE (m)"), ("min_fde", "minFDE (m)"), ("miss_rate_3s", "miss @3s"),
          ("miss_rate_5s", "miss @5s"), ("miss_rate_8s", "miss @8s"), ("miss_rate", "miss (mean)"),
          ("overlap_rate", "overlap"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path, help="a gameformer training checkpoint (.pt)")
    ap.add_argument("--split", default=DEFAULT_SPLIT,
                    help=f"split file (default {DEFAULT_SPLIT}); its test scenes are scored")
    ap.add_argument("--scenes", nargs="+", type=Path, metavar="FILE",
                    help="score these scene files instead of the split's test scenes")
    ap.add_argument("--max-windows", type=int, default=None,
                    help="at most this many current steps per scene (default: all)")
    ap.add_argument("--allow-trained-scenes", action="store_true",
                    help="score scenes the checkpoint trained on (marked) instead of refusing")
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    args = ap.parse_args(argv)

    import torch

    from magail_sumo.errors import MagailSumoError
    from magail_sumo.evaluation.openloop import evaluate_openloop
    from magail_sumo.splits import load_split, scene_stem
    from magail_sumo.training.gameformer.run import load_gameformer

    torch.set_num_threads(1)
    try:
        model, cfg = load_gameformer(args.checkpoint)
        if args.scenes:
            files = [p.resolve() for p in args.scenes]
        else:
            split_path = Path(args.split)
            if not split_path.is_absolute() and not split_path.is_file():
                split_path = ROOT / split_path
            files = load_split(split_path).files("test", ROOT)
    except MagailSumoError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    trained = {scene_stem(str(f)) for f in cfg.scenes.files}
    overlap = sorted(trained & {scene_stem(str(f)) for f in files})
    if overlap and not args.allow_trained_scenes:
        print(f"error: the checkpoint was trained on scene {overlap[0]}, which is scored here "
              "(--allow-trained-scenes scores it anyway)", file=sys.stderr)
        return 1
    t0 = time.perf_counter()
    res = evaluate_openloop(model, cfg, [str(f) for f in files], max_windows=args.max_windows)
    res.update(checkpoint=str(args.checkpoint), scene_files=[str(f) for f in files],
               trained_scenes=list(cfg.scenes.files), trained_on_scored=overlap,
               seconds=round(time.perf_counter() - t0, 1))
    if args.json:
        print(json.dumps(finite_json(res), indent=2))
        return 0
    cols = list(res["levels"]) + ["constvel"]
    table = {**res["levels"], "constvel": res["constvel"]}
    print(f"{res['samples']} focal agents in {len(res['scenes'])} scene(s), "
          f"{cfg.gameformer.model.modes} modes; constvel: one mode")
    print(f"{'metric':<14}" + "".join(f"{c:>10}" for c in cols))
    for key, label in LABELS:
        print(f"{label:<14}" + "".join(f"{table[c][key]:>10.3f}" for c in cols))
    print("scenes scored: " + ", ".join(res["scenes"]) + (
        f" (TRAINED ON: {', '.join(overlap)})" if overlap else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
