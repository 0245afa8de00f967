"""Quality of policies and baselines on held-out real WOMD scenes (the generalisation protocol).

Trains nothing. Cuts 91-step evaluation windows (:func:`magail_sumo.scene.window`: history of
11 steps, 80 simulated, tracks to predict chosen by its rule where a scene has none) out of the
test scenes of a split (``configs/splits/womd14.yaml``; or ``--scenes FILE...``), writes them as
ScenarioNet pickles into ``OUT/scenes/``, converts them once (``magail-sumo convert --out
OUT/networks``), then per seed runs ``magail-sumo evaluate`` into ``OUT/seed<k>/`` — the
baselines once, then each ``--policy NAME=SPEC`` with ``--name NAME --baselines none`` into the
same folder — and ``magail-sumo report OUT/seed<k>``. From each report's ``summary.csv`` (means
over the scenes per method) and ``metrics.csv`` (per scene) it prints, per method, the WOSAC
meta-metric and its kinematic / interactive / map-based components
(:func:`magail_sumo.evaluation.realism.bucket_metrics` of each scene's row), minADE and the
simulated collision / off-road / red-light (traffic-light violation) rates of the scored agents
(WOSAC fields) and the speed bias (report's ``speed_bias``, all simulated objects): the mean
over seeds of the mean over scenes, with the min and max over seeds; then the scenes scored and the
split part each came from. A policy whose checkpoint config trains on a scored scene is refused
(``--allow-trained-scenes`` marks such scenes instead).

Uncertainty (:mod:`magail_sumo.evaluation.bootstrap`): ``--seed-group NAME=P1,P2,P3`` says the
policies P1..P3 (each a ``--policy``) are training seeds of one recipe NAME. Every group, every
other policy and every baseline gets the 95 % bootstrap interval of each figure over the scored
scenes and the group's training seeds (each scene's value is its mean over evaluation seeds), and
every pair of them the interval of their difference in meta-metric, paired on the scenes; "A
better than B" is printed only where that interval excludes 0. The off-road rates are also given
on the scenes whose road edges agree with their log (the report's rule; ``*_agreeing``).
``--json`` has them under ``intervals`` and ``comparisons``; ``--merge`` combines the ``--json``
outputs of runs made apart (one per training seed) without new rollouts.

    python benchmarks/quality.py --policy magail=runs/magail/checkpoints/latest.pt [--json]
    python benchmarks/quality.py --policy shipped=pretrained --seeds 0 --rollouts 8 --out q
    python benchmarks/quality.py --split configs/splits/wild.yaml --policy a0=A0.pt \
        --policy a1=A1.pt --policy a2=A2.pt --seed-group A=a0,a1,a2 --seeds 0 --rollouts 8
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magail_sumo.outputs import finite_json  # noqa: E402

DEFAULT_SPLIT = "configs/splits/womd14.yaml"
DEFAULT_BASELINES = ("logreplay", "constvel", "sumo")
#: (field, label): WOSAC bucket fields (realism.bucket_metrics) and the report's speed bias
FIELDS = [
    ("realism_meta_metric", "meta-metric"),
    ("kinematic_metrics", "kinematic"),
    ("interactive_metrics", "interactive"),
    ("map_based_metrics", "map-based"),
    ("min_ade", "minADE (m)"),
    ("simulated_collision_rate", "collision"),
    ("simulated_offroad_rate", "off-road"),
    ("simulated_traffic_light_violation_rate", "red light"),
    ("speed_bias", "speed bias (m/s)"),
]
#: report fields also given per scene in --json (traffic metrics over all simulated objects)
EXTRA = ("ade", "collision_rate", "offroad_rate", "red_light_rate", "mean_speed")
#: summary.csv column of a field, where the report has it as a mean over scenes
SUMMARY_COLUMN = {"realism_meta_metric": "metametric", "speed_bias": "speed_bias"}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def cli(args: list[str]) -> int:
    """``magail-sumo ARGS`` in a subprocess running this checkout (its stdout to our stderr)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    log("$ magail-sumo " + " ".join(shlex.quote(a) for a in args))
    try:
        out = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        out = subprocess.DEVNULL
    return subprocess.run([sys.executable, "-m", "magail_sumo", *args], env=env,
                          stdout=out).returncode


