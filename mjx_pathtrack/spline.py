"""Joint-space reference paths: natural cubic splines through knots, addressed by arc length.

Two halves (docs/paths.md, docs/method.md §4-§5; paper 000 §III-B/C, Fig. 3, 4, 8):

*Offline* (NumPy/SciPy, float64) -- :func:`fit_spline` fits a natural cubic spline through the
knots with the (un-normalised) chord length as parameter, after dropping consecutive duplicate
knots; :func:`resample_by_distance` and :func:`resample_by_curvature` place new knots at equal
arc length or equal integrated curvature; :func:`make_path` turns a fit into a :class:`Path`.

*In the environment* (pure JAX, jit/vmap-able, one path per call -- ``jax.vmap`` for batches) --
:class:`Path` is a fixed-size pytree (:class:`DatasetPath` reads one row of a stacked dataset in
place, for the same functions); :func:`point_at`, :func:`knot_window`,
:func:`remaining_length`, :func:`replace_ahead` (path adjustment during motion),
:func:`deviation` (docs/method.md §2.5), :func:`truncate_at` and :func:`sample_sub_path` (episode
sub-path, end snapped to a knot, §3.4).

Representation. Segment ``i`` (between knots ``i`` and ``i+1``) is the cubic
``q(t) = c0 + c1 t + c2 t^2 + c3 t^3`` for the local parameter ``t in [0, h_i]``, ``h_i`` the chord
length of the segment [rad]. The curve equals SciPy's ``make_interp_spline(u, knots, k=3,
bc_type="natural")`` for any affine chord-length parameter ``u`` (the papers' code normalises ``u``
to [0, 1]; a natural cubic interpolant does not depend on that scaling). Arc length is tabulated
at ``M = samples_per_segment`` equally spaced parameter values per segment; each table interval is
integrated with 5-point Gauss-Legendre quadrature, so the table values are exact to ~1e-10 relative
(float64, offline). Between table points the inverse ``t(s)`` is cubic Hermite interpolation using
``dt/ds = 1/|q'(t)|`` at both ends, refined by one Newton step on the exact arc length. The local
parameter keeps float32 rounding to the order of ``eps32 * s`` in arc length.

Units: joint positions in rad (m for prismatic joints); arc length ``s`` is the Euclidean length
in joint space, in the same units. Shapes: ``n`` joints, ``K`` knots of one path, ``Kmax =
max_knots``, ``M`` samples per segment, table length ``T = (Kmax - 1) * M + 1``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.interpolate import CubicSpline

from mjx_pathtrack.reward import weighted_deviation

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


# ---------------------------------------------------------------------------------------------
# Offline fit (NumPy / SciPy, float64)
# ---------------------------------------------------------------------------------------------


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


def fit_spline(knots, samples_per_segment: int = SAMPLES_PER_SEGMENT) -> SplineFit:
    """Natural cubic spline through ``knots [K, n]`` (chord-length parameter), with arc table."""
    if samples_per_segment < 1:
        raise ValueError(f"samples_per_segment must be >= 1, got {samples_per_segment}")
    k = dedup_knots(knots)
    h = np.linalg.norm(np.diff(k, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(h)])
    cs = CubicSpline(u, k, bc_type="natural", axis=0)
    coeffs = np.ascontiguousarray(cs.c[::-1].transpose(1, 0, 2))  # [K-1, 4, n], c0..c3
    table_s, table_dtds = _arc_table(coeffs, h, samples_per_segment, np)
    return SplineFit(k, h, coeffs, table_s, table_dtds, samples_per_segment)


def resample_by_distance(fit: SplineFit, distance: float) -> np.ndarray:
    """New knots ``[K', n]`` at arc lengths ``0, d, 2d, ...`` plus the end (docs/paths.md §3)."""
    if not distance > 0:
        raise ValueError(f"resampling distance must be > 0, got {distance}")
    s = np.append(np.arange(0.0, fit.length, distance), fit.length)
    return fit.point_at(s)


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


def resample_by_curvature(fit: SplineFit, curvature_distance: float) -> np.ndarray:
    """New knots ``[K', n]`` at equal increments of integrated curvature (docs/paths.md §3,
    paper Fig. 8b), plus the end point. Straight stretches get few knots, bends many."""
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
    return fit.point_at(s)


def resample(knots, distance: float = 0.1, curvature_distance: float | None = 0.3,
             samples_per_segment: int = SAMPLES_PER_SEGMENT) -> np.ndarray:
    """The papers' dataset pipeline (docs/paths.md §3): fit, resample every ``distance`` of arc
    length, then (if ``curvature_distance`` is not None) refit and resample every
    ``curvature_distance`` of integrated curvature. Returns knots ``[K', n]``."""
    knots = resample_by_distance(fit_spline(knots, samples_per_segment), distance)
    if curvature_distance is None:
        return knots
    return resample_by_curvature(fit_spline(knots, samples_per_segment), curvature_distance)


# ---------------------------------------------------------------------------------------------
# Shared array code (xp = numpy or jax.numpy)
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Fixed-size JAX path
# ---------------------------------------------------------------------------------------------


class Path(NamedTuple):
    """A reference path padded to ``Kmax`` knots (a pytree; stack for batches).

    Only the first ``n_knots`` knots (and ``n_knots - 1`` segments, ``(n_knots - 1) * M`` table
    intervals) are meaningful; every function clips indices to them, so padding content is
    irrelevant (:func:`make_path` pads by repeating the end).

    Fields (single path; a stacked batch has a leading ``[B]`` axis on each):
      knots ``[Kmax, n]`` rad; n_knots ``[]`` int32; knot_s ``[Kmax]`` arc position of each knot
      [rad]; h ``[Kmax-1]`` chord parameter width of each segment; coeffs ``[Kmax-1, 4, n]``;
      table_s ``[T]`` arc length at the table points [rad]; table_dtds ``[T]`` dt/ds there.
    """

    knots: Array
    n_knots: Array
    knot_s: Array
    h: Array
    coeffs: Array
    table_s: Array
    table_dtds: Array

    @property
    def samples_per_segment(self) -> int:
        """``M``, static (from the shapes)."""
        return (self.table_s.shape[-1] - 1) // (self.knots.shape[-2] - 1)

    @property
    def length(self) -> Array:
        """Total arc length ``[]`` (``[B]`` for a batch) [rad]."""
        return jnp.take_along_axis(self.knot_s, (self.n_knots - 1)[..., None], axis=-1)[..., 0]


def make_path(knots, max_knots: int | None = None,
              samples_per_segment: int = SAMPLES_PER_SEGMENT, dtype=jnp.float32) -> Path:
    """Fit ``knots [K, n]`` (offline, float64) and pad to ``max_knots`` (default ``K``).

    Raises ``ValueError`` if the path has more knots than ``max_knots`` after removing
    duplicates.
    """
    return path_from_fit(fit_spline(knots, samples_per_segment), max_knots, dtype)


def path_from_fit(fit: SplineFit, max_knots: int | None = None, dtype=jnp.float32) -> Path:
    """Pad a :class:`SplineFit` to ``max_knots`` and convert to a JAX :class:`Path`."""
    return Path(*(jnp.asarray(a, jnp.int32 if i == 1 else dtype)
                  for i, a in enumerate(_padded(fit, max_knots))))


def stack_fits(fits, max_knots: int | None = None, dtype=jnp.float32) -> Path:
    """Batch of fits as one stacked :class:`Path` (padded in NumPy, converted once; fast for
    datasets). ``max_knots`` defaults to the largest knot count."""
    fits = list(fits)
    if not fits:
        raise ValueError("stack_fits needs at least one fit")
    if len({f.samples_per_segment for f in fits}) != 1:
        raise ValueError("fits differ in samples_per_segment")
    kmax = max(f.knots.shape[0] for f in fits) if max_knots is None else max_knots
    fields = zip(*(_padded(f, kmax) for f in fits))
    return Path(*(jnp.asarray(np.stack(a), jnp.int32 if i == 1 else dtype)
                  for i, a in enumerate(fields)))


def _padded(fit: SplineFit, max_knots: int | None) -> tuple[np.ndarray, ...]:
    """The :class:`Path` fields of ``fit`` as float64 NumPy arrays padded to ``max_knots``."""
    k, m = fit.knots.shape[0], fit.samples_per_segment
    kmax = k if max_knots is None else int(max_knots)
    if kmax < 2:
        raise ValueError(f"max_knots must be >= 2, got {kmax}")
    if k > kmax:
        raise ValueError(f"path has {k} knots (after dropping duplicates) but max_knots is {kmax}")
    pad_k, pad_s = kmax - k, (kmax - k) * m
    knots = np.concatenate([fit.knots, np.repeat(fit.knots[-1:], pad_k, 0)])
    h = np.concatenate([fit.h, np.full(pad_k, fit.h[-1])])
    coeffs = np.concatenate([fit.coeffs, np.zeros((pad_k,) + fit.coeffs.shape[1:])])
    coeffs[k - 1:, 0] = fit.knots[-1]   # padded segments stay at the end knot
    table_s = np.concatenate([fit.table_s, np.full(pad_s, fit.length)])
    table_dtds = np.concatenate([fit.table_dtds, np.full(pad_s, fit.table_dtds[-1])])
    knot_s = np.concatenate([fit.knot_s, np.full(pad_k, fit.length)])
    return knots, np.asarray(k), knot_s, h, coeffs, table_s, table_dtds


class DatasetPath(NamedTuple):
    """Path ``row`` of a stacked batch ``paths`` (leading axis ``[B]``), truncated to ``n_knots``,
    read in place.

    :func:`locate`, :func:`point_at`, :func:`tangent_at`, :func:`remaining_length`,
    :func:`knot_window`, :func:`end_knot`, :func:`truncate_at`, :func:`sample_sub_path`,
    :func:`deviation` and ``length`` return bit for bit what they return for
    :meth:`materialize`, the copied row, but gather only the entries they need: vmapped over
    environments, copying each environment's row of a dataset (~60 kB at 174 knots) every step
    took ~10 % of the environment step's kernel time on CPU (docs/results.md "Where the CPU time of
    training goes"). ``row`` ``[]`` int32, ``n_knots`` ``[]`` int32;
    vmap over them (not over ``paths``).
    """

    paths: Path
    row: Array
    n_knots: Array

    @classmethod
    def of(cls, paths: Path, row: Array) -> "DatasetPath":
        """The whole path ``row`` of ``paths``."""
        row = jnp.asarray(row, jnp.int32)
        return cls(paths, row, paths.n_knots[row])

    @property
    def samples_per_segment(self) -> int:
        return self.paths.samples_per_segment

    @property
    def length(self) -> Array:
        """Total arc length ``[]`` [rad]."""
        return self.paths.knot_s[self.row, self.n_knots - 1]

    def materialize(self) -> Path:
        """The row as a :class:`Path` of its own (a copy)."""
        return jax.tree.map(lambda x: x[self.row], self.paths)._replace(n_knots=self.n_knots)


AnyPath = Path | DatasetPath


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


def _at(path: AnyPath, name: str, index: Array) -> Array:
    """``getattr(path, name)[index]`` of a :class:`Path` or the row of a :class:`DatasetPath`."""
    if isinstance(path, DatasetPath):
        return getattr(path.paths, name)[path.row, index]
    return getattr(path, name)[index]


def _searchsorted(path: AnyPath, name: str, v: Array, side: str) -> Array:
    if isinstance(path, DatasetPath):
        return searchsorted_row(getattr(path.paths, name), path.row, v, side)
    return jnp.searchsorted(getattr(path, name), v, side=side)


def end_knot(path: AnyPath) -> Array:
    """The last knot ``[n]`` of the (truncated) path."""
    return _at(path, "knots", path.n_knots - 1)


def stack_paths(paths) -> Path:
    """Stack single paths of equal ``max_knots`` and ``M`` into a batch (leading axis ``[B]``)."""
    paths = list(paths)
    if not paths:
        raise ValueError("stack_paths needs at least one path")
    shapes = {p.knots.shape for p in paths}
    if len(shapes) != 1 or len({p.table_s.shape for p in paths}) != 1:
        raise ValueError(f"paths differ in shape (max_knots, n_joints or samples_per_segment): {shapes}")
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *paths)


