"""Target-point dataset (docs/paths.md §5, paper 000 §V-A): point-to-point motions between random
Cartesian targets, and the segment recorder it shares with the collision-aware random agent.

Target point. A path starts at rest in a random collision-free configuration. Repeatedly:

1. a random Cartesian target per target site (the iiwa's TCP; ARMAR's two fingertips) is drawn
   from the reachable workspace as the FK of a uniformly random configuration inside the
   position limits (a reachable-by-construction sample of the workspace);
2. inverse kinematics (:mod:`mjx_pathtrack.paths.ik`) turns it into a joint goal, seeded from the
   current configuration, two random configurations and the sampling configuration; among the
   converged solutions the one nearest (joint space) to the current configuration is the goal.
   Goals in self-collision are discarded;
3. a goal-seeking controller drives every joint to its goal through the safe action space
   (:func:`goal_seeking_acceleration`): "accelerate towards the goal unless braking is needed"
   (wanted velocity: the velocity limit, capped by a braking curve and a final exponential
   approach), the wanted acceleration mapped through the real safe range as an action in
   [-1, 1]. Joints move independently (not time-synchronised) and arrive at rest.
   Setpoints are recorded at ``substeps`` per decision step (240 Hz);
4. a segment with a self-colliding setpoint, or one that does not arrive within
   ``max_segment_steps``, is dropped and a new target drawn from the same state.

Segments are appended until the path has used ``steps`` decision steps; the recording is then
resampled by curvature (0.1 -> 0.3, docs/paths.md §3). Every path is driven by its own key
(``fold_in(seed, path index)``), so a larger split starts with the paths of a smaller one.

Collision-aware random agent (:func:`safe_random_paths`, used for robots whose random motions
almost always self-collide, e.g. ARMAR): random actions U(-1, 1) through the safe range in chunks
of ``chunk_steps`` decision steps; a chunk is accepted if it and the fastest safe stop from its
end (:func:`limits.braking_acceleration`) are collision-free, otherwise new random actions are
drawn; after ``retries`` failures the checked stop of the last accepted chunk is executed and the
agent continues from rest. This is the braking-trajectory idea of the papers' ref. [17].
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.paths import ik
from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import spline

Array = jax.Array

#: a joint has arrived when within this distance [rad] of its goal ...
REACH_POS = 1e-3
#: ... and slower than this [rad/s] (docs/method.md §3's robot-stopped threshold) ...
REACH_VEL = 1e-2
#: ... with an acceleration below this [rad/s^2]
REACH_ACC = 0.1
#: goal-seeking controller: braking curve at this fraction of the acceleration limit, final
#: exponential approach with time constant TAU [s], velocity error corrected within RESPONSE [s]
#: (tuned on random iiwa goals: no overshoot, arrival in ~3 s)
BRAKE_FRACTION = 0.3
TAU = 0.3
RESPONSE = 0.2


# ---------------------------------------------------------------------------------------------
# Controller (pure JAX)
# ---------------------------------------------------------------------------------------------


def goal_seeking_acceleration(limits: L.JointLimits, p: Array, v: Array, a: Array, goal: Array, dt,
                              brake_fraction: float = BRAKE_FRACTION, tau: float = TAU,
                              response: float = RESPONSE, speed=1.0) -> Array:
    """Next acceleration ``[..., n]`` that drives each joint to ``goal [..., n]`` (rad) at rest.

    "Accelerate towards the goal unless braking is needed": the wanted velocity is
    ``sign(d) min(V, sqrt(2 b A |d|), |d| / tau)`` for the distance ``d = goal - p`` (full speed,
    then the braking curve with ``b = brake_fraction`` of the acceleration limit ``A``, then an
    exponential final approach with time constant ``tau`` [s] so that the joint settles without
    overshoot); the wanted acceleration ``(v_wanted - v) / response`` is turned into an action in
    [-1, 1] of the real safe range of ``(p, v, a)`` and mapped back
    (:func:`limits.action_to_acceleration`), so every step is a safe-action-space step.
    ``speed`` (broadcastable to ``[..., n]``): the wanted speed's cap as a fraction of ``V``.
    """
    a_min, a_max = L.safe_acceleration_range(limits, p, v, a, dt)
    d = goal - p - v * dt   # distance left after this step (the acceleration only ramps within it)
    speed = jnp.minimum(jnp.minimum(speed * limits.vel, jnp.sqrt(2.0 * brake_fraction * limits.acc * jnp.abs(d))),
                        jnp.abs(d) / tau)
    wanted = jnp.clip((jnp.sign(d) * speed - v) / response, -limits.acc, limits.acc)
    width = a_max - a_min
    action = jnp.where(width > 0, 2.0 * (wanted - a_min) / jnp.where(width > 0, width, 1.0) - 1.0, 0.0)
    return L.action_to_acceleration(action, a_min, a_max)


def _substep_times(dt: float, substeps: int) -> Array:
    return dt * jnp.arange(1, substeps + 1) / substeps


def _step(limits, p, v, a, a1, dt, substeps):
    """Setpoints ``[B, substeps, n]`` of one decision step and the end state."""
    q, _, _ = L.integrate(p[:, None], v[:, None], a[:, None], a1[:, None], dt, _substep_times(dt, substeps)[None, :, None])
    p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
    return q, (p1, v1, a1)


@functools.partial(jax.jit, static_argnums=(3, 4, 5))
def target_segments(limits: L.JointLimits, p0: Array, goal: Array, steps: int, dt: float, substeps: int):
    """Goal-seeking motions from rest at ``p0 [B, n]`` to ``goal [B, n]``.

    Returns ``(q [B, steps*substeps + 1, n]`` setpoints (rad), ``arrived_at [B]`` int: the first
    decision step after which every joint is at rest at its goal (``steps + 1`` if never))."""
    zero = jnp.zeros_like(p0)

    def body(state, _):
        p, v, a = state
        a1 = goal_seeking_acceleration(limits, p, v, a, goal, dt)
        q, (p1, v1, a1) = _step(limits, p, v, a, a1, dt, substeps)
        done = jnp.all((jnp.abs(goal - p1) <= REACH_POS) & (jnp.abs(v1) <= REACH_VEL)
                       & (jnp.abs(a1) <= REACH_ACC), axis=-1)
        return (p1, v1, a1), (q, done)

    _, (q, done) = jax.lax.scan(body, (p0, zero, zero), None, length=steps)
    q = jnp.moveaxis(q, 0, 1).reshape(p0.shape[0], steps * substeps, -1)
    done = done.T  # [B, steps]
    arrived_at = jnp.where(done.any(axis=1), jnp.argmax(done, axis=1) + 1, steps + 1)
    return jnp.concatenate([p0[:, None], q], axis=1), arrived_at


@functools.partial(jax.jit, static_argnums=(5, 6, 7, 8))
def random_chunks(limits: L.JointLimits, key: Array, p: Array, v: Array, a: Array, steps: int, brake_steps: int,
                  dt: float, substeps: int):
    """``steps`` random-action steps from ``(p, v, a) [B, n]`` (keys ``key [B, 2]``), then the
    fastest safe stop for ``brake_steps``. Returns ``(q [B, steps*substeps, n], end state
    (p, v, a), q_stop [B, brake_steps*substeps, n], stop end state (p, v, a), stopped [B])``."""

    def body(state, x):
        k, random_step = x
        p, v, a = state
        a_min, a_max = L.safe_acceleration_range(limits, p, v, a, dt)
        u = jax.vmap(lambda kk: jax.random.uniform(kk, p.shape[-1:], minval=-1.0, maxval=1.0))(k)
        stop = L.braking_acceleration(limits, p, v, a, dt, (a_min, a_max))
        a1 = jnp.where(random_step, L.action_to_acceleration(u, a_min, a_max), stop)
        q, state = _step(limits, p, v, a, a1, dt, substeps)
        return state, (q, state)

    # one scan (random steps, then the stop): a single safe-range instance to compile
    keys = jax.vmap(lambda k: jax.random.split(k, steps))(key)                     # [B, steps, 2]
    keys = jnp.concatenate([keys, jnp.zeros((key.shape[0], brake_steps) + keys.shape[2:], keys.dtype)], axis=1)
    flags = jnp.arange(steps + brake_steps) < steps
    last, (q_all, states) = jax.lax.scan(body, (p, v, a), (jnp.moveaxis(keys, 1, 0), flags))
    end = jax.tree.map(lambda x: x[steps - 1], states)
    q, q_stop = q_all[:steps], q_all[steps:]
    stopped = jnp.all((jnp.abs(last[1]) <= REACH_VEL) & (jnp.abs(last[2]) <= REACH_VEL), axis=-1)
    flat = lambda x: jnp.moveaxis(x, 0, 1).reshape(p.shape[0], -1, p.shape[-1])  # noqa: E731
    return flat(q), end, flat(q_stop), last, stopped


# ---------------------------------------------------------------------------------------------
# Sampling helpers
# ---------------------------------------------------------------------------------------------


def _path_keys(seed: int, n: int, round_: int) -> Array:
    """One key per path for one round: ``fold_in(fold_in(seed, i), round)``."""
    base = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(base, i), round_))(jnp.arange(n))


def _uniform_configs(keys: Array, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """One uniform configuration ``[n]`` per key inside ``[lo, hi]``."""
    u = jax.vmap(lambda k: jax.random.uniform(k, lo.shape))(keys)
    return np.asarray(lo + np.asarray(u, np.float64) * (hi - lo))


def _finite_limits(limits: L.JointLimits, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(limits.pos_min, np.float64), np.asarray(limits.pos_max, np.float64)
    if not np.all(np.isfinite(lo) & np.isfinite(hi)):
        raise ValueError("target-point and safe-random generation need finite position limits on every joint")
    span = hi - lo
    return lo + margin * span, hi - margin * span


def _collision_free_starts(robot, seed: int, n: int, in_collision, margin: float, tries: int = 50) -> np.ndarray:
    lo, hi = _finite_limits(robot.limits, margin)
    starts = np.zeros((n, robot.n_joints))
    todo = np.arange(n)
    for t in range(tries):
        cand = _uniform_configs(_path_keys(seed, n, 10_000 + t), lo, hi)[todo]
        ok = ~np.asarray(in_collision(cand)) if in_collision is not None else np.ones(len(todo), bool)
        starts[todo[ok]] = cand[ok]
        todo = todo[~ok]
        if not len(todo):
            return starts
    raise RuntimeError(f"no collision-free start for {len(todo)} path(s) after {tries} tries")


# ---------------------------------------------------------------------------------------------
# Target point
# ---------------------------------------------------------------------------------------------


class TargetPointResult(NamedTuple):
    """``paths``: knot arrays ``[K_i, path joints]``; ``motions``: raw setpoints ``[T_i, n]``;
    ``goals``: per path ``[G_i, n]`` joint goals reached in order; ``targets``: per path
    ``[G_i, k, 3]`` Cartesian targets [m] they reach."""

    paths: list
    motions: list
    goals: list
    targets: list


def target_point_paths(robot, n_paths: int, seed: int, steps: int = 100, dt: float = 0.1, substeps: int = 24,
                       in_collision: Callable | None = None, max_segment_steps: int = 60, ik_seeds: int = 2,
                       sample_margin: float = 0.05, resampling_distance: float = 0.1,
                       curvature_distance: float = 0.3, max_rounds: int | None = None,
                       path_joints=None, log: Callable[[str], None] | None = None) -> TargetPointResult:
    """``n_paths`` target-point paths of ``robot`` (a :class:`robots.Robot`; see module
    docstring), deterministic for ``seed``. ``steps``: decision steps of motion per path (the
    last segment is completed); ``in_collision(q [..., n]) -> bool [...]`` (None: no check);
    ``path_joints``: indices of the joints the knots cover (default all)."""
    if n_paths < 1 or steps < 1 or max_segment_steps < 1:
        raise ValueError(f"need n_paths, steps, max_segment_steps >= 1, got {n_paths}, {steps}, {max_segment_steps}")
    limits = robot.limits
    lo, hi = _finite_limits(limits, sample_margin)
    current = _collision_free_starts(robot, seed, n_paths, in_collision, sample_margin)
    segments = [[c[None].copy()] for c in current]   # copies: current is updated in place
    goals = [[] for _ in range(n_paths)]
    targets = [[] for _ in range(n_paths)]
    used = np.zeros(n_paths, int)
    max_rounds = max_rounds or 10 * (steps // 4 + 5)
    for round_ in range(max_rounds):
        active = used < steps
        if not active.any():
            break
        keys = jax.vmap(lambda k: jax.random.split(k, 2 + ik_seeds))(_path_keys(seed, n_paths, round_))
        sample_q = _uniform_configs(keys[:, 0], lo, hi)
        target = ik.target_positions(robot, sample_q)   # [B, k, 3]
        seeds = [current] + [_uniform_configs(keys[:, 1 + s], lo, hi) for s in range(ik_seeds)] + [sample_q]
        sol = ik.solve_ik(robot, np.stack([target] * len(seeds), 1), np.stack(seeds, 1))
        q_sol, ok = np.asarray(sol.q, np.float64), np.asarray(sol.converged)
        dist = np.where(ok, np.linalg.norm(q_sol - current[:, None], axis=-1), np.inf)
        pick = np.argmin(dist, axis=1)
        goal = q_sol[np.arange(n_paths), pick]
        valid = active & np.isfinite(dist.min(axis=1))
        if in_collision is not None:
            valid &= ~np.asarray(in_collision(goal))
        q, arrived_at = target_segments(limits, jnp.asarray(current, jnp.float32), jnp.asarray(goal, jnp.float32),
                                        max_segment_steps, dt, substeps)
        q, arrived_at = np.asarray(q, np.float64), np.asarray(arrived_at)
        valid &= arrived_at <= max_segment_steps
        for i in np.flatnonzero(valid):
            seg = q[i, : arrived_at[i] * substeps + 1]
            if in_collision is not None and np.asarray(in_collision(seg)).any():
                continue
            segments[i].append(seg[1:])
            goals[i].append(goal[i])
            targets[i].append(target[i])
            current[i] = seg[-1]
            used[i] += arrived_at[i]
        if log:
            log(f"round {round_}: {int(valid.sum())} segments arrived, {int(np.sum(used >= steps))}/{n_paths} "
                f"paths done, mean steps used {used.mean():.1f}")
    else:
        if (used < steps).any():
            raise RuntimeError(f"{int(np.sum(used < steps))} of {n_paths} target-point paths unfinished after "
                               f"{max_rounds} rounds (unreachable or colliding targets?)")
    motions = [np.concatenate(s) for s in segments]
    paths = _resample(motions, path_joints, resampling_distance, curvature_distance, limits)
    return TargetPointResult(paths, motions, [np.array(g) for g in goals], [np.array(t) for t in targets])


# ---------------------------------------------------------------------------------------------
# Collision-aware random agent
# ---------------------------------------------------------------------------------------------


def safe_random_paths(robot, n_paths: int, seed: int, steps: int = 80, dt: float = 0.1, substeps: int = 24,
                      in_collision: Callable | None = None, chunk_steps: int = 5, brake_steps: int = 6,
                      retries: int = 4, start_margin: float = 0.1, resampling_distance: float = 0.1,
                      curvature_distance: float = 0.3, max_rounds: int | None = None,
                      path_joints=None) -> tuple[list, list]:
    """``(paths, motions)``: random safe motions of ``steps`` decision steps with collisions
    avoided chunk by chunk (see module docstring); deterministic for ``seed``."""
    limits = robot.limits
    p = _collision_free_starts(robot, seed, n_paths, in_collision, start_margin)
    v, a = np.zeros_like(p), np.zeros_like(p)
    stop = [None] * n_paths  # checked stop of the last accepted chunk (None: at rest)
    segments = [[x[None].copy()] for x in p]   # copies: p is updated in place
    used = np.zeros(n_paths, int)
    fails = np.zeros(n_paths, int)
    max_rounds = max_rounds or 20 * (steps // chunk_steps + 2)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    for round_ in range(max_rounds):
        active = used < steps
        if not active.any():
            break
        q, end, q_stop, last, stopped = random_chunks(limits, _path_keys(seed, n_paths, round_), f32(p), f32(v), f32(a),
                                                chunk_steps, brake_steps, dt, substeps)
        q, q_stop, stopped = np.asarray(q, np.float64), np.asarray(q_stop, np.float64), np.asarray(stopped)
        end = [np.asarray(x, np.float64) for x in end]
        last = [np.asarray(x, np.float64) for x in last]
        for i in np.flatnonzero(active):
            whole = np.concatenate([q[i], q_stop[i]])
            if stopped[i] and (in_collision is None or not np.asarray(in_collision(whole)).any()):
                segments[i].append(q[i])
                p[i], v[i], a[i] = end[0][i], end[1][i], end[2][i]
                stop[i] = (q_stop[i], last[0][i], last[1][i], last[2][i])
                used[i] += chunk_steps
                fails[i] = 0
                continue
            fails[i] += 1
            if fails[i] >= retries and stop[i] is not None:   # take the checked stop, go on from rest
                segments[i].append(stop[i][0])
                p[i], v[i], a[i] = stop[i][1:]
                stop[i] = None
                used[i] += brake_steps
                fails[i] = 0
    else:
        if (used < steps).any():
            raise RuntimeError(f"{int(np.sum(used < steps))} of {n_paths} random paths unfinished after "
                               f"{max_rounds} rounds")
    motions = [np.concatenate(s) for s in segments]
    return _resample(motions, path_joints, resampling_distance, curvature_distance, limits), motions


def _resample(motions, path_joints, distance, curvature_distance, limits) -> list[np.ndarray]:
    """Curvature-resampled knots of the path joints, clipped into the position limits: the
    resampled spline can overshoot a stop next to a limit by up to ~1e-3 rad."""
    cols = slice(None) if path_joints is None else np.asarray(path_joints)
    lo, hi = np.asarray(limits.pos_min, np.float64)[cols], np.asarray(limits.pos_max, np.float64)[cols]
    return [np.clip(spline.resample(m[:, cols], distance=distance, curvature_distance=curvature_distance), lo, hi)
            for m in motions]


# ---------------------------------------------------------------------------------------------
# Smooth target point: through the targets without stopping
# ---------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnums=(3, 4, 5, 8))
def through_goals(limits: L.JointLimits, p0: Array, goals: Array, steps: int, dt: float, substeps: int,
                  switch: Array, speed: Array, response: float = RESPONSE):
    """Goal-seeking motions from rest at ``p0 [B, n]`` through the joint goals ``goals [B, G, n]``
    in order without stopping: the controller (:func:`goal_seeking_acceleration`) heads for the
    current goal and moves on to the next as soon as every joint is within ``switch [B]`` rad of
    it (the last goal is approached to rest); ``speed [B]``: the wanted speed as a fraction of the
    velocity limits; ``response`` [s]: the controller's velocity response time (longer: rounder
    turns). Returns ``(q [B, steps*substeps + 1, n]``
    setpoints, ``passed [B, steps]`` int: goals passed after each decision step)."""
    zero = jnp.zeros_like(p0)
    n_goals = goals.shape[1]

    def body(state, _):
        p, v, a, g = state
        goal = jnp.take_along_axis(goals, jnp.minimum(g, n_goals - 1)[:, None, None], axis=1)[:, 0]
        a1 = goal_seeking_acceleration(limits, p, v, a, goal, dt, response=response, speed=speed[:, None])
        q, (p1, v1, a1) = _step(limits, p, v, a, a1, dt, substeps)
        near = jnp.max(jnp.abs(goal - p1), axis=-1) <= switch
        g = jnp.where(near & (g < n_goals - 1), g + 1, g)
        return (p1, v1, a1, g), (q, g)

    _, (q, passed) = jax.lax.scan(body, (p0, zero, zero, jnp.zeros(p0.shape[0], jnp.int32)), None, length=steps)
    q = jnp.moveaxis(q, 0, 1).reshape(p0.shape[0], steps * substeps, -1)
    return jnp.concatenate([p0[:, None], q], axis=1), passed.T


def _goal_chain(robot, seed: int, n: int, n_goals: int, start: np.ndarray, lo, hi, in_collision, ik_seeds: int,
                spread: float | None = None):
    """``[n, n_goals + 1, joints]``: the start and ``n_goals`` joint goals per path, each the IK
    solution (nearest of several seeds to the previous goal) of a random reachable Cartesian
    target: the tool point of a uniformly random configuration, or with ``spread`` [rad] of the
    previous goal moved by a normal step of that standard deviation per joint (nearer targets);
    a goal in self-collision or not reached is replaced by the previous one."""
    chain = [start.copy()]
    for g in range(n_goals):
        keys = jax.vmap(lambda k: jax.random.split(k, 2 + ik_seeds))(_path_keys(seed, n, 20_000 + g))
        sample_q = _uniform_configs(keys[:, 0], lo, hi)
        if spread is not None:
            step = np.asarray(jax.vmap(lambda k: jax.random.normal(k, lo.shape))(keys[:, 0]), np.float64)
            sample_q = np.clip(chain[-1] + spread * step, lo, hi)
        target = ik.target_positions(robot, sample_q)
        prev = chain[-1]
        seeds = [prev] + [_uniform_configs(keys[:, 1 + s], lo, hi) for s in range(ik_seeds)] + [sample_q]
        sol = ik.solve_ik(robot, np.stack([target] * len(seeds), 1), np.stack(seeds, 1))
        q_sol, ok = np.asarray(sol.q, np.float64), np.asarray(sol.converged)
        dist = np.where(ok, np.linalg.norm(q_sol - prev[:, None], axis=-1), np.inf)
        goal = q_sol[np.arange(n), np.argmin(dist, axis=1)]
        valid = np.isfinite(dist.min(axis=1))
        if in_collision is not None:
            valid &= ~np.asarray(in_collision(goal))
        chain.append(np.where(valid[:, None], goal, prev))
    return np.stack(chain, 1)


def smooth_target_point_paths(robot, n_paths: int, seed: int, steps: int = 170, dt: float = 0.1, substeps: int = 24,
                              in_collision: Callable | None = None, n_goals: int = 60,
                              switch_range: tuple[float, float] = (0.3, 0.8),
                              speed_range: tuple[float, float] = (0.5, 1.0), target_spread: float | None = 0.7,
                              response: float = 0.4, ik_seeds: int = 2,
                              sample_margin: float = 0.05, resampling_distance: float = 0.1,
                              curvature_distance: float = 0.3, min_steps: int = 40, path_joints=None,
                              max_rounds: int = 20) -> TargetPointResult:
    """Target-point paths that move *through* their targets without stopping (the papers'
    reaching agent's recordings; paper 000 §V-A): random reachable Cartesian targets as joint
    goals (:func:`_goal_chain`), driven through by :func:`through_goals` with a per-path switch
    radius drawn from ``switch_range`` [rad] (small: close to every target, sharp turns; large:
    wide sweeping curves) and a wanted speed drawn from ``speed_range`` (fractions of the velocity
    limits), targets anywhere in the workspace or (``target_spread`` [rad]) near the previous one,
    the controller's velocity response ``response`` [s], ``steps`` decision steps of motion, resampled by curvature. A motion
    with a self-colliding setpoint is cut before it; one left shorter than ``min_steps`` is
    drawn again. Deterministic for ``seed``. The defaults give the statistics of the papers' iiwa
    target-point test set within 10 % (docs/paths.md §4; docs/results.md "Datasets")."""
    if n_paths < 1 or steps < min_steps or n_goals < 1:
        raise ValueError(f"need n_paths >= 1, steps >= min_steps, n_goals >= 1; got {n_paths}, {steps}, {n_goals}")
    limits = robot.limits
    lo, hi = _finite_limits(limits, sample_margin)
    motions: list[np.ndarray] = []
    goals_out: list[np.ndarray] = []
    for round_ in range(max_rounds):
        need = n_paths - len(motions)
        if need <= 0:
            break
        sub_seed = seed * 1000 + round_
        start = _collision_free_starts(robot, sub_seed, need, in_collision, sample_margin)
        chain = _goal_chain(robot, sub_seed, need, n_goals, start, lo, hi, in_collision, ik_seeds, target_spread)
        switch = np.asarray(jax.random.uniform(jax.random.PRNGKey(sub_seed), (need,), minval=switch_range[0],
                                               maxval=switch_range[1]))
        speed = np.asarray(jax.random.uniform(jax.random.PRNGKey(sub_seed + 7), (need,), minval=speed_range[0],
                                              maxval=speed_range[1]))
        q, _ = through_goals(limits, jnp.asarray(start, jnp.float32), jnp.asarray(chain[:, 1:], jnp.float32), steps,
                             dt, substeps, jnp.asarray(switch, jnp.float32), jnp.asarray(speed, jnp.float32), response)
        q = np.asarray(q, np.float64)
        for i in range(need):
            m = q[i]
            if in_collision is not None:
                hit = np.flatnonzero(np.asarray(in_collision(m[::4])))
                if hit.size:
                    m = m[: max(4 * hit[0] - substeps, 1)]
            if len(m) >= min_steps * substeps:
                motions.append(m)
                goals_out.append(chain[i])
    else:
        if len(motions) < n_paths:
            raise RuntimeError(f"only {len(motions)} of {n_paths} smooth target-point paths after {max_rounds} rounds")
    motions = motions[:n_paths]
    paths = _resample(motions, path_joints, resampling_distance, curvature_distance, limits)
    return TargetPointResult(paths, motions, goals_out[:n_paths], [np.zeros((0, 3))] * n_paths)
