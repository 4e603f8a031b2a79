"""A user's path made ready for a policy (paths/user_paths.py): limits, re-knotting, report."""
import numpy as np
import pytest

from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.evaluation.geometry import polyline_distance
from mjx_pathtrack.core.spline_fit import fit_spline
from mjx_pathtrack.paths import datasets
from mjx_pathtrack.paths import user_paths as UP
from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.robots.registry import POS_BUFFER

LIM = iiwa.joint_limits(0.1)
NAMES = iiwa.JOINT_NAMES
RULE = KnotRule(0.1, 0.3, 0.8537)


@pytest.fixture(scope="module")
def native():
    return datasets.load_split("iiwa", "random", "test")[:4]


def test_dense_waypoints_become_training_like_knots(native):
    k = native[0]
    fit = fit_spline(k)
    dense = fit.point_at(np.append(np.arange(0.0, fit.length, 0.03), fit.length))
    out = UP.prepare_path(dense, LIM, RULE, NAMES, name="dense")
    assert len(dense) > 4 * len(k) and abs(len(out.knots) - len(k)) <= 0.06 * len(k)
    assert out.limit_shift == 0.0 and out.cartesian_distance is None
    assert 0 < out.joint_distance < 0.05
    # an independent lower bound: the re-knotted curve halfway between its knots, measured to the
    # polyline of the given waypoints (within the polyline's sag, < 3e-3 rad on these curves)
    ours = fit_spline(out.knots)
    mid = ours.point_at(0.5 * (ours.knot_s[1:] + ours.knot_s[:-1]))
    assert out.joint_distance >= polyline_distance(mid, dense).max() - 3e-3
    np.testing.assert_array_equal(out.given, dense)
    kept = UP.prepare_path(dense, LIM, None, NAMES)
    np.testing.assert_array_equal(kept.knots, dense)
    assert kept.joint_distance == 0.0


def test_knots_on_the_urdf_limits_are_moved_onto_the_models(native):
    k = native[1].copy()
    hi = np.asarray(LIM.pos_max, np.float64)
    k[5, 1] = hi[1] + POS_BUFFER            # on the URDF limit
    k[7, 3] = -np.asarray(LIM.pos_max)[3] - 0.5 * POS_BUFFER
    out = UP.prepare_path(k, LIM, RULE, NAMES, name="p", allowance=POS_BUFFER)
    assert out.limit_shift == pytest.approx(POS_BUFFER, abs=1e-12)
    assert out.given[5, 1] == pytest.approx(hi[1]) and out.given[7, 3] == pytest.approx(-hi[3])
    for q in (out.given, out.knots):
        assert np.all(q <= hi + 1e-12) and np.all(q >= -hi - 1e-12)
    lines = UP.report_lines([out], RULE)
    assert "moved onto them by up to 0.0350 rad (p)" in lines[0]


def test_knots_beyond_the_urdf_limits_are_refused_by_name(native):
    k = native[1].copy()
    k[9, 2] = np.asarray(LIM.pos_max)[2] + POS_BUFFER + 0.01
    with pytest.raises(datasets.DatasetError, match=r"^p: knot 9, iiwa_joint_3 = .* beyond the robot's limits"):
        UP.prepare_path(k, LIM, RULE, NAMES, name="p", allowance=POS_BUFFER)
    k = native[1].copy()
    k[4, 0] = np.asarray(LIM.pos_max)[0] + 0.001   # no allowance: just beyond the model's limit
    with pytest.raises(datasets.DatasetError, match="knot 4, iiwa_joint_1"):
        UP.prepare_path(k, LIM, RULE, NAMES, name="p")


@pytest.mark.parametrize("bad, match", [(np.full((3, 7), np.nan), "NaN"), (np.zeros((3, 6)), "7 joints"),
                                        (np.zeros((3, 7)), "at least 2 distinct")])
def test_bad_paths_are_refused_with_their_problem(bad, match):
    with pytest.raises(datasets.DatasetError, match=match):
        UP.prepare_path(bad, LIM, RULE, NAMES)


def test_cartesian_distance_with_fk(native):
    shift = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    k = native[2][:20]

    def fk(q):   # a planar stand-in: the first two joints as x, y [m]
        return np.concatenate([q[:, :2], np.zeros((len(q), 1))], -1)[:, None]

    out = UP.prepare_path(k + shift, LIM, RULE, NAMES, fk=fk)
    assert out.cartesian_distance is not None and 0 <= out.cartesian_distance <= out.joint_distance + 1e-9
    text = UP.report_lines([out], RULE)[-1]
    assert "target point" in text and "measured against your curve" in text
