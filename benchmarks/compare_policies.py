"""Closed-loop comparison of driving policies: ADE, collision, off-road and red-light rates, speed
bias — the evaluation's traffic metrics (:mod:`magail_sumo.evaluation.traffic`).

Each policy runs through ``magail-sumo evaluate`` (:func:`magail_sumo.evaluation.runner.
evaluate`, its one rollout loop :func:`magail_sumo.agents.rollout`): from each scene's current
step for 80 steps, every route vehicle and cyclist driven by the policy through the env with no
terminating event, every other sim agent at constant velocity; deterministic actions (the tanh
of the Gaussian mean) unless ``--sampled``. Figures per scene are
:func:`~magail_sumo.evaluation.traffic.compute_metrics` of its rollouts (``ade`` m,
``collision_rate`` / ``offroad_rate`` / ``red_light_rate`` shares of objects / vehicles with an
event, ``speed_bias`` m/s: negative = slower than the humans); the table gives their mean over
scenes. Policies: ``constant_velocity`` (zero action: speed and heading held,
:class:`~magail_sumo.agents.ConstantVelocityPolicy`), ``untrained`` (a fresh policy of the
config, observation normaliser fitted on the expert data) and any ``NAME=CHECKPOINT`` (or
``NAME=SPEC``, any ``evaluate --policy`` spec). SUMO runs in worker processes (libsumo).

    python benchmarks/compare_policies.py --expert out/expert \\
        --config configs/experiments/womd3/magail.yaml \\
        --policy bc=runs/bc/checkpoints/latest.pt --policy magail=runs/m/checkpoints/latest.pt [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENES = [ROOT / "data" / "womd" / f"{s}.tfrecord"
          for s in ("637f20cafde22ff8", "2831b6fde0420b0d", "850c48d8bbfa008f")]
#: traffic metrics shown (magail_sumo.evaluation.traffic), with their table headers
METRICS = {"ade": "ADE m", "collision_rate": "collision", "offroad_rate": "off-road",
           "red_light_rate": "red light", "speed_bias": "bias m/s"}
CONSTANT_VELOCITY = "magail_sumo.agents.constant_velocity:ConstantVelocityPolicy"


def untrained_checkpoint(config: str, expert: str, seed: int, path: Path) -> Path:
    """A fresh policy of ``config`` (observation normaliser fitted on ``expert``) saved as a
    training checkpoint at ``path``."""
    import torch

    from magail_sumo.config import load_config, to_dict
    from magail_sumo.expert import ExpertDataset
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import CHECKPOINT_FORMAT, make_policy

    cfg = load_config(config, TrainConfig)
    torch.manual_seed(seed)
    policy = make_policy(cfg)
    data = ExpertDataset(expert, observation_names(cfg.env.observation))
    policy.obs_normalizer.update(torch.as_tensor(data.s))
    torch.save({"format": CHECKPOINT_FORMAT, "update": 0, "config": to_dict(cfg),
                "policy": policy.state_dict()}, path)
    return path


def scene_metrics(out: Path, name: str) -> list[dict]:
    """Traffic metrics of method ``name``'s rollouts of every scene evaluated into ``out``."""
    from converters import iter_scenes
    from magail_sumo.evaluation.storage import read_manifest, read_rollouts, rollouts_path
    from magail_sumo.evaluation.traffic import MetricInput, compute_metrics

    rows = []
    for entry in read_manifest(out)["scenes"]:
        path = rollouts_path(out, name, entry["scenario_id"])
        if not path.is_file():  # its rollouts failed (reported by evaluate)
            continue
        scene = next(s for s in iter_scenes(entry["file"])
                     if s.scenario_id == entry["scenario_id"])
        ro = read_rollouts(path, scene)
        rows.append({"policy": name, "scene": entry["scenario_id"],
                     **compute_metrics(MetricInput.build(scene, ro), list(METRICS))})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--expert", required=True, help="expert dir (fits the untrained normaliser)")
    ap.add_argument("--config",
                    default=str(ROOT / "configs" / "experiments" / "womd3" / "magail.yaml"))
    ap.add_argument("--policy", action="append", default=[], metavar="NAME=CHECKPOINT")
    ap.add_argument("--scenes", nargs="*", default=[str(s) for s in SCENES])
    ap.add_argument("--networks", default=str(ROOT / "out" / "networks"))
    ap.add_argument("--out", help="evaluation folder kept (default: a temporary one)")
    ap.add_argument("--rollouts", type=int, default=1, help="rollouts per scene and policy")
    ap.add_argument("--sampled", action="store_true", help="sample checkpoint actions")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    from magail_sumo.evaluation.runner import evaluate

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or Path(tmp) / "eval")
        policies = [("constant_velocity", CONSTANT_VELOCITY),
                    ("untrained", str(untrained_checkpoint(args.config, args.expert, args.seed,
                                                           Path(tmp) / "untrained.pt")))]
        policies += [(item.partition("=")[0], item.partition("=")[2]) for item in args.policy]
        rows: list[dict] = []
        for name, spec in policies:
            res = evaluate(args.scenes, spec, out, n_rollouts=args.rollouts, baselines=(),
                           seed=args.seed, workers=args.workers, networks=args.networks,
                           name=name, deterministic=not args.sampled)
            for err in res.errors:
                print(f"warning: {name}: {err}", file=sys.stderr)
            rows += scene_metrics(out, name)
    table = []
    for name, _ in policies:
        rs = [r for r in rows if r["policy"] == name]
        table.append({"policy": name, "scenes": len(rs),
                      **{m: float(np.nanmean([r[m] for r in rs])) if rs else float("nan")
                         for m in METRICS}})
    if args.json:
        from magail_sumo.outputs import finite_json  # NaN -> null

        print(json.dumps(finite_json({"per_scene": rows, "table": table}), indent=2))
    else:
        print(f"{'policy':<20}" + "".join(f"{h:>11}" for h in METRICS.values()) + f"{'scenes':>8}")
        for t in table:
            print(f"{t['policy']:<20}" + "".join(f"{t[m]:>11.3f}" for m in METRICS)
                  + f"{t['scenes']:>8}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
