"""How setpoints become motion: the executor of one decision step (docs/architecture.md "Contracts").

An executor has ``init(p0) -> exec_state`` and ``execute(exec_state, p, v, a0, a1, dt) ->
(exec_state, executed [S+1, n], sensors)``: the step's acceleration goes linearly from ``a0`` to
``a1`` (limits.integrate); ``executed`` are the joint positions at the start and after each of
the ``S`` sub-steps; ``sensors`` is a dict of arrays (empty if none). Pure JAX, one environment
per call (vmap for batches).

* :class:`KinematicExecutor` -- an ideal trajectory controller: executed = setpoints. The papers'
  default for tasks without sensor feedback (docs/method.md §1: reward and observation are kinematic).
* :class:`MjxExecutor` -- position/velocity servos of a :class:`~mjx_pathtrack.robots.registry.Robot` in
  MJX physics, ``robot.n_substeps`` physics steps per decision step; executed = measured joint
  positions. Its state is the per-environment ``mjx.Data``.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
from mujoco import mjx

from mjx_pathtrack.core import limits as L

Array = jax.Array


def setpoints(p: Array, v: Array, a0: Array, a1: Array, dt: float, substeps: int) -> tuple[Array, Array]:
    """Setpoint positions ``[S+1, n]`` (start included) and velocities at the sub-step midpoints
    ``[S, n]`` of one constant-jerk step."""
    t = dt * jnp.arange(substeps + 1) / substeps
    q, _, _ = L.integrate(p, v, a0, a1, dt, t[:, None])
    t_mid = dt * (jnp.arange(substeps) + 0.5) / substeps
    _, v_mid, _ = L.integrate(p, v, a0, a1, dt, t_mid[:, None])
    return q, v_mid


class KinematicExecutor:
    """Executed motion = setpoints (ideal controller); no state, no sensors."""

    name = "kinematic"

    def __init__(self, substeps: int = 24):
        self.substeps = int(substeps)

    def init(self, p0: Array) -> None:
        del p0
        return None

    def execute(self, exec_state, p, v, a0, a1, dt):
        q, _ = setpoints(p, v, a0, a1, dt, self.substeps)
        return exec_state, q, {}


class MjxExecutor:
    """Servo-controlled MJX physics of ``robot`` over each decision step.

    Per physics step from ``t`` to ``t + sim_dt`` the servos get the setpoint position at ``t``
    and the setpoint velocity at ``t + sim_dt/2`` (:meth:`Robot.ctrl`'s timing convention);
    executed positions are the measured ``qpos`` of the controlled joints. ``sensors`` holds the
    measured joint velocities at the end of the step (``"qvel"`` ``[n]``).
    """

    name = "mjx"

    def __init__(self, robot):
        self.robot = robot
        self.substeps = int(robot.n_substeps)
        self._data0 = robot.mjx_data()
        _warn_if_slow_on_cpu()

    def init(self, p0: Array) -> Any:
        r = self.robot
        data = self._data0.replace(qpos=r.qpos(p0), qvel=jnp.zeros_like(self._data0.qvel),
                                   ctrl=r.ctrl(p0, jnp.zeros_like(p0)))
        return mjx.forward(r.mjx_model, data)

    def execute(self, data, p, v, a0, a1, dt):
        r = self.robot
        q_set, v_mid = setpoints(p, v, a0, a1, dt, self.substeps)

        def physics(data, k):
            data = data.replace(ctrl=r.ctrl(q_set[k], v_mid[k]))
            data = mjx.step(r.mjx_model, data)
            return data, data.qpos[r.qpos_adr]

        start = data.qpos[r.qpos_adr]
        data, measured = jax.lax.scan(physics, data, jnp.arange(self.substeps))
        return data, jnp.concatenate([start[None], measured]), {"qvel": data.qvel[r.dof_adr]}

    def scene(self, data) -> dict[str, Array]:
        """What a rendering needs beyond the controlled joints' positions, after a step:
        ``{"qpos": [nq]}``, the whole scene's pose in ``robot.mj_model`` (a floating base, joints
        the policy does not drive). Executors without a state (the kinematic one) have nothing to add
        and no ``scene``."""
        return {"qpos": data.qpos}


def _warn_if_slow_on_cpu() -> None:
    """A ``RuntimeWarning`` if batched MJX will run on the CPU without the fusion-emitter flag
    (mjx_pathtrack/_xla.py: ~1000x slower), naming the fix."""
    import os
    import warnings

    from mjx_pathtrack import _xla

    if jax.default_backend() == "cpu" and _xla.flag_missing(os.environ):
        warnings.warn(f"MJX physics on the CPU without XLA_FLAGS {_xla.FUSION_FLAG}: batched steps may be ~1000x "
                      f"slower. Call mjx_pathtrack.prepare_xla() before JAX starts, or set the flag in the "
                      f"environment (set {_xla.OPT_OUT_VAR}=1 to silence this).", RuntimeWarning, stacklevel=3)
