"""Ball-balancing dataset: joint paths along which the iiwa's plate stays horizontal (docs/paths.md §3, §5).

The papers' ball-balancing paths (``industrial/ball_balancing``: 12/14/19 knots, 3.2/3.8/5.1 rad,
knot spacing 0.3) were recorded from an agent whose recording code is not released; here they are
built from Cartesian curves:

1. a start pose with the plate level (random base rotation ``q1``, shoulder/elbow ``q2, q4``,
   wrist ``q6 = q4 - q2`` so the plate normal points up, random flange yaw ``q7``);
2. a smooth Cartesian curve of the plate centre: a natural cubic spline through the start point
   and ``waypoints`` random points in a box around it (in the frame turned by ``q1``), sampled
   every ``cartesian_step`` metres;
3. orientation-constrained inverse kinematics along it (damped least squares in MuJoCo,
   warm-started from the previous point): plate centre on the curve, plate normal vertical
   (the two horizontal components of the normal are driven to 0), yaw left free;
4. the joint path is resampled by distance every ``resampling_distance`` = 0.3 rad
   (:func:`mjx_pathtrack.core.spline.resample`, no curvature step) and cut at the first knot where
   the knot polyline reaches a random length drawn from a triangular distribution on
   ``length_range`` (mode at the lower end: mean ~3.8 rad as in the papers' set); it is accepted only if the fitted spline keeps the plate level within
   ``max_tilt_deg`` at points every 0.01 rad of arc length and stays inside the joint limits
   shrunk by ``limit_margin``.

:data:`REFLECTION_VECTORS` (``config.json`` key ``reflection_vectors``, docs/paths.md §5) multiply
the joint positions of a path element-wise; each is a mirror of the arm in a vertical plane (or
two of them), so a reflected path keeps the plate level and stays inside the symmetric iiwa
limits: 4x data augmentation (:func:`reflect_paths`).

Deterministic for a seed (NumPy ``Generator``; MuJoCo kinematics in float64).
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from mjx_pathtrack.core import spline

#: docs/paths.md §5: identity, all joints negated, z-axis joints negated, y-axis joints negated
REFLECTION_VECTORS = ((1.0,) * 7, (-1.0,) * 7, (-1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0),
                      (1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0))
PLATE_SITE = "plate"


@dataclasses.dataclass(frozen=True)
class BallPathConfig:
    """Generation settings (lengths in m, angles in rad unless noted)."""

    length_range: tuple[float, float] = (3.2, 5.1)  # joint-path length [rad], triangular, mode at min
    resampling_distance: float = 0.3  # rad
    waypoints: int = 10
    box: tuple[float, float, float] = (0.18, 0.22, 0.15)  # half extents of the waypoint box [m]
    cartesian_step: float = 0.002  # m
    q1_range: float = 1.5
    q2_range: tuple[float, float] = (0.3, 0.9)
    q4_range: tuple[float, float] = (-1.6, -0.8)
    q7_range: float = 1.5
    # start poses: |q4| at least this [rad] (a straight elbow is singular for the level-plate IK)
    min_elbow: float = 0.0
    # start poses: plate centre at least this high [m] above the base and this far from its axis
    min_height: float | None = None
    min_radius: float = 0.0
    max_tilt_deg: float = 0.5  # acceptance bound along the fitted spline [deg]
    max_position_error: float = 1e-3  # IK acceptance [m]
    limit_margin: float = 0.05  # rad inside the position limits
    ik_iterations: int = 3
    ik_damping: float = 1e-3
    max_attempts_per_path: int = 60


def whole_workspace() -> BallPathConfig:
    """Start poses over the iiwa's whole level-plate workspace: base rotation, shoulder and elbow
    of either sign (``q4`` in [-2, 2], ``|q4| >= 0.2``; ``q2`` in [-1.9, 1.9]), the plate
    centre from 8 cm off the base axis to full reach and at least 10 cm above the base; the
    papers' generator (the defaults) covers ``q2`` in [0.3, 0.9], ``q4`` in [-1.6, -0.8] and,
    with the reflections, the plate 0.43-0.70 m from the base axis."""
    return dataclasses.replace(BallPathConfig(), q1_range=2.8, q2_range=(-1.9, 1.9), q4_range=(-2.0, 2.0),
                               min_elbow=0.2, min_height=0.1, min_radius=0.08)


class PlateKinematics:
    """Plate-centre position, normal and their Jacobians of a robot with a ``plate`` site
    (``robots.load_robot('iiwa_ball')``), MuJoCo C in float64."""

    def __init__(self, robot):
        self.robot = robot
        self.model = robot.mj_model
        self.data = mujoco.MjData(self.model)
        self.data.qpos[:] = robot.qpos0
        self.site = self.model.site(PLATE_SITE).id
        self.adr = np.asarray(robot.qpos_adr)
        self.dof = np.asarray(robot.dof_adr)
        self._jp = np.zeros((3, self.model.nv))
        self._jr = np.zeros((3, self.model.nv))

    def pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(centre [3] m, rotation [3, 3])`` of the plate site (surface centre, z = normal)."""
        self.data.qpos[self.adr] = q
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def tilt_deg(self, q: np.ndarray) -> np.ndarray:
        """Angle [deg] between the plate normal and the world z axis for ``q [..., 7]``."""
        q = np.asarray(q, np.float64)
        flat = q.reshape(-1, q.shape[-1])
        out = np.array([np.degrees(np.arccos(np.clip(self.pose(x)[1][2, 2], -1.0, 1.0))) for x in flat])
        return out.reshape(q.shape[:-1])

    def residual_jacobian(self, q: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual ``[5]`` = (centre - target, normal_x, normal_y) and its Jacobian ``[5, 7]``."""
        pos, rot = self.pose(q)
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_jacSite(self.model, self.data, self._jp, self._jr, self.site)
        normal = rot[:, 2]
        skew = np.array([[0.0, -normal[2], normal[1]], [normal[2], 0.0, -normal[0]], [-normal[1], normal[0], 0.0]])
        jn = -skew @ self._jr[:, self.dof]  # d normal = omega x normal
        res = np.concatenate([pos - target, normal[:2]])
        return res, np.concatenate([self._jp[:, self.dof], jn[:2]])


def _start_pose(rng: np.random.Generator, cfg: BallPathConfig, pos_max: np.ndarray,
                kin: "PlateKinematics | None" = None) -> np.ndarray | None:
    """A level-plate start pose (module docstring, step 1), None if it misses the config's
    bounds (wrist limit, elbow, plate height and distance from the base axis)."""
    q2 = rng.uniform(*cfg.q2_range)
    q4 = rng.uniform(*cfg.q4_range)
    q6 = q4 - q2  # joint 4 turns about -y: the plate tilt about y is q2 - q4 + q6
    if abs(q6) > pos_max[5] - 4 * cfg.limit_margin or abs(q4) < cfg.min_elbow:
        return None
    q = np.array([rng.uniform(-cfg.q1_range, cfg.q1_range), q2, 0.0, q4, 0.0, q6,
                  rng.uniform(-cfg.q7_range, cfg.q7_range)])
    if kin is not None and (cfg.min_height is not None or cfg.min_radius > 0):
        centre, _ = kin.pose(q)
        if (cfg.min_height is not None and centre[2] < cfg.min_height) or np.hypot(*centre[:2]) < cfg.min_radius:
            return None
    return q


def _cartesian_curve(rng: np.random.Generator, cfg: BallPathConfig, start: np.ndarray, yaw: float) -> np.ndarray:
    """Points ``[P, 3]`` every ``cartesian_step`` m along a natural cubic spline from ``start``
    through random waypoints in a box around it (box axes turned by ``yaw`` about z)."""
    c, s = np.cos(yaw), np.sin(yaw)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = rng.uniform(-1.0, 1.0, (cfg.waypoints, 3)) * np.asarray(cfg.box)
    points = np.concatenate([start[None], start + local @ turn.T])
    fit = spline.fit_spline(points)
    return fit.point_at(np.arange(0.0, fit.length, cfg.cartesian_step))


def track_curve(kin: PlateKinematics, q0: np.ndarray, curve: np.ndarray, cfg: BallPathConfig,
                lo: np.ndarray, hi: np.ndarray, max_length: float | None = None) -> np.ndarray | None:
    """Joint positions ``[P', 7]`` along the plate-centre points ``curve [P, 3]`` [m] (``curve[0]``
    the start's), the plate kept level (damped least squares, warm start from ``q0``), stopped
    once the joint path is ``max_length`` [rad] long; None if IK fails or a limit ``[lo, hi]`` is
    hit first, or (``max_length`` given) the curve ends before that length."""
    q = q0.copy()
    out = [q.copy()]
    length = 0.0
    eye = np.eye(5)
    for target in curve[1:]:
        for _ in range(cfg.ik_iterations):
            res, jac = kin.residual_jacobian(q, target)
            q = q - jac.T @ np.linalg.solve(jac @ jac.T + cfg.ik_damping * eye, res)
        res, _ = kin.residual_jacobian(q, target)
        if np.linalg.norm(res[:3]) > cfg.max_position_error or np.any(q < lo) or np.any(q > hi):
            return None
        length += float(np.linalg.norm(q - out[-1]))
        out.append(q.copy())
        if max_length is not None and length >= max_length:
            return np.asarray(out)
    return None if max_length is not None else np.asarray(out)


def path_tilt_deg(kin: PlateKinematics, knots: np.ndarray, spacing: float = 0.01) -> np.ndarray:
    """Plate tilt [deg] along the natural cubic spline through ``knots`` every ``spacing`` rad."""
    return _tilt_along(kin, knots, spacing)[2]


def _tilt_along(kin: PlateKinematics, knots: np.ndarray, spacing: float):
    """``(fit, s, tilt)``: the spline through ``knots``, arc positions every ``spacing`` rad (end
    included) and the plate tilt [deg] there."""
    fit = spline.fit_spline(knots)
    s = spline.distance_positions(fit, spacing)
    return fit, s, kin.tilt_deg(fit.point_at(s))


def check_level(kin: PlateKinematics, knots: np.ndarray, max_tilt_deg: float = BallPathConfig.max_tilt_deg,
                name: str = "path", spacing: float = 0.01) -> float:
    """The largest plate tilt [deg] along the spline through ``knots [K, 7]`` (every ``spacing``
    rad); a tilt above ``max_tilt_deg`` raises :class:`~mjx_pathtrack.paths.datasets.DatasetError`
    naming the path, the knot nearest the worst point and the tilt (a ball path must keep the
    plate level, docs/paths.md §5)."""
    from mjx_pathtrack.paths.datasets import DatasetError

    fit, s, tilt = _tilt_along(kin, knots, spacing)
    worst = int(np.argmax(tilt))
    if tilt[worst] > max_tilt_deg:
        knot = int(np.argmin(np.abs(fit.knot_s - s[worst])))
        raise DatasetError(f"{name}: the plate tilts {tilt[worst]:.2f} deg near knot {knot} (arc {s[worst]:.3f} rad; "
                           f"a ball path keeps it level within {max_tilt_deg:g} deg)")
    return float(tilt[worst])


def ball_paths(robot, n_paths: int, seed: int, cfg: BallPathConfig = BallPathConfig()) -> tuple[list[np.ndarray], dict]:
    """``n_paths`` knot arrays ``[K_i, 7]`` (deterministic for ``seed``) and generation counts."""
    rng = np.random.default_rng(seed)
    kin = PlateKinematics(robot)
    lim = robot.limits
    pos_max = np.asarray(lim.pos_max, np.float64)
    lo = np.asarray(lim.pos_min, np.float64) + cfg.limit_margin
    hi = pos_max - cfg.limit_margin
    paths: list[np.ndarray] = []
    counts = {"attempts": 0, "rejected_ik_or_limits": 0, "rejected_tilt": 0}
    a, b = cfg.length_range
    while len(paths) < n_paths:
        if counts["attempts"] >= cfg.max_attempts_per_path * n_paths:
            raise RuntimeError(f"only {len(paths)} of {n_paths} ball paths after {counts['attempts']} attempts: {counts}")
        counts["attempts"] += 1
        q0 = _start_pose(rng, cfg, pos_max, kin)
        target_length = rng.triangular(a, a, b)
        if q0 is None:
            counts["rejected_ik_or_limits"] += 1
            continue
        start, _ = kin.pose(q0)
        curve = _cartesian_curve(rng, cfg, start, q0[0])
        dense = track_curve(kin, q0, curve, cfg, lo, hi, 1.25 * target_length + cfg.resampling_distance)
        if dense is None:
            counts["rejected_ik_or_limits"] += 1
            continue
        knots = spline.resample(dense, distance=cfg.resampling_distance, curvature_distance=None)
        polyline = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
        if polyline[-1] < target_length:
            counts["rejected_ik_or_limits"] += 1
            continue
        knots = knots[:int(np.argmax(polyline >= target_length)) + 1]
        fit = spline.fit_spline(knots)
        s = np.append(np.arange(0.0, fit.length, 0.01), fit.length)
        points = fit.point_at(s)
        if np.any(points < lo - cfg.limit_margin) or np.any(points > hi + cfg.limit_margin) or \
                kin.tilt_deg(points).max() > cfg.max_tilt_deg:
            counts["rejected_tilt"] += 1
            continue
        paths.append(knots)
    return paths, counts


def reflect_paths(paths, vectors=REFLECTION_VECTORS) -> list[np.ndarray]:
    """Every path times every reflection vector (element-wise), path-major: ``len(paths) * len(vectors)``."""
    vecs = np.asarray(vectors, np.float64)
    if vecs.ndim != 2:
        raise ValueError(f"reflection vectors must be [k, n_joints], got shape {vecs.shape}")
    out = []
    for p in paths:
        p = np.asarray(p, np.float64)
        if p.shape[-1] != vecs.shape[1]:
            raise ValueError(f"reflection vectors have {vecs.shape[1]} joints, a path has {p.shape[-1]}")
        out.extend(p * v for v in vecs)
    return out


#: ``workspace`` name -> the start-pose settings of :func:`generate_ball_dataset`
WORKSPACES = {"papers": BallPathConfig, "whole": whole_workspace}


def generate_ball_dataset(robot: str = "iiwa", num_train: int = 200, num_test: int = 200, seed: int = 0,
                          root=None, overwrite: bool = False, dt: float = 0.1,
                          cfg: BallPathConfig | None = None, workspace: str = "papers"):
    """Write ``<root>/<robot>/ball_balancing/{train,test}.npz, config.json`` (train split from
    ``seed``, test from ``seed + 1``). ``robot`` names the dataset folder (the iiwa); the plate
    kinematics come from ``iiwa_ball``. ``cfg``: the generator's settings, by default those of
    ``workspace`` (:data:`WORKSPACES`: ``"papers"``, the papers' start poses, or ``"whole"``,
    :func:`whole_workspace`). Returns the directory."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots import registry as robots

    if cfg is None:
        if workspace not in WORKSPACES:
            raise datasets.DatasetError(f"unknown ball workspace {workspace!r}; known: {', '.join(WORKSPACES)}")
        cfg = WORKSPACES[workspace]()

    if robot != "iiwa":
        raise datasets.DatasetError(f"ball_balancing paths exist for the iiwa only, not {robot!r}")
    directory = datasets.dataset_dir(robot, "ball_balancing", root)
    if (directory / "config.json").exists() and not overwrite:
        raise datasets.DatasetError(f"{directory} exists (use overwrite=True / --overwrite to replace it)")
    loaded = robots.load_robot("iiwa_ball", dt=dt)
    splits, counts = {}, {}
    for split, count, split_seed in (("train", num_train, seed), ("test", num_test, seed + 1)):
        if count > 0:
            splits[split], counts[split] = ball_paths(loaded, count, split_seed, cfg)
            datasets.save_split(directory / f"{split}.npz", splits[split])
    config = dict(format_version=datasets.FORMAT_VERSION, robot=robot, kind="ball_balancing", n_joints=7,
                  joint_names=list(loaded.joint_names),
                  max_dis_between_knots=datasets.max_dis_between_knots(splits.values()),
                  num_train=num_train, num_test=num_test, resampling_distance=cfg.resampling_distance,
                  curvature_sampling_distance=None, reflection_vectors=[list(v) for v in REFLECTION_VECTORS],
                  source={"type": "level_plate_cartesian_curves", "seed": seed, "scene": "iiwa_ball",
                          "settings": dataclasses.asdict(cfg), "counts": counts})
    datasets.write_config(directory / "config.json", config)
    return directory
