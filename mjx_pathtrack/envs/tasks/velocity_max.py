"""Velocity maximisation with the KUKA iiwa (paper 001 §V-A1, Tables I and II), a Brax ``Env``.

The robot starts at rest and should move every joint as fast as possible for ``duration`` (5 s)
without breaking a position, velocity, acceleration or jerk limit. One decision step of length
``dt = 1 / hz`` (``hz`` in {10, 20, 120, 240} in the paper) per environment (vmapped over the batch):

1. the action ``[n]`` in [-1, 1] becomes the acceleration ``a1`` at the end of the step:
   ``mode="safe"``: mapped into the safe acceleration range (:mod:`mjx_pathtrack.core.limits`,
   paper 001 eq. (5)); ``mode="penalty_soft"`` / ``"penalty_hard"`` (the paper's Table I
   baselines): ``a1 = action * a_max``, clipped only to the jerk limit, so nothing stops the
   joint at a position or velocity limit;
2. the acceleration goes linearly to ``a1`` over the step (constant jerk, :func:`limits.integrate`);
3. reward = mean over joints of the step's mean ``|v| / v_max`` (the exact integral of ``|v|``
   over the step, :func:`mean_abs_velocity`); ``penalty_soft`` subtracts a penalty that grows
   linearly once the current ``|p|`` or ``|v|`` passes ``soft_threshold`` (50 %) of its limit;
   ``penalty_hard`` sets the reward to zero in any step in which a position or velocity limit is
   broken (paper 001 §V-C; ``hard_terminate=True`` also ends the episode there);
4. every limit is audited at the exact extrema inside the step (:func:`limits.step_extrema`);
   the counts are in ``state.metrics`` (``violation``, ``violation/position``, ...).

Observation ``[3 n + 1]``: position normalised to [-1, 1] over its range, ``v / v_max``,
``a / a_max`` (the paper's kinematic state) and the elapsed fraction of the episode mapped to
[-1, 1] (the task-specific component: the return depends on the time left). Penalty modes can
leave the limits, so the observation is clipped to [-3, 3] rather than [-1, 1].

The comparison policy of Table II is found by search (:func:`optimal_average_velocity` over the
bang-bang family :func:`reversal_action`);
:func:`evaluate` rolls out any policy and returns the Table I / II metrics;
``python -m mjx_pathtrack.rl.velocity_max_train {train,optimal}`` is the command line
(:mod:`mjx_pathtrack.rl.velocity_max_train`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mjx_pathtrack import _quiet  # noqa: F401,I001  (before brax / mujoco.mjx: silences their Warp notices)
from brax.envs.base import Env, State

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import limits as L
from mjx_pathtrack.envs.episodes import Policy, run_episodes

Array = jax.Array

MODES = ("safe", "penalty_soft", "penalty_hard")
#: decision frequencies of paper 001 Table II [Hz]
FREQUENCIES = (10, 20, 120, 240)
#: relative tolerance of the limit audit (float32 rounding of the integrated state)
VIOLATION_TOL = 1e-5
#: |v| / v_max below which the optimal policy treats a joint as stopped (and reverses it)
STOP_FRACTION = 1e-2


@dataclasses.dataclass(frozen=True)
class VelocityMaxConfig:
    """hz [1/s]: decision frequency; mode: one of :data:`MODES`; duration [s]: episode length;
    init_spread: start positions uniform in ``centre +- init_spread * half range`` (0: at the
    centre; 0.5 by default, so that episodes differ and violation rates are rates); soft_threshold, soft_weight: the soft penalty (see :func:`soft_penalty`);
    hard_terminate: ``penalty_hard`` also ends the episode at a violation; jerk_factor: jerk
    limit ``jerk_factor * 2 a_max / dt`` (docs/limits.md §3)."""

    hz: float = 20.0
    mode: str = "safe"
    duration: float = 5.0
    init_spread: float = 0.5
    soft_threshold: float = 0.5
    soft_weight: float = 0.5
    hard_terminate: bool = False
    jerk_factor: float = 1.0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"unknown mode {self.mode!r}; known: {', '.join(MODES)}")
        if not (np.isfinite(self.hz) and self.hz > 0):
            raise ValueError(f"hz must be a positive frequency, got {self.hz}")
        if not (np.isfinite(self.duration) and self.duration > 0):
            raise ValueError(f"duration must be > 0 s, got {self.duration}")
        if self.episode_steps < 1:
            raise ValueError(f"duration {self.duration} s is shorter than one step at {self.hz} Hz")
        if not 0.0 <= self.init_spread < 1.0:
            raise ValueError(f"init_spread must be in [0, 1), got {self.init_spread}")
        if not 0.0 <= self.soft_threshold < 1.0:
            raise ValueError(f"soft_threshold must be in [0, 1), got {self.soft_threshold}")
        if not self.jerk_factor > 0:
            raise ValueError(f"jerk_factor must be > 0, got {self.jerk_factor}")

    @property
    def dt(self) -> float:
        return 1.0 / self.hz

    @property
    def episode_steps(self) -> int:
        return int(round(self.duration * self.hz))


class VelState(NamedTuple):
    """Per-environment state: p, v, a ``[n]`` at the decision instant (float32); steps ``[]``
    int32 taken; rng: key for the next (fresh) reset (:mod:`mjx_pathtrack.envs.wrappers`)."""

    p: Array
    v: Array
    a: Array
    steps: Array
    rng: Array


METRICS = ("reward", "avg_velocity", "violation", "violation/position", "violation/velocity",
           "violation/acceleration", "violation/jerk", "max_position", "max_velocity")


class VelocityMaxEnv(Env):
    """Maximise the mean absolute joint velocity for ``config.duration`` seconds (module doc).

    ``limits``: :class:`~mjx_pathtrack.core.limits.JointLimits` (default: the iiwa at ``config.dt``).
    """

    def __init__(self, config: VelocityMaxConfig = VelocityMaxConfig(), limits: L.JointLimits | None = None):
        self.config = config
        self.limits = iiwa.joint_limits(config.dt, config.jerk_factor) if limits is None else limits
        lim = self.limits
        if bool(np.any(~np.isfinite(np.asarray(lim.pos_min)))):
            raise ValueError("VelocityMaxEnv needs finite position limits on every joint")
        self.centre = 0.5 * (lim.pos_min + lim.pos_max)
        self.half = 0.5 * (lim.pos_max - lim.pos_min)

    @property
    def observation_size(self) -> int:
        return 3 * self.limits.n_joints + 1

    @property
    def action_size(self) -> int:
        return self.limits.n_joints

    @property
    def backend(self) -> str:
        return "kinematic"

    def reset(self, rng: Array) -> State:
        rng, k = jax.random.split(rng)
        n = self.limits.n_joints
        u = jax.random.uniform(k, (n,), minval=-1.0, maxval=1.0)
        p = self.centre + self.config.init_spread * self.half * u
        zero = jnp.zeros((n,), jnp.float32)
        track = VelState(p=p, v=zero, a=zero, steps=jnp.zeros((), jnp.int32), rng=rng)
        z = jnp.zeros(())
        return State(pipeline_state=track, obs=self.observe(track), reward=z, done=z,
                     metrics={k: z for k in METRICS}, info={})

    def step(self, state: State, action: Array) -> State:
        track, reward, done, metrics = self.transition(state.pipeline_state, action)
        return state.replace(pipeline_state=track, obs=self.observe(track), reward=reward,
                             done=done.astype(jnp.float32), metrics=metrics)

    def next_acceleration(self, track: VelState, action: Array) -> Array:
        """``a1 [n]`` for ``action [n]`` in [-1, 1] (clipped) under the configured mode."""
        cfg, lim = self.config, self.limits
        if cfg.mode == "safe":
            a_min, a_max = L.safe_acceleration_range(lim, track.p, track.v, track.a, cfg.dt)
            return L.action_to_acceleration(action, a_min, a_max)
        a1 = jnp.clip(action, -1.0, 1.0) * lim.acc
        step = lim.jerk * cfg.dt
        return jnp.clip(a1, track.a - step, track.a + step)

    def transition(self, track: VelState, action: Array):
        """One decision step: ``(track, action [n]) -> (track', reward, done, metrics)``."""
        cfg, lim = self.config, self.limits
        a1 = self.next_acceleration(track, action)
        p1, v1, _ = L.integrate(track.p, track.v, track.a, a1, cfg.dt, cfg.dt)
        speed = jnp.mean(mean_abs_velocity(track.p, track.v, track.a, a1, cfg.dt) / lim.vel)
        audit = audit_step(lim, track.p, track.v, track.a, a1, cfg.dt)
        if cfg.mode == "penalty_soft":
            reward = speed - soft_penalty(lim, p1, v1, cfg.soft_threshold, cfg.soft_weight)
        elif cfg.mode == "penalty_hard":
            reward = jnp.where(audit.position | audit.velocity, 0.0, speed)
        else:
            reward = speed
        steps = track.steps + 1
        done = steps >= cfg.episode_steps
        if cfg.mode == "penalty_hard" and cfg.hard_terminate:
            done = done | audit.position | audit.velocity
        metrics = {"reward": reward, "avg_velocity": speed, "violation": audit.any.astype(jnp.float32),
                   "violation/position": audit.position.astype(jnp.float32),
                   "violation/velocity": audit.velocity.astype(jnp.float32),
                   "violation/acceleration": audit.acceleration.astype(jnp.float32),
                   "violation/jerk": audit.jerk.astype(jnp.float32),
                   "max_position": audit.max_position, "max_velocity": audit.max_velocity}
        return track._replace(p=p1, v=v1, a=a1, steps=steps), reward, done, metrics

    def observe(self, track: VelState) -> Array:
        """Observation ``[3 n + 1]`` (module doc), clipped to [-3, 3]."""
        lim = self.limits
        elapsed = track.steps.astype(jnp.float32) / self.config.episode_steps
        obs = jnp.concatenate([(track.p - self.centre) / self.half, track.v / lim.vel, track.a / lim.acc,
                               (2.0 * elapsed - 1.0)[None]])
        return jnp.clip(obs, -3.0, 3.0)


# ---------------------------------------------------------------------------------------------
# Step quantities
# ---------------------------------------------------------------------------------------------


def mean_abs_velocity(p: Array, v: Array, a0: Array, a1: Array, dt) -> Array:
    """Exact mean of ``|v(t)|`` over a constant-jerk step ``[..., n]`` [rad/s].

    ``v(t) = v + a0 t + j t^2 / 2`` changes sign at most twice; between its roots (clipped to
    [0, dt]) the integral of ``|v|`` is the absolute position change, so the mean is
    ``sum |p(t_{k+1}) - p(t_k)| / dt`` over the (at most three) pieces."""
    jerk = (a1 - a0) / dt
    qa, qb, qc = 0.5 * jerk, a0, v
    disc = qb * qb - 4.0 * qa * qc
    real = disc >= 0.0
    sq = jnp.sqrt(jnp.where(real, disc, 0.0))
    q = -0.5 * (qb + jnp.where(qb >= 0.0, sq, -sq))  # stable quadratic roots q / qa and qc / q
    safe_q = jnp.where(q == 0.0, 1.0, q)
    safe_a = jnp.where(qa == 0.0, 1.0, qa)
    r1 = jnp.where(qa == 0.0, jnp.where(qb == 0.0, dt, -qc / jnp.where(qb == 0.0, 1.0, qb)), q / safe_a)
    r2 = jnp.where(q == 0.0, dt, qc / safe_q)
    r1 = jnp.where(real, r1, dt)
    r2 = jnp.where(real, r2, dt)
    t1 = jnp.clip(jnp.minimum(r1, r2), 0.0, dt)
    t2 = jnp.clip(jnp.maximum(r1, r2), 0.0, dt)

    def pos(t):
        return L.integrate(jnp.zeros_like(p), v, a0, a1, dt, t)[0]

    x1, x2, x3 = pos(t1), pos(t2), pos(jnp.full_like(v, dt))
    return (jnp.abs(x1) + jnp.abs(x2 - x1) + jnp.abs(x3 - x2)) / dt


class StepAudit(NamedTuple):
    """Limit audit of one step: bool ``[...]`` per limit kind (any joint) and the largest
    normalised position ``|p - centre| / half range`` and velocity ``|v| / v_max`` in the step."""

    position: Array
    velocity: Array
    acceleration: Array
    jerk: Array
    any: Array
    max_position: Array
    max_velocity: Array


def audit_step(limits: L.JointLimits, p: Array, v: Array, a0: Array, a1: Array, dt,
               tol: float = VIOLATION_TOL) -> StepAudit:
    """Check every limit at the exact extrema inside the step (:func:`limits.step_extrema`);
    ``tol`` is relative to each limit (float32 rounding). States ``[..., n]``."""
    ext = L.step_extrema(p, v, a0, a1, dt)
    centre = 0.5 * (limits.pos_min + limits.pos_max)
    half = 0.5 * (limits.pos_max - limits.pos_min)
    pos_use = jnp.maximum(ext.p_max - centre, centre - ext.p_min) / half
    vel_use = jnp.maximum(ext.v_max, -ext.v_min) / limits.vel
    slack = 1.0 + tol
    position = jnp.any((ext.p_max > limits.pos_max + tol * half) | (ext.p_min < limits.pos_min - tol * half), -1)
    velocity = jnp.any(vel_use > slack, -1)
    acceleration = jnp.any(ext.a_abs > limits.acc * slack, -1)
    jerk = jnp.any(ext.jerk_abs > limits.jerk * slack, -1)
    return StepAudit(position, velocity, acceleration, jerk, position | velocity | acceleration | jerk,
                     jnp.max(pos_use, -1), jnp.max(vel_use, -1))


def soft_penalty(limits: L.JointLimits, p: Array, v: Array, threshold: float = 0.5, weight: float = 0.5) -> Array:
    """Soft penalty of paper 001 §V-C ``[...]``: the mean over joints of
    ``weight * (relu(u_p - threshold) + relu(u_v - threshold)) / (1 - threshold)`` with
    ``u_p = |p - centre| / half range`` and ``u_v = |v| / v_max`` of the current state. With the
    defaults the velocity reward stops growing above 50 % of ``v_max`` (the paper's point: the
    penalty distorts the objective) and grows negative beyond the limits."""
    centre = 0.5 * (limits.pos_min + limits.pos_max)
    half = 0.5 * (limits.pos_max - limits.pos_min)
    u_p, u_v = jnp.abs(p - centre) / half, jnp.abs(v) / limits.vel
    over = jax.nn.relu(u_p - threshold) + jax.nn.relu(u_v - threshold)
    return weight * jnp.mean(over, -1) / (1.0 - threshold)


# ---------------------------------------------------------------------------------------------
# Optimal policy and evaluation
# ---------------------------------------------------------------------------------------------


def reversal_action(obs: Array, limits: L.JointLimits, factor: float | None = None, start: str = "far",
                    stop_fraction: float = STOP_FRACTION) -> Array:
    """Bang-bang oscillation between the position limits through the safe range ``[..., n]``
    from the observation ``[..., 3 n + 1]`` (safe mode): every joint takes action ``sign(v)``
    (the largest safe acceleration in its direction of travel) until the distance to the
    position limit ahead is at most ``factor`` times its full-deceleration stopping distance
    ``v^2 / (2 a_max)``, then ``-sign(v)`` (the hardest safe braking; it reverses once stopped).
    ``factor=None`` never brakes early: the safe range itself brakes at the last moment and the
    joint reverses once stopped at the limit (``|v| < stop_fraction v_max``). On the first step a
    joint at rest moves away from (``start="far"``) or towards (``"near"``) its nearer limit;
    later a joint at rest moves away from the nearer limit."""
    if start not in ("far", "near"):
        raise ValueError(f"start must be 'far' or 'near', got {start!r}")
    n = limits.n_joints
    pos, vel = obs[..., :n], obs[..., n:2 * n]
    first = obs[..., -1:] <= -1.0 + 1e-6  # elapsed time 0
    moving = jnp.abs(vel) >= stop_fraction
    travel = jnp.sign(vel)
    away = jnp.where(pos > 0.0, -1.0, 1.0)
    at_rest = jnp.where(first & (start == "near"), -away, away)
    action = jnp.where(moving, travel, at_rest)
    if factor is None:
        return action
    half = 0.5 * (limits.pos_max - limits.pos_min)
    ahead = (1.0 - pos * travel) * half  # [rad] to the limit in the direction of travel
    stopping = (vel * limits.vel) ** 2 / (2.0 * limits.acc)
    return jnp.where(moving & (ahead <= factor * stopping), -travel, action)


#: stopping-distance factors of the reversal family searched for the optimal policy
#: (``None``: brake only when the safe range forces it; factors <= 1 act like ``None`` on the
#: iiwa because the safe range brakes earlier than that)
REVERSAL_FACTORS = (None, 1.05, 1.1, 1.2, 1.3, 1.4, 1.5, 1.75, 2.0, 2.5)


def evaluate(env: VelocityMaxEnv, policy: Policy, episodes: int, key: Array) -> dict[str, float]:
    """:func:`evaluate_many` of one policy."""
    return evaluate_many(env, {"policy": policy}, episodes, key)["policy"]


def evaluate_many(env: VelocityMaxEnv, policies: dict[str, Policy], episodes: int,
                  key: Array) -> dict[str, dict[str, float]]:
    """Roll out ``episodes`` batched episodes of each policy (one compiled program; every
    policy sees the same start states and step keys) and return, per policy, the paper's
    metrics: ``avg_velocity`` (mean over episodes, joints and time of ``|v| / v_max``; steps
    after an early end count as zero), ``best_avg_velocity`` (of the best episode),
    ``violation_rate`` (share of episodes with at least one violated limit), ``max_position`` /
    ``max_velocity`` (largest normalised value over all episodes), ``return`` (mean
    undiscounted return) and the per-kind violation rates ``violation_rate/<kind>``."""
    names = list(policies)
    out, _ = rollout(env, policies, episodes, key)
    return {name: {k: float(v[i]) for k, v in out.items()} for i, name in enumerate(names)}


def rollout(env: VelocityMaxEnv, policies: dict[str, Policy], episodes: int, key: Array):
    """:func:`evaluate_many` as arrays: ``(summary, joint_speed)`` with ``summary[k]`` ``[P]``
    (policies in dict order) and ``joint_speed`` ``[P, episodes, n]``, each joint's mean
    ``|v| / v_max`` over the episode. Jitted per call."""
    if episodes < 1 or not policies:
        raise ValueError(f"need episodes >= 1 and at least one policy, got {episodes} and {list(policies)}")
    steps, dt, vel = env.config.episode_steps, env.config.dt, env.limits.vel
    names = list(policies)
    k_reset, k_run = jax.random.split(key)

    @jax.jit
    def run(k_reset, k_run):
        one = jax.vmap(env.reset)(jax.random.split(k_reset, episodes))
        state = jax.tree.map(lambda x: jnp.stack([x] * len(names)), one)  # [P, E, ...]
        step = jax.vmap(jax.vmap(env.step))

        def policy(obs, k):  # every policy acts on its own [E] batch of the [P, E] states
            return jnp.stack([policies[name](obs[i], k) for i, name in enumerate(names)])

        def accumulate(speed, before, after, live, _steps):
            before, after = before.pipeline_state, after.pipeline_state
            joint = mean_abs_velocity(before.p, before.v, before.a, after.a, dt) / vel
            return speed + jnp.where(live[..., None], joint, 0.0) / steps

        def record(_before, after, live):
            m = {name: jnp.where(live, after.metrics[name], 0.0) for name in METRICS}
            m["reward"] = jnp.where(live, after.reward, 0.0)
            return m

        speed = jnp.zeros((len(names), episodes, env.action_size))
        final, m = run_episodes(step, policy, state, jax.random.split(k_run, steps), accumulate, speed, record)  # [T, P, E]
        speed = final.acc
        per_episode = jnp.mean(m["avg_velocity"], 0)
        out = {"avg_velocity": jnp.mean(per_episode, -1), "best_avg_velocity": jnp.max(per_episode, -1),
               "return": jnp.mean(jnp.sum(m["reward"], 0), -1),
               "violation_rate": jnp.mean(jnp.any(m["violation"] > 0, 0), -1),
               "max_position": jnp.max(m["max_position"], (0, 2)), "max_velocity": jnp.max(m["max_velocity"], (0, 2))}
        for kind in ("position", "velocity", "acceleration", "jerk"):
            out[f"violation_rate/{kind}"] = jnp.mean(jnp.any(m[f"violation/{kind}"] > 0, 0), -1)
        return out, speed

    return jax.device_get(run(k_reset, k_run))


def random_policy(n_joints: int = 7) -> Policy:
    """Uniform random actions in [-1, 1] (Table II's "Random" column)."""
    def policy(obs, key):
        return jax.random.uniform(key, obs.shape[:-1] + (n_joints,), minval=-1.0, maxval=1.0)
    return policy


def reversal_policy(limits: L.JointLimits, factor: float | None = None, start: str = "far") -> Policy:
    """:func:`reversal_action` as a :data:`Policy`."""
    return lambda obs, key: reversal_action(obs, limits, factor, start)


def optimal_average_velocity(env: VelocityMaxEnv, episodes: int, key: Array,
                             others: dict[str, Policy] | None = None,
                             factors=REVERSAL_FACTORS) -> tuple[float, dict[str, Any]]:
    """Average velocity (normalised, Table II) of the optimal policy found by search, on
    ``episodes`` episodes of ``env`` (safe mode), and the metrics of the ``others`` policies
    rolled out together with it on the same episodes (one compiled program).

    The search: every member of the :func:`reversal_action` family (``factors`` x first
    direction) is rolled out; because the joints are independent and the average velocity is
    the mean over joints, the best member *per joint and episode* is a valid (deterministic,
    start-dependent) policy, and its value is returned. It is the best bang-bang oscillation
    between the position limits under every limit: accelerate at the limit of the safe range
    towards the next position limit, brake at the latest point of the family, reverse. This
    is a lower bound of the true optimum (a search over a family, not a proof), and the
    family contains the paper's "border case" of paper 001 Fig. 1 (``factor=None``).

    Returns ``(value, info)``: ``info["family"]`` maps each member to its own average
    velocity, ``info["best_factor_share"]`` to the share of (joint, episode) pairs it wins,
    ``info["violation_rate"]`` is the largest violation rate of any member (0 in safe mode),
    and ``info[name]`` holds :func:`evaluate_many`'s metrics of each of ``others``."""
    if env.config.mode != "safe":
        raise ValueError("the optimal policy is defined for mode='safe' only")
    family = {f"factor={f}/{start}": reversal_policy(env.limits, f, start)
              for f in factors for start in ("far", "near")}
    others = dict(others or {})
    clash = set(family) & set(others)
    if clash:
        raise ValueError(f"policy names {sorted(clash)} are reserved for the optimal search")
    policies = {**family, **others}
    summary, speed = rollout(env, policies, episodes, key)
    k = len(family)
    best = np.argmax(speed[:k], axis=0)  # [E, n]
    value = float(np.mean(np.max(speed[:k], axis=0)))
    names = list(policies)
    info: dict[str, Any] = {
        "family": {name: float(summary["avg_velocity"][i]) for i, name in enumerate(names[:k])},
        "best_factor_share": {name: float(np.mean(best == i)) for i, name in enumerate(names[:k])},
        "violation_rate": float(np.max(summary["violation_rate"][:k])),
        "max_position": float(np.max(summary["max_position"][:k])),
        "max_velocity": float(np.max(summary["max_velocity"][:k]))}
    for i, name in enumerate(names[k:], start=k):
        info[name] = {key_: float(v[i]) for key_, v in summary.items()}
    return value, info


def optimal_by_frequency(frequencies=FREQUENCIES, episodes: int = 64, init_spread: float = 0.5,
                         duration: float = 5.0, seed: int = 0) -> dict[float, float]:
    """:func:`optimal_average_velocity` at each decision frequency [Hz]."""
    out = {}
    for hz in frequencies:
        env = VelocityMaxEnv(VelocityMaxConfig(hz=hz, duration=duration, init_spread=init_spread))
        out[hz] = optimal_average_velocity(env, episodes, jax.random.PRNGKey(seed))[0]
    return out


def perturbation_check(hz: float, factor: float | None, perturb=(0.02, 0.1), candidates: int = 32,
                       duration: float = 5.0, seed: int = 0) -> dict[str, float]:
    """Local check of a family member at ``hz`` from the centre (a deterministic episode):
    ``base`` is its average velocity, ``perturb=<q>`` the best of ``candidates`` rollouts in
    which each action is replaced by a uniform random one with probability ``q``."""
    env = VelocityMaxEnv(VelocityMaxConfig(hz=hz, duration=duration, init_spread=0.0))
    n = env.action_size
    policies: dict[str, Policy] = {"base": reversal_policy(env.limits, factor)}
    for q in perturb:
        def noisy(obs, k, q=q):
            k1, k2 = jax.random.split(k)
            flip = jax.random.uniform(k1, obs.shape[:-1] + (n,)) < q
            return jnp.where(flip, jax.random.uniform(k2, obs.shape[:-1] + (n,), minval=-1.0, maxval=1.0),
                             reversal_action(obs, env.limits, factor))
        policies[f"perturb={q:g}"] = noisy
    metrics = evaluate_many(env, policies, candidates, jax.random.PRNGKey(seed))
    return {name: m["best_avg_velocity"] for name, m in metrics.items()}
