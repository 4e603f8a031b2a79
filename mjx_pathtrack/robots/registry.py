"""Robot registry: URDF -> MuJoCo/MJX model, joint limits, target points and forward kinematics.

``load_robot(name, **options)`` builds a :class:`Robot` for one of :data:`ROBOTS`:

=============  ======  ==========================================================================
name           joints  model
=============  ======  ==========================================================================
iiwa           7       ``assets/iiwa7/iiwa7.urdf`` (this project's KUKA LBR iiwa 7 R800)
iiwa_ball      7       iiwa + plate + free ball (see :mod:`mjx_pathtrack.robots.ball_scene`)
armar6         17      ``armar6_front`` (PyPI ``armar``, CC BY-NC 4.0; extra ``humanoids``)
armar4         18      ``armar4_fixed_hands_and_legs`` (legs welded, fixed base)
armar4_legs    30      ``armar4_fixed_hands``: 12 leg + 18 upper-body joints, floating base on a floor
armar4_standing 18     ``armar4_fixed_hands`` with the 12 leg joints welded at 0 (their initial pose):
                       18 upper-body joints, floating base on a floor (the fixed-legs balance task)
=============  ======  ==========================================================================

Simulation model (all robots): time step ``sim_dt`` (default 1/240 s, the papers' PyBullet
step, i.e. 24 setpoints per 0.1 s decision step; the fixed-legs balance task uses 1/80 s); each controlled joint has a position actuator
(ctrl = setpoint position) and a velocity actuator (ctrl = setpoint velocity, like the papers'
``targetVelocities``), so ``ctrl = [q_set, v_set]`` (:meth:`Robot.ctrl`, which also states the
timing convention). Gains are set per joint
from the joint-space inertia at the initial pose (``kp = M w^2``, ``kv = 2 zeta M w``; ``w`` 400 rad/s
at 1/240 s, ``w * sim_dt`` constant at other steps) and the
integrator is ``implicitfast`` so the large velocity gains are integrated implicitly. There is no
gravity compensation: the servos are stiff enough that gravity moves the joints by < 1e-4 rad,
and ``gravcomp`` would cost ~15 % of a batched MJX step. Joint-limit
constraints are off; contacts exist only where the scene needs them (ball-plate, feet-floor), and
the iiwa alone runs with contacts and constraints disabled.

Units: rad, rad/s (m, m/s for ARMAR-6's prismatic torso), s, kg, m.
"""

from __future__ import annotations

import dataclasses
import importlib.util
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
import mujoco
import numpy as np
from mujoco import mjx

from mjx_pathtrack.robots import ball_scene, iiwa
from mjx_pathtrack.core.limits import JointLimits
from mjx_pathtrack.robots.urdf_import import UrdfJoint, link_mesh_vertices, load_urdf, urdf_to_spec
from mjx_pathtrack.robots.scene import (FOOT_LINKS, SOLE_SOLREF, SOLVER_ITERATIONS, _add_floor_contacts, _add_pelvis_site,
                                        _add_servos, _add_target_sites, _configure_solver, _height_above_floor,
                                        _tune_servos)

Array = jax.Array

#: top-level asset folder: <repo>/assets (works for an editable install and from the repo root)
ASSETS_DIR = Path(__file__).resolve().parents[2] / "assets"
IIWA_URDF = ASSETS_DIR / "iiwa7" / "iiwa7.urdf"

