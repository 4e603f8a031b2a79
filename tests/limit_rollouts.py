"""Closed-loop rollouts of the safe action space that record the worst limit usage (test helper).

Also used by ``benchmarks/stress_limits.py``. Every check looks at the exact extrema *inside*
each decision step (``limits.step_extrema``), not only at the step ends.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import limits as L

IIWA_POS, IIWA_VEL, IIWA_ACC = iiwa.POS, iiwa.VEL, iiwa.ACC
iiwa_limits = iiwa.joint_limits

#: closed-loop policies: uniform random, constant +1 / -1, bang-bang with a period of 1..8 steps,
#: "adversarial" (push towards the nearest position limit) and "chatter" (a random sign every step)
POLICIES = ("random", "plus", "minus", "bang_bang", "adversarial", "chatter")
#: usage components (rows of the usage arrays)
COMPONENTS = ("position", "velocity", "acceleration", "jerk")


def _actions(key, t, p, limits: L.JointLimits, period) -> jax.Array:
    """Actions ``[len(POLICIES), n]`` of every policy for one state (one row per policy)."""
    n = p.shape[-1]
    centre = 0.5 * (limits.pos_min + limits.pos_max)
    k_uniform, k_sign = jax.random.split(key)
    return jnp.stack([
        jax.random.uniform(k_uniform, p.shape, minval=-1.0, maxval=1.0),  # random
        jnp.ones_like(p),  # plus
        -jnp.ones_like(p),  # minus
        jnp.where((t // period) % 2 == 0, 1.0, -1.0) * jnp.ones((n,)),  # bang_bang, period 1..8 steps
        jnp.where(p >= centre, 1.0, -1.0),  # adversarial: push towards the nearest position limit
        jnp.where(jax.random.bernoulli(k_sign, 0.5, p.shape), 1.0, -1.0),  # chatter
    ])


def usage_of(limits: L.JointLimits, ext: L.StepExtrema) -> jax.Array:
    """Normalised usage ``[4, ..., n]`` (position, velocity, acceleration, jerk) of step extrema:
    1.0 = at the limit. Position: distance from the centre over the half range."""
    centre = 0.5 * (limits.pos_min + limits.pos_max)
    half = 0.5 * (limits.pos_max - limits.pos_min)
    return jnp.stack([
        jnp.maximum(ext.p_max - centre, centre - ext.p_min) / half,
        jnp.maximum(ext.v_max, -ext.v_min) / limits.vel,
        ext.a_abs / limits.acc,
        ext.jerk_abs / limits.jerk,
    ])


def state_usage(limits: L.JointLimits, p, v, a) -> np.ndarray:
    """Usage ``[4, ..., n]`` of states themselves (the jerk row is 0)."""
    return np.asarray(usage_of(limits, L.StepExtrema(p, p, v, v, jnp.abs(a), jnp.zeros_like(a))))


def closed_loop(limits: L.JointLimits, dt: float, p0, v0, a0, policy, periods, keys, steps: int,
                vmapped: bool = True, threshold=None):
    """Episodes of ``steps`` decisions from the start states ``p0, v0, a0 [E, n]`` with the
    policies ``policy [E]`` (indices into :data:`POLICIES`), bang-bang periods ``[E]`` and
    keys ``[E]``, compiled as one program. Returns numpy ``(usage [E, 4, n], min_width [E],
    flagged [E], over [E])``: the worst usage over every step and the exact extrema inside each,
    the smallest safe-range width, the number of joint-steps flagged as a violation / empty
    range, and the number of joint-steps whose usage of any limit exceeds ``threshold``
    (``[E, 4, n]``, default ``1 + 1e-5``: the floor of benchmarks/stress_limits.py).

    ``vmapped``: ``jax.vmap`` over the episodes, as in training (the position search is then
    compacted across the batch); else the range works on the ``[E, n]`` arrays directly."""

    def make_step(split, act_fn, threshold):
        def step(carry, t):
            p, v, a, key = carry
            key, sub = split(key)
            rng = L.safe_acceleration_range_checked(limits, p, v, a, dt)
            a1 = L.action_to_acceleration(act_fn(sub, t, p), rng.a_min, rng.a_max)
            usage = usage_of(limits, L.step_extrema(p, v, a, a1, dt))
            over = jnp.any(usage > threshold, axis=0)
            p1, v1, _ = L.integrate(p, v, a, a1, dt, dt)
            return (p1, v1, a1, key), (usage, rng.a_max - rng.a_min, rng.violation, over)
        return step

    def run(step, p, v, a, key):
        _, (usage, width, flagged, over) = jax.lax.scan(step, (p, v, a, key), jnp.arange(steps))
        return usage.max(0), width.min(axis=(0, -1)), flagged.sum(axis=(0, -1)), over.sum(axis=(0, -1))

    def episode(p, v, a, period, key, which, threshold):  # one episode, [n] arrays
        def act(sub, t, p):
            return _actions(sub, t, p, limits, period)[which]
        return run(make_step(lambda k: tuple(jax.random.split(k)), act, threshold), p, v, a, key)

    def batch(p, v, a, period, key, which, threshold):  # all episodes as [E, n] arrays, no vmap of the range
        def split(k):
            both = jax.vmap(jax.random.split)(k)
            return both[:, 0], both[:, 1]

        def act(sub, t, p):
            every = jax.vmap(lambda k, pp, per: _actions(k, t, pp, limits, per))(sub, p, period)
            return jnp.take_along_axis(every, which[:, None, None], axis=1)[:, 0]
        usage, width, flagged, over = run(make_step(split, act, jnp.moveaxis(threshold, 1, 0)), p, v, a, key)
        return jnp.moveaxis(usage, 0, 1), width, flagged, over  # usage [4, E, n] -> [E, 4, n]

    p0 = jnp.asarray(p0, jnp.float32)
    threshold = jnp.broadcast_to(jnp.asarray(1.0 + 1e-5 if threshold is None else threshold, jnp.float32),
                                 (p0.shape[0], 4, p0.shape[-1]))
    args = (p0, *(jnp.asarray(x, jnp.float32) for x in (v0, a0)), jnp.asarray(periods, jnp.int32), keys,
            jnp.asarray(policy, jnp.int32), threshold)
    out = jax.jit(jax.vmap(episode) if vmapped else batch)(*args)
    return tuple(np.asarray(x) for x in out)


def rollout_usage(limits: L.JointLimits, dt: float, episodes: int, steps: int, seed: int = 0) -> dict:
    """Run ``episodes`` vmapped episodes of ``steps`` decisions *per policy* of ``POLICIES`` from
    rest at random positions, all in one compiled program. Returns ``{policy: (usage [4, n],
    min_width, violations)}``: the worst normalised usage of (position, velocity, acceleration,
    jerk) over every step *and* the exact extrema inside each step (1.0 = at the limit), the
    smallest range width, and the number of steps flagged as a violation / empty range."""
    n = limits.n_joints
    total = episodes * len(POLICIES)
    k0, k1, k2 = jax.random.split(jax.random.PRNGKey(seed), 3)
    span = limits.pos_max - limits.pos_min
    p0 = limits.pos_min + span * jax.random.uniform(k0, (total, n), minval=0.02, maxval=0.98)
    periods = jax.random.randint(k1, (total,), 1, 9)
    zeros = jnp.zeros((total, n))
    policy = np.repeat(np.arange(len(POLICIES)), episodes)
    usage, width, flagged, _ = closed_loop(limits, dt, p0, zeros, zeros, policy, periods, jax.random.split(k2, total), steps)
    out = {}
    for i, name in enumerate(POLICIES):
        rows = slice(i * episodes, (i + 1) * episodes)
        out[name] = (usage[rows].max(0), float(width[rows].min()), int(flagged[rows].sum()))
    return out


def random_limits(dt: float, n: int = 7, seed: int = 0, jerk_factor=(0.1, 0.9)) -> L.JointLimits:
    """Random joint limits; by default the jerk limit binds: jerk = f * 2 * acc / dt with f in
    ``jerk_factor`` = [0.1, 0.9] (f >= 1: it does not bind).

    Position half-ranges are 0.2..3 (rad): the narrow ones make a joint that brakes hard at one
    limit rebound towards the other (the stop to rest of ``limits._tail_plan``).
    """
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1.0, 1.0, n)
    half = rng.uniform(0.2, 3.0, n)
    acc = rng.uniform(2.0, 30.0, n)
    vel = rng.uniform(0.3, 3.0, n)
    jerk = rng.uniform(*jerk_factor, n) * 2.0 * acc / dt
    return L.JointLimits(centre - half, centre + half, vel, acc, jerk)


# --- states on and a few float32 ulps beyond a limit -------------------------------------------

#: border families: which limits the start state sits on (upper side; the lower side mirrors it)
BORDER_FAMILIES = ("position", "velocity", "acceleration", "all")


def ulps_beyond(x, k, direction) -> np.ndarray:
    """float32 ``x`` moved ``k`` ulps towards ``direction`` (+1 / -1), elementwise."""
    x = np.asarray(x, np.float32).copy()
    towards = np.where(np.asarray(direction) > 0, np.float32(np.inf), np.float32(-np.inf)).astype(np.float32)
    for _ in range(int(k)):
        x = np.nextafter(x, towards)
    return x


def stop_distance(limits: L.JointLimits, dt: float) -> np.ndarray:
    """Generous bound [rad] of the travel of a safe stop from full speed ``[n]`` (any state with
    ``|v| <= V``, ``|a| <= A``): braking time ``V/A + 2 (A/J + dt) + 2 dt`` at no more than ``V``."""
    V, A, J = (np.asarray(x, np.float64) for x in (limits.vel, limits.acc, limits.jerk))
    return V * (V / A + 2.0 * (A / J + dt) + 2.0 * dt)


def border_states(limits: L.JointLimits, dt: float, ulps=(0, 1, 2, 3, 4)):
    """Start states ``(p, v, a) [S, n]`` (float32) on, and ``k`` ulps beyond, the float32 limits,
    every joint at once, each side; plus ``family [S]``, ``k [S]`` and ``side [S]`` (+1 upper).

    Families (upper side; the lower side is the mirror image), all feasible in exact arithmetic:

    - ``position``: at rest on ``pos_max`` (+ k ulps);
    - ``velocity``: on ``pos_min`` moving away at ``vel`` (+ k ulps), zero acceleration;
    - ``acceleration``: on ``pos_max`` moving away at ``-vel``, acceleration ``+acc`` (+ k ulps);
    - ``all``: position, velocity and acceleration each ``k`` ulps beyond at once (``pos_max``,
      ``-vel``, ``+acc`` as in ``acceleration``).

    A joint for which a family is not feasible with its limits (corridor shorter than a stop
    from full speed; velocity gain of the acceleration family larger than ``vel``) starts at rest
    in the middle of its corridor instead. Mirroring negates the offsets around the centre."""
    lo, hi, vel, acc, jerk = (np.asarray(x, np.float32) for x in
                              (limits.pos_min, limits.pos_max, limits.vel, limits.acc, limits.jerk))
    centre = (0.5 * (lo.astype(np.float64) + hi)).astype(np.float32)
    room = (hi.astype(np.float64) - lo) > 1.5 * stop_distance(limits, dt)
    # the acceleration family's velocity rises from -vel: keep the whole rise below vel
    gain = acc.astype(np.float64) ** 2 / (2.0 * jerk) + 2.0 * acc * dt + jerk * dt * dt
    gentle = room & (gain <= np.asarray(vel, np.float64))
    rows = []
    for family in BORDER_FAMILIES:
        for side in (1, -1):
            p_lim, p_far = (hi, lo) if side > 0 else (lo, hi)
            for k in ulps:
                zero = np.zeros_like(vel)
                if family == "position":
                    p, v, a, ok = ulps_beyond(p_lim, k, side), zero, zero, np.ones(vel.shape, bool)
                elif family == "velocity":
                    p, v, a, ok = p_far, ulps_beyond(side * vel, k, side), zero, room
                elif family == "acceleration":
                    p, v, a, ok = p_lim, -side * vel, ulps_beyond(side * acc, k, side), gentle
                else:
                    p, v, a = ulps_beyond(p_lim, k, side), ulps_beyond(-side * vel, k, -side), ulps_beyond(side * acc, k, side)
                    ok = gentle
                rows.append((np.where(ok, p, centre), np.where(ok, v, 0.0), np.where(ok, a, 0.0), family, k, side))
    p, v, a = (np.stack([r[i] for r in rows]).astype(np.float32) for i in range(3))
    family = np.array([BORDER_FAMILIES.index(r[3]) for r in rows])
    return p, v, a, family, np.array([r[4] for r in rows]), np.array([r[5] for r in rows])


def border_usage(limits: L.JointLimits, dt: float, repeats: int, steps: int, seed: int = 0, vmapped: bool = True,
                 tolerance: float = 1e-5):
    """Closed loop from every :func:`border_states` start with every policy, ``repeats`` random
    keys and bang-bang periods each. Returns ``(excess [E, 4, n], flagged [E], min_width [E],
    family [E], over [E])``: how far the worst usage went beyond ``max(1, usage of the start
    state)``, and the joint-steps beyond that by more than ``tolerance``."""
    p, v, a, family, _, _ = border_states(limits, dt)
    n_start, n_pol = len(p), len(POLICIES)
    index = np.arange(n_start * n_pol * repeats)
    start, policy = index // (n_pol * repeats), (index // repeats) % n_pol
    k_period, k_run = jax.random.split(jax.random.PRNGKey(seed))
    periods = jax.random.randint(k_period, (len(index),), 1, 9)
    allowed = np.maximum(1.0, np.moveaxis(state_usage(limits, p[start], v[start], a[start]), 0, 1))
    usage, width, flagged, over = closed_loop(limits, dt, p[start], v[start], a[start], policy, periods,
                                              jax.random.split(k_run, len(index)), steps, vmapped, allowed + tolerance)
    return usage - allowed, flagged, width, family[start], over
