"""Dataset generation: reference paths recorded from random safe motions (docs/paths.md §5), and
the registry of dataset kinds (:data:`KINDS`: ``random``, ``target_point`` -> generator).

``random``: from a random start inside the position limits, a random agent draws actions
U(-1, 1) per joint and step, maps them into the safe acceleration range (limits.py) and records
the setpoints at ``substeps`` per decision step; motions that enter self-collision (when a
collision check is given) are rejected. Each recording is resampled by curvature (0.1 -> 0.3,
docs/paths.md §3) into a knot array. The rollouts are one jitted, vmapped scan.
"""

from __future__ import annotations

import functools
import inspect
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import spline

Array = jax.Array
#: ``in_collision(q [..., n]) -> bool [...]`` (self-collision of joint configurations)
CollisionFn = Callable[[np.ndarray], np.ndarray]


def random_motions(limits: L.JointLimits, key: Array, n: int, steps: int, dt: float, substeps: int,
                   start_margin: float = 0.1, hold: tuple[int, int] | None = None) -> Array:
    """Setpoint positions ``[n, steps * substeps + 1, joints]`` of ``n`` random-agent motions
    starting at rest, uniformly inside the position limits shrunk by ``start_margin`` of the range.

    ``hold`` None: a new action U(-1, 1) per joint at every decision step (the papers' random
    agent: the velocities random-walk, the curve bends at every step). ``hold = (lo, hi)``: each
    joint keeps its action for a random number of decision steps in ``[lo, hi]`` (drawn anew at
    every change, independently per joint), so joints cruise, often at their velocity limit,
    and reverse at speed: long low-curvature stretches with single-joint turnarounds, the curves
    of smooth user motions (the ``persistent_random`` kind)."""
    k_start, k_act = jax.random.split(key)
    lo, hi = limits.pos_min, limits.pos_max
    span = hi - lo
    p0 = jax.random.uniform(k_start, (n, lo.shape[0]), minval=lo + start_margin * span, maxval=hi - start_margin * span)
    zero = jnp.zeros_like(p0)
    t = dt * jnp.arange(1, substeps + 1) / substeps
    hold_lo, hold_hi = (1, 1) if hold is None else (int(hold[0]), int(hold[1]))
    if not 1 <= hold_lo <= hold_hi:
        raise ValueError(f"hold must be (lo, hi) decision steps with 1 <= lo <= hi, got {hold}")

    def step(state, k):
        p, v, a, u, left = state
        if hold is None:  # the papers' agent, with the key stream of the committed random datasets
            u = jax.random.uniform(k, p.shape, minval=-1.0, maxval=1.0)
        else:
            k_u, k_n = jax.random.split(k)
            change = left <= 0
            u = jnp.where(change, jax.random.uniform(k_u, p.shape, minval=-1.0, maxval=1.0), u)
            left = jnp.where(change, jax.random.randint(k_n, p.shape, hold_lo, hold_hi + 1), left) - 1
        a_min, a_max = L.safe_acceleration_range(limits, p, v, a, dt)
        a1 = L.action_to_acceleration(u, a_min, a_max)
        q, _, _ = L.integrate(p[:, None], v[:, None], a[:, None], a1[:, None], dt, t[None, :, None])
        p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
        return (p1, v1, a1, u, left), q

    init = (p0, zero, zero, zero, jnp.zeros(p0.shape, jnp.int32))
    _, q = jax.lax.scan(step, init, jax.random.split(k_act, steps))
    q = jnp.moveaxis(q, 0, 1).reshape(n, steps * substeps, -1)
    return jnp.concatenate([p0[:, None], q], axis=1)


def random_paths(limits: L.JointLimits, n_paths: int, seed: int, steps: int = 80, dt: float = 0.1,
                 substeps: int = 24, in_collision: CollisionFn | None = None, path_joints=None,
                 resampling_distance: float = 0.1, curvature_distance: float = 0.3,
                 max_attempts: int = 20, hold: tuple[int, int] | None = None) -> list[np.ndarray]:
    """``n_paths`` knot arrays ``[K_i, path joints]`` (deterministic for ``seed``).

    All joints of ``limits`` move; motions with a self-colliding setpoint (``in_collision``
    over all joints) are rejected; the knots cover ``path_joints`` (indices, default all).
    ``steps = 80`` decision steps (8 s) give paths like the papers' iiwa random set (~23 rad,
    ~150 knots, docs/paths.md §4); the recording duration is not published. ``hold``: the
    persistent agent of :func:`random_motions`."""
    key = jax.random.PRNGKey(seed)
    rollout = jax.jit(functools.partial(random_motions, hold=hold), static_argnums=(2, 3, 4, 5))
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


