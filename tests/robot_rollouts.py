"""Test helper: random safe setpoint trajectories from limits.py, sampled per physics step.

Used by the tracking tests (MJX and MuJoCo C) of tests/robots/test_registry.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import limits as L


def safe_setpoints(robot, key, n_steps: int, batch: int):
    """Random safe trajectories from ``robot.q0`` at rest, ``n_steps`` decision steps long.

    Returns float32 arrays ``[batch, n_steps * robot.n_substeps, n]``:
    ``q_start`` (setpoint at the start of each physics step: the position actuator's control),
    ``v_mid`` (setpoint velocity at the middle of the step: the velocity actuator's control) and
    ``q_end`` (setpoint at the end of the step: what the executed position must match).
    """
    lim, dt, n, sub = robot.limits, robot.dt, robot.n_joints, robot.n_substeps
    frac = jnp.arange(sub + 1, dtype=jnp.float32) / sub

    @jax.jit
    def run(key):
        def step(carry, k):
            p, v, a = carry
            lo, hi = L.safe_acceleration_range(lim, p, v, a, dt)
            a1 = L.action_to_acceleration(jax.random.uniform(k, p.shape, minval=-1.0, maxval=1.0), lo, hi)
            t = dt * frac[None, :, None]
            ps, _, _ = L.integrate(p[:, None], v[:, None], a[:, None], a1[:, None], dt, t)
            _, vm, _ = L.integrate(p[:, None], v[:, None], a[:, None], a1[:, None], dt, 0.5 * (t[:, 1:] + t[:, :-1]))
            p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
            return (p1, v1, a1), (ps[:, :-1], vm, ps[:, 1:])

        p0 = jnp.broadcast_to(jnp.asarray(robot.q0, jnp.float32), (batch, n))
        zeros = jnp.zeros_like(p0)
        _, out = jax.lax.scan(step, (p0, zeros, zeros), jax.random.split(key, n_steps))
        # [steps, batch, sub, n] -> [batch, steps * sub, n]
        return tuple(x.transpose(1, 0, 2, 3).reshape(batch, n_steps * sub, n) for x in out)

    return tuple(np.asarray(x) for x in run(key))