def _n_valid(path: AnyPath):
    return (path.n_knots - 1) * path.samples_per_segment


def locate(path: AnyPath, s: Array) -> tuple[Array, Array]:
    """Segment index ``[...]`` (int) and local parameter ``[...]`` at arc lengths ``s [...]``."""
    data, row = (path.paths, path.row) if isinstance(path, DatasetPath) else (path, None)
    return _locate(data.table_s, data.table_dtds, data.h, data.coeffs, path.samples_per_segment,
                   _n_valid(path), jnp.asarray(s, data.table_s.dtype), jnp, row)


def point_at(path: AnyPath, s: Array) -> Array:
    """Position ``[..., n]`` at arc length ``s [...]`` [rad], clamped to ``[0, length]``."""
    seg, t = locate(path, s)
    return _horner(_at(path, "coeffs", seg), t, jnp)


def tangent_at(path: AnyPath, s: Array) -> Array:
    """Unit tangent ``dq/ds [..., n]`` at arc length ``s [...]`` (clamped like point_at)."""
    seg, t = locate(path, s)
    c = _at(path, "coeffs", seg)
    tt = t[..., None]
    d1 = c[..., 1, :] + tt * (2.0 * c[..., 2, :] + 3.0 * tt * c[..., 3, :])
    return d1 / jnp.maximum(jnp.linalg.norm(d1, axis=-1, keepdims=True), 1e-20)