def parse_policies(items: list[str]) -> dict[str, str]:
    """``NAME=SPEC`` (or a bare SPEC, named as evaluate would) -> {name: spec}."""
    from magail_sumo.policies import BASELINES, BUILTIN_POLICIES, method_name
    from magail_sumo.outputs import is_safe_name

    out: dict[str, str] = {}
    for item in items:
        name, sep, spec = item.partition("=")
        if not sep:
            name, spec = method_name(item), item
        if not name or not spec:
            raise SystemExit(f"error: --policy {item!r}: expected NAME=SPEC")
        if not is_safe_name(name) or name in BASELINES + BUILTIN_POLICIES or name in out:
            raise SystemExit(f"error: --policy {item!r}: name {name!r} must be a file name "
                             "([A-Za-z0-9._-]), not a baseline's and not given twice")
        out[name] = spec
    return out


def training_scenes(spec: str) -> list[str] | None:
    """The scene files a checkpoint policy's training config names (None: not a checkpoint)."""
    from magail_sumo.policies import unguarded
    from magail_sumo.pretrained import is_pretrained_spec, resolve

    spec = unguarded(spec)  # the same policy behind the gap guard
    if is_pretrained_spec(spec):
        path = resolve(spec).checkpoint
    elif spec.endswith(".pt") and Path(spec).is_file():
        path = Path(spec)
    else:
        return None
    from magail_sumo.training.trainer import load_checkpoint

    scenes = load_checkpoint(path)["config"].get("scenes") or {}
    return [str(f) for f in scenes.get("files") or []]


def cut_windows(files: list[tuple[Path, str]], starts: list[int], out: Path
                ) -> tuple[list[dict], list[str]]:
    """Windows of every scene of ``files`` ((path, split part)) at ``starts``, written to
    ``out/<window id>.pkl``; (one record per window, skipped-window notes)."""
    from converters import iter_scenes
    from converters.scenarionet import write_scenarionet
    from magail_sumo.evaluation.realism.trajectories import evaluated_ids
    from magail_sumo.evaluation.submission import sim_agent_ids
    from magail_sumo.outputs import NameRegistry, atomic_path, inside
    from magail_sumo.scene import WindowError, window
    from magail_sumo.scene.window import WINDOW_STEPS

    out.mkdir(parents=True, exist_ok=True)
    names = NameRegistry()
    records, notes = [], []
    for path, part in files:
        for scene in iter_scenes(path):
            for start in starts:
                try:
                    w = window(scene, start)
                except WindowError as exc:
                    notes.append(str(exc))
                    continue
                dest = inside(out, f"{names.name(w.scenario_id)}.pkl")
                with atomic_path(dest) as tmp:
                    write_scenarionet(tmp, w, source_file=str(path))
                records.append({
                    "scenario_id": w.scenario_id, "source_scenario_id": scene.scenario_id,
                    "source_file": os.path.relpath(path, ROOT) if path.is_relative_to(ROOT)
                    else str(path),
                    "split": part, "window_start": start,
                    "source_steps": [start, start + WINDOW_STEPS - 1],
                    "scored_agents": int(len(evaluated_ids(w))),
                    "simulated_agents": int(len(sim_agent_ids(w))), "file": str(dest)})
    return records, notes


