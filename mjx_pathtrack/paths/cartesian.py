"""Cartesian tool paths made joint-space paths: a weld seam, a glue bead or taught tool points,
given as positions of the robot's target point (the iiwa's TCP) in metres, become the joint path
the policies track (``python -m mjx_pathtrack.paths import FILE --cartesian``,
:meth:`~mjx_pathtrack.deploy.controller.OnlineTracker.set_cartesian_path`).

:func:`tool_path_to_joints` interpolates the waypoints every :data:`SOLVE_SPACING` m along the
straight lines between them and solves the position IK (:func:`~mjx_pathtrack.paths.ik.solve_ik`)
at each point, seeded with the previous solution, so the joint path is continuous (no jump to
another IK branch); the first waypoint is solved from ``q_start`` when given, else from a fixed
set of start configurations (the collision-free solution nearest the middle of the joint ranges).
Each solve point is checked: IK residual at most :data:`MAX_RESIDUAL`, no joint moving more than
:data:`MAX_JOINT_JUMP` from the previous point, no self-collision; the joints stay inside the
position limits by construction (the IK clips into them). A failure raises
:class:`~mjx_pathtrack.paths.datasets.DatasetError` naming the path, the waypoint and the cause.
Positions only: the IK has no orientation term, so a file with orientation columns is refused.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mjx_pathtrack.paths.datasets import DatasetError

#: largest distance [m] between neighbouring IK solves along a tool path
SOLVE_SPACING = 0.005
#: largest IK residual [m] of a solve point (the target point's distance from the tool path)
MAX_RESIDUAL = 1e-3
#: largest change [rad] of any joint between neighbouring solves; more means another IK branch
MAX_JOINT_JUMP = 0.15
#: start configurations tried for the first waypoint when no ``q_start`` is given
START_SEEDS = 64
#: IK settings of one solve seeded with the previous point's solution (5 mm away)
TRACK_IK = dict(iterations=30, damping=0.02, max_step=0.1)


@dataclasses.dataclass(frozen=True)
class JointPath:
    """A tool path's joint path: ``joints [P, n]`` [rad] at the ``P`` solve points,
    ``waypoint_rows [W]`` the row of each given waypoint, ``residual [P]`` [m] the IK residual
    at each solve point."""

    name: str
    joints: np.ndarray
    waypoint_rows: np.ndarray
    residual: np.ndarray

    def report_line(self) -> str:
        return (f"{self.name}: {len(self.waypoint_rows)} waypoints -> {len(self.joints)} IK points, residual max "
                f"{1000 * self.residual.max():.3f} mm, median {1000 * np.median(self.residual):.3f} mm")


def check_tool_path(points, name: str = "path") -> np.ndarray:
    """``points`` as float64 ``[W, 3]`` [m]; :class:`DatasetError` naming the path and waypoint
    for a wrong shape, fewer than 2 waypoints, NaN or inf, or orientation columns."""
    try:
        p = np.asarray(points, np.float64)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{name}: tool positions must be numbers ({e})") from None
    if p.ndim != 2 or p.shape[1] != 3:
        extra = (" (orientations are not supported: the IK solves tool positions only)"
                 if p.ndim == 2 and p.shape[1] > 3 else "")
        raise DatasetError(f"{name}: a tool path is [waypoints, 3] positions x, y, z in m, got shape {p.shape}{extra}")
    if len(p) < 2:
        raise DatasetError(f"{name}: a tool path needs at least 2 waypoints, got {len(p)}")
    bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))
    if bad.size:
        raise DatasetError(f"{name}: waypoint {bad[0]} is not finite: {p[bad[0]].tolist()}")
    return p


def densify(points: np.ndarray, spacing: float = SOLVE_SPACING) -> tuple[np.ndarray, np.ndarray]:
    """Points ``[P, 3]`` on the straight lines between ``points [W, 3]``, at most ``spacing``
    apart, every waypoint included; returns them and the row of each waypoint ``[W]``."""
    rows, out = [0], [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        k = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        out.append(a + (b - a) * np.arange(1, k + 1)[:, None] / k)
        rows.append(rows[-1] + k)
    return np.concatenate(out), np.asarray(rows)


def _first_solution(robot, target: np.ndarray, q_start, name: str) -> np.ndarray:
    from mjx_pathtrack.paths import ik
    from mjx_pathtrack.robots.collision import in_collision

    lo, hi = (np.asarray(x, np.float64) for x in (robot.limits.pos_min, robot.limits.pos_max))
    if q_start is not None:
        seeds = np.asarray(q_start, np.float64).reshape(1, -1)
        if seeds.shape[1] != robot.n_joints or not np.all(np.isfinite(seeds)):
            raise DatasetError(f"{name}: the start configuration must be {robot.n_joints} finite joint positions")
    else:
        rng = np.random.default_rng(0)
        seeds = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (START_SEEDS, robot.n_joints))
    sol = ik.solve_ik(robot, np.broadcast_to(target, (len(seeds), 1, 3)), seeds, iterations=200)
    q, err = np.asarray(sol.q, np.float64), np.asarray(sol.error, np.float64)
    ok = (err <= MAX_RESIDUAL) & ~np.asarray(in_collision(robot, q))
    if not ok.any():
        raise DatasetError(f"{name}: waypoint 0 ({_xyz(target)}) is not reachable without self-collision "
                           f"(IK residual {1000 * err.min():.1f} mm at best)")
    middle = 0.5 * (lo + hi)
    score = np.where(ok, np.max(np.abs(q - middle) / (hi - lo), axis=1), np.inf)
    return q[int(np.argmin(score))]


def _xyz(x) -> str:
    return ", ".join(f"{v:.4f}" for v in np.asarray(x)) + " m"


def tool_path_to_joints(robot, points, q_start=None, name: str = "path") -> JointPath:
    """The joint path ``[P, n]`` of a tool path ``points [W, 3]`` [m] of ``robot``'s one target
    point (module docstring); ``q_start [n]`` [rad]: the configuration to start from (e.g. the
    robot's current one), else the first waypoint is solved from :data:`START_SEEDS` seeds.
    :class:`DatasetError` names the waypoint where the path cannot be followed."""
    from mjx_pathtrack.paths import ik
    from mjx_pathtrack.robots.collision import in_collision

    if len(robot.target_sites) != 1:
        raise DatasetError(f"{robot.name}: Cartesian paths need a robot with one target point, it has "
                           f"{len(robot.target_sites)} ({', '.join(robot.target_sites)})")
    given = check_tool_path(points, name)
    dense, rows = densify(given)
    waypoint = np.searchsorted(rows, np.arange(len(dense)), side="right") - 1   # waypoint at or before each row
    q = _first_solution(robot, dense[0], q_start, name)
    joints, residual = [], []
    for i, target in enumerate(dense):
        sol = ik.solve_ik(robot, target[None, None], q[None], **TRACK_IK)
        q_new, err = np.asarray(sol.q, np.float64)[0], float(np.asarray(sol.error)[0])
        if err > MAX_RESIDUAL:
            raise DatasetError(f"{name}: waypoint {waypoint[i]} ({_xyz(given[waypoint[i]])}) cannot be followed: the "
                               f"tool misses {_xyz(target)} by {1000 * err:.1f} mm (out of reach or at a joint limit)")
        jump = np.abs(q_new - q)
        if i > 0 and jump.max() > MAX_JOINT_JUMP:
            j = int(np.argmax(jump))
            raise DatasetError(f"{name}: after waypoint {waypoint[i]} ({_xyz(given[waypoint[i]])}) joint "
                               f"{robot.joint_names[j]} jumps by {jump[j]:.3f} rad between two points "
                               f"{1000 * SOLVE_SPACING:.0f} mm apart (another IK branch or a singularity)")
        q = q_new
        joints.append(q)
        residual.append(err)
    joints = np.stack(joints)
    hit = np.asarray(in_collision(robot, joints))
    if hit.any():
        i = int(np.argmax(hit))
        raise DatasetError(f"{name}: the robot collides with itself after waypoint {waypoint[i]} "
                           f"({_xyz(given[waypoint[i]])})")
    return JointPath(name, joints, rows, np.asarray(residual))


def tool_paths_to_joints(robot, pairs, q_start=None) -> list[JointPath]:
    """:func:`tool_path_to_joints` of each ``(name, points)`` of a user file
    (:func:`~mjx_pathtrack.paths.datasets.read_user_paths`)."""
    return [tool_path_to_joints(robot, points, q_start, name) for name, points in pairs]