def remaining_length(path: AnyPath, s: Array) -> Array:
    """Arc length from ``s`` to the end, ``>= 0`` [rad]."""
    length = path.length
    return length - jnp.clip(s, 0.0, length)


class KnotWindow(NamedTuple):
    """The knots an observation shows (docs/method.md §4 items 4-7), raw (not normalised).

    knots ``[N+1, n]``: knot0 = last knot at or before s, then the next N (end knot repeated);
    index ``[N+1]`` their knot indices; offset ``[]`` = s - s(knot0) (item 5);
    knot_distances ``[N]`` = s(knot_i) - s(knot0), i = 1..N (item 7); state_length ``[]`` =
    s(knot_N) - s(knot0) (item 6); last_s ``[]`` = s(knot_N), the reward's ``last_obs_dis``;
    close_to_end ``[]`` bool, knot_N is the end knot.
    """

    knots: Array
    index: Array
    offset: Array
    knot_distances: Array
    state_length: Array
    last_s: Array
    close_to_end: Array


def knot_window(path: AnyPath, s: Array, n: int) -> KnotWindow:
    """Knot before ``s`` and the next ``n`` knots (static ``n``), with their distances.

    ``s`` is clamped to ``[0, length]``; indices beyond the end knot repeat the end knot, so the
    distances saturate and are all 0 once ``s`` reaches the end (docs/method.md §4).
    """
    end = path.n_knots - 1
    s = jnp.clip(s, 0.0, path.length)
    i0 = jnp.clip(_searchsorted(path, "knot_s", s, "right") - 1, 0, end)
    idx = jnp.minimum(i0 + jnp.arange(n + 1), end)
    ks = _at(path, "knot_s", idx)
    return KnotWindow(knots=_at(path, "knots", idx), index=idx, offset=s - ks[0],
                      knot_distances=ks[1:] - ks[0], state_length=ks[-1] - ks[0],
                      last_s=ks[-1], close_to_end=idx[-1] == end)


