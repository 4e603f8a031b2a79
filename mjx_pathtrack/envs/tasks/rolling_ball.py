"""The cheapest executor of the ball-on-plate task: a ball rolling on a moving plate, in pure JAX.

The profile of the full-arm MJX scene (``python benchmarks/profile_ball.py``) puts 59 % of a
physics step in MJX's constraint solver for the one ball-plate contact and 30 % in the 13-dof
smooth dynamics; prescribing the plate and simulating only plate and ball in MJX
(:mod:`~mjx_pathtrack.envs.tasks.plate_executor`) keeps the solver and gains 1.2x. Here the
contact is solved in closed form instead.

Model (per environment, at the physics step ``h`` = 1/240 s of the MJX scenes):

* the plate's pose and velocity come from the setpoints through the iiwa's kinematic chain
  (the servos follow them within a few 1e-4 rad): :meth:`RollingBallExecutor.plate_motion`,
  the velocity exactly as the forward-mode derivative along the setpoint velocity;
* the ball, a solid sphere (radius, mass, rolling and torsional friction drawn per episode as in
  :class:`~mjx_pathtrack.envs.tasks.ball_on_plate.BallExecutor`), moves under gravity and one
  contact impulse per step, computed at the velocity level like MuJoCo's (semi-implicit Euler):
  the normal impulse closes the gap to the plate at the step's end (never pulls: the ball may
  lift off), the tangential impulse makes the contact point move with the plate (rolling without
  slipping: ``P_t = 2/7 m (v_plate - v - h g + r Omega x n)_t``), limited to the friction cone
  ``|P_t| <= P_n`` (friction 1, as the scene's); the rolling and torsional friction torques oppose
  the ball's rotation relative to the plate, ``mu N`` (the papers' simulator's model, PyBullet),
  and never reverse it: a ball on a still plate tilted by less than ``atan(mu_roll / r)`` stays
  put. There is a contact only over the plate's area; a ball beyond its edge falls freely.

Validated in ``tests/envs/test_ball_physics.py`` (same safe motions, same balls) against PyBullet
with the papers' settings (1.0 mm mean difference, same falls in 200 of 200 episodes) and against
the full-arm MJX scene (3.9 mm: MuJoCo's soft rolling friction lets the ball creep where the
torque limit holds it; same falls). The ball's reported position is the MJX sensor's: the ball centre in the plate
frame at the start of the step's last physics step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before mujoco.mjx: silences its Warp notices)
import mujoco
from mujoco.mjx._src import math as mjx_math

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.envs.tasks.ball_executor import BallExecutor, BallState, sample_friction
from mjx_pathtrack.robots import ball_scene as B

Array = jax.Array

#: gravity [m/s^2] (world frame, z up)
GRAVITY = np.array([0.0, 0.0, -9.81], np.float32)
#: angular speed [rad/s] below which the rolling/torsional friction torques fade out linearly
FRICTION_SPEED = 1e-2


class BallBody(NamedTuple):
    """The ball of one environment: centre ``pos [3]`` [m] and velocity ``vel [3]`` [m/s] in the
    world frame, angular velocity ``spin [3]`` [rad/s] (world), ``radius`` [m], ``mass`` [kg],
    torsional and rolling friction ``mu_spin``, ``mu_roll`` [m]."""

    pos: Array
    vel: Array
    spin: Array
    radius: Array
    mass: Array
    mu_spin: Array
    mu_roll: Array


def _quat_mat(quat) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3)


def _axis_rotation(axis: Array, angle: Array) -> Array:
    """Rotation matrix ``[3, 3]`` of ``angle`` [rad] about the unit ``axis [3]``."""
    return mjx_math.quat_to_mat(mjx_math.axis_angle_to_quat(axis, angle))


def _smooth_direction(w: Array) -> Array:
    """``w / |w|`` above :data:`FRICTION_SPEED`, fading to 0 linearly below it."""
    return w / jnp.maximum(jnp.linalg.norm(w), FRICTION_SPEED)


class RollingBallExecutor(BallExecutor):
    """The ball rolling on the plate of the arm's setpoints (module docstring). Same interface
    as :class:`BallExecutor`; its state's ``data`` is a :class:`BallBody`. ``robot``: the
    ``iiwa_ball`` registry robot (a serial chain of hinges with the plate on its last link)."""

    name = "rolling"

    def __init__(self, robot):
        m = robot.mj_model
        if "plate" not in [m.geom(i).name for i in range(m.ngeom)]:
            raise ValueError(f"robot {robot.name!r} has no plate; use robots.load_robot('iiwa_ball')")
        self.robot = robot
        self.substeps = int(robot.n_substeps)
        plate = m.geom("plate").id
        chain, body = [], int(m.geom_bodyid[plate])
        while body != 0:
            chain.append(body)
            body = int(m.body_parentid[body])
        chain.reverse()
        joints = [int(m.body_jntadr[b]) for b in chain]
        if [int(m.body_jntnum[b]) for b in chain] != [1] * len(chain) or \
                list(int(m.jnt_qposadr[j]) for j in joints) != list(map(int, robot.qpos_adr)) or \
                np.abs(m.jnt_pos[joints]).max() > 0:
            raise ValueError(f"robot {robot.name!r}: the plate is not on a chain of the robot's hinges")
        self._offsets = jnp.asarray(m.body_pos[chain], jnp.float32)  # [7, 3] in the parent frame
        self._frames = jnp.asarray(np.stack([_quat_mat(m.body_quat[b]) for b in chain]), jnp.float32)
        self._axes = jnp.asarray(m.jnt_axis[joints], jnp.float32)
        self._plate_pos = jnp.asarray(m.geom_pos[plate], jnp.float32)
        self._plate_rot = jnp.asarray(_quat_mat(m.geom_quat[plate]), jnp.float32)
        self.half = jnp.asarray(np.asarray(B.PLATE_SIZE[:2]) / 2.0, jnp.float32)
        self.thickness = float(B.PLATE_SIZE[2])

    # -- the plate ----------------------------------------------------------------------------

    def plate_pose(self, q: Array) -> tuple[Array, Array]:
        """Pose of the plate's top surface at joint positions ``q [7]``: ``(origin [3] [m],
        rotation [3, 3])`` in the world frame (columns: the plate's x, y and normal)."""
        def link(carry, x):
            pos, rot = carry
            offset, frame, axis, angle = x
            return (pos + rot @ offset, rot @ frame @ _axis_rotation(axis, angle)), None

        (pos, rot), _ = jax.lax.scan(link, (jnp.zeros(3), jnp.eye(3)), (self._offsets, self._frames, self._axes, q))
        plate = rot @ self._plate_rot
        return pos + rot @ self._plate_pos + plate[:, 2] * (self.thickness / 2.0), plate

    def plate_motion(self, q: Array, qd: Array) -> tuple[Array, Array, Array, Array]:
        """Plate pose and velocity at ``q``, ``qd [..., 7]``: ``(origin [..., 3], rotation
        [..., 3, 3], origin velocity [..., 3] [m/s], angular velocity [..., 3] [rad/s])``."""
        def one(qi, qdi):
            (pos, rot), (dpos, drot) = jax.jvp(self.plate_pose, (qi,), (qdi,))
            omega_hat = drot @ rot.T
            return pos, rot, dpos, jnp.stack([omega_hat[2, 1], omega_hat[0, 2], omega_hat[1, 0]])

        batch = q.shape[:-1]
        out = jax.vmap(one)(q.reshape(-1, q.shape[-1]), qd.reshape(-1, q.shape[-1]))
        return tuple(x.reshape(batch + x.shape[1:]) for x in out)

    # -- the ball -----------------------------------------------------------------------------

    def sample_ball(self, key: Array) -> BallBody:
        """The episode's ball parameters from ``key``, drawn exactly as :class:`BallExecutor` does
        (:func:`~mjx_pathtrack.robots.ball_scene.sample_ball`, then the frictions), at rest at the origin."""
        radius, mass = B.sample_ball(key)
        spin, roll = sample_friction(key)
        zero = jnp.zeros(3)
        return BallBody(zero, zero, zero, radius, mass, spin, roll)

    def model(self, key: Array):
        ball = self.sample_ball(key)
        return ball, ball.radius

    def init(self, p0: Array) -> BallState:
        """Arm at rest at ``p0`` [7], default ball at the plate centre."""
        p0 = jnp.asarray(p0, jnp.float32)
        target = self.robot.fk(p0)[0][0]
        state = BallState(None, jax.random.PRNGKey(0), jnp.zeros(3), jnp.zeros(3), target, jnp.zeros(3), p0)
        return self.place_ball(state, jnp.zeros(2), jnp.asarray(B.BALL_RADIUS, jnp.float32))  # (sets data)

    def place_ball(self, state: BallState, xy: Array, radius: Array) -> BallState:
        """Ball at rest on the plate at ``xy [2]`` [m] (plate frame), arm at ``state.q`` (at rest)."""
        origin, rot = self.plate_pose(state.q)
        local = jnp.concatenate([xy, radius[None]])
        ball = self.sample_ball(state.key)._replace(pos=origin + rot @ local, radius=radius)
        return state._replace(data=ball, ball_prev=local, ball=local)

    def step_ball(self, ball: BallBody, plate0, plate1, h: float) -> BallBody:
        """One physics step of length ``h`` [s]: ``plate0``/``plate1`` = ``(origin, rotation,
        origin velocity, angular velocity)`` at its start and end."""
        o0, r0, _, _ = plate0
        o1, r1, do1, w1 = plate1
        n = r1[:, 2]
        local = r0.T @ (ball.pos - o0)  # plate frame at the start
        gap = local[2] - ball.radius
        over = jnp.all(jnp.abs(local[:2]) <= self.half) & (gap > -ball.radius)
        contact = o1 + r1 @ jnp.concatenate([local[:2], jnp.zeros(1)])
        v_plate = do1 + jnp.cross(w1, contact - o1)
        v_free = ball.vel + h * jnp.asarray(GRAVITY)
        inertia = 0.4 * ball.mass * ball.radius**2
        # normal impulse: the gap to the plate closes at the step's end, never pulls
        p_n = ball.mass * jnp.maximum(jnp.dot(v_plate - v_free, n) - jnp.maximum(gap, 0.0) / h, 0.0)
        p_n = jnp.where(over, p_n, 0.0)
        # rolling and torsional friction: torques against the rotation relative to the plate,
        # no larger than what stops it
        rel = ball.spin - w1
        rel_n = jnp.dot(rel, n) * n
        rel_t = rel - rel_n
        torque = -p_n * (ball.mu_roll * _smooth_direction(rel_t) + ball.mu_spin * _smooth_direction(rel_n))
        stop = inertia * jnp.linalg.norm(rel)
        torque = torque * jnp.minimum(1.0, stop / jnp.maximum(jnp.linalg.norm(torque), 1e-12))
        spin = ball.spin + torque / inertia
        # tangential impulse: the contact point moves with the plate (no slip), within the cone
        slip = v_plate - v_free + ball.radius * jnp.cross(spin, n)
        slip = slip - jnp.dot(slip, n) * n
        p_t = (2.0 / 7.0) * ball.mass * slip
        p_t = p_t * jnp.minimum(1.0, p_n / jnp.maximum(jnp.linalg.norm(p_t), 1e-12))
        vel = v_free + (p_n * n + p_t) / ball.mass
        spin = spin - ball.radius * jnp.cross(n, p_t) / inertia
        return ball._replace(pos=ball.pos + h * vel, vel=vel, spin=spin)

    def execute(self, state: BallState, p, v, a0, a1, dt):
        t = dt * jnp.arange(self.substeps + 1) / self.substeps
        q, qd, _ = L.integrate(p, v, a0, a1, dt, t[:, None])  # [S+1, 7]
        origin, rot, dorigin, omega = self.plate_motion(q, qd)
        h = dt / self.substeps

        def physics(ball, k):
            plate0 = (origin[k], rot[k], dorigin[k], omega[k])
            plate1 = (origin[k + 1], rot[k + 1], dorigin[k + 1], omega[k + 1])
            return self.step_ball(ball, plate0, plate1, h), rot[k].T @ (ball.pos - origin[k])

        ball, seen = jax.lax.scan(physics, state.data, jnp.arange(self.substeps))
        new = state._replace(data=ball, ball_prev=state.ball, ball=seen[-1], q=q[-1])
        return new, q, {"ball": seen[-1]}
