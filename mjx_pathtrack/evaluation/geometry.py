"""Distances between executed motion and reference curves (NumPy, float64): a point's distance
from a polyline (exact, KD-tree accelerated for long curves), the angle between rotations, and a
polyline sampled at equal arc length.
Used by the evaluation's whole-path deviations (:mod:`mjx_pathtrack.evaluation.rollout`)."""

from __future__ import annotations

import numpy as np

#: arc-length spacing [rad] of the samples of the whole executed path (docs/method.md §6)
SAMPLE_SPACING = 0.01


def rotation_angle(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Angle [rad] between rotations ``[..., 3, 3]`` (= 2 arccos |<q1, q2>| of the quaternions)."""
    cos = (np.einsum("...ij,...ij->...", r1, r2) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def polyline_distance(points: np.ndarray, curve: np.ndarray) -> np.ndarray:
    """Distance from each of ``points [M, d]`` to the polyline through ``curve [R, d]`` (its
    nearest point on any segment; ``R = 1``: the distance to that point). Same units as the
    inputs; returns ``[M]``."""
    points, curve = np.asarray(points, np.float64), np.asarray(curve, np.float64)
    if len(curve) == 1:
        return np.linalg.norm(points - curve[0], axis=-1)
    if len(curve) <= 64:
        return _segment_distance(points, curve, np.arange(len(curve) - 1)[None])
    # exact with a KD-tree: a segment whose endpoints are both further than d + L/2 (L: the
    # longest segment) cannot be nearer than a distance d already found; the segments next to the
    # k nearest vertices are checked, and every point whose k-th vertex is not that far is
    # checked against all segments
    from scipy.spatial import cKDTree

    k = min(16, len(curve))
    dist, idx = cKDTree(curve).query(points, k=k)
    seg = np.concatenate([np.clip(idx - 1, 0, len(curve) - 2), np.clip(idx, 0, len(curve) - 2)], axis=1)
    best = _segment_distance(points, curve, seg)
    half = 0.5 * np.linalg.norm(np.diff(curve, axis=0), axis=-1).max()
    unsure = dist[:, -1] <= best + half
    if unsure.any():
        best[unsure] = _segment_distance(points[unsure], curve, np.arange(len(curve) - 1)[None])
    return best


def _segment_distance(points: np.ndarray, curve: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance ``[M]`` from each of ``points [M, d]`` to the nearest of the polyline segments
    ``segments [M or 1, S]`` (indices ``i``: from ``curve[i]`` to ``curve[i + 1]``), in chunks."""
    out = np.empty(len(points))
    chunk = max(1, 2_000_000 // max(segments.shape[1], 1))
    for i in range(0, len(points), chunk):
        p = points[i:i + chunk]
        sg = segments if segments.shape[0] == 1 else segments[i:i + chunk]
        a, ab = curve[sg], curve[sg + 1] - curve[sg]                       # [m, S, d]
        length2 = np.maximum(np.einsum("msd,msd->ms", ab, ab), 1e-30)
        t = np.clip(np.einsum("msd,msd->ms", p[:, None] - a, ab) / length2, 0.0, 1.0)
        out[i:i + chunk] = np.linalg.norm(p[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)
    return out


def sample_executed(points: np.ndarray, path_joints: np.ndarray, spacing: float = SAMPLE_SPACING
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Samples of an executed polyline ``points [P, n]`` every ``spacing`` of path-joint arc
    length from the start (start excluded; a motion shorter than ``spacing`` gives its end point).
    Returns ``(offsets [M] rad, positions [M, n])`` (linear interpolation between sub-steps)."""
    seg = np.linalg.norm(np.diff(points[:, path_joints], axis=0), axis=-1)
    keep = np.concatenate([[True], seg > 0])
    points = points[keep]
    cum = np.concatenate([[0.0], np.cumsum(seg[seg > 0])])
    total = cum[-1]
    count = int(np.floor(total / spacing + 1e-9))
    offsets = spacing * np.arange(1, count + 1) if count else np.array([total])
    if len(points) == 1:
        return offsets, np.repeat(points, len(offsets), 0)
    return offsets, np.stack([np.interp(offsets, cum, points[:, j]) for j in range(points.shape[1])], -1)