def truncate_at(path: AnyPath, s_end: Array) -> AnyPath:
    """The path ending at the first knot with arc position ``>= s_end`` (docs/method.md §5,
    ``set_u_end_index``). Jittable; the end is never before knot 1."""
    k = _searchsorted(path, "knot_s", s_end, "left")
    k = jnp.clip(k, 1, path.n_knots - 1)
    return path._replace(n_knots=(k + 1).astype(path.n_knots.dtype))


def sample_sub_path(path: AnyPath, key: Array, start_range: tuple[float, float] = (0.0, 0.8),
                    diff_min: float = 0.2, diff_max: float = 1.0) -> tuple[AnyPath, Array]:
    """Random episode sub-path (docs/method.md §5): ``u_start ~ U(start_range)``, ``u_end ~
    U(min(u_start + diff_min, 1), min(u_start + diff_max, 1))`` as fractions of the length; the
    end snaps to the next knot (:func:`truncate_at`). Returns ``(path, s_start)``, ``s_start``
    [rad] the arc position where the robot starts at rest. Jittable; vmap over keys/paths."""
    k_start, k_end = jax.random.split(key)
    u0 = jax.random.uniform(k_start, (), minval=start_range[0], maxval=start_range[1])
    lo = jnp.minimum(u0 + diff_min, 1.0)
    u1 = jax.random.uniform(k_end, (), minval=lo, maxval=jnp.minimum(u0 + diff_max, 1.0))
    length = path.length
    return truncate_at(path, u1 * length), u0 * length


