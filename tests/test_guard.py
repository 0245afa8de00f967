"""Gap guard (``env.guard``): the safe-speed cap on the agents' accelerations, in the env on a
real scene, and carried by a checkpoint into evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR, tiny_checkpoint
from magail_sumo.env.guard import GuardConfig, guarded, safe_speed
from magail_sumo.sim.dynamics import BicycleLimits, denormalise

SID = "637f20cafde22ff8"
GAP = GuardConfig(kind="gap", decel=4.5, tau=0.5, min_gap=1.0)


@pytest.mark.parametrize("vl", [0.0, 5.0, 12.0])
def test_safe_speed_stops_behind_a_braking_leader(vl):
    """At the safe speed the agent's reaction plus braking distance equals the gap less the
    standstill gap plus the leader's braking distance; more gap allows more speed."""
    gap = np.array([0.5, 1.0, 4.0, 20.0, 60.0])
    v = safe_speed(gap, np.full(gap.shape, vl), GAP)
    b, tau = GAP.decel, GAP.tau
    lhs = v * tau + v * v / (2 * b)
    rhs = np.maximum(gap - GAP.min_gap, 0.0) + vl * vl / (2 * b)
    assert np.allclose(lhs, rhs)
    assert (np.diff(v) >= 0).all() and (v >= 0).all()
    # an oncoming leader (negative speed along the heading) counts as a still one
    assert np.allclose(safe_speed(gap, np.full(gap.shape, -vl), GAP),
                       safe_speed(gap, np.zeros(gap.shape), GAP))


@pytest.mark.parametrize("layout", ["accel_steer", "steer_throttle"])
def test_guard_lowers_only_the_accelerations_that_are_too_high(layout):
    lim = BicycleLimits()
    act = np.array([[1.0, 0.3], [1.0, -0.2], [-0.5, 0.1], [0.2, 0.0]])
    if layout == "steer_throttle":
        act = act[:, ::-1].copy()
    speed = np.array([15.0, 15.0, 15.0, 15.0])
    gap = np.array([5.0, 5.0, 5.0, 80.0])
    lead = np.array([0.0, 0.0, 0.0, 0.0])
    found = np.array([True, False, True, True])
    out, low = guarded(act, speed, gap, lead, found, GAP, lim, layout, 0.1)
    # row 0: 15 m/s, 4 m from a still leader: must brake (to the limit); row 1: no leader;
    # row 2: already braking hard enough? no: 15 m/s needs the full brake, -0.5 is lowered;
    # row 3: the leader is far: full throttle allowed
    assert low.tolist() == [True, False, True, False]
    a_in, s_in = denormalise(act, lim, layout)
    a_out, s_out = denormalise(out, lim, layout)
    assert np.allclose(s_out, s_in)  # the steering is never touched
    assert a_out[0] == pytest.approx(-lim.max_brake) and a_out[2] == pytest.approx(-lim.max_brake)
    assert np.array_equal(out[[1, 3]], act[[1, 3]])  # untouched rows bit for bit
    # a cap between the limits: the speed after the step is the safe speed
    gap2, v2 = np.array([30.0]), np.array([15.0])
    out2, low2 = guarded(act[:1], v2, gap2, np.zeros(1), np.ones(1, bool), GAP, lim, layout, 0.1)
    a2, _ = denormalise(out2, lim, layout)
    assert low2[0] and v2[0] + 0.1 * a2[0] == pytest.approx(safe_speed(gap2, np.zeros(1), GAP)[0])


def test_guard_config_refusals():
    from magail_sumo.config import ConfigError, from_dict
    from magail_sumo.env import EnvConfig

    with pytest.raises(ValueError, match=r"^kind: must be one of"):
        GuardConfig(kind="krauss")
    with pytest.raises(ValueError, match=r"^tau: must be >= 0"):
        GuardConfig(kind="gap", tau=-1.0)
    with pytest.raises(ValueError, match=r"^range: must be a finite number"):
        GuardConfig(kind="gap", range=float("inf"))
    # a config file's error names the dotted key once
    with pytest.raises(ConfigError, match=r"^guard\.decel: must be > 0"):
        from_dict(EnvConfig, {"guard": {"kind": "gap", "decel": 0}})
    cfg = from_dict(EnvConfig, {"guard": {"kind": "gap", "tau": 0.8}})
    assert cfg.guard.on and cfg.guard.tau == 0.8 and not EnvConfig().guard.on


def _lone_speeder_collisions(envs, names, steps=50):
    """For each agent name: it floors the throttle along its recorded path (the expert's
    steering) while every other agent replays the log; per env, how many of them collide."""
    from magail_sumo.env import expert_actions

    hits = {k: 0 for k in envs}
    for name in names:
        for k, env in envs.items():
            env.reset(seed=0)
            for _ in range(steps):
                if name not in env.agents:
                    break
                act = expert_actions(env)
                act[name][0] = 1.0
                infos = env.step(act)[4]
                if infos[name]["events"].get("collision"):
                    hits[k] += 1
                    break
    return hits


