"""TOPP-RA baseline: durations against the analytic bang-bang values, episode knots, ratios."""

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
from mjx_pathtrack import baseline, iiwa, spline as S

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