def read_report(folder: Path, methods: list[str]) -> tuple[dict, list[dict]]:
    """Per method the seed's means of :data:`FIELDS` (summary.csv where it has the field,
    else the mean over scenes of metrics.csv), and the per-scene rows."""
    from magail_sumo.evaluation.realism import METRIC_FIELDS, bucket_metrics

    with open(folder / "report" / "summary.csv", newline="") as fh:
        summary = {r["method"]: r for r in csv.DictReader(fh)}
    with open(folder / "report" / "metrics.csv", newline="") as fh:
        metrics = list(csv.DictReader(fh))
    means: dict[str, dict[str, float]] = {}
    scene_rows = []
    for m in methods:
        rows = [r for r in metrics if r["method"] == m]
        if m not in summary or not rows:
            continue
        per_scene = []
        for r in rows:
            b = bucket_metrics({k: float(r[k]) for k in METRIC_FIELDS})
            b["speed_bias"] = float(r["speed_bias"])
            per_scene.append(b)
            scene_rows.append({"method": m, "scenario_id": r["scenario_id"],
                               **{f: b[f] for f, _ in FIELDS},
                               **{f: float(r[f]) for f in EXTRA},
                               "road_edges_agree": road_edges_agree(r)})
        means[m] = {}
        for f, _ in FIELDS:
            if f in SUMMARY_COLUMN:
                means[m][f] = float(summary[m][SUMMARY_COLUMN[f]])
            else:
                vals = [b[f] for b in per_scene if math.isfinite(b[f])]
                means[m][f] = float(np.mean(vals)) if vals else float("nan")
    return means, scene_rows


def parse_groups(items: list[str], policies: dict[str, str]) -> dict[str, list[str]]:
    """``NAME=P1,P2,...`` -> {NAME: [P1, P2, ...]}: training seeds of one recipe (each a
    ``--policy`` name, in one group at most)."""
    groups: dict[str, list[str]] = {}
    taken: set[str] = set()
    for item in items:
        name, sep, members = item.partition("=")
        names = [m for m in members.split(",") if m]
        if not sep or not name or not names:
            raise SystemExit(f"error: --seed-group {item!r}: expected NAME=P1,P2,...")
        bad = [m for m in names if m not in policies or m in taken]
        if bad:
            raise SystemExit(f"error: --seed-group {item!r}: {bad[0]!r} is not a --policy name "
                             "or is in another group")
        if name in groups or name in policies:
            raise SystemExit(f"error: --seed-group {item!r}: name {name!r} is taken")
        groups[name] = names
        taken.update(names)
    return groups


def summarise(scene_rows: list[dict], methods: list[str], groups: dict[str, list[str]]
              ) -> dict:
    """The result entries computed from the per-scene rows: ``scored`` (each method's scene
    windows), ``seed_groups``, ``intervals`` (per subject — a seed group, or a method in none —
    the bootstrap interval of each :data:`FIELDS` figure, and of the off-road rates on the scenes
    whose road edges agree with their log) and ``comparisons`` (the paired meta-metric
    difference of every pair of subjects)."""
    from magail_sumo.evaluation.bootstrap import bootstrap_ci, paired_difference, verdict

    grouped = {m for ms in groups.values() for m in ms}
    subjects = {**groups, **{m: [m] for m in methods if m not in grouped}}
    scenes = sorted({r["scenario_id"] for r in scene_rows})
    col = {sid: k for k, sid in enumerate(scenes)}
    fields = [f for f, _ in FIELDS] + ["offroad_rate"]
    values: dict[tuple[str, str], dict[str, list[float]]] = {}  # (method, field) -> per scene
    for r in scene_rows:
        for f in fields:
            if math.isfinite(r[f]):
                values.setdefault((r["method"], f), {}).setdefault(r["scenario_id"], []).append(
                    r[f])
    mats = {}  # (subject, field) -> (members, scenes), each cell its mean over evaluation seeds
    for name, members in subjects.items():
        for f in fields:
            m = np.full((len(members), len(scenes)), np.nan)
            for i, member in enumerate(members):
                for sid, v in values.get((member, f), {}).items():
                    m[i, col[sid]] = float(np.mean(v))
            mats[(name, f)] = m
    # off-road on the scenes whose road edges agree with their log (the off-road goal's
    # scenes); a scene is taken to agree unless a row says otherwise
    disagree = {r["scenario_id"] for r in scene_rows if r.get("road_edges_agree") is False}
    agree_cols = [col[sid] for sid in scenes if sid not in disagree]
    intervals = {}
    for name in subjects:
        intervals[name] = {f: bootstrap_ci(mats[(name, f)]).as_dict() for f, _ in FIELDS}
        for f in ("simulated_offroad_rate", "offroad_rate"):
            iv = bootstrap_ci(mats[(name, f)][:, agree_cols]).as_dict()
            intervals[name][f + "_agreeing"] = {**iv, "scenes": len(agree_cols)}
    names = list(subjects)
    comparisons = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d = paired_difference(mats[(a, "realism_meta_metric")],
                                  mats[(b, "realism_meta_metric")])
            comparisons.append({"a": a, "b": b, "metric": "realism_meta_metric",
                                "difference": d.as_dict(), "verdict": verdict(d, a, b)})
    scored = {m: sorted({r["scenario_id"] for r in scene_rows if r["method"] == m})
              for m in methods}
    return {"scored": scored, "seed_groups": groups, "comparisons": comparisons,
            "intervals": {n: {"members": subjects[n], "figures": intervals[n]} for n in names}}


