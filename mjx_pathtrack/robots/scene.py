"""What a robot's MuJoCo model gets beyond its URDF: target sites, floor contacts under the soles,
solver settings, position servos and their tuning, and the height above the floor.

Helpers of :func:`mjx_pathtrack.robots.registry.load_robot`; MuJoCo/NumPy, run once per model
(not in the step). Units: m, rad, s.
"""

from __future__ import annotations

import mujoco
import numpy as np


def _add_target_sites(spec: mujoco.MjSpec, links: tuple[str, ...], far_points: dict) -> None:
    """Sites ``target_<link>``: at the link origin (iiwa TCP link) or, for a link with a fitted
    mesh (ARMAR hands), at the far end of its fitted primitive (fingertip approximation)."""
    for link in links:
        body = spec.body(link)
        if body is None:
            raise ValueError(f"target link {link!r} not in the model")
        pos = far_points.get(link, np.zeros(3))
        body.add_site(name=f"target_{link}", pos=list(pos), size=[0.01, 0, 0], group=4)


#: links whose collision meshes are the feet's soles
FOOT_LINKS = ("leg_ank2_r0", "leg_ank2_r1")
SOLE_THICKNESS = 0.01  # m
#: a foot mesh's vertices within this height [m] of its lowest one (standing at qpos0) form the sole
SOLE_BAND = 0.002
#: the soles' and floor's contact (time constant [s], damping ratio): MuJoCo's default
SOLE_SOLREF = (0.02, 1.0)
#: Newton iterations of the contact scenes (measured: the vmapped solver dominates the step cost)
SOLVER_ITERATIONS = 4


def _add_floor_contacts(spec: mujoco.MjSpec, foot_vertices: dict[str, np.ndarray],
                        solref: tuple[float, float] = SOLE_SOLREF) -> None:
    """A floor plane at z = 0 and, per foot, a flat sole box under the bottom of the foot's
    collision mesh: the world-aligned bounds (at ``qpos0``, all joints 0, feet flat) of the
    vertices ``foot_vertices[link] [k, 3]`` (link frame) within :data:`SOLE_BAND` of the lowest
    one, its underside at that lowest point. These are the only geoms touching the floor. Soles
    and floor get the contact's ``solref`` (time constant [s], damping ratio; MuJoCo mixes the
    two geoms' values).

    The sole is the support polygon of the papers' simulator, which collides the meshes: there
    the heel and toe links hover 3-4 mm above the floor and touch it only when the foot tilts,
    and the mesh's underside (x -0.055..0.148 m on ARMAR-4) carries the robot. A sole fitted to
    the bounds of ankle, heel and toes (this model until the comparison with PyBullet, x
    -0.065..0.196 m) made the robot far too hard to tip over
    (``scripts/armar4_pybullet_fidelity.py``)."""
    probe = spec.copy().compile()
    data = mujoco.MjData(probe)
    mujoco.mj_kinematics(probe, data)  # qpos0: all joints at 0, feet flat
    for link in FOOT_LINKS:
        if link not in foot_vertices:
            raise ValueError(f"foot link {link!r}: no collision mesh vertices")
        body = probe.body(link).id
        rot, origin = data.xmat[body].reshape(3, 3), data.xpos[body]
        world = np.asarray(foot_vertices[link], np.float64) @ rot.T + origin
        bottom = world[world[:, 2] <= world[:, 2].min() + SOLE_BAND]
        lo, hi = bottom.min(axis=0), bottom.max(axis=0)
        half = [(hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2, SOLE_THICKNESS / 2]
        center = np.array([(hi[0] + lo[0]) / 2, (hi[1] + lo[1]) / 2, world[:, 2].min() + SOLE_THICKNESS / 2])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, rot.T.copy().ravel())
        spec.body(link).add_geom(name=f"sole_{link}", type=mujoco.mjtGeom.mjGEOM_BOX, size=half,
                                 pos=rot.T @ (center - origin), quat=quat, contype=1, conaffinity=0, condim=3,
                                 group=2, friction=[1.0, 0.005, 0.0001], solref=list(solref))
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05],
                            contype=0, conaffinity=1, condim=3, friction=[1.0, 0.005, 0.0001], solref=list(solref))


