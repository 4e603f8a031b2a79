"""Tests of mjx_pathtrack.core.spline: offline fit, arc length, resampling, JAX path queries."""

from __future__ import annotations

import mjx_pathtrack  # noqa: F401  (XLA flags before jax)

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.interpolate import CubicSpline, make_interp_spline
from scipy.optimize import brentq

from mjx_pathtrack.core import spline as S

MAX_KNOTS = 64
N_WINDOW = 8

point_at = jax.jit(S.point_at)
knot_window = jax.jit(S.knot_window, static_argnums=2)
replace_ahead = jax.jit(S.replace_ahead)
remaining_length = jax.jit(S.remaining_length)


def smooth_knots(n_knots: int = 40, n_joints: int = 7, seed: int = 0) -> np.ndarray:
    """A smooth joint-space curve (sums of sines, |q| < 2.5 rad), ~0.2 rad between knots."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, n_knots)[:, None]
    freq = rng.uniform(1.0, 3.0, (3, n_joints))
    phase = rng.uniform(0, 2 * np.pi, (3, n_joints))
    amp = rng.uniform(0.3, 0.8, (3, n_joints))
    return np.sum(amp[:, None] * np.sin(2 * np.pi * freq[:, None] * x[None] + phase[:, None]), axis=0)


@pytest.fixture(scope="module")
def fit():
    return S.fit_spline(smooth_knots())


@pytest.fixture(scope="module")
def path(fit):
    return S.path_from_fit(fit, MAX_KNOTS)


def _exact_points(fit: S.SplineFit, s_values: np.ndarray) -> np.ndarray:
    """Positions at arc lengths by adaptive quadrature + root finding on SciPy's spline."""
    cs = fit.scipy_spline()
    u = np.concatenate([[0.0], np.cumsum(fit.h)])
    speed = lambda x: np.linalg.norm(cs(x, 1))  # noqa: E731
    cum = np.concatenate([[0.0], np.cumsum([quad(speed, u[i], u[i + 1], epsabs=1e-13, epsrel=1e-13)[0]
                                            for i in range(len(fit.h))])])
    out = []
    for s in s_values:
        i = min(np.searchsorted(cum, s, side="right") - 1, len(fit.h) - 1)
        f = lambda x: cum[i] + quad(speed, u[i], x, epsabs=1e-13, epsrel=1e-13)[0] - s  # noqa: E731
        out.append(cs(brentq(f, u[i], u[i + 1], xtol=1e-15)))
    return np.array(out), cum


# --------------------------------------------------------------------------------------------
# offline fit
# --------------------------------------------------------------------------------------------


def test_fit_equals_papers_bspline_and_passes_through_knots(fit):
    knots = smooth_knots()
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
    u /= u[-1]  # the papers' normalised chord length; the curve does not depend on the scaling
    bspl = make_interp_spline(u, knots, k=3, bc_type="natural")
    x = np.linspace(0, 1, 997)
    np.testing.assert_allclose(fit.scipy_spline()(x * fit.h.sum()), bspl(x), atol=1e-10)
    np.testing.assert_allclose(fit.point_at(fit.knot_s), knots, atol=1e-12)


def test_arc_table_matches_adaptive_quadrature(fit, path):
    _, cum = _exact_points(fit, np.array([]))
    rel = np.abs(fit.knot_s - cum)[1:] / cum[1:]
    assert rel.max() < 1e-8          # requirement: 1e-4
    # the float32 JAX copy of the table
    np.testing.assert_allclose(np.asarray(path.knot_s[: len(cum)], np.float64), cum, rtol=1e-6, atol=1e-6)


def test_point_at_equals_scipy_at_exact_arc_length(fit, path):
    rng = np.random.default_rng(1)
    # float32-representable arc lengths, so that the JAX input carries no rounding of s
    s = np.sort(rng.uniform(0, fit.length, 40)).astype(np.float32).astype(np.float64)
    exact, _ = _exact_points(fit, s)
    assert np.abs(fit.point_at(s) - exact).max() < 1e-8
    got = np.asarray(point_at(path, jnp.asarray(s, jnp.float32)), np.float64)
    scale = max(fit.length, np.abs(fit.knots).max())
    # requirement: 1e-6 relative to the path scale (18 rad here); float32 reaches ~4e-7 rad,
    # i.e. ~2e-8 relative (eps32 = 1.2e-7 times |q| and s); checked with 4x margin
    assert np.abs(got - exact).max() < 1e-7 * scale
    np.testing.assert_allclose(np.asarray(point_at(path, path.knot_s[:40])), fit.knots, atol=2e-6)


