"""The ball on the plate's reference physics (docs/robots.md §4): the servo-driven iiwa of the
``iiwa_ball`` scene with a free, randomised ball on the plate at its flange, in MJX
(:class:`BallExecutor`), and what the faster executors of the task share with it
(:class:`BallState`, :func:`sample_friction`: :mod:`~mjx_pathtrack.envs.tasks.plate_executor`,
:mod:`~mjx_pathtrack.envs.tasks.rolling_ball`). The task itself, which picks one of them, is
:mod:`~mjx_pathtrack.envs.tasks.ball_on_plate`.
"""

from __future__ import annotations

import copy
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
import mujoco
import numpy as np
from mujoco import mjx

from mjx_pathtrack.envs.executors import setpoints
from mjx_pathtrack.robots import ball_scene as B

Array = jax.Array


#: rolling and torsional friction range of the ball (docs/robots.md §1) [m]
FRICTION_RANGE = (1e-4, 6e-4)


def sample_friction(key: Array) -> tuple[Array, Array]:
    """The episode's torsional and rolling friction ``(mu_spin, mu_roll)`` [m], each ~ U(
    :data:`FRICTION_RANGE`), drawn from the ball's ``key`` (its radius and mass come from the same
    key: :func:`~mjx_pathtrack.robots.ball_scene.sample_ball`). Pure JAX, scalars."""
    spin, roll = jax.random.uniform(jax.random.fold_in(key, 1), (2,), minval=FRICTION_RANGE[0], maxval=FRICTION_RANGE[1])
    return spin, roll


class BallState(NamedTuple):
    """Executor state of one environment: ``data`` (``mjx.Data``); ``key``: the episode's ball
    parameters (radius, mass, friction are re-derived from it); ``ball_prev``/``ball`` ``[3]``:
    ball centre in the plate frame [m] before/after the last step; ``target``/``relative``
    ``[3]``: Cartesian reference point and reference minus executed end point [m]; ``q`` ``[7]``:
    the arm's executed joint positions [rad]."""

    data: Any
    key: Array
    ball_prev: Array
    ball: Array
    target: Array
    relative: Array
    q: Array


class BallExecutor:
    """Servo-controlled MJX physics of the ``iiwa_ball`` scene with a randomised ball (one
    environment per call; vmap for batches). Same interface as
    :class:`~mjx_pathtrack.envs.executors.MjxExecutor`, plus :meth:`randomize`."""

    name = "mjx"

    def __init__(self, robot):
        if "ball" not in [robot.mj_model.body(i).name for i in range(robot.mj_model.nbody)]:
            raise ValueError(f"robot {robot.name!r} has no ball; use robots.load_robot('iiwa_ball')")
        model = self._use_model(robot, copy.copy(robot.mj_model))
        data = mujoco.MjData(model)
        data.qpos[:] = robot.qpos0
        data.ctrl[:] = np.concatenate([robot.q0, np.zeros(robot.n_joints)])
        mujoco.mj_forward(model, data)
        self._data0 = mjx.put_data(model, data)

    def _use_model(self, robot, model: mujoco.MjModel) -> mujoco.MjModel:
        """Simulate ``model`` (a scene with the plate, the ball and its sensor; changed in place:
        the ball's contact gets rolling and torsional friction) for ``robot``; returns it."""
        self.ids = B.ball_ids(model)
        model.geom_condim[self.ids[1]] = 6  # rolling/torsional friction act
        model.geom_friction[model.geom("plate").id] = [1.0, 0.0, 0.0]  # contact friction = max of both: the ball's
        self.mj_model = model
        self.robot = robot
        self.mjx_model = mjx.put_model(model)
        self.substeps = int(robot.n_substeps)
        self.plate_site = model.site("plate").id
        self.ball_qpos = int(model.jnt_qposadr[model.joint("ball").id])
        self.sensor_adr = int(model.sensor_adr[model.sensor("ball_in_plate").id])
        self.target_site = int(np.asarray(robot.site_ids)[0])
        return model

    def model(self, key: Array):
        """The episode's ``mjx.Model`` (ball radius, mass, friction drawn from ``key``) and the radius."""
        model, radius, _ = B.randomize_ball(self.mjx_model, key, *self.ids)
        spin, roll = sample_friction(key)
        friction = model.geom_friction.at[self.ids[1]].set(jnp.stack([1.0, spin, roll]))
        return model.tree_replace({"geom_friction": friction}), radius

    def init(self, p0: Array) -> BallState:
        """Robot at rest at ``p0`` [7], default ball at the plate centre (kinematics only)."""
        r = self.robot
        data = self._data0.replace(qpos=jnp.asarray(self._data0.qpos).at[r.qpos_adr].set(p0),
                                   qvel=jnp.zeros_like(self._data0.qvel), ctrl=r.ctrl(p0, jnp.zeros_like(p0)))
        data = mjx.kinematics(self.mjx_model, data)
        state = BallState(data, jax.random.PRNGKey(0), jnp.zeros(3), jnp.zeros(3),
                          data.site_xpos[self.target_site], jnp.zeros(3), jnp.asarray(p0, jnp.float32))
        return self.place_ball(state, jnp.zeros(2), jnp.asarray(B.BALL_RADIUS, jnp.float32))

    def place_ball(self, state: BallState, xy: Array, radius: Array) -> BallState:
        """Ball at rest on the plate at ``xy [2]`` [m] (plate frame) using the plate pose in ``state.data``."""
        d = state.data
        pose = B.ball_pose_on_plate(d.site_xpos[self.plate_site], d.site_xmat[self.plate_site], xy, radius)
        data = d.replace(qpos=d.qpos.at[self.ball_qpos:self.ball_qpos + 7].set(pose))
        ball = jnp.concatenate([xy, radius[None]])
        return state._replace(data=data, ball_prev=ball, ball=ball)

    def randomize(self, state: BallState, key: Array) -> BallState:
        """New ball parameters and start position from ``key`` (robot pose unchanged)."""
        k_model, k_xy = jax.random.split(key)
        _, radius = self.model(k_model)
        return self.place_ball(state._replace(key=k_model), B.sample_start_xy(k_xy), radius)

    def execute(self, state: BallState, p, v, a0, a1, dt):
        r = self.robot
        model, _ = self.model(state.key)
        q_set, v_mid = setpoints(p, v, a0, a1, dt, self.substeps)

        def physics(data, k):
            data = mjx.step(model, data.replace(ctrl=r.ctrl(q_set[k], v_mid[k])))
            return data, data.qpos[r.qpos_adr]

        start = state.data.qpos[r.qpos_adr]
        data, measured = jax.lax.scan(physics, state.data, jnp.arange(self.substeps))
        ball = data.sensordata[self.sensor_adr:self.sensor_adr + 3]
        new = state._replace(data=data, ball_prev=state.ball, ball=ball, q=measured[-1])
        return new, jnp.concatenate([start[None], measured]), {"ball": ball}

    def scene(self, state: BallState) -> dict[str, Array]:
        """What a rendering needs beyond the arm's joints: ``{"ball": [3]}``, the ball centre in the
        plate frame [m] (every ball executor keeps it, whatever its physics)."""
        return {"ball": state.ball}
