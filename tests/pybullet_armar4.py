"""The papers' simulator as a test-only oracle for ARMAR-4 standing on its feet with its legs
held: PyBullet 3.2.7 with the papers' settings, and the same replay on our model (MuJoCo C, the
model and options MJX steps), both reporting the pelvis tilt per 240 Hz step.

* PyBullet (:class:`PyBulletArmar4`): 240 Hz, 50 solver iterations, position control with
  ``targetVelocities = 0.87 v`` and velocity gain 1, the URDF's efforts as force limits,
  self-collision on, the URDF's own collision meshes on a plane. Self-collision excludes all
  ancestors (``URDF_USE_SELF_COLLISION_EXCLUDE_ALL_PARENTS``): with PyBullet's default (the parent
  only) the foot's heel and toe links push against the ankle and the robot, holding still, slides
  2 m and tilts by 0.64 rad in 3 s, so the papers' robot cannot have used that. Every replay
  starts from a fresh simulation (PyBullet's contact caches would otherwise carry one motion's
  history into the next).
* Ours (:func:`mujoco_tilts`): ``load_robot("armar4_legs")``, legs held at ``q0`` by their servos,
  or ``load_robot("armar4_standing")``, legs welded.
* Motions from rest at the start pose: :func:`toppra_motion` (a path traversed time-optimally,
  velocity and acceleration limits, no jerk limit) and :func:`agent_motions` (random or
  bang-bang actions mapped into the safe acceleration range).

Never imported by the package: PyBullet is a test extra. ``scripts/armar4_pybullet_fidelity.py``
runs the whole comparison.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjx_pathtrack.core import limits as L

HZ = 240
TARGET_VELOCITY_FACTOR = 0.87  # the papers' targetVelocities = 0.87 v_setpoint, velocity gain 1
SOLVER_ITERATIONS = 50


# -- motions --------------------------------------------------------------------------------------

def toppra_motion(knots: np.ndarray, vel: np.ndarray, acc: np.ndarray, hold: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Setpoints ``(q [K, m], v [K, m])`` at 240 Hz of the time-optimal traversal of the spline
    through ``knots``, then ``hold`` s at its end."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    ss = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
    path = ta.SplineInterpolator(ss, knots, bc_type="natural")
    cons = [constraint.JointVelocityConstraint(np.stack([-vel, vel], 1)),
            constraint.JointAccelerationConstraint(np.stack([-acc, acc], 1))]
    traj = algo.TOPPRA(cons, path, parametrizer="ParametrizeConstAccel").compute_trajectory(0.0, 0.0)
    t = np.arange(0.0, traj.duration + hold, 1.0 / HZ)
    tc = np.minimum(t, traj.duration)
    return traj(tc), np.where((t <= traj.duration)[:, None], traj(tc, 1), 0.0)


def agent_motions(limits: L.JointLimits, p0: np.ndarray, key, n: int, seconds: float, bang: bool,
                  dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Setpoints ``(q [n, K, m], v [n, K, m])`` of ``n`` motions from rest at ``p0``: random
    (``bang`` false, actions U(-1, 1)) or bang-bang actions, mapped into the safe range."""
    steps, sub = int(round(seconds / dt)), int(round(dt * HZ))
    k_act, k_keep = jax.random.split(key)
    if bang:
        flips = jax.random.randint(k_keep, (n, limits.pos_min.shape[0]), 1, 7)  # steps a sign is kept
        signs0 = jnp.sign(jax.random.uniform(k_act, flips.shape, minval=-1, maxval=1))
        idx = jnp.arange(steps)[:, None, None]
        actions = signs0[None] * (-1.0) ** (idx // flips[None])
    else:
        actions = jax.random.uniform(k_act, (steps, n, limits.pos_min.shape[0]), minval=-1.0, maxval=1.0)
    t = dt * jnp.arange(1, sub + 1) / sub
    p = jnp.broadcast_to(jnp.asarray(p0, jnp.float32), (n, p0.shape[0]))

    def step(state, action):
        p, v, a = state
        lo, hi = L.safe_acceleration_range(limits, p, v, a, dt)
        a1 = L.action_to_acceleration(action, lo, hi)
        q, qd, _ = L.integrate(p[:, None], v[:, None], a[:, None], a1[:, None], dt, t[None, :, None])
        p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
        return (p1, v1, a1), (q, qd)

    zero = jnp.zeros_like(p)
    _, (q, qd) = jax.lax.scan(step, (p, zero, zero), actions)
    q = jnp.concatenate([p[:, None], jnp.moveaxis(q, 0, 1).reshape(n, steps * sub, -1)], axis=1)
    qd = jnp.concatenate([zero[:, None], jnp.moveaxis(qd, 0, 1).reshape(n, steps * sub, -1)], axis=1)
    return np.asarray(q, np.float64), np.asarray(qd, np.float64)


# -- simulators -----------------------------------------------------------------------------------

def tilt_of(z_axis: np.ndarray) -> float:
    return float(np.arccos(np.clip(z_axis[2], -1.0, 1.0)))


def load_model(spec: str):
    """Our model named ``NAME[@HZ[:OMEGA]]``: registry robot NAME at physics rate HZ (a divisor of
    240; default the registry's) with servos of bandwidth OMEGA rad/s (default the registry's for HZ)."""
    from mjx_pathtrack.robots.registry import load_robot

    name, _, rate = spec.partition("@")
    hz, _, omega = rate.partition(":")
    return load_robot(name, **({"sim_dt": 1.0 / float(hz)} if hz else {}),
                      **({"servo_omega": float(omega)} if omega else {}))


def mujoco_tilts(robot, upper: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Pelvis tilt [rad] per physics step of our model replaying upper-body setpoints ``q, v [K, m]``
    given at 240 Hz (a model whose time step is a multiple of 1/240 s takes every such sample)."""
    model, data = robot.mj_model, robot.mj_data()
    every = int(round(model.opt.timestep * HZ))
    if every < 1 or abs(every / HZ - model.opt.timestep) > 1e-9:
        raise ValueError(f"{robot.name}: time step {model.opt.timestep} s is not a multiple of 1/{HZ} s")
    q, v = q[::every], v[::every]
    q_all, v_all = np.asarray(robot.q0, np.float64).copy(), np.zeros(robot.n_joints)
    q_all[upper] = q[0]
    data.qpos[robot.qpos_adr] = q_all
    mujoco.mj_forward(model, data)
    tilts = [tilt_of(data.xmat[1].reshape(3, 3)[:, 2])]
    for k in range(len(q) - 1):
        q_all[upper], v_all[upper] = q[k], 0.5 * (v[k] + v[k + 1])  # robot.ctrl's timing convention
        data.ctrl[:] = np.concatenate([q_all, v_all])
        mujoco.mj_step(model, data)
        tilts.append(tilt_of(data.xmat[1].reshape(3, 3)[:, 2]))
    return np.array(tilts)


class PyBulletArmar4:
    """The floating-base ``armar4_fixed_hands`` URDF on a plane, papers' settings (module
    docstring). Every replay starts from a fresh simulation (PyBullet's contact caches would
    otherwise carry one motion's history into the next)."""

    def __init__(self, robot):
        import pybullet as pb

        self.pb = pb
        self.c = pb.connect(pb.DIRECT)
        self.robot_joints = robot.joint_names
        self.q0 = np.asarray(robot.q0, np.float64)

    def _reset(self):
        import armar
        import pybullet_data

        pb, c = self.pb, self.c
        pb.resetSimulation(physicsClientId=c)
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=1.0 / HZ, numSolverIterations=SOLVER_ITERATIONS, physicsClientId=c)
        pb.loadURDF(str(Path(pybullet_data.getDataPath()) / "plane.urdf"), physicsClientId=c)
        self.body = pb.loadURDF(armar.get_path_to_urdf_file("armar4_fixed_hands"), [0, 0, 0], useFixedBase=False,
                                flags=pb.URDF_USE_SELF_COLLISION | pb.URDF_USE_SELF_COLLISION_EXCLUDE_ALL_PARENTS,
                                physicsClientId=c)
        index = {pb.getJointInfo(self.body, j, physicsClientId=c)[1].decode(): j
                 for j in range(pb.getNumJoints(self.body, physicsClientId=c))}
        self.joints = [index[n] for n in self.robot_joints]
        for j, q in zip(self.joints, self.q0):
            pb.resetJointState(self.body, j, q, 0.0, physicsClientId=c)
        lowest = min(pb.getAABB(self.body, j, physicsClientId=c)[0][2]
                     for j in range(-1, pb.getNumJoints(self.body, physicsClientId=c)))
        pb.resetBasePositionAndOrientation(self.body, [0, 0, -lowest + 1e-4], [0, 0, 0, 1], physicsClientId=c)

    def tilts(self, upper: np.ndarray, q: np.ndarray, v: np.ndarray, settle: int = HZ // 2) -> np.ndarray:
        """Pelvis tilt [rad] per 240 Hz step replaying upper-body setpoints ``q, v [K, m]`` (after
        ``settle`` steps holding the start pose, so that the robot rests on its feet)."""
        pb, c = self.pb, self.c
        self._reset()
        q_all, v_all = self.q0.copy(), np.zeros(len(self.q0))
        q_all[upper] = q[0]
        for j, qj in zip(self.joints, q_all):
            pb.resetJointState(self.body, j, qj, 0.0, physicsClientId=c)
        out = []
        for k in range(-settle, len(q)):
            if k >= 0:
                q_all[upper], v_all[upper] = q[k], v[k]
            pb.setJointMotorControlArray(self.body, self.joints, pb.POSITION_CONTROL, targetPositions=q_all.tolist(),
                                         targetVelocities=(TARGET_VELOCITY_FACTOR * v_all).tolist(),
                                         velocityGains=[1.0] * len(self.joints), physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)
            if k >= 0:
                orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=c)[1]
                out.append(tilt_of(np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)[:, 2]))
        return np.array(out)
