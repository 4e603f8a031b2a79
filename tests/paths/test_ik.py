"""Inverse kinematics: converges on reachable targets inside the limits, reports unreachable
ones, rejects malformed input with a clear message."""

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401

from mjx_pathtrack.paths import ik
from mjx_pathtrack.robots import registry as robots

B = 8  # one batch shape for every call: one compilation


@pytest.fixture(scope="module")
def iiwa():
    return robots.load_robot("iiwa")


def _configs(robot, rng, n, margin=0.1):
    lo, hi = np.asarray(robot.limits.pos_min), np.asarray(robot.limits.pos_max)
    return rng.uniform(lo + margin * (hi - lo), hi - margin * (hi - lo), (n, robot.n_joints))


def test_converges_on_reachable_targets_inside_the_limits(iiwa):
    rng = np.random.default_rng(0)
    q_true = _configs(iiwa, rng, B)
    targets = np.asarray(iiwa.fk(q_true)[0])                       # [B, 1, 3], reachable by construction
    seeds = np.clip(q_true + rng.uniform(-0.4, 0.4, q_true.shape), iiwa.limits.pos_min, iiwa.limits.pos_max)
    res = ik.solve_ik(iiwa, targets, seeds)
    assert res.q.shape == (B, 7) and res.converged.shape == (B,)
    assert np.all(res.converged)
    reached = np.asarray(iiwa.fk(res.q)[0])                        # independent check with Robot.fk
    assert np.max(np.linalg.norm(reached - targets, axis=-1)) <= ik.TOL
    np.testing.assert_allclose(np.asarray(res.error), np.linalg.norm(reached - targets, axis=-1)[:, 0], atol=1e-5)
    q = np.asarray(res.q)
    assert np.all(q >= np.asarray(iiwa.limits.pos_min)) and np.all(q <= np.asarray(iiwa.limits.pos_max))
    # the jitted target_positions agree with Robot.fk
    np.testing.assert_allclose(ik.target_positions(iiwa, q), reached, atol=1e-5)


def test_unreachable_targets_are_reported_not_raised(iiwa):
    targets = np.tile(np.array([[[5.0, 0.0, 1.0]]]), (B, 1, 1))   # 5 m away: beyond the ~1.3 m reach
    res = ik.solve_ik(iiwa, targets, np.zeros((B, 7)))
    assert not np.any(res.converged) and np.all(np.asarray(res.error) > 1.0)
    q = np.asarray(res.q)
    assert np.all(q >= np.asarray(iiwa.limits.pos_min)) and np.all(q <= np.asarray(iiwa.limits.pos_max))


@pytest.mark.parametrize("targets, seed, message", [
    (np.zeros((B, 3)), np.zeros((B, 7)), r"targets must have shape \[\.\.\., 1, 3\]"),
    (np.zeros((B, 2, 3)), np.zeros((B, 7)), r"targets must have shape"),
    (np.full((B, 1, 3), np.nan), np.zeros((B, 7)), "targets contain NaN"),
    (np.zeros((B, 1, 3)), np.zeros((B, 6)), r"q_seed must have shape \[\.\.\., 7\]"),
    (np.zeros((B, 1, 3)), np.full((B, 7), 3.0), "iiwa_joint_1 = 3 is outside the position limits"),
    (np.zeros((B, 1, 3)), np.zeros((3, 7)), "does not match the targets' batch shape"),
])
def test_bad_input_is_rejected_with_a_clear_message(iiwa, targets, seed, message):
    with pytest.raises(ValueError, match=message):
        ik.solve_ik(iiwa, targets, seed)


def test_bad_parameters_are_rejected(iiwa):
    with pytest.raises(ValueError, match="damping > 0"):
        ik.solve_ik(iiwa, np.zeros((B, 1, 3)), np.zeros((B, 7)), damping=0.0)
