"""TOPP-RA baseline: durations against the analytic bang-bang values, episode knots, ratios."""

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
from mjx_pathtrack.evaluation import baseline
from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import spline as S

V, A = float(iiwa.VEL[0]), float(iiwa.ACC[0])


@pytest.mark.parametrize("length", [0.05, 0.3, 1.0, 2.5])
def test_straight_segment_matches_bang_bang(length):
    """A single straight segment along joint 0 (other joints fixed): TOPP-RA's rest-to-rest time
    equals the triangular (short) or trapezoidal (long) bang-bang profile."""
    knots = np.zeros((2, 7))
    knots[1, 0] = length
    expected = baseline.bang_bang_duration(length, V, A)
    assert (length < V * V / A) == (expected == pytest.approx(2 * np.sqrt(length / A)))  # both regimes covered
    assert baseline.toppra_duration(knots, iiwa.VEL, iiwa.ACC) == pytest.approx(expected, rel=2e-3)


def test_diagonal_segment_is_limited_by_the_slowest_joint():
    # equal motion on joints 0 and 1: joint 1 has half the acceleration limit of joint 0
    knots = np.zeros((2, 7))
    knots[1, :2] = 1.5
    expected = baseline.bang_bang_duration(1.5, min(iiwa.VEL[:2]), min(iiwa.ACC[:2]))
    assert baseline.toppra_duration(knots, iiwa.VEL, iiwa.ACC) == pytest.approx(expected, rel=2e-3)


def test_episode_knots_start_at_the_start_point_and_keep_the_rest():
    knots = np.zeros((5, 7))
    knots[:, 0] = [0.0, 0.5, 1.0, 1.5, 2.0]
    path = S.make_path(knots)
    got = baseline.episode_knots(path, 0.7)
    np.testing.assert_allclose(got[:, 0], [0.7, 1.0, 1.5, 2.0], atol=1e-5)
    # starting exactly on a knot does not duplicate it
    assert len(baseline.episode_knots(path, 1.0)) == 3
    # the sub-path from 0.7 to 2.0 along joint 0 is a straight segment of 1.3 rad
    duration = baseline.toppra_duration(got, iiwa.VEL, iiwa.ACC)
    assert duration == pytest.approx(baseline.bang_bang_duration(1.3, V, A), rel=2e-3)


def test_ratio_is_nan_where_unknown():
    r = baseline.duration_ratio(np.array([2.0, np.nan, 1.0]), np.array([1.6, 1.0, 0.0]))
    assert r[0] == pytest.approx(1.25) and np.isnan(r[1]) and np.isnan(r[2])


# --- jerk-limited optimum (TOPP3 of copp-py) ---------------------------------------------------

from mjx_pathtrack.evaluation import jerk_optimum  # noqa: E402


@pytest.mark.parametrize("length,vel,acc,jerk", [
    (1.0, 1.0, 2.0, 10.0),   # acceleration limit and velocity limit reached, cruise
    (3.0, 1.0, 2.0, 10.0),   # long cruise
    (0.2, 1.0, 2.0, 10.0),   # velocity limit not reached, acceleration limit reached
    (0.05, 1.0, 2.0, 10.0),  # neither: pure jerk phases
])
def test_topp3_of_a_straight_segment_matches_the_analytic_jerk_limited_time(length, vel, acc, jerk):
    """One straight segment (5 collinear knots): the analytic time-optimal jerk-limited
    rest-to-rest time, which TOPP3 on its station grid may exceed by ~1 % but never undercut."""
    knots = np.linspace([0.0, 0.3], [length, 0.3], 5)
    limits = [np.array([x, x]) for x in (vel, acc, jerk)]
    exact = jerk_optimum.jerk_limited_rest_to_rest(length, vel, acc, jerk)
    got = jerk_optimum.topp3_duration(knots, *limits)
    assert exact * (1 - 1e-4) <= got <= exact * 1.015, (got, exact)
    assert got > baseline.toppra_duration(knots, limits[0], limits[1])


def test_analytic_jerk_limited_time_has_the_textbook_values():
    # v = 1, a = 2, j = 10: accelerating takes v/a + a/j = 0.7 s over 0.35 rad
    assert jerk_optimum.jerk_limited_rest_to_rest(1.0, 1.0, 2.0, 10.0) == pytest.approx(1.4 + 0.3)
    # tiny jerk-only move: 4 jerk phases, L = 2 j (t/4)^3 * ... -> t = 4 (L / (2 j))^(1/3)
    assert jerk_optimum.jerk_limited_rest_to_rest(1e-4, 1.0, 2.0, 10.0) == pytest.approx(4 * (1e-4 / 20) ** (1 / 3))
    # infinite jerk approaches the bang-bang (TOPP-RA) value
    assert jerk_optimum.jerk_limited_rest_to_rest(0.3, 1.0, 2.0, 1e9) == pytest.approx(
        baseline.bang_bang_duration(0.3, 1.0, 2.0), rel=1e-4)


def test_topp3_is_never_faster_than_toppra_on_test_paths_and_the_cache_is_reused(tmp_path):
    """Sub-paths of the iiwa test split under the iiwa's limits (dt 0.1 jerk): TOPP3 >= TOPP-RA
    on every one; a second call reads the cache instead of solving again."""
    from mjx_pathtrack.paths import datasets

    lim = iiwa.joint_limits(0.1)
    paths = datasets.load_split("iiwa", "random", "test")[:4]
    rng = np.random.default_rng(0)
    problems = []
    for knots in paths:
        start = rng.integers(0, len(knots) // 2)
        problems.append((knots[start:start + 25], np.asarray(lim.vel), np.asarray(lim.acc), np.asarray(lim.jerk)))
    cache = tmp_path / "topp3.json"
    got = jerk_optimum.durations(problems, cache=cache, workers=2)
    toppra = np.array([baseline.toppra_duration(p[0], p[1], p[2]) for p in problems])
    assert np.all(np.isfinite(got)) and np.all(got >= toppra * (1 - 1e-6)), (got, toppra)
    assert np.all(got <= 2.0 * toppra)
    stored = cache.read_text()
    assert len(__import__("json").loads(stored)) == 4
    again = jerk_optimum.durations(problems, cache=cache, workers=1)
    np.testing.assert_array_equal(got, again)
    assert cache.read_text() == stored