def deviation(path: AnyPath, s0: Array, offsets: Array, points: Array,
              weights: Array | None = None) -> Array:
    """Deviation ``[k]`` between executed positions and the reference at equal arc length.

    docs/method.md §2.5: ``points [k, n]`` are the executed (action-spline) positions at arc lengths
    ``offsets [k]`` from the step's start; each is compared with the reference at ``s0 +
    offsets`` (the end knot beyond the end). Per sample ``|(q_ref - q) * w| * sqrt(n / sum w^2)``
    (plain L2 without ``weights [n]``). ``d_mean``/``d_max`` are the caller's mean/max over the
    valid samples.
    """
    return weighted_deviation(point_at(path, s0 + offsets), points, weights)


# ---------------------------------------------------------------------------------------------
# Path adjustment during motion (paper Fig. 4)
# ---------------------------------------------------------------------------------------------


def fit_clamped_natural(points: Array, count: Array, d0: Array) -> tuple[Array, Array, Array, Array]:
    """Cubic spline (JAX, fixed size) through ``points[:count]`` ``[P, n]`` with chord-length
    parameter, first derivative ``d0 [n]`` (per unit chord length) at the start and a natural end.

    Consecutive duplicate points (closer than ``DUPLICATE_DISTANCE``) are dropped first.
    Returns ``(points' [P, n], h [P-1], coeffs [P-1, 4, n], count')``: the kept points
    (compacted, padded with the last one) and their number ``count'``; segments
    ``>= count' - 1`` are padding (constant at the last point, ``h`` = 1).
    """
    p_max = points.shape[0]
    ar = jnp.arange(p_max)
    gap = jnp.linalg.norm(jnp.diff(points, axis=0), axis=-1)
    keep = jnp.concatenate([jnp.ones(1, bool), gap > DUPLICATE_DISTANCE]) & (ar < count)
    dest = jnp.where(keep, jnp.cumsum(keep) - 1, p_max)
    cnt = jnp.sum(keep)
    pts = jnp.zeros_like(points).at[dest].set(points, mode="drop")
    pts = jnp.where((ar < cnt)[:, None], pts, pts[jnp.maximum(cnt - 1, 0)])
    h_raw = jnp.linalg.norm(jnp.diff(pts, axis=0), axis=-1)                 # [P-1]
    seg_ok = ar[:-1] < cnt - 1
    h = jnp.where(seg_ok, h_raw, 1.0)
    delta = jnp.diff(pts, axis=0) / h[:, None]                              # [P-1, n]
    # tridiagonal system in the slopes D_i (rows i = 0..P-1)
    h_prev = jnp.concatenate([h[:1], h])        # h_{i-1} (row 0 unused)
    h_next = jnp.concatenate([h, h[-1:]])       # h_i     (last row unused)
    d_prev = jnp.concatenate([delta[:1], delta])
    d_next = jnp.concatenate([delta, delta[-1:]])
    interior = (ar > 0) & (ar < cnt - 1)
    last = (ar == cnt - 1) & (ar > 0)
    first = ar == 0
    dl = jnp.where(interior, h_next, jnp.where(last, 1.0, 0.0))
    dd = jnp.where(interior, 2.0 * (h_prev + h_next), jnp.where(last, 2.0, 1.0))
    du = jnp.where(interior, h_prev, 0.0)
    rhs = jnp.where(interior[:, None], 3.0 * (h_next[:, None] * d_prev + h_prev[:, None] * d_next),
                    jnp.where(last[:, None], 3.0 * d_prev, 0.0))
    rhs = jnp.where(first[:, None], d0[None, :], rhs)
    dl = dl.at[0].set(0.0)
    du = du.at[-1].set(0.0)
    slopes = jax.lax.linalg.tridiagonal_solve(dl, dd, du, rhs)             # [P, n]
    d_i, d_j = slopes[:-1], slopes[1:]
    hh = h[:, None]
    c2 = (3.0 * delta - 2.0 * d_i - d_j) / hh
    c3 = (d_i + d_j - 2.0 * delta) / (hh * hh)
    coeffs = jnp.stack([pts[:-1], d_i, c2, c3], axis=1)
    pad = jnp.stack([pts[:-1], jnp.zeros_like(d_i), jnp.zeros_like(d_i), jnp.zeros_like(d_i)], 1)
    coeffs = jnp.where(seg_ok[:, None, None], coeffs, pad)
    return pts, h, coeffs, cnt


