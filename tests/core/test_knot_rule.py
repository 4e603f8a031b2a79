"""The training knot rule applied to any curve (core/knot_rule.py)."""
import numpy as np
import pytest

from mjx_pathtrack.core.knot_rule import KnotRule, cap_spacing, curve_distance, polyline_hausdorff, reknot
from mjx_pathtrack.core.spline_fit import fit_spline, resample
from mjx_pathtrack.paths import datasets

RULE = KnotRule(0.1, 0.3, 0.8537)


def respaced(knots, spacing):
    """The curve through ``knots`` given again with knots every ``spacing`` of arc length."""
    fit = fit_spline(knots)
    return fit.point_at(np.append(np.arange(0.0, fit.length, spacing), fit.length))


@pytest.fixture(scope="module")
def native():
    return datasets.load_split("iiwa", "random", "test")[:6]


def test_rule_of_a_dataset_is_read_from_its_config():
    random = KnotRule.of_dataset(datasets.read_config("iiwa", "random"))
    assert (random.resampling_distance, random.curvature_distance) == (0.1, 0.3)
    assert random.max_spacing == pytest.approx(datasets.read_config("iiwa", "random")["max_dis_between_knots"])
    ball = KnotRule.of_dataset(datasets.read_config("iiwa", "ball_balancing"))
    assert (ball.resampling_distance, ball.curvature_distance) == (0.3, None)
    assert KnotRule.from_json(random.to_json()) == random
    with pytest.raises(ValueError, match="unknown knot rule field"):
        KnotRule.from_json({"spacing": 1.0})


@pytest.mark.parametrize("bad", [dict(resampling_distance=0.0), dict(curvature_distance=-1.0),
                                 dict(max_spacing=float("nan")), dict(resampling_distance=float("inf"))])
def test_bad_rule_is_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        KnotRule(**bad)


def test_rule_without_curvature_reproduces_the_distance_resampling(native):
    k = native[0]
    out = reknot(k, KnotRule(0.3, None, None))
    np.testing.assert_allclose(out, resample(k, 0.3, None), atol=1e-12)


@pytest.mark.parametrize("spacing", [0.03, 0.09, 0.15])
def test_any_spacing_of_one_curve_gets_training_like_knots(native, spacing):
    """Planner-dense, every third and uniform re-givings of the committed paths: after
    re-knotting, the knot count and spacing are those of the native knots (within a few %), the
    spacing never exceeds the cap, and the curve stays on the given one."""
    for k in native:
        given = respaced(k, spacing)
        out = reknot(given, RULE)
        spacing_out = np.diff(fit_spline(out).knot_s)
        assert spacing_out.max() <= RULE.max_spacing + 1e-9
        assert abs(len(out) - len(k)) <= 0.06 * len(k), (len(out), len(k), len(given))
        assert abs(np.median(spacing_out) - np.median(np.diff(fit_spline(k).knot_s))) < 0.02
        np.testing.assert_array_equal(out[[0, -1]], given[[0, -1]])
        joint, cart = curve_distance(given, out)
        assert joint < 0.05 and cart is None


def test_cap_splits_long_straight_stretches():
    line = np.linspace(0.0, 1.0, 3)[:, None] * np.array([[3.0, -2.0, 1.0]])   # 3.7 rad, straight
    out = reknot(line, KnotRule(0.1, 0.3, 0.5))
    gaps = np.diff(fit_spline(out).knot_s)
    assert gaps.max() <= 0.5 + 1e-9 and len(out) == int(np.ceil(np.linalg.norm(line[-1]) / (0.95 * 0.5))) + 1
    assert curve_distance(line, out)[0] < 1e-9
    np.testing.assert_allclose(cap_spacing(np.array([0.0, 0.1, 1.0]), 0.4), [0.0, 0.1, 0.4, 0.7, 1.0])


def test_hausdorff_distance_of_known_curves():
    t = np.linspace(0.0, 1.0, 201)[:, None]
    a = np.concatenate([t, 0 * t], 1)
    b = np.concatenate([t, 0 * t + 0.01], 1)
    assert polyline_hausdorff(a, b) == pytest.approx(0.01, abs=1e-12)
    assert polyline_hausdorff(a, a[::50]) < 1e-12            # the same line, fewer vertices
    assert polyline_hausdorff(a, a[:101]) == pytest.approx(0.5)   # one covers only half


def test_start_slope_is_kept():
    k = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.0], [3.0, 1.0]])
    slope = np.array([0.0, 1.0])
    out = reknot(k, RULE, start_slope=slope)
    d = fit_spline(out, start_slope=slope).coeffs[0, 1]
    np.testing.assert_allclose(d, slope, atol=1e-12)
    assert curve_distance(k, out, start_slope=slope)[0] < 0.05
