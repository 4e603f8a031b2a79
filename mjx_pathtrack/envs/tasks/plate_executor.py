"""A cheaper executor of the ball-on-plate task: only the plate and the ball are simulated.

The arm's servos follow their setpoints within a few 1e-4 rad (``tests/robots/test_registry.py -k
tracking``), so :class:`PrescribedPlateExecutor` takes the arm's motion to *be* the setpoints
and prescribes the plate's motion from their forward kinematics: before every physics step the
plate (a free body in :func:`~mjx_pathtrack.robots.ball_scene.plate_and_ball_model`, too heavy
for the ball to move) gets the pose of the ``iiwa_ball`` scene's plate at the step's start and
the constant velocity that carries it to the pose at the step's end, so that the contact sees
the plate moving (a mocap body would be still for the contact's friction). The ball is the same
free body with the same per-episode randomisation (radius, mass, rolling and torsional friction)
and contact settings as in :class:`~mjx_pathtrack.envs.tasks.ball_on_plate.BallExecutor`, the
full-arm executor, which stays the reference (speed: ``benchmarks/bench_ball.py``; fidelity:
docs/results.md "Ball on plate").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
import mujoco
from mujoco import mjx
from mujoco.mjx._src import math as mjx_math

from mjx_pathtrack.envs.executors import setpoints
from mjx_pathtrack.envs.tasks.ball_executor import BallExecutor, BallState
from mjx_pathtrack.robots import ball_scene as B

Array = jax.Array


class PrescribedPlateExecutor(BallExecutor):
    """The ball on a plate whose motion is prescribed by the arm's setpoints (module docstring).
    Same interface and state (:class:`BallState`; ``data`` is the plate-and-ball model's) as
    :class:`BallExecutor`; ``robot``: the ``iiwa_ball`` registry robot."""

    name = "mjx_plate"

    def __init__(self, robot):
        if "plate" not in [robot.mj_model.geom(i).name for i in range(robot.mj_model.ngeom)]:
            raise ValueError(f"robot {robot.name!r} has no plate; use robots.load_robot('iiwa_ball')")
        model = self._use_model(robot, B.plate_and_ball_model(robot.mj_model))
        full = robot.mj_model
        geom = full.geom("plate").id
        self._plate_body = int(full.geom_bodyid[geom])
        self._plate_pos = jnp.asarray(full.geom_pos[geom], jnp.float32)  # plate in its arm link's frame
        self._plate_quat = jnp.asarray(full.geom_quat[geom], jnp.float32)
        self._fk_data = mjx.make_data(robot.mjx_model)
        self._data0 = mjx.put_data(model, mujoco.MjData(model))

    def arm_kinematics(self, q: Array) -> tuple[Array, Array, Array]:
        """Plate pose and target point of the arm at joint positions ``q [..., 7]``: ``(pos [..., 3],
        quat [..., 4] (w first), target [..., 3])``, world frame [m]."""
        r = self.robot

        def one(qi):
            d = mjx.kinematics(r.mjx_model, self._fk_data.replace(qpos=r.qpos(qi)))
            link_pos, link_quat = d.xpos[self._plate_body], d.xquat[self._plate_body]
            pos = link_pos + mjx_math.rotate(self._plate_pos, link_quat)
            return pos, mjx_math.quat_mul(link_quat, self._plate_quat), d.site_xpos[self.target_site]

        batch = q.shape[:-1]
        pos, quat, target = jax.vmap(one)(q.reshape(-1, q.shape[-1]))
        return pos.reshape(batch + (3,)), quat.reshape(batch + (4,)), target.reshape(batch + (3,))

    def _with_plate(self, data, pos: Array, quat: Array, lin: Array, ang: Array):
        return data.replace(qpos=data.qpos.at[0:7].set(jnp.concatenate([pos, quat])),
                            qvel=data.qvel.at[0:6].set(jnp.concatenate([lin, ang])))

    def init(self, p0: Array) -> BallState:
        """Arm at rest at ``p0`` [7], default ball at the plate centre (kinematics only)."""
        p0 = jnp.asarray(p0, jnp.float32)
        pos, quat, target = self.arm_kinematics(p0)
        data = self._with_plate(self._data0, pos, quat, jnp.zeros(3), jnp.zeros(3))
        data = mjx.kinematics(self.mjx_model, data)
        state = BallState(data, jax.random.PRNGKey(0), jnp.zeros(3), jnp.zeros(3), target, jnp.zeros(3), p0)
        return self.place_ball(state, jnp.zeros(2), jnp.asarray(B.BALL_RADIUS, jnp.float32))

    def execute(self, state: BallState, p, v, a0, a1, dt):
        model, _ = self.model(state.key)
        q_set, _ = setpoints(p, v, a0, a1, dt, self.substeps)  # [S+1, 7]
        pos, quat, _ = self.arm_kinematics(q_set)
        h = dt / self.substeps
        lin = (pos[1:] - pos[:-1]) / h  # world frame
        ang = jax.vmap(mjx_math.quat_sub)(quat[1:], quat[:-1]) / h  # plate frame (a free joint's convention)

        def physics(data, k):
            data = self._with_plate(data, pos[k], quat[k], lin[k], ang[k])
            return mjx.step(model, data), None

        data, _ = jax.lax.scan(physics, state.data, jnp.arange(self.substeps))
        ball = data.sensordata[self.sensor_adr:self.sensor_adr + 3]
        new = state._replace(data=data, ball_prev=state.ball, ball=ball, q=q_set[-1])
        return new, q_set, {"ball": ball}
