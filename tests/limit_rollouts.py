"""Closed-loop rollouts of the safe action space that record the worst limit usage (test helper)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack import iiwa
from mjx_pathtrack import limits as L

IIWA_POS, IIWA_VEL, IIWA_ACC = iiwa.POS, iiwa.VEL, iiwa.ACC
iiwa_limits = iiwa.joint_limits

POLICIES = ("random", "plus", "minus", "bang_bang", "adversarial")


def _actions(key, t, p, limits: L.JointLimits, period) -> jax.Array:
    """Actions ``[len(POLICIES), n]`` of every policy for one state (one row per policy)."""
    n = p.shape[-1]
    centre = 0.5 * (limits.pos_min + limits.pos_max)
    return jnp.stack([
        jax.random.uniform(key, p.shape, minval=-1.0, maxval=1.0),  # random
        jnp.ones_like(p),  # plus
        -jnp.ones_like(p),  # minus
        jnp.where((t // period) % 2 == 0, 1.0, -1.0) * jnp.ones((n,)),  # bang_bang, period 1..8 steps
        jnp.where(p >= centre, 1.0, -1.0),  # adversarial: push towards the nearest position limit
    ])


def rollout_usage(limits: L.JointLimits, dt: float, episodes: int, steps: int, seed: int = 0) -> dict:
    """Run ``episodes`` vmapped episodes of ``steps`` decisions *per policy* of ``POLICIES``, all
    in one compiled program. Returns ``{policy: (usage [4, n], min_width, violations)}``: the worst
    normalised usage of (position, velocity, acceleration, jerk) over every step *and* the exact
    extrema inside each step (1.0 = at the limit), the smallest range width, and the number of
    steps flagged as a violation / empty range."""
    n = limits.n_joints
    total = episodes * len(POLICIES)
    key = jax.random.PRNGKey(seed)
    k0, k1, k2 = jax.random.split(key, 3)
    span = limits.pos_max - limits.pos_min
    p0 = limits.pos_min + span * jax.random.uniform(k0, (total, n), minval=0.02, maxval=0.98)
    periods = jax.random.randint(k1, (total, 1), 1, 9)
    keys = jax.random.split(k2, total)
    policy = jnp.repeat(jnp.arange(len(POLICIES)), episodes)

    def episode(p, period, key, which):
        def step(carry, t):
            p, v, a, key = carry
            key, sub = jax.random.split(key)
            rng = L.safe_acceleration_range_checked(limits, p, v, a, dt)
            act = _actions(sub, t, p, limits, period)[which]
            a1 = L.action_to_acceleration(act, rng.a_min, rng.a_max)
            ext = L.step_extrema(p, v, a, a1, dt)
            centre = 0.5 * (limits.pos_min + limits.pos_max)
            half = 0.5 * span
            usage = jnp.stack([
                jnp.maximum(ext.p_max - centre, centre - ext.p_min) / half,
                jnp.maximum(ext.v_max, -ext.v_min) / limits.vel,
                ext.a_abs / limits.acc,
                ext.jerk_abs / limits.jerk,
            ])
            p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
            width = rng.a_max - rng.a_min
            return (p1, v1, a1, key), (usage, width, rng.violation)

        zeros = jnp.zeros((n,))
        _, (usage, width, viol) = jax.lax.scan(step, (p, zeros, zeros, key), jnp.arange(steps))
        return usage.max(0), width.min(), viol.sum()

    usage, width, viol = (np.asarray(x) for x in jax.jit(jax.vmap(episode))(p0, periods, keys, policy))
    out = {}
    for i, name in enumerate(POLICIES):
        rows = slice(i * episodes, (i + 1) * episodes)
        out[name] = (usage[rows].max(0), float(width[rows].min()), int(viol[rows].sum()))
    return out


def random_limits(dt: float, n: int = 7, seed: int = 0) -> L.JointLimits:
    """Random joint limits whose jerk limit binds: jerk = f * 2 * acc / dt with f in [0.1, 0.9].

    Position half-ranges are 0.2..3 (rad): the narrow ones make a joint that brakes hard at one
    limit rebound towards the other (the stop to rest of ``limits._tail_plan``).
    """
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1.0, 1.0, n)
    half = rng.uniform(0.2, 3.0, n)
    acc = rng.uniform(2.0, 30.0, n)
    vel = rng.uniform(0.3, 3.0, n)
    jerk = rng.uniform(0.1, 0.9, n) * 2.0 * acc / dt
    return L.JointLimits(centre - half, centre + half, vel, acc, jerk)
