"""Path families a user brings, made independently of the training generators (benchmarks only).

The training data come from :mod:`~mjx_pathtrack.paths.generate` (a random agent through the safe
action space) and :mod:`~mjx_pathtrack.paths.target` (goal-seeking motions between targets), both
curvature-knotted. The families here are how paths reach a robot elsewhere, each with its own
knot spacing, so that ``benchmarks/generalisation.py`` measures a policy on paths it never saw:

=====================  =========================================================================
``cartesian_lines``    a tool seam (welding, gluing): 2-4 straight Cartesian segments of 10-40 cm
                       with corners, IK every 5 mm (joint waypoints ~0.01-0.05 rad apart)
``cartesian_circles``  a circle or arc of the tool, radius 5-20 cm, in a random plane, IK every 5 mm
``pick_and_place``     2-3 cycles above pick, down, up, above place, down, up: sparse teach
                       points (IK solutions), down-and-up reversals at every pick and place
``planner_dense``      a smooth joint-space motion (random sums of sines) given as a motion
                       planner would: waypoints every 0.03 rad of arc length
``teach_points``       4-12 joint-space via points 0.3-1.0 rad apart (sparse teach-in)
``near_limits``        sine motions whose joints run to within 1 % of their position limits,
                       a few knots put on the URDF limits (beyond the model's by its buffer)
``level_plate``        (ball on plate, :data:`BALL_FAMILIES`) a tray carried level: the plate
                       centre along 2-4 horizontal straight segments or a horizontal arc, from
                       a random configuration levelled by IK (either elbow, any reach),
                       waypoints every 0.05 rad
=====================  =========================================================================

Every path is free of self-collision at samples every 0.01 rad (iiwa: :mod:`~mjx_pathtrack.robots.collision`)
and inside the model's position limits (``near_limits``: inside the URDF's). Deterministic for a
seed (NumPy ``Generator``). Cartesian families need a robot with one target site (the iiwa).
Units: rad, m.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from mjx_pathtrack.core.spline_fit import fit_spline
from mjx_pathtrack.paths.cartesian import MAX_JOINT_JUMP, SOLVE_SPACING, TRACK_IK, densify

#: Cartesian sample spacing of the IK families [m]
CARTESIAN_STEP = SOLVE_SPACING
#: arc spacing [rad] of the collision and limit checks
CHECK_STEP = 0.01


def _limits(robot, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(robot.limits.pos_min, np.float64)
    hi = np.asarray(robot.limits.pos_max, np.float64)
    span = hi - lo
    return lo + margin * span, hi - margin * span


def _ok(robot, knots: np.ndarray, lo: np.ndarray, hi: np.ndarray, collide) -> bool:
    """The spline through ``knots`` stays in ``[lo, hi]`` and (if ``collide``) free of self-collision."""
    fit = fit_spline(knots)
    q = fit.point_at(np.linspace(0.0, fit.length, max(int(fit.length / CHECK_STEP), 2) + 1))
    if np.any(q < lo - 1e-9) or np.any(q > hi + 1e-9):
        return False
    return not (collide is not None and np.asarray(collide(q)).any())


def _collide(robot):
    from mjx_pathtrack.robots.collision import in_collision

    return lambda q: in_collision(robot, q)


def _single_site(robot):
    if len(robot.target_sites) != 1 or not np.all(robot.path_mask):
        raise ValueError(f"{robot.name}: the Cartesian families need a robot with one target site whose joints are "
                         f"all path joints (the iiwa)")


def _ik_track(robot, points: list[np.ndarray], q0: np.ndarray) -> list[np.ndarray | None]:
    """Per path ``b`` the joint positions ``[P_b, n]`` along Cartesian ``points[b] [P_b, 3]``, each
    IK solve seeded with the path's previous solution (continuity), all paths solved together;
    None for a path with a point not reached or a solution jump (> :data:`MAX_JOINT_JUMP`)."""
    from mjx_pathtrack.paths import ik

    count = np.array([len(p) for p in points])
    padded = np.stack([np.concatenate([p, np.repeat(p[-1:], count.max() - len(p), 0)]) for p in points])
    q = np.asarray(q0, np.float64)
    ok = np.ones(len(points), bool)
    out = []
    for i in range(count.max()):
        sol = ik.solve_ik(robot, padded[:, i, None], q, **TRACK_IK)
        qn = np.asarray(sol.q, np.float64)
        live = i < count
        ok &= ~live | (np.asarray(sol.converged) & (np.max(np.abs(qn - q), axis=-1) <= MAX_JOINT_JUMP))
        q = np.where(ok[:, None], qn, q)
        out.append(q)
    out = np.stack(out, 1)
    return [out[b, :count[b]] if ok[b] else None for b in range(len(points))]


def _collect(count: int, what: str, candidate: Callable[[], np.ndarray | None]) -> list[np.ndarray]:
    """``count`` paths from ``candidate()`` (None: rejected), at most ``40 count`` tries."""
    paths = []
    for _ in range(40 * count):
        if len(paths) == count:
            return paths
        path = candidate()
        if path is not None:
            paths.append(path)
    if len(paths) == count:
        return paths
    raise RuntimeError(f"only {len(paths)} of {count} {what} paths after {40 * count} tries")


def _start(robot, rng, lo, hi, collide, tries: int = 200) -> np.ndarray:
    for _ in range(tries):
        q = rng.uniform(lo, hi)
        if collide is None or not bool(np.asarray(collide(q[None]))[0]):
            return q
    raise RuntimeError(f"{robot.name}: no collision-free configuration in {tries} tries")


def _tool(robot, q: np.ndarray) -> np.ndarray:
    from mjx_pathtrack.paths import ik

    return ik.target_positions(robot, q[None])[0, 0]


def _cartesian(robot, count: int, seed: int, curve: Callable, max_tries: int) -> list[np.ndarray]:
    _single_site(robot)
    rng = np.random.default_rng(seed)
    lo, hi = _limits(robot, 0.05)
    collide = _collide(robot)
    paths, tried = [], 0
    while len(paths) < count and tried < max_tries:
        batch = 2 * (count - len(paths)) + 2
        tried += batch
        q0 = np.stack([_start(robot, rng, lo, hi, collide) for _ in range(batch)])
        from mjx_pathtrack.paths import ik

        x0 = ik.target_positions(robot, q0)[:, 0]
        for start, q in zip(q0, _ik_track(robot, [curve(rng, x) for x in x0], q0)):
            if q is None or len(paths) == count:
                continue
            q = np.concatenate([start[None], q])
            if _ok(robot, q, lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo), collide):
                paths.append(q)
    if len(paths) < count:
        raise RuntimeError(f"only {len(paths)} of {count} paths after {tried} tries")
    return paths


def _polyline(rng, x0: np.ndarray) -> np.ndarray:
    corners = [x0]
    for _ in range(rng.integers(2, 5)):
        d = rng.normal(size=3)
        corners.append(corners[-1] + rng.uniform(0.10, 0.40) * d / np.linalg.norm(d))
    return densify(np.stack(corners), CARTESIAN_STEP)[0][1:]


def _circle(rng, x0: np.ndarray) -> np.ndarray:
    radius = rng.uniform(0.05, 0.20)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, rng.normal(size=3))
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    centre = x0 - radius * u   # the tool starts on the circle
    turns = rng.choice([0.5, 0.75, 1.0, 1.5])
    k = int(np.ceil(2 * np.pi * radius * turns / CARTESIAN_STEP))
    phi = 2 * np.pi * turns * np.arange(1, k + 1) / k
    return centre + radius * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w)


def cartesian_lines(robot, count: int, seed: int) -> list[np.ndarray]:
    """Tool seams: straight Cartesian segments with corners, IK every 5 mm (module docstring)."""
    return _cartesian(robot, count, seed, _polyline, 40 * count)


def cartesian_circles(robot, count: int, seed: int) -> list[np.ndarray]:
    """Tool circles and arcs, IK every 5 mm (module docstring)."""
    return _cartesian(robot, count, seed, _circle, 40 * count)


def pick_and_place(robot, count: int, seed: int, approach: float = 0.15) -> list[np.ndarray]:
    """Pick-and-place cycles as sparse teach points (module docstring); ``approach`` [m] above."""
    from mjx_pathtrack.paths import ik

    _single_site(robot)
    rng = np.random.default_rng(seed)
    lo, hi = _limits(robot, 0.05)
    collide = _collide(robot)
    paths = []
    for _ in range(40 * count):
        if len(paths) == count:
            return paths
        q = _start(robot, rng, lo, hi, collide)
        knots = []
        ok = True
        for _ in range(2 * rng.integers(2, 4)):   # picks and places, alternating
            spot = None
            for _ in range(20):
                cand = _tool(robot, rng.uniform(lo, hi))
                if 0.35 <= np.linalg.norm(cand[:2]) <= 0.7 and 0.05 <= cand[2] <= 0.45:
                    spot = cand
                    break
            if spot is None:
                ok = False
                break
            for x in (spot + [0, 0, approach], spot, spot + [0, 0, approach]):
                sol = ik.solve_ik(robot, x[None, None], q[None])
                if not bool(sol.converged[0]):
                    ok = False
                    break
                q = np.asarray(sol.q[0], np.float64)
                knots.append(q)
            if not ok:
                break
        if ok and _ok(robot, np.stack(knots), lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo), collide):
            paths.append(np.stack(knots))
    raise RuntimeError(f"only {len(paths)} of {count} pick-and-place paths")


def _sines(rng, lo: np.ndarray, hi: np.ndarray, duration: float, reach: float, dt: float = 1e-3) -> np.ndarray:
    """A smooth joint curve ``[T, n]``: per joint a centre and three random sines whose sum
    spans ``reach`` of the half range, sampled every ``dt`` s of a ``duration``."""
    n = len(lo)
    t = np.arange(0.0, duration + dt, dt)
    freq = rng.uniform(0.05, 0.35, (3, n))
    phase = rng.uniform(0, 2 * np.pi, (3, n))
    weight = rng.dirichlet(np.ones(3), n).T                      # [3, n], sums to 1 per joint
    wave = np.sum(weight[:, None] * np.sin(2 * np.pi * freq[:, None] * t[None, :, None] + phase[:, None]), 0)
    half = 0.5 * (hi - lo)
    amp = reach * half * rng.uniform(0.4, 1.0, n)
    centre = rng.uniform(lo + amp, hi - amp)
    return centre + amp * wave


def _arc_resample(q: np.ndarray, spacing: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(q, axis=0), axis=-1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.append(np.arange(0.0, cum[-1], spacing), cum[-1])
    return np.stack([np.interp(s, cum, q[:, j]) for j in range(q.shape[1])], -1)


def planner_dense(robot, count: int, seed: int, spacing: float = 0.03) -> list[np.ndarray]:
    """Smooth joint motions given as waypoints every ``spacing`` rad (module docstring)."""
    rng = np.random.default_rng(seed)
    lo, hi = _limits(robot, 0.05)
    collide = _collide(robot)
    pj = np.flatnonzero(np.asarray(robot.path_mask))

    def candidate():
        q = _sines(rng, lo, hi, rng.uniform(6.0, 14.0), 0.6)
        if collide is not None and np.asarray(collide(q[::50])).any():
            return None
        return _arc_resample(q[:, pj], spacing)

    return _collect(count, "planner-dense", candidate)


def teach_points(robot, count: int, seed: int) -> list[np.ndarray]:
    """Sparse joint-space via points, 0.3-1.0 rad apart (module docstring)."""
    rng = np.random.default_rng(seed)
    lo, hi = _limits(robot, 0.1)
    collide = _collide(robot)
    pj = np.flatnonzero(np.asarray(robot.path_mask))
    full_lo, full_hi = _limits(robot, 0.0)

    def candidate():
        q = [_start(robot, rng, lo, hi, collide)]
        for _ in range(rng.integers(3, 12)):
            d = rng.normal(size=len(lo))
            q.append(np.clip(q[-1] + rng.uniform(0.3, 1.0) * d / np.linalg.norm(d), lo, hi))
        knots = np.stack(q)
        return knots[:, pj] if _ok(robot, knots, full_lo, full_hi, collide) else None

    return _collect(count, "teach-point", candidate)


def near_limits(robot, count: int, seed: int, spacing: float = 0.1, buffer: float | None = None) -> list[np.ndarray]:
    """Sine motions running to within 1 % of the position limits, with the knots at a limit's
    extreme moved onto the URDF limit (``buffer`` [rad] beyond the model's; default the
    registry's :data:`~mjx_pathtrack.robots.registry.POS_BUFFER`) (module docstring)."""
    from mjx_pathtrack.robots.registry import POS_BUFFER

    buffer = POS_BUFFER if buffer is None else buffer
    rng = np.random.default_rng(seed)
    lo, hi = _limits(robot, 0.0)
    collide = _collide(robot)
    pj = np.flatnonzero(np.asarray(robot.path_mask))

    def candidate():
        q = _sines(rng, lo, hi, rng.uniform(3.0, 6.0), 0.6)
        hug = rng.choice(len(lo), size=min(3, len(lo)), replace=False)
        for j in hug:   # stretch the joint's motion to 99 % of its range
            span = q[:, j].max() - q[:, j].min()
            q[:, j] = lo[j] + 0.005 * (hi[j] - lo[j]) + (q[:, j] - q[:, j].min()) * 0.99 * (hi[j] - lo[j]) / span
        if collide is not None and np.asarray(collide(q[::50])).any():
            return None
        knots = _arc_resample(q, spacing)
        for j in hug:   # the extreme knots on the URDF limits
            knots[np.argmax(knots[:, j]), j] = hi[j] + buffer
            knots[np.argmin(knots[:, j]), j] = lo[j] - buffer
        return knots[:, pj]

    return _collect(count, "near-limit", candidate)


def _levelled_start(kin, rng, lo, hi, iterations: int = 60, damping: float = 1e-3) -> np.ndarray | None:
    """A random configuration in ``[lo, hi]`` turned level by damped least squares on the plate
    normal, the plate centre held (None: not level within 0.05 deg, or outside the limits)."""
    q = rng.uniform(lo, hi)
    target, _ = kin.pose(q)
    for _ in range(iterations):
        res, jac = kin.residual_jacobian(q, target)
        q = q - jac.T @ np.linalg.solve(jac @ jac.T + damping * np.eye(5), res)
    ok = np.all(q >= lo) and np.all(q <= hi) and float(kin.tilt_deg(q)) < 0.05
    return q if ok else None


def _horizontal_curve(rng, start: np.ndarray, step: float) -> np.ndarray:
    """Points ``[P, 3]`` every ``step`` m from ``start`` (excluded) in its horizontal plane: 2-4
    straight segments of 10-30 cm, or an arc of radius 5-20 cm over 90-270 deg."""
    if rng.random() < 0.5:
        corners = [start]
        for _ in range(rng.integers(2, 5)):
            phi = rng.uniform(0, 2 * np.pi)
            corners.append(corners[-1] + rng.uniform(0.10, 0.30) * np.array([np.cos(phi), np.sin(phi), 0.0]))
        pts = []
        for a, b in zip(corners[:-1], corners[1:]):
            k = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
            pts.append(a + (b - a) * np.arange(1, k + 1)[:, None] / k)
        return np.concatenate(pts)
    radius, phi0 = rng.uniform(0.05, 0.20), rng.uniform(0, 2 * np.pi)
    sweep = rng.choice([-1.0, 1.0]) * np.radians(rng.uniform(90, 270))
    centre = start - radius * np.array([np.cos(phi0), np.sin(phi0), 0.0])
    k = int(np.ceil(abs(sweep) * radius / step))
    phi = phi0 + sweep * np.arange(1, k + 1) / k
    return centre + radius * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)


