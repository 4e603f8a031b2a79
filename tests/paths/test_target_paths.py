"""Target-point generation and the collision-aware random agent: goals reached at rest, inside
the limits, collision-free, deterministic for a seed; IK goals reach their Cartesian targets."""

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401

from mjx_pathtrack.paths import target as G
from mjx_pathtrack.paths import ik
from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.robots.collision import in_collision

B, SEG = 2, 60  # shapes shared by every call below (one compilation each)


@pytest.fixture(scope="module")
def iiwa():
    return robots.load_robot("iiwa")


def _inside(robot, q):
    lo, hi = np.asarray(robot.limits.pos_min), np.asarray(robot.limits.pos_max)
    return np.all(q >= lo - 1e-6) and np.all(q <= hi + 1e-6)


def _continuous(robot, motion):
    """240 Hz setpoints from the start on: no jump larger than the velocity limit allows."""
    step = np.max(np.abs(np.diff(motion, axis=0)), axis=0)
    assert np.all(step <= np.asarray(robot.limits.vel) / 240.0 * 1.001), step


def test_goal_seeking_motion_reaches_the_goal_at_rest_without_overshoot(iiwa):
    p0 = np.array([[0.0, 0.5, -1.0, 1.2, 0.3, -1.5, 2.5], [-2.5, -1.0, 2.0, -1.8, 2.5, 1.8, -2.8]])
    goal = np.array([[2.0, -1.0, 1.5, -0.5, -2.0, 1.0, -2.0], [-2.4, -0.9, 2.1, -1.9, 2.4, 1.9, -2.9]])
    q, arrived_at = G.target_segments(iiwa.limits, p0, goal, SEG, 0.1, 24)
    q, arrived_at = np.asarray(q, np.float64), np.asarray(arrived_at)
    assert np.all(arrived_at <= SEG)
    for i in range(B):
        end = q[i, arrived_at[i] * 24]
        assert np.max(np.abs(end - goal[i])) <= G.REACH_POS
        direction = np.sign(goal[i] - p0[i])
        assert np.max((q[i] - goal[i]) * direction) <= G.REACH_POS   # never beyond the goal
    assert _inside(iiwa, q)
    # setpoints at 240 Hz: finite-difference velocities within the limits (safe action space)
    vel = np.abs(np.diff(q, axis=1)) * 240.0
    assert np.all(vel <= np.asarray(iiwa.limits.vel) * 1.001)


@pytest.fixture(scope="module")
def target_paths(iiwa):
    collide = lambda q: in_collision(iiwa, q)  # noqa: E731
    return [G.target_point_paths(iiwa, B, seed, steps=12, in_collision=collide, max_segment_steps=SEG)
            for seed in (3, 3, 4)]


def test_target_point_paths_are_deterministic_inside_limits_and_collision_free(iiwa, target_paths):
    a, b, c = target_paths
    assert len(a.paths) == B
    for x, y in zip(a.paths, b.paths):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a.motions[0][:5], c.motions[0][:5])
    for knots, motion in zip(a.paths, a.motions):
        assert knots.shape[1] == 7 and len(knots) >= 2
        assert _inside(iiwa, knots) and _inside(iiwa, motion)
        assert not np.any(in_collision(iiwa, motion))
        assert not np.any(in_collision(iiwa, knots))
        _continuous(iiwa, motion)


def test_target_point_goals_reach_their_cartesian_targets(iiwa, target_paths):
    result = target_paths[0]
    goals, targets = np.concatenate(result.goals), np.concatenate(result.targets)
    assert len(goals) >= B and targets.shape == (len(goals), 1, 3)
    reached = ik.target_positions(iiwa, goals)                 # FK at the recorded goals (one jitted call)
    assert np.max(np.linalg.norm(reached - targets, axis=-1)) <= 1e-3
    for path_goals, motion in zip(result.goals, result.motions):  # the motion stops at each goal
        for g in path_goals:
            assert np.min(np.max(np.abs(motion - g), axis=-1)) <= G.REACH_POS


def test_safe_random_agent_avoids_a_forbidden_region(iiwa):
    def forbidden(q):  # a "collision" whenever joint 1 is above 0.3 rad
        return np.asarray(q)[..., 0] > 0.3

    paths, motions = G.safe_random_paths(iiwa, B, seed=1, steps=10, in_collision=forbidden)
    again, _ = G.safe_random_paths(iiwa, B, seed=1, steps=10, in_collision=forbidden)
    assert len(paths) == B
    for x, y in zip(paths, again):
        np.testing.assert_array_equal(x, y)
    for m in motions:
        assert not forbidden(m).any() and _inside(iiwa, m)
        _continuous(iiwa, m)
        assert len(m) >= 10 * 24  # at least the requested decision steps of setpoints


def test_smooth_target_point_paths_move_through_their_targets(iiwa):
    """The papers' kind: the robot passes its targets without stopping (the speed stays up between
    the start and the end), inside the limits, collision-free, continuous, deterministic."""
    kw = dict(steps=60, min_steps=20, n_goals=12, in_collision=lambda q: in_collision(iiwa, q))
    res = G.smooth_target_point_paths(iiwa, B, 5, **kw)
    again = G.smooth_target_point_paths(iiwa, B, 5, **kw)
    for path, motion, other in zip(res.paths, res.motions, again.paths):
        np.testing.assert_array_equal(path, other)
        assert _inside(iiwa, path) and _inside(iiwa, motion)
        _continuous(iiwa, motion)
        assert not in_collision(iiwa, motion[::8]).any()
        speed = np.linalg.norm(np.diff(motion, axis=0), axis=-1) * 240.0
        inner = speed[240:-240]   # one second after the start and before the end
        assert inner.min() > 0.01, f"stopped on the way ({inner.min():.4f} rad/s)"   # (target_point: 0)
        assert len(path) >= 10


def test_committed_smooth_and_mixed_sets_are_the_papers_kind():
    """The smooth target-point test split is within 10 % of the papers' target-point statistics
    (160 knots, 25.4 rad, median spacing 0.125; docs/paths.md §4), and the mixed set (the iiwa's
    default training data) has no knot interval above its 0.3 rad cap."""
    from mjx_pathtrack.paths import datasets

    st = datasets.split_stats(datasets.load_split("iiwa", "smooth_target_point", "test"))
    assert st.knots[1] == pytest.approx(160, rel=0.1) and st.length[1] == pytest.approx(25.4, rel=0.1)
    assert st.spacing_median == pytest.approx(0.125, rel=0.1)
    cfg = datasets.read_config("iiwa", "mixed")
    assert cfg["source"]["max_spacing"] == 0.3 and cfg["max_dis_between_knots"] <= 0.3
    for split in ("train", "test"):
        assert datasets.split_stats(datasets.load_split("iiwa", "mixed", split)).spacing_max <= 0.3
