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

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core.reward import weighted_deviation
from mjx_pathtrack.core.spline_fit import (DUPLICATE_DISTANCE, SAMPLES_PER_SEGMENT, SplineFit, _horner, _locate, _segment_arc, fit_spline,
                                          searchsorted_row)
# the offline half, re-exported: ``spline.fit_spline``, ``spline.resample`` etc.
from mjx_pathtrack.core.spline_fit import (curvature_table, dedup_knots, distance_positions, resample,  # noqa: F401
                                          resample_by_curvature, resample_by_distance)

Array = jax.Array




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


def drop_behind(path: Path, s: Array) -> tuple[Path, Array]:
    """The same reference without the knots before the one at or before ``s`` [rad] (knot0 of
    the observation), arc positions shifted so that knot0 is at 0; returns ``(path', s')``, same
    array shapes (jittable). Keeps the capacity of a fixed-size path for knots ahead when the
    reference is adjusted often (:class:`~mjx_pathtrack.deploy.controller.OnlineTracker`)."""
    kmax = path.knots.shape[0]
    m = path.samples_per_segment
    end = path.n_knots - 1
    i0 = knot_window(path, s, 0).index[0]
    base = path.knot_s[i0]
    n_knots = path.n_knots - i0
    n_valid_old = end * m
    kar, sar, tar = jnp.arange(kmax), jnp.arange(kmax - 1), jnp.arange(path.table_s.shape[0])
    knots = path.knots[jnp.minimum(kar + i0, end)]
    knot_s = path.knot_s[jnp.minimum(kar + i0, end)] - base
    h = path.h[jnp.minimum(sar + i0, kmax - 2)]
    end_knot = path.knots[end]
    pad = jnp.zeros_like(path.coeffs[0]).at[0].set(end_knot)
    coeffs = jnp.where((sar < n_knots - 1)[:, None, None], path.coeffs[jnp.minimum(sar + i0, kmax - 2)], pad)
    ti = jnp.minimum(tar + i0 * m, n_valid_old)
    table_s = path.table_s[ti] - base
    table_dtds = path.table_dtds[ti]
    new = Path(knots, n_knots.astype(path.n_knots.dtype), knot_s, h, coeffs, table_s, table_dtds)
    return new, jnp.maximum(s - base, 0.0)