def road_edges_agree(row: dict) -> bool:
    """Whether a metrics.csv row's scene has road edges that agree with its log (the report's
    rule, :func:`magail_sumo.evaluation.traffic.events.road_edges_disagree_with_log`)."""
    from magail_sumo.evaluation.traffic.events import road_edges_disagree_with_log

    try:
        share, count = float(row.get("log_offroad_rate", "nan")), float(
            row.get("log_offroad_vehicles") or 0)
    except ValueError:
        return True
    return not road_edges_disagree_with_log(share, count)


def _fmt(v: float) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.4f}"


def show(result: dict, methods: list[str], as_json: bool) -> int:
    """Print ``result`` (the table, the intervals, the comparisons, the scenes; or JSON);
    1 when it holds errors."""
    rows, scenes, scored = result["rows"], result["scenes"], result["scored"]
    intervals, comparisons, errors = result["intervals"], result["comparisons"], result["errors"]
    if as_json:
        print(json.dumps(finite_json(result), indent=2))
        return 1 if errors else 0
    split_path = Path(result["split"])
    print(f"{len(scenes)} scene window(s) from the {result['scenes_from']} "
          f"({os.path.relpath(split_path, ROOT) if split_path.is_relative_to(ROOT) else split_path})"
          f", seeds {' '.join(map(str, result['seeds']))}, {result['rollouts']} rollouts; "
          f"mean over scenes [min, max over seeds]; evaluation in {result['out']}")
    cell = {(r["method"], r["metric"]): r for r in rows}
    text = {(m, f): _fmt(cell[(m, f)]["mean"]) + (
        f" [{_fmt(cell[(m, f)]['min'])}, {_fmt(cell[(m, f)]['max'])}]"
        if len(cell[(m, f)]["seeds"]) > 1 else "") for m in methods for f, _ in FIELDS}
    width = {m: max(len(m), *(len(text[(m, f)]) for f, _ in FIELDS)) + 2 for m in methods}
    print(f"{'metric':<18}" + "".join(f"{m:>{width[m]}}" for m in methods))
    for f, label in FIELDS:
        print(f"{label:<18}" + "".join(f"{text[(m, f)]:>{width[m]}}" for m in methods))
    print("95 % bootstrap intervals over the scored scenes (and a group's training seeds):")
    agreeing = next(iter(intervals.values()), {}).get("figures", {}).get(
        "simulated_offroad_rate_agreeing", {})
    shown = [("realism_meta_metric", "meta-metric"), ("simulated_collision_rate", "collision"),
             ("simulated_offroad_rate", "off-road"),
             ("simulated_offroad_rate_agreeing",
              f"off-road where road edges agree ({agreeing.get('scenes', 0)} scenes)"),
             ("speed_bias", "speed bias")]
    for name, rec in intervals.items():
        members = f" ({', '.join(rec['members'])})" if len(rec["members"]) > 1 else ""
        print(f"  {name}{members}: " + "; ".join(
            f"{label} {_fmt(rec['figures'][f]['mean'])} [{_fmt(rec['figures'][f]['lo'])}, "
            f"{_fmt(rec['figures'][f]['hi'])}]" for f, label in shown))
    for c in comparisons:
        d = c["difference"]
        print(f"  meta-metric {c['a']} - {c['b']}: {_fmt(d['mean'])} [{_fmt(d['lo'])}, "
              f"{_fmt(d['hi'])}]: {c['verdict']}")
    print("scenes scored:")
    for rec in scenes:
        mark = f"  TRAINED ON by {', '.join(rec['trained_on_by'])}" if rec["trained_on_by"] \
            else ""
        missing = [m for m in methods if rec["scenario_id"] not in scored[m]]
        print(f"  {rec['scenario_id']:<24} {rec['split']:<6} {rec['source_file']} steps "
              f"{rec['source_steps'][0]}-{rec['source_steps'][1]}, {rec['scored_agents']} "
              f"scored / {rec['simulated_agents']} simulated agents"
              + (f"; not scored for {', '.join(missing)}" if missing else "") + mark)
    for e in errors:
        print(f"error: {e}", file=sys.stderr)
    return 1 if errors else 0


