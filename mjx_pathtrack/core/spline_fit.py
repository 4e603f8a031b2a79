"""Offline half of the reference path (NumPy/SciPy, float64): fit a natural cubic spline through
knots with chord-length parameter, tabulate its arc length, resample it.

:func:`fit_spline` drops consecutive duplicate knots and fits; :func:`resample_by_distance` and
:func:`resample_by_curvature` place new knots at equal arc length or equal integrated curvature.
The arc-length helpers (``_horner``, ``_speed``, ``_arc_table``, ``_locate``) take the array
module ``xp`` and serve :mod:`mjx_pathtrack.core.spline` (JAX, in the environment) as well.
Representation, units and shapes: see :mod:`mjx_pathtrack.core.spline`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from scipy.interpolate import CubicSpline

Array = jax.Array


#: consecutive knots closer than this [rad] count as duplicates and are dropped
DUPLICATE_DISTANCE = 1e-9
#: offset added to a lone knot so that a path has two knots (as in the papers' code)
LONE_KNOT_OFFSET = 1e-6
#: default number of arc-length table samples per knot segment
SAMPLES_PER_SEGMENT = 8
# 5-point Gauss-Legendre rule on [0, 1]
_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)
_GL_X = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W


@dataclasses.dataclass(frozen=True)
class SplineFit:
    """A fitted path in float64 (offline).

    ``knots [K, n]`` (duplicates removed), ``h [K-1]`` chord lengths, ``coeffs [K-1, 4, n]``
    (``c0..c3`` in the local parameter), ``table_s [(K-1)*M + 1]`` arc length at the table
    points, ``table_dtds`` the same shape, ``dt/ds`` there. ``samples_per_segment`` is ``M``.
    """

    knots: np.ndarray
    h: np.ndarray
    coeffs: np.ndarray
    table_s: np.ndarray
    table_dtds: np.ndarray
    samples_per_segment: int

    @property
    def length(self) -> float:
        """Total arc length [rad]."""
        return float(self.table_s[-1])

    @property
    def knot_s(self) -> np.ndarray:
        """``[K]`` arc-length position of each knot [rad]."""
        return self.table_s[:: self.samples_per_segment]

    def point_at(self, s) -> np.ndarray:
        """Positions ``[..., n]`` at arc lengths ``s [...]`` (clamped to ``[0, length]``)."""
        seg, t = _locate(self.table_s, self.table_dtds, self.h, self.coeffs, self.samples_per_segment,
                         len(self.h) * self.samples_per_segment, np.asarray(s, np.float64), np)
        return _horner(self.coeffs[seg], t, np)

    def scipy_spline(self) -> CubicSpline:
        """The same curve as a SciPy ``CubicSpline`` in the global chord-length parameter."""
        u = np.concatenate([[0.0], np.cumsum(self.h)])
        return CubicSpline(u, self.knots, bc_type="natural", axis=0)


def dedup_knots(knots) -> np.ndarray:
    """Knots ``[K, n]`` without consecutive duplicates (closer than ``DUPLICATE_DISTANCE``).

    A single remaining knot gets a second one at ``+LONE_KNOT_OFFSET`` in every joint, as in the
    papers' code. Raises ``ValueError`` for a non-2-D, empty or non-finite array.
    """
    k = np.asarray(knots, dtype=np.float64)
    if k.ndim != 2 or k.shape[0] < 1 or k.shape[1] < 1:
        raise ValueError(f"knots must be a [K, n_joints] array with K >= 1, got shape {k.shape}")
    if not np.all(np.isfinite(k)):
        row = int(np.flatnonzero(~np.all(np.isfinite(k), axis=1))[0])
        raise ValueError(f"knot {row} is not finite: {k[row]}")
    keep = np.concatenate([[True], np.linalg.norm(np.diff(k, axis=0), axis=1) > DUPLICATE_DISTANCE])
    k = k[keep]
    if k.shape[0] == 1:
        k = np.concatenate([k, k + LONE_KNOT_OFFSET])
    return k


def fit_spline(knots, samples_per_segment: int = SAMPLES_PER_SEGMENT, start_slope=None) -> SplineFit:
    """Natural cubic spline through ``knots [K, n]`` (chord-length parameter), with arc table.
    ``start_slope [n]``: the first derivative at the start (per unit chord length) instead of a
    natural start, as :func:`~mjx_pathtrack.core.spline.replace_ahead` continues a path."""
    if samples_per_segment < 1:
        raise ValueError(f"samples_per_segment must be >= 1, got {samples_per_segment}")
    k = dedup_knots(knots)
    h = np.linalg.norm(np.diff(k, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(h)])
    start = (2, np.zeros(k.shape[1])) if start_slope is None else (1, np.asarray(start_slope, np.float64))
    cs = CubicSpline(u, k, bc_type=(start, (2, np.zeros(k.shape[1]))), axis=0)
    coeffs = np.ascontiguousarray(cs.c[::-1].transpose(1, 0, 2))  # [K-1, 4, n], c0..c3
    table_s, table_dtds = _arc_table(coeffs, h, samples_per_segment, np)
    return SplineFit(k, h, coeffs, table_s, table_dtds, samples_per_segment)


def distance_positions(fit: SplineFit, distance: float) -> np.ndarray:
    """Arc positions ``0, d, 2d, ...`` plus the end [rad] (docs/paths.md §3)."""
    if not distance > 0:
        raise ValueError(f"resampling distance must be > 0, got {distance}")
    return np.append(np.arange(0.0, fit.length, distance), fit.length)


def resample_by_distance(fit: SplineFit, distance: float) -> np.ndarray:
    """New knots ``[K', n]`` at arc lengths ``0, d, 2d, ...`` plus the end (docs/paths.md §3)."""
    return fit.point_at(distance_positions(fit, distance))


def curvature_table(fit: SplineFit) -> np.ndarray:
    """Integrated curvature ``[(K-1)*M + 1]`` at the table points (``int kappa ds``, kappa =
    ``|d^2 q / ds^2|`` [1/rad]), by Gauss-Legendre quadrature of the analytic curvature."""
    m = fit.samples_per_segment
    ta = np.arange(m)[:, None] / m + _GL_X[None, :] / m          # [M, G] fractions of a segment
    t = fit.h[:, None, None] * ta[None]                          # [S, M, G]
    c = fit.coeffs[:, None, None]                                # [S, 1, 1, 4, n]
    d1 = c[..., 1, :] + t[..., None] * (2 * c[..., 2, :] + 3 * t[..., None] * c[..., 3, :])
    d2 = 2 * c[..., 2, :] + 6 * t[..., None] * c[..., 3, :]
    speed2 = np.maximum(np.sum(d1 * d1, -1), 1e-300)
    normal = d2 - (np.sum(d1 * d2, -1) / speed2)[..., None] * d1
    kappa_ds_dt = np.linalg.norm(normal, axis=-1) / np.sqrt(speed2)   # kappa * |q'|
    pieces = (kappa_ds_dt @ _GL_W) * (fit.h[:, None] / m)          # [S, M]
    return np.concatenate([[0.0], np.cumsum(pieces.ravel())])


def curvature_positions(fit: SplineFit, curvature_distance: float) -> np.ndarray:
    """Arc positions [rad] at equal increments of integrated curvature plus the end
    (:func:`resample_by_curvature`), ``0`` and ``fit.length`` included."""
    if not curvature_distance > 0:
        raise ValueError(f"curvature distance must be > 0, got {curvature_distance}")
    kap = curvature_table(fit)
    levels = np.append(np.arange(0.0, kap[-1], curvature_distance), kap[-1])
    # first table interval where the integrated curvature reaches each level, then linear in s
    j = np.clip(np.searchsorted(kap, levels, side="left") - 1, 0, len(kap) - 2)
    dk = kap[j + 1] - kap[j]
    frac = np.where(dk > 0, (levels - kap[j]) / np.where(dk > 0, dk, 1.0), 0.0)
    s = fit.table_s[j] + np.clip(frac, 0.0, 1.0) * (fit.table_s[j + 1] - fit.table_s[j])
    s[0], s[-1] = 0.0, fit.length
    return s


def resample_by_curvature(fit: SplineFit, curvature_distance: float) -> np.ndarray:
    """New knots ``[K', n]`` at equal increments of integrated curvature (docs/paths.md §3,
    paper Fig. 8b), plus the end point. Straight stretches get few knots, bends many."""
    return fit.point_at(curvature_positions(fit, curvature_distance))


def resample(knots, distance: float = 0.1, curvature_distance: float | None = 0.3,
             samples_per_segment: int = SAMPLES_PER_SEGMENT) -> np.ndarray:
    """The papers' dataset pipeline (docs/paths.md §3): fit, resample every ``distance`` of arc
    length, then (if ``curvature_distance`` is not None) refit and resample every
    ``curvature_distance`` of integrated curvature. Returns knots ``[K', n]``."""
    knots = resample_by_distance(fit_spline(knots, samples_per_segment), distance)
    if curvature_distance is None:
        return knots
    return resample_by_curvature(fit_spline(knots, samples_per_segment), curvature_distance)


def _horner(c, t, xp):
    """``c [..., 4, n]``, ``t [...]`` -> ``c0 + c1 t + c2 t^2 + c3 t^3`` ``[..., n]``."""
    t = t[..., None]
    return c[..., 0, :] + t * (c[..., 1, :] + t * (c[..., 2, :] + t * c[..., 3, :]))


def _speed(c, t, xp):
    """``|q'(t)|`` for coefficients ``c [..., 4, n]`` and ``t [...]``."""
    tt = t[..., None]
    d1 = c[..., 1, :] + tt * (2.0 * c[..., 2, :] + 3.0 * tt * c[..., 3, :])
    return xp.sqrt(xp.sum(d1 * d1, axis=-1))


def _segment_arc(coeffs, h, m, xp):
    """Arc length of each table interval ``[S, M]`` and ``dt/ds`` at its start ``[S, M]`` plus
    ``dt/ds`` at each segment end ``[S]``."""
    frac = xp.arange(m) / m
    ta = h[:, None, None] * (frac[:, None] + xp.asarray(_GL_X)[None, :] / m)   # [S, M, G]
    speed = _speed(coeffs[:, None, None], ta, xp)
    pieces = (speed @ xp.asarray(_GL_W)) * (h[:, None] / m)                     # [S, M]
    v0 = _speed(coeffs[:, None], h[:, None] * frac[None, :], xp)               # [S, M]
    v_end = _speed(coeffs, h, xp)                                               # [S]
    tiny = 1e-30 if xp is np else 1e-20
    return pieces, 1.0 / xp.maximum(v0, tiny), 1.0 / xp.maximum(v_end, tiny)


def _arc_table(coeffs, h, m, xp):
    """``table_s [S*M + 1]`` (from 0) and ``table_dtds [S*M + 1]``."""
    pieces, dtds0, dtds_end = _segment_arc(coeffs, h, m, xp)
    table_s = xp.concatenate([xp.zeros(1, pieces.dtype), xp.cumsum(pieces.reshape(-1))])
    table_dtds = xp.concatenate([dtds0.reshape(-1), dtds_end[-1:]])
    return table_s, table_dtds


def _locate(table_s, table_dtds, h, coeffs, m, n_valid, s, xp, row=None):
    """Segment index and local parameter for arc lengths ``s [...]``.

    ``n_valid`` is the number of valid table intervals ``(K-1)*M``; ``s`` is clamped to
    ``[0, table_s[n_valid]]``. With ``row`` (JAX only) the arrays are a stacked batch and the
    path is their row ``row``, read in place. Cubic Hermite interpolation of ``t(s)`` inside a table interval
    (position error up to ~3e-5 rad for 0.4-rad segments at M = 8), refined by one Newton step
    on the exact arc length (5-point Gauss-Legendre over the partial interval): ~3e-9 rad in
    float64; in float32 the rounding of ``s`` itself (~eps32 * s) dominates.
    """
    at = (lambda a, i: a[i]) if row is None else (lambda a, i: a[row, i])
    s = xp.clip(s, 0.0, at(table_s, n_valid))
    above = xp.searchsorted(table_s, s, side="right") if row is None else searchsorted_row(table_s, row, s, "right")
    j = xp.clip(above - 1, 0, n_valid - 1)
    seg = j // m
    hs = at(h, seg)
    t0 = (j % m) * hs / m
    dt = hs / m
    s_j = at(table_s, j)
    ds = at(table_s, j + 1) - s_j
    safe_ds = xp.where(ds > 0, ds, 1.0)
    x = xp.where(ds > 0, (s - s_j) / safe_ds, 0.0)
    # dt/ds at both ends scaled by the interval's ds, relative to dt
    m0 = at(table_dtds, j) * ds
    m1 = at(table_dtds, j + 1) * ds
    x2, x3 = x * x, x * x * x
    t = t0 + (x2 * (3.0 - 2.0 * x)) * dt + (x3 - 2.0 * x2 + x) * m0 + (x3 - x2) * m1
    t = xp.clip(t, t0, t0 + dt)
    # one Newton step on s(t) = table_s[j] + int_{t0}^{t} |q'|, Gauss-Legendre on [t0, t]
    c = at(coeffs, seg)
    width = t - t0
    nodes = t0[..., None] + width[..., None] * xp.asarray(_GL_X, width.dtype)
    s_t = s_j + width * (_speed(c[..., None, :, :], nodes, xp) @ xp.asarray(_GL_W, width.dtype))
    speed_t = _speed(c, t, xp)
    step = xp.where(speed_t > 0, (s - s_t) / xp.where(speed_t > 0, speed_t, 1.0), 0.0)
    return seg, xp.clip(t + step, t0, t0 + dt)


def searchsorted_row(table: Array, row: Array, v: Array, side: str = "left") -> Array:
    """``jnp.searchsorted(table[row], v, side)`` for a sorted row of ``table [B, T]``, without
    copying the row: a fixed-length bisection that gathers one entry per level. ``v [...]``;
    int32 ``[...]`` in ``[0, T]``. (Only NaN in ``v`` is ordered differently.)"""
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    table = jnp.asarray(table)
    n = table.shape[-1]
    v = jnp.asarray(v, table.dtype)

    def level(_, bounds):
        lo, hi = bounds              # the answer is in [lo, hi]
        active = lo < hi
        mid = (lo + hi) // 2
        x = table[row, jnp.minimum(mid, n - 1)]
        after = active & ((x < v) if side == "left" else (x <= v))
        return jnp.where(after, mid + 1, lo), jnp.where(active & ~after, mid, hi)

    lo = jnp.zeros(v.shape, jnp.int32)
    lo, _ = jax.lax.fori_loop(0, int(np.ceil(np.log2(n + 1))), level, (lo, jnp.full(v.shape, n, jnp.int32)))
    return lo