def replace_ahead(path: Path, s: Array, new_knots: Array, n_new: Array | None = None) -> Path:
    """Replace the reference ahead of arc length ``s`` by a spline through ``new_knots[:n_new]``.

    Jittable, same shapes as ``path``. Everything before ``s`` (coefficients, arc table, knot arc
    positions) is kept bit for bit; the segment containing ``s`` is cut at ``s`` and the position
    ``q(s)`` becomes a knot; from there a new cubic spline (chord-length parameter, unit tangent of
    the old path at ``s`` as start slope, natural end) runs through the new knots, so position
    and direction are continuous at ``s``. ``new_knots [m, n]``; ``n_new`` (default ``m``).

    Knots that do not fit into ``max_knots`` are dropped from the far end (check ``n_knots``).
    ``s`` is clamped to ``[0, length]``.
    """
    kmax, n = path.knots.shape
    m_samples = path.samples_per_segment
    m_new = new_knots.shape[0]
    if new_knots.ndim != 2 or m_new < 1 or new_knots.shape[1] != n:
        raise ValueError(f"new_knots must be [m >= 1, {n}], got shape {new_knots.shape}")
    n_new = jnp.asarray(m_new if n_new is None else n_new, jnp.int32)
    dtype = path.table_s.dtype
    s = jnp.clip(jnp.asarray(s, dtype), 0.0, path.length)
    seg, t_s = locate(path, s)
    q_s = _horner(path.coeffs[seg], t_s, jnp)
    tangent = tangent_at(path, s)

    # tail spline: q(s) followed by the new knots, at most kmax - seg - 1 points
    tail_cap = jnp.minimum(n_new + 1, kmax - seg - 1)
    tail_pts = jnp.concatenate([q_s[None], jnp.asarray(new_knots, dtype)])   # [m+1, n]
    t_knots, th, tc, tcount = fit_clamped_natural(tail_pts, tail_cap, tangent)

    # assemble: segments < seg old, segment seg cut at t_s, segments seg+1+k from the tail
    kar = jnp.arange(kmax)
    sar = jnp.arange(kmax - 1)
    tail_seg = jnp.clip(sar - seg - 1, 0, m_new - 1)
    tail_knot = jnp.clip(kar - seg - 1, 0, m_new)
    h = jnp.where(sar < seg, path.h, jnp.where(sar == seg, t_s, th[tail_seg]))
    coeffs = jnp.where((sar < seg)[:, None, None] | (sar == seg)[:, None, None], path.coeffs,
                       tc[tail_seg])
    knots = jnp.where((kar <= seg)[:, None], path.knots, t_knots[tail_knot])
    n_knots = (seg + 1 + tcount).astype(path.n_knots.dtype)

    # arc table: keep entries up to the start of segment seg, recompute the rest
    pieces, dtds0, dtds_end = _segment_arc(coeffs, h, m_samples, jnp)
    tj = jnp.arange(path.table_s.shape[0])
    first = seg * m_samples
    inc = jnp.where(tj[:-1] >= first, pieces.reshape(-1), 0.0)
    table_new = path.table_s[first] + jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(inc)])
    table_s = jnp.where(tj <= first, path.table_s, table_new)
    dtds_all = jnp.concatenate([dtds0.reshape(-1), dtds_end[-1:]])
    # the last valid table point is a segment end: use the end slope of the segment before it
    n_valid = (n_knots - 1) * m_samples
    dtds_all = dtds_all.at[n_valid].set(dtds_end[jnp.maximum(n_knots - 2, 0)])
    table_dtds = jnp.where(tj < first, path.table_dtds, dtds_all)
    # padding beyond the end: constant arc length
    table_s = jnp.where(tj <= n_valid, table_s, table_s[n_valid])
    knot_s = jnp.where(kar < n_knots, table_s[kar * m_samples], table_s[n_valid])
    return Path(knots, n_knots, knot_s, h, coeffs, table_s, table_dtds)