#: the papers' position safety buffer subtracted from URDF limits [rad or m] (docs/limits.md §3)
POS_BUFFER = 0.035
#: decision step [s] (docs/limits.md §3)
DECISION_DT = 0.1
#: simulation step [s]: the papers' PyBullet step
SIM_DT = 1.0 / 240.0
#: servo bandwidth [rad/s] at the papers' physics step :data:`SIM_DT`, and damping ratio of the joint
#: controllers. At another physics step ``sim_dt`` the default bandwidth keeps ``omega * sim_dt``
#: (5/3): the position gain is integrated explicitly, so a coarser step needs a softer servo
#: (measured on ARMAR-4 against PyBullet: at 120 Hz 400 rad/s topples it on 40 % of the time-optimal
#: paths where PyBullet's falls on 15 %; 200 rad/s agrees as well as 240 Hz does)
SERVO_OMEGA = 400.0
SERVO_ZETA = 1.0
#: ``armar4_standing``'s sole contact (time constant [s], damping ratio; MuJoCo's default 0.02, 1):
#: softer than the default, standing in for the give of the servo-held legs that welding removes.
#: Picked among 0.02-0.08 s and damping 0.5-1 against PyBullet on 200 fast motions
#: (``scripts/armar4_pybullet_fidelity.py --model armar4_standing``, seeds 0 and 7): same
#: fall/no-fall in 94 % / 96 %, peak-tilt ratio 0.88 / 0.86 (the default contact: 91 % / 96 %, 0.61 / 0.61)
STANDING_SOLE_SOLREF = (0.025, 1.0)
HUMANOIDS_EXTRA = 'armar (CC BY-NC 4.0) is not installed: install the extra "humanoids", e.g. pip install -e ".[humanoids]"'


@dataclasses.dataclass(frozen=True)
class _Spec:
    """Static description of a registry entry. ``armature`` [kg m^2 or kg]: added joint inertia,
    standing in for the reflected rotor inertia of geared joints (not in the URDFs); it keeps the
    lightest joints (e.g. the iiwa's wrist) from dominating the servo stability."""

    urdf: Callable[[], Path]
    n_joints: int
    acc: Callable[[str], float]  # joint name -> acceleration limit [rad/s^2 or m/s^2]
    target_links: tuple[str, ...]
    path_joint: Callable[[str], bool] = lambda name: True
    floating: bool = False
    ball: bool = False
    gravcomp: bool = False  # measured: body gravcomp costs ~15 % of a batched MJX step
    armature: float = 0.0
    welded: Callable[[str], bool] = lambda name: False  # URDF joints removed: their child links rigid at 0
    sole_solref: tuple[float, float] = SOLE_SOLREF  # floating robots: the soles' contact (time constant [s], damping ratio)
    solver_iterations: int = SOLVER_ITERATIONS  # Newton iterations of a scene with contacts


def _armar_urdf(robot_name: str) -> Callable[[], Path]:
    def path() -> Path:
        if importlib.util.find_spec("armar") is None:
            raise ImportError(HUMANOIDS_EXTRA)
        import armar

        return Path(armar.get_path_to_urdf_file(robot_name))

    return path


def _armar4_acc(name: str) -> float:
    """docs/limits.md §3: legs 3.0; torso yaw 7, pitch 4.5; arm sho1 7.5, other arm joints 15."""
    if name.startswith("leg_"):
        return 3.0
    if name == "torso_yaw_joint":
        return 7.0
    if name == "torso_pitch_joint":
        return 4.5
    return 7.5 if name.startswith("arm_sho1_joint") else 15.0


ROBOTS: dict[str, _Spec] = {
    "iiwa": _Spec(lambda: IIWA_URDF, 7, lambda n: float(iiwa.ACC[iiwa.JOINT_NAMES.index(n)]), ("iiwa_link_ee",),
                  armature=0.1),
    "iiwa_ball": _Spec(lambda: IIWA_URDF, 7, lambda n: float(iiwa.ACC[iiwa.JOINT_NAMES.index(n)]), ("iiwa_link_ee",),
                       ball=True, armature=0.1, solver_iterations=ball_scene.ITERATIONS),
    "armar6": _Spec(_armar_urdf("armar6_front"), 17, lambda n: 15.0, ("hand_fixed_r0", "hand_fixed_r1"),
                    armature=0.1),
    "armar4": _Spec(_armar_urdf("armar4_fixed_hands_and_legs"), 18, _armar4_acc, ("arm_wri2_r0", "arm_wri2_r1"),
                    armature=0.1),
    "armar4_legs": _Spec(_armar_urdf("armar4_fixed_hands"), 30, _armar4_acc, ("arm_wri2_r0", "arm_wri2_r1"),
                         path_joint=lambda n: not n.startswith("leg_"), floating=True,
                         armature=0.1),
    # welded legs lack the give of servo-held ones: a softer sole contact stands in for it
    # (STANDING_SOLE_SOLREF; docs/results.md "ARMAR-4 against the papers' simulator")
    "armar4_standing": _Spec(_armar_urdf("armar4_fixed_hands"), 18, _armar4_acc, ("arm_wri2_r0", "arm_wri2_r1"),
                             floating=True, armature=0.1, welded=lambda n: n.startswith("leg_"),
                             sole_solref=STANDING_SOLE_SOLREF),
}