def test_straight_line_has_exact_arc_length():
    direction = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    dist = np.array([0.0, 0.1, 0.5, 0.6, 1.7, 2.0])
    fit = S.fit_spline(0.3 + dist[:, None] * direction)
    assert fit.length == pytest.approx(2.0, abs=1e-12)
    s = np.linspace(0, 2, 33)
    np.testing.assert_allclose(fit.point_at(s), 0.3 + s[:, None] * direction, atol=1e-12)


def test_duplicates_dropped_and_lone_knot_padded():
    k = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    np.testing.assert_array_equal(S.dedup_knots(k), [[0, 0], [1, 0], [1, 1]])
    lone = S.dedup_knots([[0.5, 0.5], [0.5, 0.5]])
    np.testing.assert_allclose(lone, [[0.5, 0.5], [0.5 + 1e-6, 0.5 + 1e-6]])
    with pytest.raises(ValueError, match="not finite"):
        S.fit_spline([[0.0, 0.0], [np.nan, 1.0]])
    with pytest.raises(ValueError, match="K, n_joints"):
        S.fit_spline(np.zeros(3))


def test_clamped_to_the_ends(path, fit):
    out = np.asarray(point_at(path, jnp.array([-1.0, fit.length + 5.0])))
    np.testing.assert_allclose(out, fit.knots[[0, -1]], atol=1e-6)
    np.testing.assert_allclose(remaining_length(path, jnp.array([-1.0, 2.0, 1e3])),
                               [fit.length, fit.length - 2.0, 0.0], atol=1e-5)


# --------------------------------------------------------------------------------------------
# resampling
# --------------------------------------------------------------------------------------------


def test_distance_resampling_has_equal_arc_spacing(fit):
    new = S.resample_by_distance(fit, 0.1)
    assert len(new) == int(np.ceil(fit.length / 0.1)) + 1
    spacing = np.diff(S.fit_spline(new).knot_s)
    # on the refitted spline the spacing is 0.1 up to the refit's deviation from the original
    np.testing.assert_allclose(spacing[:-1], 0.1, rtol=1e-3)
    assert 0 < spacing[-1] <= 0.1 + 1e-4


def _bend_path() -> tuple[np.ndarray, float]:
    """2-D: 2 rad straight, a quarter circle of radius 0.2, 2 rad straight."""
    line1 = np.stack([np.linspace(0, 2, 201), np.zeros(201)], 1)
    a = np.linspace(0, np.pi / 2, 60)[1:]
    arc = np.stack([2 + 0.2 * np.sin(a), 0.2 - 0.2 * np.cos(a)], 1)
    line2 = np.stack([np.full(200, 2.2), np.linspace(0.2, 2.2, 201)[1:]], 1)
    return np.concatenate([line1, arc, line2]), 2.0 + 0.1 * np.pi


def test_curvature_resampling_puts_knots_into_bends():
    raw, bend_end = _bend_path()
    dist_knots = S.resample(raw, 0.1, None)
    curv_knots = S.resample(raw, 0.1, 0.3)
    refit = S.fit_spline(curv_knots)
    s = refit.knot_s
    in_bend = np.sum((s > 1.95) & (s < bend_end + 0.05))
    straight = np.sum(s < 1.5) + np.sum(s > bend_end + 0.5)
    # integrated curvature of the bend is pi/2 -> ~5 knots there, few on 3.5 rad of straights
    assert in_bend >= 4
    assert in_bend / 0.414 > 5 * straight / 3.4
    assert len(curv_knots) < len(dist_knots) / 3
    # the new knots lie on the distance-resampled curve (the refit between them may cut corners
    # on long straights: that is the method, docs/paths.md §3)
    fine = S.fit_spline(dist_knots)
    gap = np.linalg.norm(curv_knots[:, None] - fine.point_at(np.linspace(0, fine.length, 40001))[None],
                         axis=-1).min(1)
    assert gap.max() < 1e-4