#: decision steps a ``persistent_random`` joint keeps its action (min, max): curvature median and
#: 95th percentile ~0.7 / 2.1 rad/rad, against ~1.6 / 4.3 of the step-wise random agent
PERSISTENT_HOLD = (2, 8)


def _random_split(robot, count: int, seed: int, steps: int = 80, dt: float = 0.1, agent: str | None = None):
    """``random`` kind: ``agent="reject"`` rejects whole self-colliding motions
    (:func:`random_paths`, the iiwa default); ``"chunked"`` avoids collisions chunk by chunk
    (:func:`generate_target.safe_random_paths`, the default for the ARMAR robots, whose whole
    random motions almost all self-collide)."""
    from mjx_pathtrack.paths import target as generate_target
    from mjx_pathtrack.robots.collision import in_collision

    agent = agent or RANDOM_AGENT.get(robot.name, "reject")
    path_joints = np.flatnonzero(np.asarray(robot.path_mask))
    collide = lambda q: in_collision(robot, q)  # noqa: E731
    source = {"type": "random_agent", "agent": agent, "seed": seed, "steps": steps, "dt": dt, "substeps": 24,
              "resampling_distance": 0.1, "curvature_sampling_distance": 0.3,
              "collision_check": "robots.in_collision on every setpoint"}
    if agent == "reject":
        return random_paths(robot.limits, count, seed, steps=steps, dt=dt, in_collision=collide,
                            path_joints=path_joints), source
    if agent == "chunked":
        paths, _ = generate_target.safe_random_paths(robot, count, seed, steps=steps, dt=dt, in_collision=collide,
                                                     path_joints=path_joints)
        return paths, source
    raise ValueError(f"unknown random agent {agent!r}; known: reject, chunked")


def _persistent_random_split(robot, count: int, seed: int, steps: int = 80, dt: float = 0.1,
                             hold: tuple[int, int] = PERSISTENT_HOLD):
    """``persistent_random`` kind: the random agent with actions held ``hold`` decision steps per
    joint (:func:`random_motions`): smooth curves whose joints cruise near their velocity limits
    and turn around one at a time, whole self-colliding motions rejected (iiwa only: the ARMARs'
    random motions need the chunked agent)."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots.collision import in_collision

    if RANDOM_AGENT.get(robot.name, "reject") != "reject":
        raise datasets.DatasetError(f"persistent_random paths need whole collision-free random motions, which "
                                    f"{robot.name} rarely has; use kind random (chunked agent)")
    hold = (int(hold[0]), int(hold[1]))
    source = {"type": "persistent_random_agent", "seed": seed, "steps": steps, "dt": dt, "substeps": 24,
              "hold": list(hold), "resampling_distance": 0.1, "curvature_sampling_distance": 0.3,
              "collision_check": "robots.in_collision on every setpoint"}
    paths = random_paths(robot.limits, count, seed, steps=steps, dt=dt, in_collision=lambda q: in_collision(robot, q),
                         path_joints=np.flatnonzero(np.asarray(robot.path_mask)), hold=hold)
    return paths, source


def _target_point_split(robot, count: int, seed: int, steps: int = 190, dt: float = 0.1):
    """``target_point`` kind (:mod:`mjx_pathtrack.paths.target`)."""
    from mjx_pathtrack.paths import target as generate_target
    from mjx_pathtrack.robots.collision import in_collision

    result = generate_target.target_point_paths(
        robot, count, seed, steps=steps, dt=dt, in_collision=lambda q: in_collision(robot, q),
        path_joints=np.flatnonzero(np.asarray(robot.path_mask)))
    source = {"type": "target_point", "seed": seed, "steps": steps, "dt": dt, "substeps": 24,
              "ik": "ik.solve_ik (damped least squares), nearest converged of 4 seeds",
              "controller": "goal_seeking_acceleration through the safe range",
              "resampling_distance": 0.1, "curvature_sampling_distance": 0.3,
              "collision_check": "robots.in_collision on every setpoint and goal"}
    return result.paths, source


def _smooth_target_point_split(robot, count: int, seed: int, steps: int = 170, dt: float = 0.1):
    """``smooth_target_point`` kind (:func:`mjx_pathtrack.paths.target.smooth_target_point_paths`):
    through random reachable targets without stopping, like the papers' reaching recordings."""
    from mjx_pathtrack.paths import target as generate_target
    from mjx_pathtrack.robots.collision import in_collision

    result = generate_target.smooth_target_point_paths(
        robot, count, seed, steps=steps, dt=dt, in_collision=lambda q: in_collision(robot, q),
        path_joints=np.flatnonzero(np.asarray(robot.path_mask)))
    source = {"type": "smooth_target_point", "seed": seed, "steps": steps, "dt": dt, "substeps": 24,
              "generator": "target.smooth_target_point_paths (defaults: 60 targets near the previous, "
                           "switch 0.3-0.8 rad, speed 0.5-1.0 of the limits, response 0.4 s)",
              "resampling_distance": 0.1, "curvature_sampling_distance": 0.3,
              "collision_check": "robots.in_collision on every 4th setpoint; a motion is cut before a collision"}
    return result.paths, source


