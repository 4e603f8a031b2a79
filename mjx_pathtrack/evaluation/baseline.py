"""TOPP-RA baseline (paper 000 Table VI): time-optimal durations of the evaluated sub-paths.

For each episode, a joint-space cubic spline (natural, chord-length parameterised) through the
start point and the remaining knots of the episode's reference up to its end is parameterised
time-optimally by TOPP-RA (``toppra``) under the same per-joint velocity and acceleration limits
as the policy, starting and ending at rest. Jerk is not limited (TOPP-RA cannot), so the baseline
is a lower bound the jerk-limited policy cannot reach; the paper reports the policy/TOPP-RA
duration ratio (1.27 for the iiwa).
"""

from __future__ import annotations

import logging

import numpy as np

from mjx_pathtrack.core import spline as S

#: consecutive knots closer than this [rad] are merged
MIN_KNOT_DISTANCE = 1e-6


def episode_knots(path: S.Path, s_start: float) -> np.ndarray:
    """Knots ``[K, m]`` of one episode: the start point at arc length ``s_start`` [rad] of the
    (single, unbatched) reference ``path``, then every knot after it up to the path's end."""
    n = int(path.n_knots)
    knots = np.asarray(path.knots, np.float64)[:n]
    knot_s = np.asarray(path.knot_s, np.float64)[:n]
    start = np.asarray(S.point_at(path, s_start), np.float64)
    rest = knots[knot_s > s_start + MIN_KNOT_DISTANCE]
    out = [start]
    for k in rest:
        if np.linalg.norm(k - out[-1]) > MIN_KNOT_DISTANCE:
            out.append(k)
    return np.asarray(out)


def toppra_duration(knots: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> float:
    """Time-optimal duration [s] from rest to rest along the spline through ``knots [K, m]`` with
    ``|v| <= vel [m]`` [rad/s] and ``|a| <= acc [m]`` [rad/s^2]; 0 for a path without motion;
    NaN if TOPP-RA fails."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    logging.getLogger("toppra").setLevel(logging.ERROR)
    knots = np.asarray(knots, np.float64)
    if len(knots) < 2:
        return 0.0
    ss = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
    path = ta.SplineInterpolator(ss, knots, bc_type="natural")
    vel, acc = np.asarray(vel, np.float64), np.asarray(acc, np.float64)
    constraints = [constraint.JointVelocityConstraint(np.stack([-vel, vel], 1)),
                   constraint.JointAccelerationConstraint(np.stack([-acc, acc], 1))]
    instance = algo.TOPPRA(constraints, path, parametrizer="ParametrizeConstAccel")
    trajectory = instance.compute_trajectory(0.0, 0.0)
    return float(trajectory.duration) if trajectory is not None else float("nan")


def bang_bang_duration(length: float, vel: float, acc: float) -> float:
    """Analytic rest-to-rest time [s] of a straight segment of ``length`` with speed ``vel`` and
    acceleration ``acc`` limits: trapezoidal ``L/v + v/a`` if ``L >= v^2/a``, else triangular
    ``2 sqrt(L/a)``."""
    if length >= vel * vel / acc:
        return length / vel + vel / acc
    return 2.0 * float(np.sqrt(length / acc))


def baseline_durations(paths: S.Path, s_start: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """TOPP-RA durations ``[B]`` [s] of the episodes of a stacked reference batch ``paths [B]``
    starting at ``s_start [B]``, with the path joints' limits ``vel, acc [m]``."""
    import jax

    out = np.empty(len(s_start))
    for b in range(len(s_start)):  # offline, one TOPP-RA problem per episode
        path = jax.tree.map(lambda x: x[b], paths)
        out[b] = toppra_duration(episode_knots(path, float(s_start[b])), vel, acc)
    return out


def toppra_columns(env, paths: S.Path, s_start: np.ndarray, stop_time_s: np.ndarray) -> dict[str, np.ndarray]:
    """The per-episode TOPP-RA columns of an evaluation table: ``toppra_duration_s [B]`` of the
    episodes ``paths [B]`` from ``s_start [B]`` under the environment's path-joint limits, and
    ``ratio_to_toppra [B]``, the episodes' ``stop_time_s [B]`` over it."""
    pj = np.asarray(env.path_joints)
    durations = baseline_durations(paths, s_start, np.asarray(env.limits.vel)[pj], np.asarray(env.limits.acc)[pj])
    return {"toppra_duration_s": durations, "ratio_to_toppra": duration_ratio(stop_time_s, durations)}


def duration_ratio(policy_duration: np.ndarray, baseline: np.ndarray) -> np.ndarray:
    """Per-episode policy/TOPP-RA duration ratio (NaN where either is unknown or 0)."""
    policy_duration, baseline = np.asarray(policy_duration, float), np.asarray(baseline, float)
    ok = np.isfinite(policy_duration) & np.isfinite(baseline) & (baseline > 0)
    return np.where(ok, policy_duration / np.where(ok, baseline, 1.0), np.nan)


def jerk_limited_durations(paths: S.Path, s_start: np.ndarray, vel: np.ndarray, acc: np.ndarray, jerk: np.ndarray,
                           cache=None, workers: int = 1) -> np.ndarray:
    """Jerk-limited time-optimal durations ``[B]`` [s] (TOPP3 of ``copp-py``,
    :mod:`mjx_pathtrack.evaluation.jerk_optimum`) of the same episodes as :func:`baseline_durations`, with
    the path joints' velocity, acceleration and jerk limits ``[m]``; ``cache``: a JSON file of
    durations already solved (~1 s per 7-joint path otherwise), ``workers``: processes."""
    import jax

    from mjx_pathtrack.evaluation import jerk_optimum

    problems = []
    for b in range(len(s_start)):
        path = jax.tree.map(lambda x: x[b], paths)
        problems.append((episode_knots(path, float(s_start[b])), vel, acc, jerk))
    return jerk_optimum.durations(problems, cache=cache, workers=workers)