def level_plate(robot, count: int, seed: int, spacing: float = 0.05) -> list[np.ndarray]:
    """Tray paths for the ball on the plate (module docstring): the plate level along horizontal
    lines and arcs, waypoints every ``spacing`` rad; each checked level (0.5 deg) along its
    spline and inside the limits shrunk by 0.05 rad. The iiwa's plate kinematics (``iiwa_ball``)."""
    from mjx_pathtrack.paths import ball
    from mjx_pathtrack.robots import registry as robots

    if robot.name not in ("iiwa", "iiwa_ball"):
        raise ValueError(f"{robot.name}: level-plate paths exist for the iiwa only")
    plate = robots.load_robot("iiwa_ball", dt=0.1)
    kin = ball.PlateKinematics(plate)
    rng = np.random.default_rng(seed)
    lo, hi = _limits(plate, 0.0)
    lo, hi = lo + 0.05, hi - 0.05
    cfg = ball.BallPathConfig()

    def candidate():
        q0 = _levelled_start(kin, rng, lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo))
        if q0 is None:
            return None
        centre, _ = kin.pose(q0)
        dense = ball.track_curve(kin, q0, np.concatenate([centre[None], _horizontal_curve(rng, centre, 0.002)]),
                                 cfg, lo, hi)
        if dense is None:
            return None
        knots = _arc_resample(dense, spacing)
        fit = fit_spline(knots)
        q = fit.point_at(np.linspace(0.0, fit.length, max(int(fit.length / CHECK_STEP), 2) + 1))
        if fit.length < 0.5 or np.any(q < lo) or np.any(q > hi) or kin.tilt_deg(q).max() > cfg.max_tilt_deg:
            return None
        return knots

    return _collect(count, "level-plate", candidate)