def test_curvature_table_of_circle():
    a = np.linspace(0, np.pi, 80)
    fit = S.fit_spline(np.stack([np.cos(a), np.sin(a)], 1) * 0.5)
    # integrated curvature = turning angle, independent of the radius; away from the natural
    # ends (zero curvature there) knots 10..70 span 60/79 of pi
    kap = S.curvature_table(fit)[:: fit.samples_per_segment]
    assert kap[70] - kap[10] == pytest.approx(np.pi * 60 / 79, rel=1e-4)


# --------------------------------------------------------------------------------------------
# JAX path: knot window, batching, sub-paths
# --------------------------------------------------------------------------------------------


def test_knot_window_start_middle_end(path, fit):
    ks = fit.knot_s
    k = len(ks)
    w = knot_window(path, 0.0, N_WINDOW)
    np.testing.assert_array_equal(w.index, np.arange(N_WINDOW + 1))
    assert float(w.offset) == 0.0
    np.testing.assert_allclose(w.knot_distances, ks[1:N_WINDOW + 1], rtol=1e-6)
    np.testing.assert_allclose(w.knots, fit.knots[: N_WINDOW + 1], atol=1e-6)

    s = 0.5 * (ks[10] + ks[11])
    w = knot_window(path, s, N_WINDOW)
    np.testing.assert_array_equal(w.index, np.arange(10, 11 + N_WINDOW))
    assert float(w.offset) == pytest.approx(s - ks[10], abs=1e-5)
    assert float(w.state_length) == pytest.approx(ks[10 + N_WINDOW] - ks[10], abs=1e-5)
    assert float(w.last_s) == pytest.approx(ks[10 + N_WINDOW], abs=1e-5)
    assert not bool(w.close_to_end)
    # exactly on a knot: that knot is knot0
    w = knot_window(path, path.knot_s[12], N_WINDOW)
    assert int(w.index[0]) == 12 and float(w.offset) == 0.0

    s = 0.5 * (ks[k - 4] + ks[k - 3])      # 3 knots ahead: the end knot repeats
    w = knot_window(path, s, N_WINDOW)
    np.testing.assert_array_equal(w.index, [k - 4, k - 3, k - 2, k - 1] + [k - 1] * (N_WINDOW - 3))
    np.testing.assert_allclose(w.knot_distances[3:], ks[-1] - ks[k - 4], rtol=1e-6)
    assert bool(w.close_to_end)

    w = knot_window(path, fit.length + 1.0, N_WINDOW)
    np.testing.assert_array_equal(w.index, [k - 1] * (N_WINDOW + 1))
    np.testing.assert_array_equal(w.knot_distances, 0.0)
    assert float(w.offset) == 0.0 and float(w.state_length) == 0.0


def test_stack_and_vmap_match_single_paths(path):
    other = S.make_path(smooth_knots(25, seed=3), MAX_KNOTS)
    batch = S.stack_paths([path, other])
    s = jnp.array([1.5, 2.5])
    got = jax.vmap(S.point_at)(batch, s)
    np.testing.assert_allclose(got[0], point_at(path, 1.5), atol=1e-7)
    np.testing.assert_allclose(got[1], point_at(other, 2.5), atol=1e-7)
    win = jax.vmap(lambda p, x: S.knot_window(p, x, N_WINDOW))(batch, s)
    np.testing.assert_array_equal(win.index[1], knot_window(other, 2.5, N_WINDOW).index)
    np.testing.assert_allclose(batch.length, [path.length, other.length])
    fast = S.stack_fits([S.fit_spline(smooth_knots()), S.fit_spline(smooth_knots(25, seed=3))], MAX_KNOTS)
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(batch)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="differ in shape"):
        S.stack_paths([path, S.make_path(smooth_knots(25), 30)])
    with pytest.raises(ValueError, match="max_knots is 10"):
        S.make_path(smooth_knots(25), 10)


@pytest.mark.parametrize("side", ["left", "right"])
def test_searchsorted_row_equals_searchsorted_of_the_copied_row(side):
    rng = np.random.default_rng(4)
    for n in (1, 2, 7, 8, 1385):
        # sorted rows with ties (rounded values) and queries on, between and outside the entries
        table = np.sort(np.round(rng.uniform(0, 5, (3, n)), 1), axis=1).astype(np.float32)
        queries = np.concatenate([table[1], table[1] + 0.05, [-1.0, 0.0, 5.0, 6.0]]).astype(np.float32)
        got = jax.jit(lambda r, v: S.searchsorted_row(table, r, v, side))(1, queries)
        np.testing.assert_array_equal(got, np.searchsorted(table[1], queries, side=side))
        rows = np.arange(3)
        got = jax.vmap(lambda r: S.searchsorted_row(table, r, queries, side))(rows)
        np.testing.assert_array_equal(got, [np.searchsorted(table[r], queries, side=side) for r in rows])
    with pytest.raises(ValueError, match="side"):
        S.searchsorted_row(table, 0, queries, "middle")