_OPTIONS = {"dt": DECISION_DT, "jerk_factor": 1.0, "sim_dt": SIM_DT, "pos_buffer": POS_BUFFER,
            "servo_omega": None, "servo_zeta": SERVO_ZETA}


@dataclasses.dataclass(frozen=True, eq=False)
class Robot:
    """A loaded robot (see module docstring). ``n`` = number of controlled joints.

    Attributes:
        name: registry name.
        mj_model: compiled ``mujoco.MjModel``; ``mjx_model``: the same on device (``mjx.put_model``).
        joint_names: ``n`` controlled joints, in ``JointLimits`` order.
        limits: :class:`JointLimits` ``[n]`` (URDF position limits minus ``pos_buffer``, URDF
            velocities, accelerations from docs/limits.md §3, jerk ``jerk_factor * 2 a / dt``).
        path_mask: bool ``[n]``: joints whose positions the reference path specifies.
        target_sites: names of the MuJoCo sites used as FK target points (TCP / fingertips).
        q0: ``[n]`` initial joint positions (0 clipped into the limits) [rad].
        qpos0: ``[nq]`` full initial ``qpos`` (floating base pose and ball included).
        qpos_adr, dof_adr: ``[n]`` int: where each controlled joint lives in ``qpos`` / ``qvel``.
        site_ids: ``[k]`` int MuJoCo ids of ``target_sites``.
        dt: decision step [s]; n_substeps: physics steps per decision step.
        floating: True if the root has a free joint (``qpos[0:7]``).
    """

    name: str
    mj_model: mujoco.MjModel
    mjx_model: Any
    joint_names: tuple[str, ...]
    limits: JointLimits
    path_mask: np.ndarray
    target_sites: tuple[str, ...]
    q0: np.ndarray
    qpos0: np.ndarray
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    site_ids: np.ndarray
    dt: float
    n_substeps: int
    floating: bool
    _cache: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def _check_q(self, q, what: str = "q"):
        shape = np.shape(q)
        if len(shape) == 0 or shape[-1] != self.n_joints:
            raise ValueError(f"{self.name}: {what} must have shape [..., {self.n_joints}] "
                             f"(joints {self.joint_names[0]} .. {self.joint_names[-1]}), got {shape}")

    def qpos(self, q: Array) -> Array:
        """Full ``qpos [..., nq]`` from joint positions ``q [..., n]`` (rest as in ``qpos0``). Pure JAX."""
        self._check_q(q)
        q = jnp.asarray(q, jnp.float32)
        base = jnp.broadcast_to(jnp.asarray(self.qpos0, jnp.float32), q.shape[:-1] + self.qpos0.shape)
        return base.at[..., self.qpos_adr].set(q)

    def ctrl(self, q_set: Array, v_set: Array) -> Array:
        """Actuator controls ``[..., 2n]`` = ``[q_set, v_set]`` for one physics step.

        Timing convention (what the tracking accuracy of 1e-3 rad is measured with): for the
        physics step from ``t`` to ``t + sim_dt``, ``q_set`` is the setpoint position at ``t``
        (the servo compares it with the current position) and ``v_set`` the setpoint velocity at
        ``t + sim_dt/2``; after the step, ``qpos`` then matches the setpoint at ``t + sim_dt``.
        Feeding the end-of-step setpoint instead makes the robot lead by ``sim_dt * v``.
        """
        self._check_q(q_set, "q_set")
        self._check_q(v_set, "v_set")
        return jnp.concatenate([jnp.asarray(q_set), jnp.asarray(v_set)], axis=-1)

    def fk(self, q: Array) -> tuple[Array, Array]:
        """Forward kinematics of the target points, pure JAX (jit/vmap/grad friendly).

        ``q [..., n]`` joint positions (a floating base stays at its initial pose, i.e.
        static-base FK) -> ``(pos [..., k, 3] in m, rot [..., k, 3, 3])`` in the world frame,
        ``k = len(target_sites)``; ``rot`` columns are the site axes.
        """
        self._check_q(q)
        q = jnp.asarray(q, jnp.float32)
        batch = q.shape[:-1]
        data = self._fk_data()
        sites = jnp.asarray(self.site_ids)

        def one(qi):
            d = mjx.kinematics(self.mjx_model, data.replace(qpos=self.qpos(qi)))
            return d.site_xpos[sites], d.site_xmat[sites].reshape(-1, 3, 3)

        pos, rot = jax.vmap(one)(q.reshape((-1, self.n_joints)))
        k = len(self.target_sites)
        return pos.reshape(batch + (k, 3)), rot.reshape(batch + (k, 3, 3))

    def _fk_data(self):
        if "fk_data" not in self._cache:
            self._cache["fk_data"] = mjx.make_data(self.mjx_model)
        return self._cache["fk_data"]

    def mj_data(self) -> mujoco.MjData:
        """A fresh ``MjData`` at ``qpos0`` with ``ctrl`` holding ``q0`` and forward kinematics done."""
        data = mujoco.MjData(self.mj_model)
        data.qpos[:] = self.qpos0
        data.ctrl[:] = np.concatenate([self.q0, np.zeros(self.n_joints)])
        mujoco.mj_forward(self.mj_model, data)
        return data

    def mjx_data(self):
        """``mjx.Data`` at ``qpos0`` with ``ctrl`` holding ``q0`` (for ``jax.vmap`` over a batch)."""
        return mjx.put_data(self.mj_model, self.mj_data())