#: site at the floating base link's centre of mass (the pelvis position of the balance task)
PELVIS_SITE = "pelvis"


def _add_pelvis_site(spec: mujoco.MjSpec) -> None:
    """Site :data:`PELVIS_SITE` on the floating root body at its centre of mass as compiled now
    (``body_ipos``, the URDF's fixed links fused in). Add it before welding further links to the
    root, which moves the root's centre of mass but not the site."""
    probe = spec.copy().compile()
    root = spec.worldbody.first_body()
    root.add_site(name=PELVIS_SITE, pos=probe.body_ipos[probe.body(root.name).id], size=[0.01, 0, 0])


def _configure_solver(spec: mujoco.MjSpec, has_contacts: bool, iterations: int = SOLVER_ITERATIONS) -> None:
    """Batched-MJX-friendly solver settings: no constraints at all when the scene has no contacts
    (``has_contacts`` false: no ball, no floating base); otherwise few (``iterations``) Newton
    iterations (measured: the vmapped solver dominates the step cost)."""
    if not has_contacts:
        spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    else:
        spec.option.iterations = iterations
        spec.option.ls_iterations = 8
    # joint-limit constraints are off per joint already; equality constraints do not exist
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_LIMIT


def _add_servos(spec: mujoco.MjSpec, joint_names: list[str]) -> None:
    """Position actuators ``pos_<joint>`` then velocity actuators ``vel_<joint>`` (gains set later)."""
    for prefix in ("pos", "vel"):
        for joint in joint_names:
            act = spec.add_actuator(name=f"{prefix}_{joint}", target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            if prefix == "pos":
                act.set_to_position(kp=1.0)
            else:
                act.set_to_velocity(kv=1.0)


def _tune_servos(model: mujoco.MjModel, qpos0: np.ndarray, qpos_adr: np.ndarray, dof_adr: np.ndarray,
                 lower: np.ndarray, upper: np.ndarray, omega: float, zeta: float, samples: int = 64) -> None:
    """Set per-joint gains from the largest joint-space inertia diagonal ``M_ii`` (armature
    included) over ``qpos0`` and ``samples`` random joint configurations within the limits:
    ``kp = M w^2`` (position actuators), ``kv = 2 zeta M w`` (velocity actuators). Where the
    actual inertia is smaller the implicitly integrated damping keeps the loop stable."""
    rng = np.random.default_rng(0)
    lo = np.where(np.isfinite(lower), lower, -np.pi)
    hi = np.where(np.isfinite(upper), upper, np.pi)
    data = mujoco.MjData(model)
    full = np.zeros((model.nv, model.nv))
    inertia = np.zeros(len(dof_adr))
    for k in range(samples + 1):
        data.qpos[:] = qpos0
        if k:
            data.qpos[qpos_adr] = rng.uniform(lo, hi)
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, full)
        inertia = np.maximum(inertia, np.diag(full)[dof_adr])
    n = len(dof_adr)
    kp, kv = inertia * omega**2, 2.0 * zeta * inertia * omega
    model.actuator_gainprm[:n, 0] = kp
    model.actuator_biasprm[:n, 1] = -kp
    model.actuator_gainprm[n:2 * n, 0] = kv
    model.actuator_biasprm[n:2 * n, 2] = -kv


def _height_above_floor(model: mujoco.MjModel, qpos: np.ndarray) -> float:
    """Vertical shift [m] that puts the lowest floor-colliding geom point on the floor (z = 0)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    lowest = np.inf
    for g in range(model.ngeom):
        if model.geom_contype[g] and model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE:
            lowest = min(lowest, _geom_lowest_z(model, data, g))
    if not np.isfinite(lowest):
        raise ValueError(f"{model.names}: no foot geoms collide with the floor")
    return float(-lowest)


def _geom_lowest_z(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> float:
    size, pos, mat = model.geom_size[g], data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
        return float(pos[2] - np.abs(mat[2]) @ size)
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return float(pos[2] - abs(mat[2, 2]) * size[1] - size[0])
    return float(pos[2] - size[0])
