"""``env.end_of_life``: agents end at their log's last step in training; in evaluation every
sim agent drives all 80 steps, as WOSAC simulates it (an agent removed earlier vanished from
the others' world while its scored trajectory went on at constant velocity through them)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from magail_sumo.config import ConfigError

SID = "637f20cafde22ff8"
EARLY = "1603"  # a sim agent of SID whose recorded track ends at step 16


def _env(end_of_life: bool):
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    return scene, SumoDrivingEnv(scene, ROOT / "networks" / SID, EnvConfig(
        controlled="all", start_step=10, max_steps=80, terminate_on=(), sumo_mirror=False,
        end_of_life=end_of_life))


@pytest.mark.sumo
@pytest.mark.parametrize("end_of_life", [True, False])
def test_agents_end_with_their_log_only_when_asked(end_of_life):
    from magail_sumo.evaluation.submission import sim_agent_ids

    scene, env = _env(end_of_life)
    try:
        obs, _ = env.reset(seed=0)
        # the sim agents the env drives (the others are off the SUMO routes: log-replayed)
        sim = {str(int(i)) for i in sim_agent_ids(scene)} & set(env.agents)
        assert EARLY in sim and len(sim) >= 20
        ended, steps = {}, 0
        while env.agents:
            obs, _, terms, truncs, infos = env.step({n: np.zeros(2, np.float32) for n in obs})
            steps += 1
            for n in truncs:
                if truncs[n] or terms[n]:
                    ended[n] = (steps, infos[n]["reason"])
    finally:
        env.close()
    assert steps == 80
    if end_of_life:
        assert ended[EARLY] == (6, "end_of_life")  # log step 16 = 6 steps after step 10
    else:  # every sim agent drives to the episode's end
        assert all(ended[n][0] == 80 and ended[n][1] != "end_of_life" for n in sim)


@pytest.mark.sumo
def test_evaluation_keeps_every_sim_agent_to_the_horizon(scene_637f, env_configs):
    """Evaluation's env has end_of_life off: an agent whose log ends early has a driven
    (not constant-velocity) trajectory to the last step."""
    from magail_sumo.evaluation import methods

    ro = methods.simulate(scene_637f, "random", [0], seed=0, bundle_dir=ROOT / "networks" / SID)
    assert [c.end_of_life for c in env_configs] == [False]
    a = [int(i) for i in ro.object_id].index(int(EARLY))
    x, y = ro.x[0, a], ro.y[0, a]
    # random accelerations and steering: the path after the log's end (step 16: column 5 on)
    # is no straight line at constant speed
    jerk = np.hypot(np.diff(x[5:], 2), np.diff(y[5:], 2))
    assert np.isfinite(x).all() and (jerk > 1e-3).mean() > 0.5


def test_end_of_life_must_be_a_bool():
    from magail_sumo.config import from_dict
    from magail_sumo.env import EnvConfig

    with pytest.raises(ConfigError, match="end_of_life: expected true or false"):
        from_dict(EnvConfig, {"end_of_life": "no"})
