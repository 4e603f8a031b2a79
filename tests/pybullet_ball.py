"""The papers' simulator as a test-only oracle for the ball on the plate: PyBullet 3.2.7 with the
papers' settings (240 Hz, 50 solver iterations; docs/robots.md §1), a box plate of the scene's
size whose motion is prescribed, and a sphere with the episode's radius, mass, rolling and
spinning friction (lateral friction 1 on both bodies: PyBullet multiplies the two bodies'
coefficients, so the contact gets the drawn values, as the MuJoCo scene's does).

* :func:`still_plate_travel`: how far a ball starting at rest on a still plate tilted by
  ``tilt_deg`` rolls in ``seconds``;
* :func:`replay`: the ball on a plate that follows given poses, one per physics step (the
  plate's velocity between two poses is set before each step, so friction sees it move), seen
  as the ball task's sensor sees it;
* :func:`replay_arm`: the same with PyBullet's iiwa carrying the plate under position control
  towards joint setpoints (the papers' robot); :func:`arm_plate_pose` its plate's pose.

Never imported by the package: PyBullet is a test extra, not a dependency.
"""

from __future__ import annotations

import contextlib

import mujoco
import numpy as np
import pybullet as pb

from mjx_pathtrack.robots import ball_scene as B

HZ = 240
SOLVER_ITERATIONS = 50
GRAVITY = 9.81
_PLATE_MASS = 1e4  # kg: the plate's pose and velocity are overwritten every step; gravity compensated
_HALF = np.asarray(B.PLATE_SIZE) / 2.0


@contextlib.contextmanager
def _client(step: float):
    c = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0.0, 0.0, -GRAVITY, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=step, numSolverIterations=SOLVER_ITERATIONS, physicsClientId=c)
        yield c
    finally:
        pb.disconnect(c)


def _ball(c: int, radius: float, mass: float, mu_roll: float, mu_spin: float) -> int:
    """The episode's ball (lateral friction 1) in client ``c``."""
    sphere = pb.createCollisionShape(pb.GEOM_SPHERE, radius=radius, physicsClientId=c)
    ball = pb.createMultiBody(mass, sphere, physicsClientId=c)
    pb.changeDynamics(ball, -1, lateralFriction=1.0, rollingFriction=mu_roll, spinningFriction=mu_spin,
                      physicsClientId=c)
    return ball


def _bodies(c: int, plate_mass: float, radius: float, mass: float, mu_roll: float, mu_spin: float) -> tuple[int, int]:
    box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=_HALF.tolist(), physicsClientId=c)
    plate = pb.createMultiBody(plate_mass, box, physicsClientId=c)
    pb.changeDynamics(plate, -1, lateralFriction=1.0, physicsClientId=c)
    return plate, _ball(c, radius, mass, mu_roll, mu_spin)


def _xyzw(rot: np.ndarray) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot, np.float64).ravel())
    return [q[1], q[2], q[3], q[0]]


def still_plate_travel(tilt_deg: float, radius: float, mass: float, mu_roll: float, mu_spin: float,
                       seconds: float = 2.0) -> float:
    """Distance [m] a ball released at rest at the centre of a still plate tilted by
    ``tilt_deg`` about its x axis travels in ``seconds``."""
    rot = np.array(pb.getMatrixFromQuaternion(pb.getQuaternionFromEuler([np.radians(tilt_deg), 0.0, 0.0]))).reshape(3, 3)
    with _client(1.0 / HZ) as c:
        plate, ball = _bodies(c, 0.0, radius, mass, mu_roll, mu_spin)  # mass 0: static
        pb.resetBasePositionAndOrientation(plate, [0.0, 0.0, 0.0], _xyzw(rot), physicsClientId=c)
        start = rot @ np.array([0.0, 0.0, _HALF[2] + radius])
        pb.resetBasePositionAndOrientation(ball, start.tolist(), [0, 0, 0, 1], physicsClientId=c)
        for _ in range(int(round(seconds * HZ))):
            pb.stepSimulation(physicsClientId=c)
        end = np.array(pb.getBasePositionAndOrientation(ball, physicsClientId=c)[0])
    return float(np.linalg.norm(end - start))


def replay(surface: np.ndarray, rot: np.ndarray, start_xy: np.ndarray, radius: float, mass: float,
           mu_roll: float, mu_spin: float, substeps: int) -> np.ndarray:
    """The ball on a plate whose top-surface centre ``surface [K+1, 3]`` [m] and rotation
    ``rot [K+1, 3, 3]`` (columns: plate x, y, normal) are prescribed at every physics step of
    ``1/240`` s; the ball starts at rest at ``start_xy [2]`` [m] (plate frame). Returns the ball
    centre in the plate frame ``[K // substeps, 3]`` [m] at the start of the last physics step of
    every decision step of ``substeps`` physics steps (what the ball task's sensor reports)."""
    h = 1.0 / HZ
    centre = surface - rot[:, :, 2] * _HALF[2]  # the box's centre
    seen = []
    with _client(h) as c:
        plate, ball = _bodies(c, _PLATE_MASS, radius, mass, mu_roll, mu_spin)
        pos0 = surface[0] + rot[0] @ np.array([start_xy[0], start_xy[1], radius])
        pb.resetBasePositionAndOrientation(ball, pos0.tolist(), [0, 0, 0, 1], physicsClientId=c)
        for k in range(len(surface) - 1):
            omega = np.zeros(3)
            dq = np.zeros(4)
            mujoco.mju_mat2Quat(dq, (rot[k + 1] @ rot[k].T).ravel())
            mujoco.mju_quat2Vel(omega, dq, h)
            pb.resetBasePositionAndOrientation(plate, centre[k].tolist(), _xyzw(rot[k]), physicsClientId=c)
            pb.resetBaseVelocity(plate, ((centre[k + 1] - centre[k]) / h).tolist(), omega.tolist(), physicsClientId=c)
            pb.applyExternalForce(plate, -1, [0.0, 0.0, GRAVITY * _PLATE_MASS], centre[k].tolist(), pb.WORLD_FRAME,
                                  physicsClientId=c)
            if k % substeps == substeps - 1:
                p = np.array(pb.getBasePositionAndOrientation(ball, physicsClientId=c)[0])
                seen.append(rot[k].T @ (p - surface[k]))
            pb.stepSimulation(physicsClientId=c)
    return np.array(seen)