def _mixed_split(robot, count: int, seed: int, dt: float = 0.1, max_spacing: float = 0.3,
                 target_share: float = 0.5, persistent_share: float = 0.0):
    """``mixed`` kind: the training distribution of the default policies, interleaved:
    smooth target-point paths (:func:`_smooth_target_point_split`, ``target_share``),
    persistent random-agent paths (:func:`_persistent_random_split`, ``persistent_share``; none
    by default: a third of them did not make the paper-preset policy better on the
    generalisation families, docs/results.md "Any path a user brings") and
    step-wise random-agent paths (:func:`_random_split`, the rest); every knot interval longer than
    ``max_spacing`` [rad] split (:func:`~mjx_pathtrack.core.knot_rule.cap_spacing`). Knots dense
    in bends (curvature rule) and never sparser than ``max_spacing`` on smooth stretches: a
    low-curvature curve (a user's smooth motion) then shows the policy knots like any other curve
    instead of a few far apart, which the uncapped rule gives it and no training path has
    (docs/results.md "Any path a user brings")."""
    from mjx_pathtrack.core.knot_rule import KnotRule, SPACING_SAFETY, cap_spacing
    from mjx_pathtrack.paths import datasets

    if not (0 <= target_share and 0 <= persistent_share and target_share + persistent_share <= 1):
        raise datasets.DatasetError(f"mixed: shares must be >= 0 with target_share + persistent_share <= 1, got "
                                    f"{target_share} and {persistent_share}")
    n_target = int(round(target_share * count))
    n_persistent = min(int(round(persistent_share * count)), count - n_target)
    n_random = count - n_target - n_persistent
    random, random_source = _random_split(robot, n_random, seed, dt=dt) if n_random else ([], {})
    target, target_source = _smooth_target_point_split(robot, n_target, seed, dt=dt) if n_target else ([], {})
    persistent, persistent_source = _persistent_random_split(robot, n_persistent, seed, dt=dt) if n_persistent \
        else ([], {})
    paths = []
    for i in range(max(len(random), len(target), len(persistent))):
        paths += random[i:i + 1] + target[i:i + 1] + persistent[i:i + 1]
    capped = []
    for p in paths:
        fit = spline.fit_spline(p)
        if np.diff(fit.knot_s).max() > max_spacing:
            p = spline.fit_spline(p).point_at(cap_spacing(fit.knot_s, SPACING_SAFETY * max_spacing))
        capped.append(p)
    source = {"type": "mixed", "seed": seed, "dt": dt, "max_spacing": max_spacing, "target_share": target_share,
              "persistent_share": persistent_share,
              "parts": {"random": random_source, "smooth_target_point": target_source,
                        "persistent_random": persistent_source},
              "knot_rule": KnotRule(0.1, 0.3, max_spacing).to_json(),
              "resampling_distance": 0.1, "curvature_sampling_distance": 0.3}
    return capped, source