@pytest.mark.sumo
def test_guard_prevents_collisions_of_a_speeding_agent_on_a_real_scene():
    """One agent at a time floors the throttle along its recorded path on a real scene (the
    others replay the log): without the guard most run into someone; behind it far fewer do
    (the rest are hit from behind or beside, which a limit on one's own acceleration cannot
    prevent), and the guard reports the accelerations it lowered."""
    from converters import load_scene
    from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    envs = {kind: SumoDrivingEnv(scene, ROOT / "networks" / SID, EnvConfig(
        controlled="all", start_step=10, max_steps=50, terminate_on=(), sumo_mirror=False,
        limits=REPLAY_LIMITS, guard=GuardConfig(kind=kind))) for kind in ("none", "gap")}
    try:
        envs["none"].reset(seed=0)
        names = list(envs["none"].agents)
        hits = _lone_speeder_collisions(envs, names)
        assert envs["none"].guarded == 0 and envs["gap"].guarded > 0
    finally:
        for env in envs.values():
            env.close()
    assert len(names) >= 20
    assert hits["none"] >= len(names) // 2 and hits["gap"] <= 0.7 * hits["none"], hits


def _guard_checkpoint(tmp_path):
    return tiny_checkpoint(tmp_path / "guard.pt", {"guard": {"kind": "gap", "tau": 0.7}})


@pytest.mark.sumo
def test_checkpoint_brings_its_guard_to_evaluation(tmp_path, env_configs):
    """A policy trained behind the guard carries it, and evaluation's env drives it so."""
    from converters import load_scene
    from magail_sumo import policies
    from magail_sumo.evaluation import methods

    ckpt = _guard_checkpoint(tmp_path)
    policy = policies.make_policy(str(ckpt), 0)
    assert policy.guard == GuardConfig(kind="gap", tau=0.7)
    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    ro = methods.simulate(scene, str(ckpt), [0], seed=0, bundle_dir=ROOT / "networks" / SID)
    assert np.isfinite(ro.x).any()
    assert [c.guard for c in env_configs] == [GuardConfig(kind="gap", tau=0.7)]
    # any policy behind the guard's defaults in evaluation: the guarded: prefix
    assert policies.method_name("guarded:random") == "random-guarded"
    methods.simulate(scene, "guarded:random", [0], seed=0, bundle_dir=ROOT / "networks" / SID)
    methods.simulate(scene, "random", [0], seed=0, bundle_dir=ROOT / "networks" / SID)
    assert [c.guard for c in env_configs[1:]] == [GuardConfig(kind="gap"), GuardConfig()]


def test_quality_knows_what_a_guarded_policy_trained_on():
    """benchmarks/quality.py refuses to score a policy on its own training scenes, guarded or
    not (the guard does not change what the policy learned from)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("quality_bench",
                                                  ROOT / "benchmarks" / "quality.py")
    quality = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(quality)
    assert quality.training_scenes("guarded:pretrained") == quality.training_scenes("pretrained")
    assert quality.training_scenes("guarded:pretrained")
    assert quality.training_scenes("guarded:random") is None


@pytest.mark.sumo
def test_training_logs_what_the_guard_did(tmp_path):
    """A run behind the guard reports, each update, the share of agent-steps the guard slowed
    and the shares of agent episodes ended by collision / off-road; the vector env's totals
    agree with the events the workers reported."""
    from magail_sumo.config import from_dict
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import record_expert
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import train

    scene = str(WOMD_DIR / f"{SID}.tfrecord")
    nets = ROOT / "networks"
    record_expert(scene_specs([scene], nets), tmp_path / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 0, "expert_dir": str(tmp_path / "expert"), "out_dir": str(tmp_path / "runs"),
        "updates": 2, "bc": {"epochs": 0},
        "env": {"max_steps": 40, "sumo_mirror": False, "guard": {"kind": "gap"}},
        "scenes": {"files": [scene], "networks": str(nets)},
        "policy": {"actor_hidden": [16], "critic_hidden": [16]},
        "ppo": {"n_steps": 64, "batch_size": 64, "n_epochs": 1},
        "discriminator": {"epochs": 1, "batch_size": 64}})
    lines: list[str] = []
    train(cfg, run_dir=tmp_path / "run", log=lines.append)
    updates = [s for s in lines if s.startswith("update ")]
    assert len(updates) == 2
    assert all("guard slowed" in s and "collision" in s for s in updates), updates
    shares = [float(s.split("guard slowed ")[1].split("%")[0]) for s in updates]
    assert all(0.0 < x < 100.0 for x in shares), updates
