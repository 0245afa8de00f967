"""Where a policy's agents stand in a city: agent-seconds below 0.5 m/s per SUMO lane.

Drives ``--policy`` on one city scenario for ``--steps`` 0.1-s steps after ``--warmup-s`` (as
``benchmarks/city_driving.py`` and ``evaluate --city`` do, mean actions with
``--deterministic``), samples every second which lane each standing agent and each standing
SUMO-driven vehicle is on, and prints the lanes with the most standing time: the queues that
cost a policy its trips. Used for docs/results/city.md ("The drivers' own desired speeds")::

    python benchmarks/city_standing.py --deterministic --policy runs/speed_seed0/checkpoints/latest.pt \\
        --city data/sumo/cologne8/cologne8.sumocfg
"""

from __future__ import annotations

import argparse
import collections

from magail_sumo.agents import env_settings
from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
from magail_sumo.evaluation.city import city_config
from magail_sumo.env.config import EnvConfig
from magail_sumo.policies import make_policy

#: below this speed (m/s) a vehicle stands
STANDING = 0.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True)
    ap.add_argument("--city", required=True, help="a city scenario (.sumocfg or its folder)")
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--warmup-s", type=float, default=600.0)
    ap.add_argument("--max-agents", type=int, default=200)
    ap.add_argument("--demand-scale", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--deterministic", action="store_true")
    ap.add_argument("--top", type=int, default=12)
    args = ap.parse_args()
    policy = make_policy(args.policy, args.seed, args.deterministic)
    cfg = CityEnvConfig.from_env(EnvConfig(**env_settings(policy)), max_agents=args.max_agents,
                                 control_fraction=1.0, warmup_s=args.warmup_s,
                                 max_steps=args.steps, demand_scale=args.demand_scale)
    env = SumoCityEnv(city_config(args.city), cfg)
    agents, others = collections.Counter(), collections.Counter()
    every = max(1, round(1.0 / env.dt))
    try:
        obs, _ = env.reset(seed=args.seed)
        api = env._session.api
        for t in range(args.steps):
            obs, *_ = env.step(policy.act(obs))
            if t % every:
                continue
            f = env.fleet
            live = f.live()
            # a diagnostic sampled once a second, not the env's hot path: one query per vehicle
            for k in live[f.speed[live] < STANDING]:
                agents[api.vehicle.getLaneID(f.names[k])] += 1
            for v in api.vehicle.getIDList():
                if v not in f.index and api.vehicle.getSpeed(v) < STANDING:
                    others[api.vehicle.getLaneID(v)] += 1
    finally:
        env.close()
    print(f"{env.scenario_id}: agent-seconds standing {sum(agents.values())}, "
          f"SUMO-driven vehicle-seconds standing {sum(others.values())}")
    for name, counter in (("agents", agents), ("SUMO-driven", others)):
        print(f"{name}: lane, seconds standing")
        for lane, n in counter.most_common(args.top):
            print(f"  {lane:48s} {n:7d}")


if __name__ == "__main__":
    main()