def _ball_balancing_split(robot, count: int, seed: int, dt: float = 0.1):
    """``ball_balancing`` kind (:mod:`mjx_pathtrack.paths.ball`): level-plate paths of the
    iiwa; the plate kinematics come from ``iiwa_ball`` whatever the registry robot."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.paths import ball as generate_ball
    from mjx_pathtrack.robots import registry as robots

    if robot.name not in ("iiwa", "iiwa_ball"):
        raise datasets.DatasetError(f"ball_balancing paths exist for the iiwa only, not {robot.name!r}")
    paths, counts = generate_ball.ball_paths(robots.load_robot("iiwa_ball", dt=dt), count, seed)
    return paths, {"type": "level_plate_cartesian_curves", "seed": seed, "dt": dt, "scene": "iiwa_ball",
                   "counts": counts}


#: random-agent default per robot (see :func:`_random_split`)
RANDOM_AGENT = {"armar6": "chunked", "armar4": "chunked", "armar4_legs": "chunked"}
#: dataset kind -> ``generator(robot: robots.Robot, count, seed, **params) -> (paths, source dict)``;
#: paths are knot arrays ``[K_i, path joints]``; ``source`` is stored in config.json and must hold
#: ``seed`` and the params needed to regenerate (:func:`generate_split`).
KINDS: dict[str, Callable] = {"random": _random_split, "target_point": _target_point_split,
                              "smooth_target_point": _smooth_target_point_split,
                              "persistent_random": _persistent_random_split, "mixed": _mixed_split,
                              "ball_balancing": _ball_balancing_split}


def generate_split(robot: str, kind: str, count: int, seed: int, dt: float = 0.1, **params):
    """``(paths, source)``: ``count`` paths of ``kind`` for a registry robot (deterministic for
    ``seed`` and params). Params unknown to the kind's generator raise ``DatasetError``."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots import registry as robots

    if kind not in KINDS:
        raise datasets.DatasetError(f"unknown dataset kind {kind!r} to generate; known: {', '.join(KINDS)}")
    if robot not in robots.known_robots():
        raise datasets.DatasetError(f"unknown robot {robot!r}; known: {', '.join(robots.known_robots())}")
    fn = KINDS[kind]
    accepted = set(inspect.signature(fn).parameters) - {"robot", "count", "seed"}
    unknown = set(params) - accepted
    if unknown:
        raise datasets.DatasetError(f"{kind}: unknown generation parameter(s) {sorted(unknown)}; "
                                    f"known: {sorted(accepted)}")
    return fn(robots.load_robot(robot, dt=dt), count, seed, dt=dt, **params)


def source_params(kind: str, source: dict) -> dict:
    """The generator params of ``kind`` found in a config.json ``source`` (for regeneration)."""
    accepted = set(inspect.signature(KINDS[kind]).parameters) - {"robot", "count", "seed"}
    params = {k: v for k, v in source.items() if k in accepted}
    if kind == "mixed" and "persistent_share" not in source:  # written before the persistent part existed
        params["persistent_share"] = 0.0
    return params


def generate_dataset(robot: str, kind: str = "random", num_train: int = 200, num_test: int = 200,
                     seed: int = 0, root=None, overwrite: bool = False, **params):
    """Generate ``<root>/<robot>/<kind>/{train,test}.npz`` and ``config.json`` (deterministic for
    ``seed``: the train split uses ``seed``, the test split ``seed + 1``); ``params`` go to the
    kind's generator (e.g. ``steps``, ``dt``). Returns the directory."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots import registry as robots

    if kind not in KINDS:
        raise datasets.DatasetError(f"unknown dataset kind {kind!r} to generate; known: {', '.join(KINDS)}")
    if kind == "ball_balancing":  # its own config.json (reflection vectors, plate settings)
        from mjx_pathtrack.paths.ball import generate_ball_dataset

        unknown = set(params) - {"dt", "cfg", "workspace"}
        if unknown:
            raise datasets.DatasetError(f"ball_balancing: unknown generation parameter(s) {sorted(unknown)}; "
                                        f"known: ['dt', 'workspace']")
        return generate_ball_dataset(robot, num_train, num_test, seed, root, overwrite, **params)
    if robot not in robots.known_robots():
        raise datasets.DatasetError(f"unknown robot {robot!r}; known: {', '.join(robots.known_robots())}")
    directory = datasets.dataset_dir(robot, kind, root)
    if (directory / "config.json").exists() and not overwrite:
        raise datasets.DatasetError(f"{directory} exists (use overwrite=True / --overwrite to replace it)")
    loaded = robots.load_robot(robot)
    path_joints = np.flatnonzero(np.asarray(loaded.path_mask))
    names = [loaded.joint_names[i] for i in path_joints]
    splits, source = {}, {}
    for split, count, split_seed in (("train", num_train, seed), ("test", num_test, seed + 1)):
        if count > 0:
            splits[split], source = generate_split(robot, kind, count, split_seed, **params)
            datasets.save_split(directory / f"{split}.npz", splits[split])
    source["seed"] = seed
    config = dict(format_version=datasets.FORMAT_VERSION, robot=robot, kind=kind, n_joints=len(path_joints),
                  joint_names=names, max_dis_between_knots=datasets.max_dis_between_knots(splits.values()),
                  num_train=num_train, num_test=num_test, source=source)
    datasets.write_config(directory / "config.json", config)
    return directory