def known_robots() -> tuple[str, ...]:
    return tuple(ROBOTS)


def load_robot(name: str, **options) -> Robot:
    """Load a registry robot (see module docstring).

    Options: ``dt`` decision step [s] (0.1), ``jerk_factor`` (1.0; jerk = factor * 2 a / dt),
    ``sim_dt`` physics step [s] (1/240), ``pos_buffer`` [rad] subtracted from URDF position limits
    (0.035), ``servo_omega`` [rad/s] (default :data:`SERVO_OMEGA` ``* SIM_DT / sim_dt``) and
    ``servo_zeta`` of the joint servos.
    Raises ``ValueError`` for unknown names/options, ``ImportError`` naming the ``humanoids``
    extra when an ARMAR robot is asked for without ``armar`` installed.
    """
    if name not in ROBOTS:
        raise ValueError(f"unknown robot {name!r}; known robots: {', '.join(ROBOTS)}")
    unknown = set(options) - set(_OPTIONS)
    if unknown:
        raise ValueError(f"unknown option(s) {sorted(unknown)} for load_robot; known: {sorted(_OPTIONS)}")
    opts = {**_OPTIONS, **options}
    if not opts["sim_dt"] > 0:
        raise ValueError(f"sim_dt must be > 0 s, got {opts['sim_dt']}")
    n_substeps = int(round(opts["dt"] / opts["sim_dt"]))
    if n_substeps < 1 or abs(n_substeps * opts["sim_dt"] - opts["dt"]) > 1e-9:
        raise ValueError(f"dt={opts['dt']} must be a whole multiple of sim_dt={opts['sim_dt']}")
    if opts["servo_omega"] is None:
        opts["servo_omega"] = SERVO_OMEGA * SIM_DT / opts["sim_dt"]
    return _build(name, ROBOTS[name], opts, n_substeps)