def merge(files: list[Path], group_items: list[str]) -> tuple[dict, list[str]]:
    """(result, methods) of earlier ``--json`` outputs combined: their methods side by side on
    the same scene windows, with intervals and comparisons over all of them (``group_items``:
    ``--seed-group``). SystemExit naming the file when they cannot be combined."""
    from magail_sumo.inputs import read_json

    methods: dict[str, str] = {}
    rows, scene_rows, errors, scenes, first = [], [], [], None, None
    for f in files:
        try:
            got = read_json(f, expected="a quality.py --json output")
            ids = sorted(r["scenario_id"] for r in got["scenes"])
            part = {k: got[k] for k in ("seeds", "rollouts", "windows", "split")}
        except Exception as exc:  # noqa: BLE001 - any malformed file is named, one line
            raise SystemExit(f"error: --merge {f}: not a quality.py --json output "
                             f"({type(exc).__name__}: {str(exc)[:200]})") from None
        if first is None:
            first, base = f, part
            scenes = [{**r, "trained_on_by": []} for r in got["scenes"]]
        elif ids != sorted(r["scenario_id"] for r in scenes) or part != base:
            raise SystemExit(f"error: --merge {f}: other scene windows, seeds, rollouts or split "
                             f"than {first}")
        twice = [m for m in got["methods"] if m in methods]
        if twice:
            raise SystemExit(f"error: --merge {f}: method {twice[0]!r} is also in another file")
        methods.update(got["methods"])
        by_id = {r["scenario_id"]: r for r in got["scenes"]}
        for r in scenes:
            r["trained_on_by"] += by_id[r["scenario_id"]].get("trained_on_by", [])
        rows += got["rows"]
        scene_rows += got["scene_rows"]
        errors += [f"{f}: {e}" for e in got["errors"]]
    known = {r["scenario_id"]: r["road_edges_agree"] for r in scene_rows
             if "road_edges_agree" in r}  # a scene property: any run that recorded it
    for r in scene_rows:
        r.setdefault("road_edges_agree", known.get(r["scenario_id"], True))
    names = list(methods)
    result = {"out": ", ".join(map(str, files)), **base, "scenes_from": "merged runs",
              "methods": methods, "scenes": scenes, "rows": rows, "scene_rows": scene_rows,
              **summarise(scene_rows, names, parse_groups(group_items, methods)),
              "skipped_windows": [], "errors": errors}
    return result, names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", action="append", default=[], metavar="NAME=SPEC",
                    help="a policy to score (repeatable); SPEC: anything magail-sumo evaluate "
                         "--policy takes (checkpoint, pretrained[:NAME], random, module:factory, "
                         "guarded:SPEC)")
    ap.add_argument("--baselines", nargs="*", default=list(DEFAULT_BASELINES),
                    metavar="B", help="baselines (default: logreplay constvel sumo; none: "
                                      "give the flag alone)")
    ap.add_argument("--split", default=DEFAULT_SPLIT,
                    help=f"split file (default {DEFAULT_SPLIT}); its test scenes are scored")
    ap.add_argument("--scenes", nargs="+", type=Path, metavar="FILE",
                    help="score these scene files instead of the split's test scenes (each is "
                         "labelled with the split part it is in)")
    ap.add_argument("--windows", nargs="+", type=int, default=[0], metavar="START",
                    help="window start steps (default 0); a start a scene is too short for is "
                         "skipped")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--rollouts", type=int, default=32)
    ap.add_argument("--noise-scale", type=float, default=None, metavar="K",
                    help="evaluate --noise-scale for every policy (default: each policy's own)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timeout-s", default="1800", help="evaluate / convert --timeout-s")
    ap.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    ap.add_argument("--seed-group", action="append", default=[], metavar="NAME=P1,P2",
                    help="policies (--policy names) that are training seeds of one recipe: "
                         "figures and intervals over them together (repeatable)")
    ap.add_argument("--allow-trained-scenes", action="store_true",
                    help="score scenes a policy was trained on (marked), instead of refusing")
    ap.add_argument("--reuse", action="store_true",
                    help="no rollouts: read the reports already in --out (of a run with the "
                         "same arguments) again")
    ap.add_argument("--json", action="store_true", help="print rows as JSON")
    ap.add_argument("--merge", nargs="+", type=Path, metavar="JSON",
                    help="no rollouts: combine the --json outputs of earlier runs on the same "
                         "scene windows (e.g. one per training seed) into one table with "
                         "intervals and comparisons (with --seed-group)")
    args = ap.parse_args(argv)
    if args.merge:
        result, names = merge(args.merge, args.seed_group)
        return show(result, names, args.json)

    from magail_sumo.errors import MagailSumoError
    from magail_sumo.policies import BASELINES
    from magail_sumo.splits import load_split, scene_stem
    from magail_sumo.outputs import claim_output_dir

    baselines = [b for item in args.baselines for b in item.split(",") if b and b != "none"]
    bad = [b for b in baselines if b not in BASELINES]
    if bad:
        ap.error(f"--baselines: unknown {bad[0]} (known: {', '.join(BASELINES)})")
    policies = parse_policies(args.policy)
    groups = parse_groups(args.seed_group, policies)
    if not policies and not baselines:
        ap.error("nothing to score: give --policy NAME=SPEC and/or --baselines")
    if args.rollouts < 1 or args.workers < 1 or any(w < 0 for w in args.windows):
        ap.error("--rollouts and --workers must be >= 1, --windows >= 0")
    split_path = Path(args.split)
    if not split_path.is_absolute() and not split_path.is_file():
        split_path = ROOT / split_path
    try:
        split = load_split(split_path)
        test_stems = {scene_stem(f) for f in split.test}
        train_stems = {scene_stem(f) for f in split.train}
        if args.scenes:
            files = [(p.resolve(), "test" if scene_stem(str(p)) in test_stems else
                      "train" if scene_stem(str(p)) in train_stems else "outside the split")
                     for p in args.scenes]
        else:
            files = [(p.resolve(), "test") for p in split.files("test", ROOT)]
        trained = {n: training_scenes(s) for n, s in policies.items()}
    except MagailSumoError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    for path, part in files:
        if not path.is_file():
            print(f"error: {path}: no such scene file", file=sys.stderr)
            return 1
        if part == "train":
            log(f"warning: {path.name} is a training scene of {split_path.name}: not held out")
    overlap = {n: sorted({scene_stem(f) for f in fs} & {scene_stem(str(p)) for p, _ in files})
               for n, fs in trained.items() if fs}
    overlap = {n: v for n, v in overlap.items() if v}
    if overlap and not args.allow_trained_scenes:
        n, v = next(iter(overlap.items()))
        print(f"error: policy {n} was trained on scene {v[0]}, which is scored here "
              "(--allow-trained-scenes marks such scenes instead)", file=sys.stderr)
        return 1

    if args.reuse and args.out is None:
        ap.error("--reuse needs --out DIR")
    out = (args.out or Path(tempfile.mkdtemp(prefix="quality_"))).resolve()
    seed_dirs = [f"seed{s}" for s in args.seeds]
    try:
        claim_output_dir(out, "quality", ["scenes", "networks", *seed_dirs])
        scenes, notes = cut_windows(files, args.windows, out / "scenes")
    except MagailSumoError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    for n in notes:
        log(f"note: window skipped: {n}")
    for rec in scenes:
        rec["trained_on_by"] = [n for n, v in overlap.items()
                                if scene_stem(rec["source_file"]) in v]
    if not scenes:
        print("error: no window fits any scene", file=sys.stderr)
        return 1
    errors: list[str] = []
    scene_files = [rec["file"] for rec in scenes]
    common = ["--scenes", *scene_files, "--rollouts", str(args.rollouts),
              "--workers", str(args.workers), "--timeout-s", str(args.timeout_s)]
    methods = baselines + list(policies)
    if (any(m not in ("logreplay", "constvel") for m in baselines) or policies) \
            and not args.reuse:
        if cli(["convert", *scene_files, "--out", str(out / "networks"), "--no-baseline",
                "--workers", str(args.workers), "--timeout-s", str(args.timeout_s)]):
            errors.append("convert: some scenes failed (see above)")
        common += ["--networks", str(out / "networks")]
    per_seed: dict[int, dict] = {}
    scene_rows: list[dict] = []
    for seed, sd in zip(args.seeds, seed_dirs):
        folder = out / sd
        runs = []
        if baselines:
            runs.append(["--policy", baselines[0], "--baselines", ",".join(baselines[1:]) or
                         "none"])
        scale = [] if args.noise_scale is None else ["--noise-scale", str(args.noise_scale)]
        runs += [["--policy", spec, "--name", name, "--baselines", "none", *scale]
                 for name, spec in policies.items()]
        for run in [] if args.reuse else runs:
            if cli(["evaluate", *run, *common, "--seed", str(seed), "--out", str(folder)]):
                errors.append(f"seed {seed}: evaluate {' '.join(run[:2])}: problems (see above)")
        if not args.reuse and cli(["report", str(folder), "--workers", str(args.workers)]):
            errors.append(f"seed {seed}: report: problems (see above)")
        try:
            means, rows = read_report(folder, methods)
        except (OSError, KeyError, ValueError) as exc:
            errors.append(f"seed {seed}: cannot read the report ({type(exc).__name__}: {exc})")
            continue
        per_seed[seed] = means
        scene_rows += [{"seed": seed, **r} for r in rows]
    rows = []
    for m in methods:
        for f, label in FIELDS:
            vals = [per_seed[s][m][f] for s in per_seed if m in per_seed[s]]
            fin = [v for v in vals if math.isfinite(v)]
            rows.append({"method": m, "metric": f, "label": label,
                         "mean": float(np.mean(fin)) if fin else float("nan"),
                         "min": min(fin) if fin else float("nan"),
                         "max": max(fin) if fin else float("nan"),
                         "per_seed": vals, "seeds": [s for s in per_seed if m in per_seed[s]]})
    result = {"out": str(out), "split": str(split_path), "scenes_from": "--scenes" if
              args.scenes else "test split", "seeds": args.seeds, "rollouts": args.rollouts,
              "windows": args.windows, "methods": {**{b: b for b in baselines}, **policies},
              "scenes": scenes, "rows": rows, "scene_rows": scene_rows,
              **summarise(scene_rows, methods, groups), "skipped_windows": notes,
              "errors": errors}
    return show(result, methods, args.json)


if __name__ == "__main__":
    sys.exit(main())
