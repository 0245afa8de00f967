"""Kinematic bicycle model: forward/inverse consistency and log-replay fidelity on real scenes."""

from __future__ import annotations

import numpy as np
import pytest

from magail_sumo.scene import ObjectType
from magail_sumo.sim.dynamics import (
    WHEELBASE_RATIO, BicycleLimits, VehicleState, clip_action, denormalise, inverse, normalise, step,
    wrap_angle,
)

LIM = BicycleLimits()


def test_inverse_then_step_lands_on_target():
    rng = np.random.default_rng(0)
    n = 200
    st = VehicleState(rng.uniform(-50, 50, n), rng.uniform(-50, 50, n), rng.uniform(-np.pi, np.pi, n),
                      rng.uniform(0, 20, n))
    wb = rng.uniform(2.5, 3.5, n)
    accel = rng.uniform(-3, 3, n)
    steer = rng.uniform(-0.3, 0.3, n)
    target = step(st, accel, steer, wb, 0.1, LIM)
    a, d = inverse(st, target.x, target.y, wb, 0.1)
    np.testing.assert_allclose(a, accel, atol=1e-6)
    np.testing.assert_allclose(d, steer, atol=1e-6)
    again = step(st, a, d, wb, 0.1, LIM)
    np.testing.assert_allclose(np.c_[again.x, again.y], np.c_[target.x, target.y], atol=1e-9)


def test_actions_clipped_nan_counted_and_normalised_round_trip():
    a, d, clipped = clip_action(np.array([np.nan, 100.0, 1.0]), np.array([0.1, 0.0, -5.0]), LIM)
    assert a.tolist() == [0.0, LIM.max_accel, 1.0] and d[2] == -LIM.max_steer
    assert clipped.tolist() == [True, True, True]
    norm = np.array([[0.5, -0.25], [-1.0, 1.0]])
    np.testing.assert_allclose(normalise(*denormalise(norm, LIM), LIM), norm)


def test_reverse_target():
    st = VehicleState(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    a, d = inverse(st, np.array([-0.05]), np.array([0.0]), np.array([3.0]), 0.1)
    assert a[0] < 0 and abs(d[0]) < 1e-9
    nxt = step(st, a, d, np.array([3.0]), 0.1, LIM)
    assert nxt.x[0] == pytest.approx(-0.05)


def test_log_replay_fidelity_on_real_scenes(real_scene):
    """Every vehicle/cyclist driven by closed-loop inverse dynamics stays within 0.2 m of its log.

    Replayed without limits: recorded positions carry sensor noise (a parked car jitters
    sideways by centimetres) that a limited bicycle model cannot follow exactly.
    """
    tr = real_scene.tracks
    dt = 0.1
    worst = 0.0
    yaw_err = []
    for i in np.flatnonzero(np.isin(tr.type, [ObjectType.VEHICLE, ObjectType.CYCLIST])):
        steps = np.flatnonzero(tr.valid[i])
        # drive each contiguous valid run from its first state
        runs = np.split(steps, np.flatnonzero(np.diff(steps) > 1) + 1)
        for run in runs:
            if len(run) < 2:
                continue
            t0 = run[0]
            st = VehicleState(tr.x[i, t0:t0 + 1].copy(), tr.y[i, t0:t0 + 1].copy(),
                              tr.heading[i, t0:t0 + 1].astype(float),
                              np.array([np.hypot(tr.vx[i, t0], tr.vy[i, t0])], float))
            wb = np.array([max(float(tr.length[i, t0]), 1.0) * WHEELBASE_RATIO])
            for t in run[1:]:
                yaw_t = tr.heading[i, t:t + 1].astype(float)
                a, d = inverse(st, tr.x[i, t:t + 1], tr.y[i, t:t + 1], wb, dt, yaw_next=yaw_t)
                st = step(st, a, d, wb, dt, None)
                worst = max(worst, float(np.hypot(st.x[0] - tr.x[i, t], st.y[0] - tr.y[i, t])))
                yaw_err.append(abs(float(wrap_angle(st.yaw - yaw_t)[0])))
    assert worst < 0.1, worst
    # headings follow the log too (waiting vehicles do not spin on position noise)
    assert np.percentile(yaw_err, 95) < np.radians(5), np.degrees(np.percentile(yaw_err, 95))


def test_seed_action_layout_swaps_entries():
    act = np.array([[0.3, -0.5]])  # seed layout: steer 0.3, brake 0.5
    a, d = denormalise(act, LIM, "steer_throttle")
    assert a[0] == pytest.approx(-0.5 * LIM.max_brake) and d[0] == pytest.approx(0.3 * LIM.max_steer)
    np.testing.assert_allclose(normalise(a, d, LIM, "steer_throttle"), act)
    with pytest.raises(ValueError, match="action layout"):
        denormalise(act, LIM, "throttle_only")
