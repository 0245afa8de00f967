"""Training curves against agent-steps of SAC and PPO runs on the same scenes (sample efficiency).

Trains nothing. For each ``NAME=RUN_DIR`` it prints, per bin of ``--bin`` agent-steps, the mean
policy speed along the heading (m/s; the ``speed`` feature of s over the bin's agent-steps)
and, where the run has them, the discriminator's accuracy on policy samples and the SAC task
reward per agent-step:

* a SAC run (``algorithm: sac`` / ``sac_gail``): from the replay buffer of its last checkpoint
  (every live-agent transition in collection order, absorbing rows left out; the collision
  buffer's few rows are not in it) — exact per transition; the discriminator accuracy and
  the task reward per agent-step from its TensorBoard log (``RUN/tb``) where logged;
* a PPO run: from its TensorBoard log (``env/agent_steps_total``, ``diag/speed_policy``,
  ``discriminator/policy_accuracy``; one point per update).

    python benchmarks/sac_curve.py --run sac_gail=runs/sac_gail --run ppo=runs/magail --bin 5000
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def tb_scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    """TensorBoard scalars of ``run/tb`` (tag -> [(step, value)]); empty without the log."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, list[tuple[int, float]]] = {}
    for d in sorted({p.parent for p in (run / "tb").rglob("events.out.tfevents.*")}):
        acc = EventAccumulator(str(d), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags().get("scalars", []):
            out.setdefault(tag, []).extend((e.step, e.value) for e in acc.Scalars(tag))
    return out


def by_agent_steps(sc: dict, tag: str) -> tuple[np.ndarray, np.ndarray]:
    """(agent-steps, value) of ``tag``, matched to ``env/agent_steps_total`` by TB step."""
    steps = dict(sc.get("env/agent_steps_total") or sc.get("sac/agent_steps", []))
    pts = [(steps[s], v) for s, v in sc.get(tag, []) if s in steps]
    a = np.array(pts, np.float64).reshape(-1, 2)
    return a[:, 0], a[:, 1]


def binned(x: np.ndarray, v: np.ndarray, width: int, end: float) -> list[float]:
    """Mean of ``v`` per bin [k·width, (k+1)·width) of ``x`` (NaN where empty)."""
    out = []
    for k in range(int(np.ceil(end / width))):
        sel = (x >= k * width) & (x < (k + 1) * width)
        out.append(float(v[sel].mean()) if sel.any() else float("nan"))
    return out


def sac_rows(run: Path, width: int) -> dict[str, list[float]]:
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.trainer import checkpoint_config, load_checkpoint

    path = run / "checkpoints" / "latest.pt"
    state = load_checkpoint(path)
    cfg = checkpoint_config(state, path)
    buf = (state.get("buffers") or {}).get("main")
    if buf is None:
        raise SystemExit(f"{run}: checkpoint without replay buffers (sac.save_buffers: false)")
    names = observation_names(cfg.env.observation)
    obs = buf["obs"].numpy()
    if buf["size"] == len(obs) and buf["pos"] and len(obs) == cfg.sac.buffer_size:
        obs = np.roll(obs, -buf["pos"], axis=0)  # ring wrapped: oldest first
    live = obs[:, len(names)] == 0
    speed = obs[live, names.index("speed")]
    x = np.arange(speed.size, dtype=np.float64)
    sc = tb_scalars(run)
    rows = {"speed": binned(x, speed, width, speed.size)}
    for tag, label in (("discriminator/policy_accuracy", "D acc policy"),
                       ("sac/task_reward_per_agent_step", "task reward")):
        ax, av = by_agent_steps(sc, tag)
        if ax.size:
            rows[label] = binned(ax, av, width, speed.size)
    return rows


def ppo_rows(run: Path, width: int) -> dict[str, list[float]]:
    sc = tb_scalars(run)
    x, speed = by_agent_steps(sc, "diag/speed_policy")
    end = x.max() + 1 if x.size else 0
    rows = {"speed": binned(x, speed, width, end)}
    ax, av = by_agent_steps(sc, "discriminator/policy_accuracy")
    if ax.size:
        rows["D acc policy"] = binned(ax, av, width, end)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", required=True, metavar="NAME=RUN_DIR")
    ap.add_argument("--bin", type=int, default=5000, help="agent-steps per bin")
    args = ap.parse_args(argv)
    from magail_sumo.training.trainer import checkpoint_config, load_checkpoint

    for spec in args.run:
        name, _, d = spec.partition("=")
        run = Path(d)
        path = run / "checkpoints" / "latest.pt"
        state = load_checkpoint(path)
        cfg = checkpoint_config(state, path)
        rows = sac_rows(run, args.bin) if cfg.algorithm in ("sac", "sac_gail") \
            else ppo_rows(run, args.bin)
        steps = int(state.get("env_counters", [0])[0])
        print(f"{name} ({cfg.algorithm}, {steps} agent-steps, "
              f"{len(cfg.scenes.files)} scene file(s))")
        n = max(len(v) for v in rows.values())
        print("  agent-steps    " + "  ".join(f"{label:>12}" for label in rows))
        for k in range(n):
            vals = [rows[label][k] if k < len(rows[label]) else float("nan") for label in rows]
            print(f"  {k * args.bin:>6}-{(k + 1) * args.bin:<7}"
                  + "  ".join(f"{v:>12.3f}" for v in vals))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