def _arm_urdf(iiwa_urdf: str) -> str:
    """A copy of the iiwa URDF (text) with the scene's plate fixed to ``iiwa_link_7`` (0.135 m
    along its z, yaw -pi/2, 0.508 kg), as the papers' ``one_robot_balance.urdf`` attaches its board."""
    from pathlib import Path

    text = Path(iiwa_urdf).read_text()
    h = _HALF
    plate = f"""
  <link name="plate">
    <inertial><origin xyz="0 0 0"/><mass value="{B.PLATE_MASS}"/>
      <inertia ixx="{B.PLATE_MASS / 3 * (h[1]**2 + h[2]**2)}" ixy="0" ixz="0" iyy="{B.PLATE_MASS / 3 * (h[0]**2 + h[2]**2)}"
               iyz="0" izz="{B.PLATE_MASS / 3 * (h[0]**2 + h[1]**2)}"/></inertial>
    <collision><geometry><box size="{2 * h[0]} {2 * h[1]} {2 * h[2]}"/></geometry></collision>
  </link>
  <joint name="plate_joint" type="fixed">
    <parent link="iiwa_link_7"/><child link="plate"/>
    <origin xyz="0 0 {B.PLATE_OFFSET}" rpy="0 0 {-np.pi / 2}"/>
  </joint>
</robot>"""
    return text.replace("</robot>", plate)


@contextlib.contextmanager
def _arm(c: int, iiwa_urdf: str, joint_names):
    """The iiwa with the plate loaded into client ``c``: ``(body, joint indices, plate link index)``."""
    import os
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as f:
        f.write(_arm_urdf(iiwa_urdf))
        path = f.name
    try:
        arm = pb.loadURDF(path, useFixedBase=True, physicsClientId=c)
    finally:
        os.unlink(path)
    index = {pb.getJointInfo(arm, j, physicsClientId=c)[1].decode(): j for j in range(pb.getNumJoints(arm, physicsClientId=c))}
    yield arm, [index[n] for n in joint_names], index["plate_joint"]


def _plate_surface(c: int, arm: int, plate: int) -> tuple[np.ndarray, np.ndarray]:
    state = pb.getLinkState(arm, plate, computeForwardKinematics=True, physicsClientId=c)
    rot = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
    return np.array(state[4]) + rot[:, 2] * _HALF[2], rot


def arm_plate_pose(iiwa_urdf: str, joint_names, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PyBullet's plate surface centre ``[3]`` and rotation ``[3, 3]`` with the arm at ``q [7]``."""
    with _client(1.0 / HZ) as c, _arm(c, iiwa_urdf, joint_names) as (arm, joints, plate):
        for j, qj in zip(joints, q):
            pb.resetJointState(arm, j, float(qj), 0.0, physicsClientId=c)
        return _plate_surface(c, arm, plate)


def replay_arm(iiwa_urdf: str, joint_names, q: np.ndarray, start_xy: np.ndarray, radius: float, mass: float,
               mu_roll: float, mu_spin: float, substeps: int, velocity_factor: float = 0.87) -> np.ndarray:
    """As :func:`replay`, but PyBullet simulates the arm carrying the plate, driven like the papers'
    robot: position control towards the setpoints ``q [K+1, 7]`` (one per physics step) with target
    velocities ``velocity_factor`` times the setpoint velocity (velocity gain 1). Returns the ball
    centre in the plate's surface frame ``[K // substeps, 3]`` [m], seen as by the task's sensor."""
    h = 1.0 / HZ
    seen = []
    with _client(h) as c, _arm(c, iiwa_urdf, joint_names) as (arm, joints, plate):
        pb.changeDynamics(arm, plate, lateralFriction=1.0, physicsClientId=c)
        for j, qj in zip(joints, q[0]):
            pb.resetJointState(arm, j, float(qj), 0.0, physicsClientId=c)
        ball = _ball(c, radius, mass, mu_roll, mu_spin)
        o, rot = _plate_surface(c, arm, plate)
        pb.resetBasePositionAndOrientation(ball, (o + rot @ np.array([start_xy[0], start_xy[1], radius])).tolist(),
                                           [0, 0, 0, 1], physicsClientId=c)
        for k in range(len(q) - 1):
            v = (q[k + 1] - q[k]) / h
            pb.setJointMotorControlArray(arm, joints, pb.POSITION_CONTROL, targetPositions=q[k + 1].tolist(),
                                         targetVelocities=(velocity_factor * v).tolist(),
                                         velocityGains=[1.0] * len(joints), physicsClientId=c)
            if k % substeps == substeps - 1:
                o, rot = _plate_surface(c, arm, plate)
                p = np.array(pb.getBasePositionAndOrientation(ball, physicsClientId=c)[0])
                seen.append(rot.T @ (p - o))
            pb.stepSimulation(physicsClientId=c)
    return np.array(seen)