def test_dataset_path_reads_the_row_in_place_bit_for_bit(path):
    """Every function on a DatasetPath equals the same function on the copied row (vmapped)."""
    batch = S.stack_paths([path, S.make_path(smooth_knots(25, seed=3), MAX_KNOTS),
                           S.make_path(smooth_knots(12, seed=5), MAX_KNOTS)])
    rows = jnp.array([2, 0, 1, 0])
    cut = jnp.array([5, 40, 20, 3], jnp.int32)
    s = jnp.array([[0.0, 0.3, 9.9], [1.5, 2.5, 1e3], [-1.0, 0.7, 2.2], [0.1, 0.2, 0.4]])

    def both(fn):
        lazy = jax.jit(jax.vmap(lambda r, k, x: fn(S.DatasetPath.of(batch, r)._replace(n_knots=k), x)))(rows, cut, s)
        copy = jax.jit(jax.vmap(lambda r, k, x: fn(S.DatasetPath.of(batch, r).materialize()._replace(n_knots=k), x)))(
            rows, cut, s)
        for a, b in zip(jax.tree_util.tree_leaves(lazy), jax.tree_util.tree_leaves(copy)):
            np.testing.assert_array_equal(a, b)
        return lazy

    both(S.point_at)
    both(S.tangent_at)
    both(S.locate)
    both(S.remaining_length)
    both(lambda p, x: (p.length, S.end_knot(p)))
    window = both(lambda p, x: S.knot_window(p, x[1], N_WINDOW))
    assert int(window.index[3, -1]) == 2   # row 0 cut to 3 knots: the window saturates at its end
    both(lambda p, x: S.truncate_at(p, x[1]).n_knots)
    both(lambda p, x: S.deviation(p, x[0], jnp.array([0.1, 0.2]), jnp.zeros((2, 7))))
    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    lazy = jax.vmap(lambda r, k: S.sample_sub_path(S.DatasetPath.of(batch, r), k))(rows, keys)
    copy = jax.vmap(lambda r, k: S.sample_sub_path(S.DatasetPath.of(batch, r).materialize(), k))(rows, keys)
    np.testing.assert_array_equal(lazy[0].n_knots, copy[0].n_knots)
    np.testing.assert_array_equal(lazy[1], copy[1])
    full = S.DatasetPath.of(batch, 1)
    assert int(full.n_knots) == 25 and full.samples_per_segment == path.samples_per_segment


def test_truncate_at_snaps_to_next_knot(path, fit):
    ks = fit.knot_s
    short = S.truncate_at(path, 0.5 * (ks[20] + ks[21]))
    assert int(short.n_knots) == 22
    assert float(short.length) == pytest.approx(ks[21], rel=1e-6)
    np.testing.assert_allclose(point_at(short, 1e3), fit.knots[21], atol=1e-6)
    np.testing.assert_array_equal(knot_window(short, ks[19], 4).index, [19, 20, 21, 21, 21])


def test_sample_sub_path_ranges(path, fit):
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    sub, s0 = jax.jit(jax.vmap(S.sample_sub_path, in_axes=(None, 0)))(path, keys)
    frac0 = np.asarray(s0) / fit.length
    assert frac0.min() >= 0 and frac0.max() <= 0.8 and frac0.max() > 0.7
    end = np.asarray(sub.length)
    # the end is a knot at least 0.2 of the length after the start
    assert np.all(end >= np.asarray(s0) + 0.2 * fit.length - 1e-4)
    assert np.all(np.min(np.abs(end[:, None] - fit.knot_s[None]), axis=1) < 1e-5)
    np.testing.assert_array_equal(np.asarray(sub.knot_s)[np.arange(256), np.asarray(sub.n_knots) - 1], end)


# --------------------------------------------------------------------------------------------
# path adjustment and deviation
# --------------------------------------------------------------------------------------------


