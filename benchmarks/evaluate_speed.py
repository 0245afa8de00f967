"""Wall time of ``magail-sumo evaluate`` on scenes x methods x rollouts: this checkout against an
earlier commit, runs alternated (median over repeats).

    python benchmarks/evaluate_speed.py SCENE... --against COMMIT [--rollouts 32]
        [--policy pretrained] [--baselines logreplay,constvel,sumo] [--workers 2] [--repeats 3]
        [--batch N] [--report]

The earlier commit is checked out with ``git worktree add`` into a temporary folder (removed at
the end) and run with ``PYTHONPATH`` and the working folder set to it. Both versions first run
once with one rollout, untimed: the scenes' SUMO bundles are converted there (the timed runs
reuse them through ``--networks``) and both checkouts' numba caches are filled. Then each repeat
runs both versions, alternating which goes first (AB, BA, AB, ...), each into a fresh folder;
it prints every run's wall time, the medians, the speed-up, and whether the two versions wrote
the same rollouts (the SHA-256 of every ``rollouts/**/*.parquet``).

``--batch N`` times one worker batch instead: ``simulate`` of N rollouts of ``--policy`` on the
first scene, in one process per version and repeat (after an untimed one-rollout warm-up: the
imports, the policy's first load and numba's kernels), which is what evaluation's per-batch
preparation changes, without the process starts, the baselines and the files around it.

``--report`` also times ``magail-sumo report`` of every timed run's folder (same checkout) and
prints evaluate, report and their sum per run; the medians and the speed-up are then of the
sum (the issue's "evaluate + report").
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _evaluate(tree: Path, scenes: list[str], out: Path, args: argparse.Namespace,
              rollouts: int, networks: Path) -> float:
    """Seconds of one ``magail-sumo evaluate`` run of checkout ``tree`` (raises on failure)."""
    cmd = [sys.executable, "-m", "magail_sumo", "evaluate", "--policy", args.policy,
           "--scenes", *scenes, "--baselines", args.baselines, "--rollouts", str(rollouts),
           "--workers", str(args.workers), "--networks", str(networks), "--out", str(out)]
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"{tree}: evaluate failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return wall


#: ``--batch``: one process timing ``simulate`` of N rollouts (argv: scene, bundles, policy, N)
BATCH = """
import sys, time
from pathlib import Path
from converters.scene_files import iter_scenes
try:
    from magail_sumo.evaluation.methods import simulate
except ImportError:  # before the split
    from magail_sumo.evaluation.rollouts import simulate
scene = next(iter(iter_scenes(sys.argv[1])))
bundle = Path(sys.argv[2]) / scene.scenario_id
simulate(scene, sys.argv[3], [0], bundle_dir=bundle)
t0 = time.perf_counter()
simulate(scene, sys.argv[3], range(int(sys.argv[4])), bundle_dir=bundle)
print(time.perf_counter() - t0)
"""


def _batch(tree: Path, scene: str, networks: Path, policy: str, n: int) -> float:
    """Seconds of ``simulate`` of ``n`` rollouts in a process of checkout ``tree``."""
    res = subprocess.run([sys.executable, "-c", BATCH, scene, str(networks), policy, str(n)],
                         cwd=tree, env=dict(os.environ, PYTHONPATH=str(tree)),
                         capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{tree}: batch failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return float(res.stdout.split()[-1])


def _report(tree: Path, out: Path) -> float:
    """Seconds of one ``magail-sumo report`` run of checkout ``tree`` on ``out``."""
    cmd = [sys.executable, "-m", "magail_sumo", "report", str(out)]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=tree, env=dict(os.environ, PYTHONPATH=str(tree)),
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"{tree}: report failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return wall


def _digest(out: Path) -> str:
    """One SHA-256 over every rollouts Parquet file of ``out`` (path and bytes)."""
    h = hashlib.sha256()
    for f in sorted((out / "rollouts").rglob("*.parquet")):
        h.update(str(f.relative_to(out)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="scene files")
    ap.add_argument("--against", required=True, metavar="COMMIT",
                    help="the earlier commit to compare with")
    ap.add_argument("--rollouts", type=int, default=32)
    ap.add_argument("--policy", default="pretrained")
    ap.add_argument("--baselines", default="logreplay,constvel,sumo")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch", type=int, default=0, metavar="N",
                    help="time one worker batch of N rollouts of --policy on the first scene "
                         "in-process instead of whole evaluate runs")
    ap.add_argument("--report", action="store_true",
                    help="also time magail-sumo report of each run (medians of the sum)")
    args = ap.parse_args()
    scenes = [str(Path(s).resolve()) for s in args.scenes]
    with tempfile.TemporaryDirectory(prefix="evaluate_speed_") as tmp_s:
        tmp = Path(tmp_s)
        old = tmp / "against"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old),
                        args.against], check=True, capture_output=True)
        try:
            trees = {f"{args.against}": old, "this checkout": ROOT}
            nets = tmp / "warm-networks"
            (tmp / "empty").mkdir()
            _evaluate(ROOT, scenes, nets, args, 1, tmp / "empty")  # converts the bundles
            nets = nets / "networks"
            for k, (name, tree) in enumerate(trees.items()):
                wall = _evaluate(tree, scenes, tmp / f"warm-{k}", args, 1, nets)
                print(f"{name}: warm-up (1 rollout) {wall:.1f} s", flush=True)
            walls: dict[str, list[float]] = {n: [] for n in trees}
            digests: dict[str, set[str]] = {n: set() for n in trees}
            order = list(trees)
            for rep in range(args.repeats):
                for k, name in enumerate(order if rep % 2 == 0 else order[::-1]):
                    if args.batch:
                        walls[name].append(_batch(trees[name], scenes[0], nets, args.policy,
                                                  args.batch))
                        print(f"repeat {rep + 1}: {name}: batch {walls[name][-1]:.2f} s",
                              flush=True)
                        continue
                    out = tmp / f"run-{rep}-{k}"
                    ev = _evaluate(trees[name], scenes, out, args, args.rollouts, nets)
                    digests[name].add(_digest(out))
                    if not args.report:
                        walls[name].append(ev)
                        print(f"repeat {rep + 1}: {name}: {ev:.1f} s", flush=True)
                        continue
                    rp = _report(trees[name], out)
                    walls[name].append(ev + rp)
                    print(f"repeat {rep + 1}: {name}: evaluate {ev:.1f} s + report {rp:.1f} s "
                          f"= {ev + rp:.1f} s", flush=True)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)],
                           capture_output=True)
    med = {n: statistics.median(w) for n, w in walls.items()}
    base, new = med[order[0]], med[order[1]]
    if args.batch:
        print(f"one batch of {args.batch} {args.policy} rollouts of {Path(scenes[0]).name}, "
              f"{args.repeats} repeats: {order[0]} median {base:.2f} s, this checkout median "
              f"{new:.2f} s ({base / new:.2f}x, {100 * (1 - new / base):.0f}% less)")
        return 0
    n_methods = 1 + len([b for b in args.baselines.split(",") if b.strip() and b != "none"])
    print(f"{len(scenes)} scene(s) x {n_methods} method(s) x {args.rollouts} rollouts, "
          f"{args.workers} workers, {args.repeats} repeats"
          f"{' (evaluate + report)' if args.report else ''}: {order[0]} median {base:.1f} s, "
          f"this checkout median {new:.1f} s ({base / new:.2f}x, {100 * (1 - new / base):.0f}% "
          "less wall time)")
    same = len(digests[order[0]] | digests[order[1]]) == 1
    print("rollouts identical across versions and repeats: " + ("yes" if same else "NO"))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
