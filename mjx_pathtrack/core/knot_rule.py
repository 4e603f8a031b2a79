"""The knot rule of a policy's training paths, applied to any curve (offline, NumPy, float64).

A policy observes the next N knots of its reference (docs/method.md §4), so it has learned
paths whose knots sit where its training data put them: curvature-based knots (docs/paths.md §3:
fit, resample every 0.1 rad of arc length, refit, knots at equal increments of 0.3 of the
integrated curvature) at most ``max_dis_between_knots`` apart, or distance-based ones (the ball
paths: every 0.3 rad). The same geometric curve given with other knots (a planner's dense
waypoints, sparse teach points, uneven spacing) looks unlike anything it trained on.
:func:`reknot` re-places the knots of a user's curve by the training rule, so that the policy
sees knots like its training knots whatever the spacing given; :func:`curve_distance` measures
how far the re-knotted curve lies from the user's.

Units: joint positions and arc lengths in rad (m for prismatic joints); integrated curvature is
dimensionless (``int |d^2 q / ds^2| ds``, docs/paths.md §3).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.spatial import cKDTree

from mjx_pathtrack.core.spline_fit import SplineFit, curvature_positions, distance_positions, fit_spline

#: a capped interval is split so that its parts are at most this share of ``max_spacing``: the
#: refitted spline's arc between two knots differs slightly from the chord-parameter positions
#: it was placed at
SPACING_SAFETY = 0.95
#: default sample spacing [rad] of :func:`curve_distance`
DISTANCE_STEP = 2e-3


@dataclasses.dataclass(frozen=True)
class KnotRule:
    """Where a policy's training paths have their knots (docs/paths.md §3).

    resampling_distance [rad]: the first stage places knots every this much arc length;
    curvature_distance: then, if not None, knots at equal increments of this much integrated
    curvature of the spline through those; max_spacing [rad]: no two consecutive knots further
    apart along the curve (the observation's scale, ``max_dis_between_knots``; None: no cap).
    """

    resampling_distance: float = 0.1
    curvature_distance: float | None = 0.3
    max_spacing: float | None = None

    def __post_init__(self):
        if not (math.isfinite(self.resampling_distance) and self.resampling_distance > 0):
            raise ValueError(f"resampling_distance must be a finite number > 0 [rad], got {self.resampling_distance}")
        if self.curvature_distance is not None and not (math.isfinite(self.curvature_distance)
                                                         and self.curvature_distance > 0):
            raise ValueError(f"curvature_distance must be a finite number > 0 or None, got {self.curvature_distance}")
        if self.max_spacing is not None and not (math.isfinite(self.max_spacing) and self.max_spacing > 0):
            raise ValueError(f"max_spacing must be a finite number > 0 [rad] or None, got {self.max_spacing}")

    @classmethod
    def of_dataset(cls, config: dict) -> "KnotRule":
        """The rule of a dataset from its ``config.json`` (``paths.datasets``): the generation
        parameters where it records them (top level or its ``source``), the papers' curvature
        rule otherwise; ``max_spacing`` is its ``max_dis_between_knots``."""
        source = config.get("source") or {}
        source = source if "resampling_distance" in source or "curvature_sampling_distance" in source else {}
        pick = lambda key, default: config.get(key, source.get(key, default))  # noqa: E731
        curvature = pick("curvature_sampling_distance", 0.3)
        return cls(float(pick("resampling_distance", 0.1)), None if curvature is None else float(curvature),
                   float(config["max_dis_between_knots"]) if config.get("max_dis_between_knots") else None)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "KnotRule":
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown knot rule field(s) {sorted(unknown)}")
        return cls(**data)


def rule_positions(fit: SplineFit, rule: KnotRule, start_slope=None) -> tuple[SplineFit, np.ndarray]:
    """``(base, s [K'])``: the curve the rule's knots lie on and their arc positions [rad] on it
    (increasing, ``0`` and ``base.length`` included). With a curvature rule the base is the
    spline through the distance-stage knots, as in the dataset pipeline."""
    s = distance_positions(fit, rule.resampling_distance)
    if rule.curvature_distance is None:
        base = fit
    else:
        base = fit_spline(fit.point_at(s), fit.samples_per_segment, start_slope)
        s = curvature_positions(base, rule.curvature_distance)
    s = np.unique(s)   # a zero-curvature stretch repeats a level's position
    if rule.max_spacing is not None:
        s = cap_spacing(s, SPACING_SAFETY * rule.max_spacing)
    return base, s


def cap_spacing(s: np.ndarray, cap: float) -> np.ndarray:
    """Arc positions ``s [K]`` with every gap longer than ``cap`` split into equal parts of at
    most ``cap`` [rad] (the original positions kept)."""
    gaps = np.diff(s)
    parts = np.maximum(np.ceil(gaps / cap - 1e-12), 1).astype(int)
    pieces = [s[i] + gaps[i] * np.arange(parts[i]) / parts[i] for i in range(len(gaps))]
    return np.concatenate(pieces + [s[-1:]])


def reknot(knots, rule: KnotRule, start_slope=None) -> np.ndarray:
    """Knots ``[K', n]`` placed by ``rule`` on the natural cubic spline through ``knots [K, n]``
    (the user's curve; docs/paths.md §1; ``start_slope [n]``: with that first derivative at the
    start instead, see :func:`~spline_fit.fit_spline`). The first and last knot are kept exactly;
    the spline through the result is within :func:`curve_distance` of the user's curve.

    Raises ``ValueError`` for a non-2-D or non-finite array (:func:`~spline_fit.dedup_knots`)."""
    fit = fit_spline(knots, start_slope=start_slope)
    base, s = rule_positions(fit, rule, start_slope)
    out = base.point_at(s)
    out[0], out[-1] = fit.knots[0], fit.knots[-1]
    if rule.max_spacing is not None:   # the refit's arcs can exceed the placement's: split again
        for _ in range(3):
            refit = fit_spline(out, start_slope=start_slope)
            if np.diff(refit.knot_s).max() <= rule.max_spacing:
                break
            s = cap_spacing(refit.knot_s, SPACING_SAFETY * rule.max_spacing)
            out = refit.point_at(s)
            out[0], out[-1] = fit.knots[0], fit.knots[-1]
    return out


def dense_points(fit: SplineFit, step: float = DISTANCE_STEP) -> np.ndarray:
    """Points ``[P, n]`` of a fitted curve every ``step`` of arc length, both ends included."""
    count = max(int(np.ceil(fit.length / step)), 1)
    return fit.point_at(np.linspace(0.0, fit.length, count + 1))


def polyline_hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Hausdorff distance between the polylines through ``a [P, d]`` and ``b [Q, d]``:
    the largest distance of a vertex of either from the other polyline (nearest point on its
    segments). Same units as the inputs."""
    return max(_one_sided(a, b), _one_sided(b, a))


def _one_sided(points: np.ndarray, curve: np.ndarray) -> float:
    if len(curve) == 1:
        return float(np.linalg.norm(points - curve[0], axis=-1).max())
    _, nearest = cKDTree(curve).query(points)
    best = np.full(len(points), np.inf)
    for offset in (-1, 0):   # the segments before and after the nearest vertex
        i = np.clip(nearest + offset, 0, len(curve) - 2)
        a, ab = curve[i], curve[i + 1] - curve[i]
        t = np.clip(np.einsum("pd,pd->p", points - a, ab) / np.maximum(np.einsum("pd,pd->p", ab, ab), 1e-30), 0, 1)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * ab), axis=-1))
    return float(best.max())


def curve_distance(knots_a, knots_b, step: float = DISTANCE_STEP, fk=None, start_slope=None
                   ) -> tuple[float, float | None]:
    """``(joint [rad], Cartesian [m] or None)``: the largest distance between the natural cubic
    splines through ``knots_a`` and ``knots_b`` (symmetric Hausdorff distance of their points
    every ``step`` rad, each to the other's polyline; the polyline's sag adds at most
    ``~ curvature * step^2 / 8``). ``fk(q [P, n]) -> [P, T, 3]`` (target-point positions [m]):
    also the largest distance of any target point between the two curves' images. ``start_slope``:
    both curves start with that derivative (:func:`~spline_fit.fit_spline`)."""
    pa = dense_points(fit_spline(knots_a, start_slope=start_slope), step)
    pb = dense_points(fit_spline(knots_b, start_slope=start_slope), step)
    joint = polyline_hausdorff(pa, pb)
    if fk is None:
        return joint, None
    xa, xb = np.asarray(fk(pa), np.float64), np.asarray(fk(pb), np.float64)
    return joint, max(polyline_hausdorff(xa[:, t], xb[:, t]) for t in range(xa.shape[1]))
