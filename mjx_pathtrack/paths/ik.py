"""Position inverse kinematics of a robot's target points: damped least squares in pure JAX.

``solve_ik(robot, targets, q_seed)`` finds joint positions ``q [..., n]`` whose target points
(``robot.target_sites``, e.g. the iiwa's TCP or ARMAR's two fingertips; positions only, no
orientation) reach ``targets [..., k, 3]`` [m], starting from ``q_seed``. Each iteration takes the
damped least-squares step ``dq = J^T (J J^T + lambda^2 I)^-1 e`` (``e`` = target - FK position,
``J`` the geometric Jacobian of the target points from one ``mjx.kinematics`` call, the same
kinematics as :meth:`Robot.fk`), shortens it to at most
``max_step`` rad per joint and clips ``q`` into the position limits (shrunk by ``margin``), so
every iterate and the result respect the joint limits. The best iterate (lowest error) is
returned. The loop is a ``lax.fori_loop`` vmapped over the batch and jitted once per robot,
batch shape and iteration count.

Unreachable targets do not raise: ``IKResult.converged`` is False where the error stays above
``tol``. Malformed input (shapes, NaN, seeds outside the limits) raises ``ValueError`` naming it.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

#: default convergence tolerance on the largest target-point error [m]
TOL = 1e-3


class IKResult(NamedTuple):
    """``q [..., n]`` joint positions (rad, inside the limits), ``error [...]`` the largest
    target-point distance at ``q`` [m], ``converged [...]`` bool (``error <= tol``)."""

    q: Array
    error: Array
    converged: Array


def _bounds(robot, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(robot.limits.pos_min, np.float64)
    hi = np.asarray(robot.limits.pos_max, np.float64)
    shrink = margin * np.where(np.isfinite(hi - lo), hi - lo, 0.0)
    return lo + shrink, hi - shrink


def check_input(robot, targets, q_seed) -> tuple[np.ndarray, np.ndarray]:
    """Validate and broadcast ``targets [..., k, 3]`` and ``q_seed [..., n]`` (same batch
    shape, or a single seed ``[n]`` for every target); ``ValueError`` names the problem."""
    k, n = len(robot.target_sites), robot.n_joints
    if k == 0:
        raise ValueError(f"{robot.name}: the robot has no target sites to solve for")
    t = np.asarray(targets, np.float64)
    q = np.asarray(q_seed, np.float64)
    if t.ndim < 2 or t.shape[-2:] != (k, 3):
        raise ValueError(f"{robot.name}: targets must have shape [..., {k}, 3] (one xyz point in m per target "
                         f"site {', '.join(robot.target_sites)}), got {t.shape}")
    if q.ndim < 1 or q.shape[-1] != n:
        raise ValueError(f"{robot.name}: q_seed must have shape [..., {n}], got {q.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{robot.name}: targets contain NaN/inf at index {tuple(np.argwhere(~np.isfinite(t))[0])}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"{robot.name}: q_seed contains NaN/inf at index {tuple(np.argwhere(~np.isfinite(q))[0])}")
    lo, hi = np.asarray(robot.limits.pos_min), np.asarray(robot.limits.pos_max)
    bad = np.argwhere((q < lo - 1e-6) | (q > hi + 1e-6))
    if bad.size:
        j = int(bad[0][-1])
        raise ValueError(f"{robot.name}: q_seed {robot.joint_names[j]} = {q[tuple(bad[0])]:.6g} is outside the "
                         f"position limits [{lo[j]:.6g}, {hi[j]:.6g}]")
    batch = t.shape[:-2]
    if q.shape[:-1] != batch:
        try:
            q = np.broadcast_to(q, batch + (n,))
        except ValueError:
            raise ValueError(f"{robot.name}: q_seed batch shape {q.shape[:-1]} does not match the targets' "
                             f"batch shape {batch}") from None
    return t, q


def solve_ik(robot, targets, q_seed, iterations: int = 100, damping: float = 0.05, max_step: float = 0.3,
             tol: float = TOL, margin: float = 1e-3) -> IKResult:
    """Joint positions reaching ``targets [..., k, 3]`` [m] from ``q_seed [..., n]`` (see module
    docstring). ``damping`` lambda [m], ``max_step`` [rad] per joint and iteration, ``margin``:
    fraction of each joint range kept free at both limits."""
    if iterations < 1 or not damping > 0 or not max_step > 0 or not tol > 0 or not 0 <= margin < 0.5:
        raise ValueError(f"solve_ik: need iterations >= 1, damping > 0, max_step > 0, tol > 0, 0 <= margin < 0.5; "
                         f"got {iterations}, {damping}, {max_step}, {tol}, {margin}")
    t, q = check_input(robot, targets, q_seed)
    batch = t.shape[:-2]
    lo, hi = _bounds(robot, margin)
    q = np.clip(q, lo, hi)
    fn = _solver(robot, int(iterations))
    qs, err = fn(jnp.asarray(t.reshape((-1,) + t.shape[-2:]), jnp.float32),
                 jnp.asarray(q.reshape(-1, robot.n_joints), jnp.float32),
                 jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32),
                 jnp.float32(damping), jnp.float32(max_step))
    qs, err = qs.reshape(batch + (robot.n_joints,)), err.reshape(batch)
    return IKResult(qs, err, err <= tol)


#: jitted functions per (robot name, what): a registry name always means the same kinematics
_JITTED: dict = {}


def _solver(robot, iterations: int):
    """The jitted batched solver of ``robot`` (cached per robot name and iteration count)."""
    key = (robot.name, "solve", iterations)
    if key not in _JITTED:
        _JITTED[key] = jax.jit(functools.partial(_solve_batch, _kinematics(robot), iterations))
    return _JITTED[key]


def target_positions(robot, q) -> np.ndarray:
    """Target-point positions ``[..., k, 3]`` [m] of ``q [..., n]`` (jitted; same kinematics as
    :meth:`Robot.fk`)."""
    robot._check_q(q)
    q = np.asarray(q, np.float32)
    key = (robot.name, "positions")
    if key not in _JITTED:
        kin = _kinematics(robot)
        _JITTED[key] = jax.jit(jax.vmap(lambda qi: kin(qi)[0]))
    pos = _JITTED[key](jnp.asarray(q.reshape(-1, robot.n_joints)))
    return np.asarray(pos, np.float64).reshape(q.shape[:-1] + (len(robot.target_sites), 3))


def _kinematics(robot):
    """``f(q [n]) -> (pos [k*3], jac [k*3, n])``: target-point positions and their geometric
    Jacobian from one ``mjx.kinematics`` call (hinge column ``axis x (p - anchor)``, slide column
    ``axis``; zero where the joint is not an ancestor of the site's body). Cheaper to compile
    than ``jax.jacfwd`` through the kinematics."""
    from mujoco import mjx

    model = robot.mj_model
    joint_ids = np.array([model.joint(name).id for name in robot.joint_names])
    hinge = jnp.asarray(model.jnt_type[joint_ids] == 3)  # mjJNT_HINGE; else mjJNT_SLIDE
    if not np.all(np.isin(model.jnt_type[joint_ids], (2, 3))):
        raise ValueError(f"{robot.name}: IK supports hinge and slide joints only")
    site_bodies = model.site_bodyid[robot.site_ids]
    depends = np.zeros((len(site_bodies), len(joint_ids)), bool)
    for s, body in enumerate(site_bodies):
        chain = set()
        while body > 0:
            chain.add(int(body))
            body = int(model.body_parentid[body])
        depends[s] = [int(model.jnt_bodyid[j]) in chain for j in joint_ids]
    depends = jnp.asarray(depends, jnp.float32)[:, None, :]       # [k, 1, n]
    sites = jnp.asarray(robot.site_ids)
    joints = jnp.asarray(joint_ids)
    data = mjx.make_data(robot.mjx_model)

    def f(q):
        d = mjx.kinematics(robot.mjx_model, data.replace(qpos=robot.qpos(q)))
        pos = d.site_xpos[sites]                                   # [k, 3]
        axis, anchor = d.xaxis[joints], d.xanchor[joints]          # [n, 3]
        rot = jnp.cross(axis[None], pos[:, None] - anchor[None])   # [k, n, 3]
        col = jnp.where(hinge[None, :, None], rot, axis[None])
        jac = jnp.swapaxes(col, 1, 2) * depends                    # [k, 3, n]
        return pos.reshape(-1), jac.reshape(-1, q.shape[-1])

    return f


def _solve_batch(kin, iterations: int, targets: Array, q: Array, lo: Array, hi: Array, damping: Array,
                 max_step: Array) -> tuple[Array, Array]:
    """``targets [B, k, 3]``, ``q [B, n]`` -> best ``q [B, n]`` and its error ``[B]`` [m]."""

    def one(ti, q0):
        goal = ti.reshape(-1)
        eye = jnp.eye(goal.shape[0], dtype=q0.dtype)

        def err(pos):
            return jnp.max(jnp.linalg.norm((pos - goal).reshape(-1, 3), axis=-1))

        def body(_, carry):
            qi, best_q, best_e = carry
            pos, jac = kin(qi)
            e_i = err(pos)
            better = e_i < best_e
            best_q, best_e = jnp.where(better, qi, best_q), jnp.where(better, e_i, best_e)
            dq = jac.T @ jnp.linalg.solve(jac @ jac.T + damping**2 * eye, goal - pos)
            dq = dq * jnp.minimum(1.0, max_step / jnp.maximum(jnp.max(jnp.abs(dq)), 1e-12))
            return jnp.clip(qi + dq, lo, hi), best_q, best_e

        q_last, best_q, best_e = jax.lax.fori_loop(0, iterations, body, (q0, q0, jnp.inf))
        e_last = err(kin(q_last)[0])
        better = e_last < best_e
        return jnp.where(better, q_last, best_q), jnp.where(better, e_last, best_e)

    return jax.vmap(one)(targets, q)