def _build(name: str, spec_def: _Spec, opts: dict, n_substeps: int) -> Robot:
    urdf_path = spec_def.urdf()
    urdf = load_urdf(urdf_path)
    conv = urdf_to_spec(urdf, urdf_path, floating=spec_def.floating, armature=spec_def.armature)
    spec = conv.spec
    welded = [j for j in conv.joints if spec_def.welded(j.name)]
    for j in welded:
        if not j.lower <= 0.0 <= j.upper:
            raise ValueError(f"{name}: cannot weld joint {j.name!r} at 0, outside its limits [{j.lower}, {j.upper}]")
    joints = [j for j in conv.joints if not spec_def.welded(j.name)]
    if len(joints) != spec_def.n_joints:
        raise ValueError(f"{name}: {urdf_path} has {len(joints)} movable joints, expected {spec_def.n_joints}")
    spec.modelname = name
    spec.option.timestep = opts["sim_dt"]
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    _add_target_sites(spec, spec_def.target_links, conv.far_points)
    if spec_def.gravcomp:
        for body in spec.bodies[1:]:
            body.gravcomp = 1.0
    if spec_def.ball:
        ball_scene.add_plate_and_ball(spec)
    if spec_def.floating:
        _add_floor_contacts(spec, {link: link_mesh_vertices(urdf, urdf_path, link) for link in FOOT_LINKS},
                            solref=spec_def.sole_solref)
        _add_pelvis_site(spec)
    for j in welded:  # after the soles are placed on the feet: the compiler fuses rigid links into their parent
        spec.delete(spec.joint(j.name))
    _configure_solver(spec, has_contacts=spec_def.ball or spec_def.floating, iterations=spec_def.solver_iterations)
    names = [j.name for j in joints]
    _add_servos(spec, names)
    model = spec.compile()
    q0 = np.clip(0.0, [j.lower for j in joints], [j.upper for j in joints])
    qpos_adr = np.array([model.jnt_qposadr[model.joint(n).id] for n in names])
    dof_adr = np.array([model.jnt_dofadr[model.joint(n).id] for n in names])
    qpos0 = model.qpos0.copy()
    qpos0[qpos_adr] = q0
    if spec_def.floating:
        qpos0[2] += _height_above_floor(model, qpos0)
    if spec_def.ball:
        qpos0 = ball_scene.ball_on_plate_qpos(model, qpos0)
    _tune_servos(model, qpos0, qpos_adr, dof_adr, np.array([j.lower for j in joints]),
                 np.array([j.upper for j in joints]), opts["servo_omega"], opts["servo_zeta"])
    limits = _joint_limits(name, joints, spec_def, opts)
    sites = tuple(f"target_{link}" for link in spec_def.target_links)
    return Robot(
        name=name, mj_model=model, mjx_model=mjx.put_model(model), joint_names=tuple(names), limits=limits,
        path_mask=np.array([spec_def.path_joint(n) for n in names]), target_sites=sites,
        q0=q0, qpos0=qpos0, qpos_adr=qpos_adr, dof_adr=dof_adr,
        site_ids=np.array([model.site(s).id for s in sites]), dt=float(opts["dt"]), n_substeps=n_substeps,
        floating=spec_def.floating,
    )


def _joint_limits(name: str, joints: list[UrdfJoint], spec_def: _Spec, opts: dict) -> JointLimits:
    """URDF position limits minus ``pos_buffer``, URDF velocities, registry accelerations. The iiwa
    with the default buffer uses :mod:`mjx_pathtrack.robots.iiwa` (the single source of its constants,
    which are the same numbers rounded to 5 digits as in docs/limits.md §3)."""
    names = tuple(j.name for j in joints)
    if name.startswith("iiwa") and opts["pos_buffer"] == POS_BUFFER:
        if names != iiwa.JOINT_NAMES:
            raise ValueError(f"{name}: URDF joints {names} differ from {iiwa.JOINT_NAMES}")
        return iiwa.joint_limits(opts["dt"], opts["jerk_factor"])
    lower = np.array([j.lower for j in joints]) + opts["pos_buffer"]
    upper = np.array([j.upper for j in joints]) - opts["pos_buffer"]
    vel = np.array([j.velocity for j in joints])
    bad = [n for n, v in zip(names, vel) if not v > 0]
    if bad:
        raise ValueError(f"{name}: joints without a URDF velocity limit: {bad}")
    acc = np.array([spec_def.acc(n) for n in names])
    return JointLimits.from_acc(lower, upper, vel, acc, opts["dt"], opts["jerk_factor"], names=names)


# ---------------------------------------------------------------------------------------------
# Self-collision check (dataset generation; MuJoCo C, not for the hot path)
# ---------------------------------------------------------------------------------------------