def papers_ball_region(robot, count: int, seed: int) -> list[np.ndarray]:
    """Ball paths of the training generator with the papers' start poses (:mod:`..paths.ball`,
    default :class:`~mjx_pathtrack.paths.ball.BallPathConfig`: ``q2`` in [0.3, 0.9], ``q4`` in
    [-1.6, -0.8]), path ``i`` multiplied by reflection vector ``i % 4``: the part of the
    workspace the papers' ball policies cover, for a policy trained on another part (not an
    independent generator: a region check)."""
    from mjx_pathtrack.paths import ball
    from mjx_pathtrack.robots import registry as robots

    if robot.name not in ("iiwa", "iiwa_ball"):
        raise ValueError(f"{robot.name}: level-plate paths exist for the iiwa only")
    paths, _ = ball.ball_paths(robots.load_robot("iiwa_ball", dt=0.1), count, seed)
    return [p * np.asarray(ball.REFLECTION_VECTORS[i % len(ball.REFLECTION_VECTORS)]) for i, p in enumerate(paths)]


#: family name -> ``generator(robot, count, seed) -> [K_i, n_path] knot arrays``
FAMILIES: dict[str, Callable] = {"cartesian_lines": cartesian_lines, "cartesian_circles": cartesian_circles,
                                 "pick_and_place": pick_and_place, "planner_dense": planner_dense,
                                 "teach_points": teach_points, "near_limits": near_limits}
#: the families of the ball-on-plate task (level plate along the whole path)
BALL_FAMILIES: dict[str, Callable] = {"level_plate": level_plate, "papers_ball_region": papers_ball_region}
