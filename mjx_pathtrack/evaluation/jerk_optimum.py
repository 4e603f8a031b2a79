"""Jerk-limited time-optimal durations of reference paths (TOPP3, the PyPI package ``copp-py``).

TOPP-RA (:mod:`mjx_pathtrack.evaluation.baseline`) limits velocity and acceleration only, so it is a lower
bound that no jerk-limited motion reaches. TOPP3 parameterises the *same* path (the natural,
chord-length cubic spline through the knots) time-optimally under the velocity, acceleration
**and jerk** limits of every joint, rest to rest: the physical limit of a tracker that follows
the path exactly. (A tracker that may deviate from the path can be faster still.)

Method (all of it ``copp-py``'s: nothing is re-implemented here): the path's ``q, q', q'', q'''``
on ``stations`` equally spaced arc-length stations; ``topp2_ra`` (velocity and acceleration only,
agrees with toppra) gives a feasible seed; its profile becomes the first-order upper bound
(``amax_substitute``); then ``topp3_socp`` is solved ``passes`` times, each time linearising the
jerk constraints around the previous solution (adaptive linearisation with its ``b`` profile),
and ``s_to_t_topp3`` integrates the profile into the duration. The limits hold at the stations;
between them the cubic spline's piecewise-constant ``q'''`` and the linearisation leave the
duration within ~1 % of the analytic jerk-limited optimum of a straight segment
(``tests/evaluation/test_baseline.py``).

This module imports neither JAX nor the rest of the package, so worker processes start fast.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

#: arc-length stations of the TOPP3 grid (at most; see MIN_SPACING)
STATIONS = 1000
#: smallest station spacing [rad]: finer grids of short paths make Clarabel stall
#: (InsufficientProgress below ~1e-4 rad), without changing the duration
MIN_SPACING = 5e-4
#: SOCP solves, each re-linearising the jerk constraints around the previous profile
PASSES = 4
#: bump when the method changes: cached durations of another version are not reused
VERSION = 1


def topp3_duration(knots: np.ndarray, vel: np.ndarray, acc: np.ndarray, jerk: np.ndarray,
                   stations: int = STATIONS, passes: int = PASSES) -> float:
    """Jerk-limited time-optimal duration [s] from rest to rest along the natural cubic spline
    (chord-length parameter) through ``knots [K, m]`` [rad] under ``|v| <= vel``, ``|a| <= acc``,
    ``|jerk| <= jerk`` (each ``[m]``, rad/s, rad/s^2, rad/s^3). 0 for a path without motion; NaN
    if the solver fails on every grid. Grid: ``stations`` (fewer for a short path, at least
    ``MIN_SPACING`` apart); if the solver fails, again on half as many, down to 100."""
    from scipy.interpolate import CubicSpline

    knots = np.asarray(knots, np.float64)
    if len(knots) < 2:
        return 0.0
    ss = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
    if ss[-1] <= 0:
        return 0.0
    spline = CubicSpline(ss, knots, bc_type="natural")
    n = int(min(stations, max(100, np.ceil(ss[-1] / MIN_SPACING) + 1)))
    while True:
        duration = _solve(spline, np.linspace(0.0, ss[-1], n), vel, acc, jerk, passes)
        if np.isfinite(duration) or n <= 100:
            return duration
        n = max(100, n // 2)


def _solve(spline, s: np.ndarray, vel, acc, jerk, passes: int) -> float:
    """TOPP2 seed, then ``passes`` re-linearised TOPP3-SOCP solves on the station grid ``s``;
    the duration of the last pass that converged (NaN if none did)."""
    import copp_py as copp

    vel, acc, jerk = (np.asarray(x, np.float64) for x in (vel, acc, jerk))
    robot = copp.Robot(spline.c.shape[-1])
    robot.append_s(s)
    robot.set_q(spline(s), spline(s, 1), spline(s, 2), 0, dddq=spline(s, 3))
    robot.add_velocity_limits(vel, -vel, start_idx_s=0, length=len(s))
    robot.add_acceleration_limits(acc, -acc, start_idx_s=0, length=len(s))
    robot.add_jerk_limits(jerk, -jerk, start_idx_s=0, length=len(s))
    try:
        seed = np.asarray(copp.solver.topp2_ra.solve(
            copp.solver.topp2_ra.Problem(robot.constraints, idx_s_interval=(0, len(s) - 1), a_boundary=(0.0, 0.0))))
    except copp.CoppError:
        return float("nan")
    robot.constraints.amax_substitute(seed, 0)
    a_lin, b_lin, duration = seed, None, float("nan")
    for _ in range(int(passes)):
        try:
            problem = copp.solver.topp3_socp.Problem(robot.constraints, a_lin, idx_s_start=0, a_boundary=(0.0, 0.0),
                                                     b_boundary=(0.0, 0.0), num_stationary_max=1,
                                                     b_linearization=b_lin)
            profile = copp.solver.topp3_socp.solve(problem)
        except copp.CoppError:
            break  # keep the last pass that converged
        duration = float(copp.interpolation.s_to_t_topp3(s, profile)[0])
        a_lin, b_lin = np.asarray(profile.a), np.asarray(profile.b)
    return duration


def jerk_limited_rest_to_rest(length: float, vel: float, acc: float, jerk: float) -> float:
    """Analytic time-optimal rest-to-rest duration [s] of a straight segment of ``length`` with
    velocity, acceleration and jerk limits (the test's known answer): the symmetric profile of
    jerk phases ``+J, 0, -J``, a cruise at the peak velocity, and the mirror image."""
    def accel_phase(v_peak):
        """(time, distance) from rest to v_peak at zero acceleration, fastest."""
        if v_peak >= acc * acc / jerk:  # the acceleration limit is reached
            t = v_peak / acc + acc / jerk
        else:
            t = 2.0 * np.sqrt(v_peak / jerk)
        return t, 0.5 * v_peak * t

    t, d = accel_phase(vel)
    if 2.0 * d <= length:
        return 2.0 * t + (length - 2.0 * d) / vel
    lo, hi = 0.0, vel  # bisect the peak velocity whose two phases cover the length
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if 2.0 * accel_phase(mid)[1] <= length else (lo, mid)
    return 2.0 * accel_phase(lo)[0]


def _key(knots, vel, acc, jerk, stations, passes) -> str:
    h = hashlib.sha1()
    for x in (knots, vel, acc, jerk):
        h.update(np.ascontiguousarray(np.asarray(x, np.float64)).tobytes())
    h.update(f"{stations},{passes},{VERSION}".encode())
    return h.hexdigest()


def default_cache() -> Path:
    """``$XDG_CACHE_HOME/mjx_pathtrack/topp3.json`` (``~/.cache`` if unset)."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "mjx_pathtrack" / "topp3.json"


def durations(problems: list[tuple], cache: Path | None = None, workers: int = 1,
              stations: int = STATIONS, passes: int = PASSES) -> np.ndarray:
    """:func:`topp3_duration` of every ``(knots, vel, acc, jerk)`` in ``problems`` ``[B]``, reusing
    and extending the JSON ``cache`` (keyed by the inputs and the method's settings; None: no
    cache), solving the new ones on ``workers`` processes."""
    from mjx_pathtrack.fileio import atomic_write_bytes

    keys = [_key(*p, stations, passes) for p in problems]
    known = {}
    if cache is not None and Path(cache).is_file():
        try:
            known = json.loads(Path(cache).read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            known = {}  # a corrupt cache is rebuilt
    todo = [i for i, k in enumerate(keys) if k not in known]
    if todo:
        args = [(*problems[i], stations, passes) for i in todo]
        if workers > 1 and len(todo) > 1:
            import multiprocessing

            with multiprocessing.get_context("spawn").Pool(workers) as pool:
                solved = pool.starmap(topp3_duration, args)
        else:
            solved = [topp3_duration(*a) for a in args]
        for i, value in zip(todo, solved):
            known[keys[i]] = value if np.isfinite(value) else None
        if cache is not None:
            atomic_write_bytes(Path(cache), json.dumps(known).encode())
    return np.asarray([np.nan if known[k] is None else known[k] for k in keys], np.float64)