def test_fit_clamped_natural_matches_scipy():
    pts = smooth_knots(12, 3, seed=5)
    d0 = np.array([0.6, 0.0, -0.8])
    padded = np.concatenate([pts, np.repeat(pts[-1:], 4, 0)])
    padded = np.insert(padded, 3, padded[3], axis=0)   # a duplicate to drop
    kept, h, coeffs, count = jax.jit(S.fit_clamped_natural)(jnp.asarray(padded, jnp.float32), 13,
                                                             jnp.asarray(d0, jnp.float32))
    assert int(count) == 12
    np.testing.assert_allclose(kept[:12], pts, atol=1e-6)
    u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    ref = CubicSpline(u, pts, bc_type=((1, d0), (2, np.zeros(3))), axis=0)
    np.testing.assert_allclose(np.asarray(coeffs[:11]), ref.c[::-1].transpose(1, 0, 2), atol=2e-4)


def test_replace_ahead_keeps_past_and_position_continuous(path, fit):
    rng = np.random.default_rng(7)
    s0 = float(0.5 * (fit.knot_s[9] + fit.knot_s[10]) + 0.01)
    q0 = fit.point_at(s0)
    new = q0 + np.cumsum(rng.normal(0, 0.1, (12, 7)), axis=0) + 0.2
    out = replace_ahead(path, s0, jnp.asarray(new, jnp.float32))
    assert int(out.n_knots) == 10 + 1 + 12   # knots 0..9, q(s0), the new knots
    # traversed part identical, bit for bit in the table and knots
    first = 9 * path.samples_per_segment
    np.testing.assert_array_equal(out.table_s[: first + 1], path.table_s[: first + 1])
    np.testing.assert_array_equal(out.knots[:10], path.knots[:10])
    before = jnp.linspace(0.0, s0, 50)
    np.testing.assert_allclose(point_at(out, before), point_at(path, before), atol=2e-6)
    # the current position is a knot; position and direction continuous there
    assert float(out.knot_s[10]) == pytest.approx(s0, abs=1e-5)
    np.testing.assert_allclose(out.knots[10], q0, atol=2e-6)
    eps = 1e-3
    jump = np.linalg.norm(point_at(out, s0 + eps) - point_at(out, s0 - eps))
    assert jump == pytest.approx(2 * eps, rel=0.05)
    np.testing.assert_allclose(S.tangent_at(out, s0 + 1e-5), S.tangent_at(path, s0), atol=1e-3)
    # then through the new knots to the new end
    np.testing.assert_allclose(point_at(out, out.knot_s[11:23]), new, atol=3e-6)
    np.testing.assert_allclose(point_at(out, 1e4), new[-1], atol=3e-6)
    ref = S.fit_spline(np.concatenate([q0[None], new]))   # arc length of the tail ~ a natural fit
    assert float(out.length) - s0 == pytest.approx(ref.length, rel=0.05)


def test_replace_ahead_drops_what_does_not_fit(path, fit):
    new = jnp.asarray(fit.knots[-1] + np.linspace(0.1, 3.0, 60)[:, None] * np.ones(7) * 0.1, jnp.float32)
    s0 = float(fit.knot_s[30]) + 0.05
    out = replace_ahead(path, s0, new)
    assert int(out.n_knots) == MAX_KNOTS
    np.testing.assert_allclose(out.knots[-1], new[MAX_KNOTS - 32 - 1], atol=1e-6)
    assert np.all(np.diff(np.asarray(out.knot_s)) > 0)


def test_deviation_equal_arc_length():
    dir_ = np.array([3.0, 4.0]) / 5.0
    path = S.make_path(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]) @ np.array([[dir_[0], dir_[1]], [0, 0]]),
                       4)
    offsets = jnp.array([0.1, 0.2, 5.0])
    on_path = np.array([0.6, 0.7, 2.0])[:, None] * dir_
    np.testing.assert_allclose(S.deviation(path, 0.5, offsets, jnp.asarray(on_path, jnp.float32)),
                               0.0, atol=1e-6)
    shifted = on_path + np.array([0.0, 0.1])
    np.testing.assert_allclose(S.deviation(path, 0.5, offsets, jnp.asarray(shifted, jnp.float32)),
                               0.1, atol=1e-6)
    w = jnp.array([1.0, 0.5])   # normaliser sqrt(2 / 1.25)
    np.testing.assert_allclose(S.deviation(path, 0.5, offsets, jnp.asarray(shifted, jnp.float32), w),
                               0.05 * np.sqrt(2 / 1.25), rtol=1e-5)
