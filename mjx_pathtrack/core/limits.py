"""Safe acceleration range for jerk-limited joints (paper 001), in pure JAX.

A policy picks, at each decision step of length ``dt``, the acceleration ``a1`` that a joint
reaches at the *end* of the step; the acceleration is linear in time within the step (constant
jerk). :func:`safe_acceleration_range` returns, per joint, the interval of ``a1`` for which
position, velocity, acceleration and jerk limits hold at every instant of the step **and** a
valid choice exists at every later decision step. Any action in [-1, 1] mapped into that
interval (:func:`action_to_acceleration`, paper 001 eq. (5)) is therefore feasible.

How the bounds are derived (upper side; the lower side is the mirror image)
----------------------------------------------------------------------------
*Jerk and acceleration*: ``a1 in [a0 - J dt, a0 + J dt]`` and ``|a1| <= A``.

*Velocity*: after ``a1`` the acceleration is lowered on the decision grid as fast as the jerk
limit allows, and the step in which it would cross zero ends at a small negative "settling"
acceleration ``-a_settle`` (``a_settle = settle_factor * A``, 0.01 by default, like klimits'
``acceleration_after_max_vel_limit_factor``) instead of overshooting to a large negative value.
``a1_max`` is the largest value whose velocity peak (inside the current step or later) equals
``V``. This is the discrete-grid reasoning of paper 001 applied to velocity: the limit is
approached so that the acceleration is ~0 on a decision step when ``V`` is reached, which avoids
the chattering a pure continuous-time bound would cause. The inversion is closed form (one
quadratic per candidate count of full-jerk steps).

*Position*: ``a1_max`` is the largest value (searched inside the velocity-feasible range) for
which a *velocity-safe stop* stays below ``P`` at every instant: after ``a1`` the acceleration
falls by ``J dt`` per decision step down to ``-A`` (the pointwise lowest motion), except that on
the steps around the stop it never goes below the velocity lower bound, so braking towards
``P`` cannot push the velocity below ``-V`` once the joint has stopped (without this, states
arise where position and velocity limits conflict). Far from the stop the descent has a closed
form; the last few decision steps are simulated ("tail").

The bound is not bisected any more. After step 1 the acceleration only falls, so the peak is
the position at the one downward zero crossing of the velocity (full-jerk part, partial step to
``-A`` or hold at ``-A``) or inside step 0. Its root in ``a1`` is found with a few safeguarded
Newton steps on this piecewise closed form (``_stop_model``; in the hold piece the peak is a
quadratic in ``a1`` and solved exactly; the step-0 piece is a quadratic in the crossing time);
the root is snapped down to the grid a 14-step bisection would return (``lo + i (hi - lo)
2^-14``) and checked once with the exact stop (if rounding made it fail, one grid value or a
Newton step lower is checked, else ``lo``). The simulated tail is skipped for joints where the velocity floor provably
cannot bind (``A dt + A^2/(2J) + J dt^2/8 <= V``, a static per-joint split; true for the iiwa
at ``dt <= 0.05`` and for all joints but iiwa_joint_1 at ``dt = 0.1``). Joints where it can bind
(dt = 0.4, low jerk limits, traced limits) still bisect the exact stop with the simulated tail
(14 steps) and are as slow as before. Every returned value has passed the exact check (or is
``lo``, as before).

*Only where a limit is within reach*: far from its position limits a joint's search would
return the upper end of its velocity-feasible range after checking it. A cheap test makes the
same check (and the decisions the search makes there); the search itself runs only for the
other joints, gathered across the whole batch into chunks (``compaction.where_needed``, a
``custom_vmap`` rule under ``vmap``), so its cost scales with the joints near a limit (a few
percent in training rollouts), not with the batch. The compiled search rounds a few results
differently from the search run on every lane (under 1 % of bounds, nearly all by one ulp).

Paper 001's discrete profile (D) -- reach ``P`` with zero velocity *exactly on a
decision step* ``K`` (acceleration falling at full jerk, held at ``-A``, one free last grid
value; a 2x2 linear solve per candidate ``K``) -- is used instead when it is tighter and its own
stop passes the same check: it avoids overshoot-and-return oscillations. Against klimits 1.1.3
(the papers' C library) the result agrees within 1e-3 a_max on 99.91 % (dt = 0.1) and 99.80 %
(dt = 0.05) of random-rollout states (99.96 / 99.83 % with the former bisection: the closed
form's grid candidate sometimes lands one grid value lower) and is never wider there; the rare narrower states are next to a limit,
where klimits' profile accepts stops that overshoot ``P`` inside a step or leave no velocity-safe
continuation. klimits solves each piece of its profile family in closed form (generated C code,
docs/limits.md §2) and has no velocity-safe tail and no float32 reserve; here the pieces are
simpler (one braking profile) but verified with an exact check, and the tail is the extra cost.

Float32: limits are pulled in by ``MARGIN``; each planned stop keeps a position reserve per
decision step until the stop and a small velocity reserve, and each velocity plan aims a little
lower per decision step until its peak (never at the hard limit itself), so re-evaluating the
same plan on the next step after rounding never turns it infeasible. A state that rounding
left on a limit or a few ulps beyond it is treated as *on* it (tests/core/test_limits_border.py).

*Narrow corridors*: a stop that brakes as hard as possible reaches ``P`` with the acceleration
near ``-A``; with a low jerk limit the joint then rebounds, and in a position corridor that is
narrow against that rebound it could reach the opposite limit (random limits at dt = 0.4 showed
it). For joints whose corridor is narrower than ``NARROW_FACTOR`` times a bound of the rebound
(a static per-joint test, :func:`_tail_plan`; never true for the iiwa at dt <= 0.1), the planned
stop comes to near rest instead: its velocity floor is ``REST_FACTOR * V`` (settling exactly),
except that a joint already moving away keeps the speed it has. Such a stop never swings back,
so one side's plan cannot push the joint into the other side. It costs a longer simulated tail
and approaches the limits more cautiously.

States that already violate a limit (bad input) get the range that recovers fastest without
breaking the opposite side later (the other side's own bound),
collapsed to one value, and are flagged; the result is never NaN.

Shapes: limits are ``[n]``; states ``[..., n]`` with any leading batch shape. Units: rad, rad/s,
rad/s^2, rad/s^3 (m for prismatic joints); ``dt`` in s.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core.joint_limits import JointLimits
from mjx_pathtrack.core.stop_plan import REST_FACTOR, _narrow, _tail_plan
from mjx_pathtrack.core.stopping import (MARGIN, POSITION_ITERATIONS, SETTLE_FACTOR, TAIL_VEL_MARGIN,
                                         _position_upper_bound, _segment_max_position, _velocity_upper_bound,
                                         jerk_budget, materialized)
# the public names of this module's building blocks, re-exported (``limits.integrate`` etc.)
from mjx_pathtrack.core.stopping import integrate  # noqa: F401
from mjx_pathtrack.core.stopping import _position_search  # noqa: F401  (a test swaps it in)

Array = jax.Array

#: braking_acceleration holds a joint whose |v| <= this * V and |a| <= SETTLED_ACCELERATION * A
#: (at rest up to float32 rounding)
SETTLED_VELOCITY = 1e-6
SETTLED_ACCELERATION = 1e-5


# ---------------------------------------------------------------------------------------------
# Kinematics of one decision step
# ---------------------------------------------------------------------------------------------


def action_to_acceleration(action: Array, a_min: Array, a_max: Array) -> Array:
    """Paper 001 eq. (5): ``a_min + (1 + action)/2 * (a_max - a_min)``; action in [-1, 1] (clipped)."""
    action = jnp.clip(action, -1.0, 1.0)
    return a_min + 0.5 * (1.0 + action) * (a_max - a_min)


def acceleration_to_action(acc: Array, a_min: Array, a_max: Array) -> Array:
    """Inverse of :func:`action_to_acceleration`: the action in [-1, 1] ``[..., n]`` that gives
    acceleration ``acc`` [rad/s^2] (clipped into ``[a_min, a_max]``); 0 where the range is a point."""
    span = a_max - a_min
    wide = span > 0
    action = -1.0 + 2.0 * (jnp.clip(acc, a_min, a_max) - a_min) / jnp.where(wide, span, 1.0)
    return jnp.where(wide, jnp.clip(action, -1.0, 1.0), 0.0)


def hold_action(limits: JointLimits, p: Array, v: Array, a: Array, dt, home: Array, omega: float) -> Array:
    """Actions ``[..., n]`` that hold joints at ``home`` ``[n]`` [rad]: the acceleration of a
    critically damped spring of natural frequency ``omega`` [rad/s], ``-2 omega v - omega^2
    (p - home)`` [rad/s^2], clipped into the safe range of the state ``p, v, a`` ``[..., n]`` for
    a step of ``dt`` [s] and mapped to an action. Smooth in the state, unlike the fastest stop
    (:func:`braking_acceleration`), so a network learns it, and a policy can add to it
    (:mod:`mjx_pathtrack.envs.action_prior`)."""
    a_min, a_max = safe_acceleration_range(limits, p, v, a, dt)
    spring = -2.0 * omega * v - omega ** 2 * (p - home)
    return acceleration_to_action(spring, a_min, a_max)


class SafeRange(NamedTuple):
    a_min: Array
    a_max: Array
    violation: Array  # bool: state outside its limits or no safe acceleration exists


def safe_acceleration_range(limits: JointLimits, p: Array, v: Array, a: Array, dt,
                            settle_factor: float = SETTLE_FACTOR,
                            iterations: int = POSITION_ITERATIONS) -> tuple[Array, Array]:
    """Range ``(a_min, a_max)`` of safe accelerations at the end of the next step, ``[..., n]``.

    ``p, v, a`` [..., n]: the state at the decision instant; ``dt`` [s]. See the module
    docstring for the construction. Use :func:`safe_acceleration_range_checked` to also get
    the violation flag.
    """
    r = safe_acceleration_range_checked(limits, p, v, a, dt, settle_factor, iterations)
    return r.a_min, r.a_max


def safe_acceleration_range_checked(limits: JointLimits, p: Array, v: Array, a: Array, dt,
                                    settle_factor: float = SETTLE_FACTOR,
                                    iterations: int = POSITION_ITERATIONS) -> SafeRange:
    """:func:`safe_acceleration_range` plus a bool ``violation`` [..., n] for states that are
    outside their limits or admit no safe acceleration; those get the fastest-recovery value."""
    p, v, a = (jnp.asarray(x, jnp.float32) for x in (p, v, a))
    A, J = limits.acc, limits.jerk
    # float32 rounding of the integrated state is absorbed by planning against limits pulled
    # in by a few ulps; only states beyond the same margin count as violations.
    p_tol = MARGIN * jnp.maximum(jnp.maximum(jnp.abs(limits.pos_max), jnp.abs(limits.pos_min)), 1.0)
    p_tol = jnp.where(jnp.isfinite(p_tol), p_tol, 0.0)
    V = limits.vel * (1.0 - MARGIN)
    P_hi, P_lo = limits.pos_max - p_tol, limits.pos_min + p_tol
    plan = _tail_plan(limits, dt)
    narrow = _narrow(limits, dt, jnp) if plan.narrow is None else plan.narrow
    # velocity floor of the planned stop: the velocity limit less a reserve (so that a plan that
    # ends exactly at P keeps a little braking in reserve for float32 rounding), or near rest
    V_limit = V * (1.0 - TAIL_VEL_MARGIN)
    floor_v = jnp.where(narrow, REST_FACTOR * V, V_limit)
    settle = settle_factor * A
    # the stop to rest settles exactly (a settling acceleration would keep a small drift)
    settle_tail = jnp.where(narrow, 0.0, settle)
    reserve = 0.25 * p_tol
    delta = jerk_budget(J, A, dt)
    j_lo, j_hi = jnp.maximum(a - delta, -A), jnp.minimum(a + delta, A)
    k_lo = jnp.maximum(j_lo, -_velocity_upper_bound(-v, -a, V, dt, A, delta, settle))
    k_hi = jnp.minimum(j_hi, _velocity_upper_bound(v, a, V, dt, A, delta, settle))
    k_lo, k_hi = materialized(k_lo), materialized(k_hi)  # each has many consumers
    # Position bounds are searched inside the velocity-feasible range: an a1 that breaks a
    # velocity limit by itself is excluded there already and must not hide a position-safe one.
    feasible = k_lo <= k_hi
    s_lo, s_hi = jnp.where(feasible, k_lo, j_lo), jnp.where(feasible, k_hi, j_hi)

    # Both sides in one pass: the lower bound is the upper bound of the mirrored joint, so the
    # mirrored lanes are appended to the joint axis ([..., 2n]) and searched together (one
    # program instead of two of the same size).
    n = limits.n_joints

    def both(upper, lower):
        return jnp.concatenate([jnp.broadcast_to(upper, p.shape), jnp.broadcast_to(lower, p.shape)], axis=-1)

    def twice(x):  # per-joint values [n] for the [..., 2n] lanes
        return jnp.concatenate([x, x], axis=-1)

    per_joint = [twice(x) for x in (reserve, floor_v, V_limit, jnp.broadcast_to(settle_tail, (n,)), A, delta)]

    def group_bound(P, p, v, a, lo, hi, idx, steps):
        """Position bound of the lanes ``idx`` (static, of [..., 2n]), with ``steps`` simulated tail steps."""
        def take(x):
            return x if idx is None else x[..., idx]

        Pg = take(P)
        finite = jnp.isfinite(Pg)
        reserve_g, floor_g, V_limit_g, settle_g, A_g, delta_g = (take(x) for x in per_joint)
        bound = _position_upper_bound(jnp.where(finite, take(p), 0.0), take(v), take(a), jnp.where(finite, Pg, 0.0),
                                      reserve_g, floor_g, V_limit_g, settle_g, dt, A_g, delta_g, take(lo),
                                      take(hi), iterations, steps)
        return jnp.where(finite, bound, jnp.inf)

    # Static split: joints whose velocity floor cannot bind skip the simulated tail, narrow
    # corridors simulate the longer stop to rest (traced limits: everyone the longer tail).
    if plan.needs_tail is None:
        groups = [(None, plan.rest_steps)]
    else:
        masks = ((~plan.needs_tail, 0), (plan.needs_tail & ~plan.narrow, plan.steps), (plan.narrow, plan.rest_steps))
        groups = [(np.concatenate([np.flatnonzero(m), n + np.flatnonzero(m)]), steps) for m, steps in masks if m.any()]
        if len(groups) == 1:
            groups = [(None, groups[0][1])]

    def position_bound(P, p, v, a, lo, hi):
        if groups[0][0] is None:
            return group_bound(P, p, v, a, lo, hi, None, groups[0][1])
        parts = jnp.concatenate([group_bound(P, p, v, a, lo, hi, idx, steps) for idx, steps in groups], axis=-1)
        return parts[..., np.argsort(np.concatenate([idx for idx, _ in groups]))]

    bounds = position_bound(both(P_hi, -P_lo), both(p, -p), both(v, -v), both(a, -a), both(s_lo, -s_hi), both(s_hi, -s_lo))
    hi = jnp.minimum(k_hi, bounds[..., :n])
    lo = jnp.maximum(k_lo, -bounds[..., n:])
    over_p, under_p = p > limits.pos_max + p_tol, p < limits.pos_min - p_tol
    over_v, under_v = v > limits.vel * (1.0 + MARGIN), v < -limits.vel * (1.0 + MARGIN)
    outside = over_p | under_p | over_v | under_v | (jnp.abs(a) > A * (1.0 + MARGIN))
    empty = lo > hi + MARGIN * A
    # Recovery from an empty range: a violated upper side pushes a1 down as far as the lower
    # side's own bound allows (the lowest a1 from which the lower side's later steps stay
    # feasible), a violated lower side up as far as the upper bound allows. Pushing further, to
    # the jerk limit, would trade the violation for one on the other side a few steps later
    # (with a binding jerk limit the acceleration cannot swing back in time).
    upper_bad = over_p | over_v | (hi <= j_lo)
    lower_bad = under_p | under_v | (lo >= j_hi)
    mid = 0.5 * (lo + hi)
    rec = jnp.where(upper_bad & ~lower_bad, lo, jnp.where(lower_bad & ~upper_bad, hi, mid))
    rec = jnp.clip(rec, j_lo, j_hi)  # the jerk and acceleration limits can always be kept
    # ranges that are empty only by rounding collapse to their midpoint
    a_min = jnp.where(empty, rec, jnp.minimum(lo, mid))
    a_max = jnp.where(empty, rec, jnp.maximum(hi, mid))
    # non-finite states (bad input) get "no change of acceleration" clipped to the limits
    bad_input = ~(jnp.isfinite(p) & jnp.isfinite(v) & jnp.isfinite(a))
    hold = jnp.clip(jnp.where(jnp.isfinite(a), a, 0.0), -A, A)
    a_min = jnp.where(bad_input, hold, jnp.clip(a_min, -A, A))
    a_max = jnp.where(bad_input, hold, jnp.clip(a_max, -A, A))
    a_min, a_max = materialized(a_min), materialized(a_max)
    return SafeRange(a_min, a_max, outside | empty | bad_input)


def braking_acceleration(limits: JointLimits, p: Array, v: Array, a: Array, dt,
                         safe_range: tuple[Array, Array] | None = None) -> Array:
    """Next acceleration of the fastest safe stop ``[..., n]``: drive the velocity to zero as
    fast as jerk and acceleration limits allow, arriving with zero acceleration on the grid
    (velocity target 0 treated as a velocity limit with no settling margin), clipped to the
    safe range so that position limits still hold. Pass ``safe_range=(a_min, a_max)`` of the
    same state if it was computed already."""
    p, v, a = (jnp.asarray(x, jnp.float32) for x in (p, v, a))
    A, J = limits.acc, limits.jerk
    delta = J * dt
    zero = jnp.zeros_like(v)
    # v > 0: the lowest a1 that does not push the velocity below 0 (hardest braking without
    # undershoot); v < 0: the mirror image
    hardest_down = materialized(-_velocity_upper_bound(-v, -a, zero, dt, A, delta, 0.0))
    hardest_up = materialized(_velocity_upper_bound(v, a, zero, dt, A, delta, 0.0))
    # at v = 0 the acceleration decides where the velocity goes (v = 0 with a = +1e-7 used to take
    # the "keep v <= 0" bound, which no a1 can meet for the whole step: its fallback -A kicked the
    # stopped joint to -A dt / 2 and back, two more steps and up to ~0.1 rad of extra motion)
    rising = (v > 0) | ((v == 0) & (a > 0))
    falling = (v < 0) | ((v == 0) & (a < 0))
    target = jnp.where(rising, hardest_down, jnp.where(falling, hardest_up, zero))
    # at rest up to rounding (the stop's last grid acceleration comes out a few ulps off zero):
    # hold still
    settled = (jnp.abs(v) <= SETTLED_VELOCITY * limits.vel) & (jnp.abs(a) <= SETTLED_ACCELERATION * A)
    target = jnp.where(settled, zero, target)
    target = jnp.clip(target, jnp.maximum(a - delta, -A), jnp.minimum(a + delta, A))
    a_min, a_max = safe_acceleration_range(limits, p, v, a, dt) if safe_range is None else safe_range
    return jnp.clip(target, a_min, a_max)


class StepExtrema(NamedTuple):
    p_min: Array
    p_max: Array
    v_min: Array
    v_max: Array
    a_abs: Array
    jerk_abs: Array


def step_extrema(p: Array, v: Array, a0: Array, a1: Array, dt) -> StepExtrema:
    """Exact extrema over ``t in [0, dt]`` of position, velocity, |acceleration| and |jerk| of
    one constant-jerk step (elementwise, ``[..., n]``); used to audit limits between steps."""
    jerk = (a1 - a0) / dt
    p_max = _segment_max_position(p, v, a0, jerk, dt)
    p_min = -_segment_max_position(-p, -v, -a0, -jerk, dt)
    v1 = v + 0.5 * (a0 + a1) * dt
    crosses = a0 * a1 < 0
    t_star = jnp.where(crosses, a0 * dt / jnp.where(crosses, a0 - a1, 1.0), 0.0)
    v_star = v + 0.5 * a0 * t_star
    v_max = jnp.maximum(jnp.maximum(v, v1), jnp.where(crosses, v_star, -jnp.inf))
    v_min = jnp.minimum(jnp.minimum(v, v1), jnp.where(crosses, v_star, jnp.inf))
    return StepExtrema(p_min, p_max, v_min, v_max, jnp.maximum(jnp.abs(a0), jnp.abs(a1)), jnp.abs(jerk))
