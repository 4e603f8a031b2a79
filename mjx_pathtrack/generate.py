"""Dataset generation: reference paths recorded from random safe motions (REFERENCE §4.4).

``random``: from a random start inside the position limits, a random agent draws actions
U(-1, 1) per joint and step, maps them into the safe acceleration range (limits.py) and records
the setpoints at ``substeps`` per decision step; motions that enter self-collision (when a
collision check is given) are rejected. Each recording is resampled by curvature (0.1 -> 0.3,
REFERENCE §3.5) into a knot array. The rollouts are one jitted, vmapped scan.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack import limits as L
from mjx_pathtrack import spline

Array = jax.Array
#: ``in_collision(q [..., n]) -> bool [...]`` (self-collision of joint configurations)
CollisionFn = Callable[[np.ndarray], np.ndarray]


def random_motions(limits: L.JointLimits, key: Array, n: int, steps: int, dt: float, substeps: int,
                   start_margin: float = 0.1) -> Array:
    """Setpoint positions ``[n, steps * substeps + 1, joints]`` of ``n`` random-agent motions
    starting at rest, uniformly inside the position limits shrunk by ``start_margin`` of the range."""
    k_start, k_act = jax.random.split(key)
    lo, hi = limits.pos_min, limits.pos_max
    span = hi - lo
    p0 = jax.random.uniform(k_start, (n, lo.shape[0]), minval=lo + start_margin * span, maxval=hi - start_margin * span)
    zero = jnp.zeros_like(p0)
    t = dt * jnp.arange(1, substeps + 1) / substeps

    def step(state, k):
        p, v, a = state
        a_min, a_max = L.safe_acceleration_range(limits, p, v, a, dt)
        a1 = L.action_to_acceleration(jax.random.uniform(k, p.shape, minval=-1.0, maxval=1.0), a_min, a_max)
        q, _, _ = L.integrate(p[:, None], v[:, None], a[:, None], a1[:, None], dt, t[None, :, None])
        p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
        return (p1, v1, a1), q

    _, q = jax.lax.scan(step, (p0, zero, zero), jax.random.split(k_act, steps))
    q = jnp.moveaxis(q, 0, 1).reshape(n, steps * substeps, -1)
    return jnp.concatenate([p0[:, None], q], axis=1)


def random_paths(limits: L.JointLimits, n_paths: int, seed: int, steps: int = 80, dt: float = 0.1,
                 substeps: int = 24, in_collision: CollisionFn | None = None, path_joints=None,
                 resampling_distance: float = 0.1, curvature_distance: float = 0.3,
                 max_attempts: int = 20) -> list[np.ndarray]:
    """``n_paths`` knot arrays ``[K_i, path joints]`` (deterministic for ``seed``).

    All joints of ``limits`` move; motions with a self-colliding setpoint (``in_collision``
    over all joints) are rejected; the knots cover ``path_joints`` (indices, default all).
    ``steps = 80`` decision steps (8 s) give paths like the papers' iiwa random set (~23 rad,
    ~150 knots, REFERENCE §4.1); the recording duration is not published."""
    key = jax.random.PRNGKey(seed)
    rollout = jax.jit(random_motions, static_argnums=(2, 3, 4, 5))
    paths: list[np.ndarray] = []
    for _ in range(max_attempts):
        key, sub = jax.random.split(key)
        motions = np.asarray(rollout(limits, sub, n_paths, steps, dt, substeps), np.float64)
        if in_collision is not None:
            hit = np.asarray(in_collision(motions)).any(axis=1)
            motions = motions[~hit]
        if path_joints is not None:
            motions = motions[..., np.asarray(path_joints)]
        for m in motions:
            paths.append(spline.resample(m, distance=resampling_distance, curvature_distance=curvature_distance))
            if len(paths) == n_paths:
                return paths
    raise RuntimeError(f"only {len(paths)} of {n_paths} collision-free motions after {max_attempts} batches")


KINDS = ("random", "ball_balancing")


def generate_dataset(robot: str, kind: str = "random", num_train: int = 200, num_test: int = 200,
                     seed: int = 0, root=None, overwrite: bool = False, steps: int = 80, dt: float = 0.1):
    """Generate ``<root>/<robot>/<kind>/{train,test}.npz`` and ``config.json`` (deterministic for
    ``seed``: the train split uses ``seed``, the test split ``seed + 1``). Returns the directory."""
    from mjx_pathtrack import datasets, robots

    if kind not in KINDS:
        raise datasets.DatasetError(f"unknown dataset kind {kind!r} to generate; known: {', '.join(KINDS)}")
    if kind == "ball_balancing":  # level-plate paths (mjx_pathtrack.generate_ball)
        from mjx_pathtrack.generate_ball import generate_ball_dataset

        return generate_ball_dataset(robot, num_train, num_test, seed, root, overwrite, dt)
    if robot not in robots.known_robots():
        raise datasets.DatasetError(f"unknown robot {robot!r}; known: {', '.join(robots.known_robots())}")
    directory = datasets.dataset_dir(robot, kind, root)
    if (directory / "config.json").exists() and not overwrite:
        raise datasets.DatasetError(f"{directory} exists (use overwrite=True / --overwrite to replace it)")
    loaded = robots.load_robot(robot, dt=dt)
    path_joints = np.flatnonzero(np.asarray(loaded.path_mask))
    names = [loaded.joint_names[i] for i in path_joints]
    splits = {}
    for split, count, split_seed in (("train", num_train, seed), ("test", num_test, seed + 1)):
        if count > 0:
            splits[split] = random_paths(loaded.limits, count, split_seed, steps=steps, dt=dt,
                                         in_collision=lambda q: robots.in_collision(loaded, q),
                                         path_joints=path_joints)
            datasets.save_split(directory / f"{split}.npz", splits[split])
    config = dict(format_version=datasets.FORMAT_VERSION, robot=robot, kind=kind, n_joints=len(path_joints),
                  joint_names=names, max_dis_between_knots=datasets.max_dis_between_knots(splits.values()),
                  num_train=num_train, num_test=num_test,
                  source={"type": "random_agent", "seed": seed, "steps": steps, "dt": dt, "substeps": 24,
                          "resampling_distance": 0.1, "curvature_sampling_distance": 0.3,
                          "collision_check": "robots.in_collision on every setpoint"})
    datasets.write_config(directory / "config.json", config)
    return directory
