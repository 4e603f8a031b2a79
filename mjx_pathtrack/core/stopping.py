"""The braking models behind the safe acceleration range (:mod:`mjx_pathtrack.core.limits`).

Pure JAX, elementwise over ``[..., n]``: the constant-jerk step, the velocity bound (the largest
``a1`` whose velocity peak, with the acceleration lowered at full jerk afterwards, stays at the
velocity limit), the position bound (the largest ``a1`` from which a velocity-safe stop stays
inside the position limit at every instant: closed-form peak, safeguarded Newton steps, exact
check, simulated tail near the stop), paper 001's discrete stop profile (D) and the static plan
of the simulated tail. :mod:`mjx_pathtrack.core.limits`' docstring explains the construction;
docs/limits.md the derivations. Units: rad, rad/s, rad/s^2, rad/s^3, s.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import compaction

Array = jax.Array


#: default ``a_settle / A`` (klimits' ``acceleration_after_max_vel_limit_factor`` in the papers' code)
SETTLE_FACTOR = 0.01
#: Newton iterations (on the closed-form braking peak) of the position bound before the exact
#: check of the candidate (see _position_upper_bound); the result is always exactly verified
POSITION_ITERATIONS = 4
#: bisection steps of the position bound for joints whose velocity floor can bind (see
#: _tail_steps), below the closed-form upper estimate; the other joints snap their closed-form
#: root down to the same grid (``(hi - lo) 2**-14``); always on the safe side
POSITION_BISECTIONS = 14
#: relative margin by which position/velocity limits are pulled in against float32 rounding
MARGIN = 2e-6
#: relative velocity reserve of the planned stop in the position bound (see _safe_stop_peak)
TAIL_VEL_MARGIN = 1e-4


def integrate(p: Array, v: Array, a0: Array, a1: Array, dt, t) -> tuple[Array, Array, Array]:
    """State ``(p, v, a)`` at time ``t in [0, dt]`` of a step whose acceleration goes linearly
    from ``a0`` to ``a1`` (constant jerk ``(a1 - a0)/dt``). All arguments broadcast."""
    return _constant_jerk(p, v, a0, (a1 - a0) / dt, t)


def _constant_jerk(p, v, a, jerk, t):
    """State ``(p, v, a)`` after time ``t`` at constant ``jerk`` (Horner form)."""
    return (p + t * (v + t * (0.5 * a + t * jerk / 6.0)),
            v + t * (a + 0.5 * t * jerk),
            a + jerk * t)


def _segment_argmax(p, v, a, jerk, length):
    """``(max, argmax)`` over ``s in [0, length]`` of ``p + v s + a s^2/2 + jerk s^3/6`` (elementwise)."""
    end = _constant_jerk(p, v, a, jerk, length)[0]
    best, s_best = jnp.where(end > p, end, p), jnp.where(end > p, length, 0.0)
    # stationary points: jerk/2 s^2 + a s + v = 0, solved in the cancellation-free form
    disc = a * a - 2.0 * jerk * v
    root = jnp.sqrt(jnp.maximum(disc, 0.0))
    q = -0.5 * (a + jnp.where(a >= 0, root, -root))
    safe_q = jnp.where(q == 0, 1.0, q)
    safe_j = jnp.where(jerk == 0, 1.0, jerk)
    candidates = (jnp.where(jerk == 0, jnp.inf, q / (0.5 * safe_j)), jnp.where(q == 0, jnp.inf, v / safe_q))
    for s in candidates:
        inside = (disc >= 0) & (s > 0) & (s < length)
        s = jnp.where(inside, s, 0.0)
        value = _constant_jerk(p, v, a, jerk, s)[0]
        higher = inside & (value > best)
        best, s_best = jnp.where(higher, value, best), jnp.where(higher, s, s_best)
    return best, s_best


def _segment_max_position(p, v, a, jerk, length):
    """Max over ``s in [0, length]`` of ``p + v s + a s^2/2 + jerk s^3/6`` (elementwise)."""
    return _segment_argmax(p, v, a, jerk, length)[0]


def _braking_peak(p0, v0, a0, a1, dt, A, delta):
    """Highest position reached if the step ends at ``a1`` and the acceleration is then lowered
    as fast as possible on the decision grid (by ``delta = J dt`` per step, the last step ending
    at ``-A``, then held at ``-A``). Elementwise."""
    peak0 = _segment_max_position(p0, v0, a0, (a1 - a0) / dt, dt)
    p1, v1, _ = integrate(p0, v0, a0, a1, dt, dt)
    # full-jerk steps while the acceleration stays above -A
    m = jnp.maximum(jnp.ceil((a1 + A) / delta) - 1.0, 0.0)
    t_full = m * dt
    jerk = -delta / dt
    peak_full = _segment_max_position(p1, v1, a1, jerk, t_full)
    p2, v2, a2 = _constant_jerk(p1, v1, a1, jerk, t_full)
    peak_last = _segment_max_position(p2, v2, a2, -(a2 + A) / dt, dt)
    p3, v3, _ = integrate(p2, v2, a2, -A, dt, dt)
    peak_hold = p3 + jnp.square(jnp.maximum(v3, 0.0)) / (2.0 * A)
    peak = jnp.maximum(jnp.maximum(peak0, peak_full), jnp.maximum(peak_last, peak_hold))
    # decision step at (or right after) which the velocity has dropped to zero
    k_stop = jnp.where(v2 <= 0, 1.0 + jnp.ceil(_first_zero_time(v1, a1, jerk, t_full) / dt),
                       jnp.where(v3 <= 0, m + 2.0, m + 2.0 + jnp.ceil(v3 / (A * dt))))
    return peak, jnp.where(v1 <= 0, 1.0, k_stop)


def _descent_state(p1, v1, a1, k, dt, A, delta):
    """State on decision step ``1 + k`` (``k >= 0``) of the fastest descent that starts on step 1
    at ``(p1, v1, a1)`` (see :func:`_braking_peak`). Elementwise."""
    m = jnp.maximum(jnp.ceil((a1 + A) / delta) - 1.0, 0.0)
    jerk = -delta / dt
    t_full = m * dt
    pf, vf, af = _constant_jerk(p1, v1, a1, jerk, jnp.minimum(k, m) * dt)
    p3, v3, _ = integrate(*_constant_jerk(p1, v1, a1, jerk, t_full)[:2], a1 - m * delta, -A, dt, dt)
    hold = jnp.maximum(k - m - 1.0, 0.0) * dt
    ph, vh = p3 + v3 * hold - 0.5 * A * hold * hold, v3 - A * hold
    after = k > m
    return jnp.where(after, ph, pf), jnp.where(after, vh, vf), jnp.where(after, -A, af)


def _safe_stop_peak(p0, v0, a0, a1, dt, A, delta, V_floor, V_limit, settle, tail_steps):
    """Highest position of the lowest continuation that also keeps a velocity floor.

    After the step that ends at ``a1``, the acceleration is lowered as fast as the jerk and
    acceleration limits allow, but never so low that the velocity would fall below
    ``-V_floor`` (settling rule of :func:`_velocity_upper_bound`). ``V_floor`` is the velocity
    limit (less a reserve), so braking towards ``P`` cannot push the velocity below ``-V`` once
    the joint has stopped (``V_limit``: the limit less that reserve); in a narrow corridor it is a small "rest" velocity instead, so the
    stop comes to (near) rest and cannot rebound into the opposite limit (:func:`mjx_pathtrack.core.stop_plan._tail_plan`). Far from the stop
    the velocity bound cannot bind and the descent has a closed form; the last ``tail_steps``
    decision steps before and after the stop are simulated. Returns ``(peak, k_stop)``: the
    peak is ``inf`` if the simulated steps do not reach a stop; ``k_stop`` is the decision step
    of the stop."""
    peak, k_stop = _braking_peak(p0, v0, a0, a1, dt, A, delta)
    p1, v1, _ = integrate(p0, v0, a0, a1, dt, dt)
    # steps of plain descent that certainly come before the velocity bound can bind
    back = jnp.ceil(A / delta) + 2.0
    n_skip = jnp.clip(k_stop - 1.0 - back, 0.0, None)
    p, v, a = _descent_state(p1, v1, a1, n_skip, dt, A, delta)
    best = jnp.maximum(_segment_max_position(p0, v0, a0, (a1 - a0) / dt, dt), p)
    # A joint already moving away faster than the floor keeps its speed (capped at the
    # velocity limit): the stop must not swing back towards P just to meet a rest floor.
    # (including what it still gains while the acceleration rises back to zero on the grid,
    # n = ceil(a / delta) steps, with 2 % slack so that the floor is not met only by rounding)
    V_floor = jnp.minimum(jnp.maximum(V_floor, 1.02 * (_rise_loss(jnp.maximum(-a, 0.0), delta, dt) - v)), V_limit)
    def tail_step(_, state):
        p, v, a, best = state
        floor = -_velocity_upper_bound(-v, -a, V_floor, dt, A, delta, settle)
        # (the search range is velocity-feasible, so the floor exceeds the jerk range only by
        # the V_tail reserve; the clip keeps the jerk limit)
        # (materialised: it has several consumers, each of which would re-evaluate the floor)
        a_next = materialized(jnp.clip(jnp.maximum(jnp.maximum(a - delta, -A), floor), None, jnp.minimum(a + delta, A)))
        best = jnp.maximum(best, _segment_max_position(p, v, a, (a_next - a) / dt, dt))
        p, v, _ = integrate(p, v, a, a_next, dt, dt)
        return p, v, a_next, best

    # a loop, not unrolled: the tail is traced and compiled once per call site (unrolled, the
    # 8-16 steps of jerk-binding limits made the range's program ~3x larger and slower to build)
    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in (p, v, a, best, V_floor, A, delta)))
    p, v, a, best = jax.lax.fori_loop(0, tail_steps, tail_step, tuple(jnp.broadcast_to(x, shape) for x in (p, v, a, best)))
    # Still rising after the simulated steps: bound the rest of the rise. The velocity grows by
    # at most a t_ramp while the acceleration falls to zero, and the stop takes at most
    # 2 t_ramp + v_up / A more (fall to -A, hold, and the rise of the settling).
    t_ramp = (jnp.ceil(A / delta) + 1.0) * dt
    v_up = v + jnp.maximum(a, 0.0) * t_ramp
    rest = p + v_up * (2.0 * t_ramp + v_up / A)
    return jnp.maximum(best, jnp.where(v > 0, rest, -jnp.inf)), k_stop


def _first_zero_time(v, a, jerk, length):
    """First ``s in [0, length]`` with ``v + a s + jerk s^2/2 = 0`` for ``jerk < 0`` (else length)."""
    disc = a * a - 2.0 * jerk * v
    s = (a + jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.where(jerk < 0, -jerk, 1.0)
    return jnp.clip(jnp.where(jerk < 0, s, length), 0.0, length)


def _grid_stop_bound(p0, v0, a0, P, dt, A, delta, K, n_full):
    """Paper 001 profile (D) on the decision grid: ``a1`` such that the joint reaches ``P`` with
    zero velocity exactly at decision step ``K >= 2``, the acceleration after ``a1`` falling by
    ``delta`` per step for ``n_full`` steps, then held at ``-A``, and the last grid value ``y``
    free. Grid values enter ``v_K``/``p_K`` linearly (weights ``dt/2, dt, .., dt/2`` and
    ``dt^2 (K/2 - 1/6), dt^2 (K - k), .., dt^2/6``), so this is a 2x2 linear solve.
    Returns ``(a1, feasible)``."""
    L = jnp.clip(n_full + 1.0, 1.0, K - 1.0)  # grid steps 1..L descend from a1
    H = K - 1.0 - L  # grid steps held at -A
    s1 = L * K - 0.5 * L * (L + 1.0)
    s2 = 0.5 * (K - 1.0) * L * (L - 1.0) - (L - 1.0) * L * (2.0 * L - 1.0) / 6.0
    # v_K = 0:  y = cv - 2 L x
    cv = 2.0 * (-v0 / dt - 0.5 * a0 + 0.5 * delta * L * (L - 1.0) + A * H)
    # p_K = P:  s1 x + y/6 = rp
    rp = (P - p0 - K * dt * v0) / (dt * dt) - (0.5 * K - 1.0 / 6.0) * a0 + delta * s2 + 0.5 * A * H * (H + 1.0)
    det = s1 - L / 3.0
    x = (rp - cv / 6.0) / jnp.where(det == 0, 1.0, det)
    y = cv - 2.0 * L * x
    last = jnp.where(H > 0, -A, x - (L - 1.0) * delta)
    descent_ok = jnp.where(H > 0, x - L * delta <= -A + 1e-6 * A, True) & (x - (L - 1.0) * delta >= -A - 1e-6 * A)
    feasible = ((det != 0) & (jnp.abs(y) <= A) & (jnp.abs(y - last) <= delta) & descent_ok & (jnp.abs(x) <= A))
    return x, feasible


def _stop_model(p0, v0, a0, a1, dt, A, delta):
    """Newton model of :func:`_position_upper_bound`: the highest position *after step 1* of
    the braking profile of :func:`_braking_peak` (elementwise). Returns ``(peak, slope,
    k_stop, hold_root)``: ``slope = d peak / d a1``, ``k_stop`` the decision step of the stop,
    and ``hold_root(T)`` the exact ``a1`` with ``peak = T`` if the stop stays in the hold at
    ``-A`` with the same number of full-jerk steps (``None``-like ``nan`` otherwise).

    After step 0 the acceleration only falls, so the velocity has one downward zero crossing
    (in the full-jerk part, the partial step to ``-A`` or the hold at ``-A``); the peak is
    there (or at the end of step 0 if the velocity is not positive after it). At a maximum
    the velocity is zero, so the slope is the partial derivative of the position at the fixed
    stop time. For a fixed number ``m`` of full-jerk steps, position and velocity at the start
    of the hold are linear in ``a1`` and the hold peak ``p3 + v3^2/(2A)`` is a quadratic."""
    h = 0.5 * dt
    jerk_full = delta / dt
    p1, v1, _ = integrate(p0, v0, a0, a1, dt, dt)
    m = jnp.maximum(jnp.ceil((a1 + A) / delta) - 1.0, 0.0)
    tf = m * dt
    a2 = a1 - m * delta
    v2 = v1 + 0.5 * tf * (a1 + a2)
    p2 = p1 + tf * (v1 + tf * (0.5 * a1 - jerk_full * tf / 6.0))
    v3 = v2 + 0.5 * (a2 - A) * dt
    p3 = p2 + dt * v2 + dt * dt * (a2 / 3.0 - A / 6.0)
    dv2 = h + tf
    dp2 = dt * dt / 6.0 + tf * (h + 0.5 * tf)
    dv3 = dv2 + h
    dp3 = dp2 + dt * dv2 + dt * dt / 3.0
    full, last = v2 <= 0, v3 <= 0

    def pick(x_full, x_last, x_hold):
        return jnp.where(full, x_full, jnp.where(last, x_last, x_hold))

    ps, vs, as_ = pick(p1, p2, p3), pick(v1, v2, v3), pick(a1, a2, -A)
    js = pick(-jerk_full, -(a2 + A) / dt, 0.0)
    r = jnp.sqrt(jnp.maximum(as_ * as_ - 2.0 * js * vs, 0.0))
    s = jnp.where(vs > 0, 2.0 * vs / jnp.maximum(r - as_, 1e-30),
                  jnp.where(js < 0, (as_ + r) / jnp.where(js < 0, -js, 1.0), 0.0))
    s = jnp.clip(s, 0.0, pick(tf, dt, jnp.inf))
    peak = ps + s * (vs + s * (0.5 * as_ + js * s / 6.0))
    dps, dvs = pick(dt * dt / 6.0, dp2, dp3), pick(h, dv2, dv3)
    das, djs = pick(1.0, 1.0, 0.0), pick(0.0, -1.0 / dt, 0.0)
    slope = dps + s * (dvs + s * (0.5 * das + djs * s / 6.0))
    k_stop = jnp.where(v1 <= 0, 1.0, pick(1.0 + jnp.ceil(s / dt), m + 2.0, m + 2.0 + jnp.ceil(s / dt)))
    hold = ~full & ~last

    def hold_root(T):
        # u = v3 at the root: u^2/(2A) + c1 u + c0 = 0 with p3 + c1 (u - v3) = position part
        c1 = dp3 / dv3
        c0 = p3 - c1 * v3 - T
        u = A * (jnp.sqrt(jnp.maximum(c1 * c1 - 2.0 * c0 / A, 0.0)) - c1)
        return jnp.where(hold, a1 + (u - v3) / dv3, jnp.nan)

    return peak, slope, k_stop, hold_root


def _step0_root(p0, v0, a0, T, dt):
    """Largest ``a1`` whose in-step position maximum (velocity crossing zero at ``s <= dt``
    inside step 0) equals ``T``, ``inf`` if the in-step maximum cannot reach ``T``.
    Parametrised by the crossing time ``s``: ``jerk = -2 (v0 + a0 s)/s^2`` and the peak is
    ``p0 + 2/3 v0 s + a0 s^2/6``, a quadratic in ``s``. Elementwise."""
    beta = (2.0 / 3.0) * v0
    c = p0 - T
    disc = beta * beta - (2.0 / 3.0) * a0 * c
    s = 2.0 * (-c) / (beta + jnp.sqrt(jnp.maximum(disc, 0.0)))
    valid = (v0 > 0) & (c <= 0) & (disc >= 0) & (s <= dt)
    s = jnp.maximum(jnp.where(valid, s, dt), 1e-30)
    a1 = a0 - 2.0 * (v0 + a0 * s) * dt / (s * s)
    return jnp.where(valid, a1, jnp.inf)


def _stop_excess(p0, v0, a0, a1, P, reserve, V_floor, V_limit, settle, dt, A, delta, tail_steps):
    """Exact stop peak from ``a1`` minus the target ``max(P - reserve k_stop, p0)`` (> 0: ``a1``
    is not safe) and the stop step ``k_stop``: the velocity-safe stop with ``tail_steps``
    simulated steps, or the plain braking peak when ``tail_steps == 0``. Elementwise."""
    if tail_steps:
        peak, k_stop = _safe_stop_peak(p0, v0, a0, a1, dt, A, delta, V_floor, V_limit, settle, tail_steps)
    else:
        peak, k_stop = _braking_peak(p0, v0, a0, a1, dt, A, delta)
    return peak - jnp.maximum(P - reserve * k_stop, p0), k_stop


def _position_upper_bound(p0, v0, a0, P, reserve, V_floor, V_limit, settle, dt, A, delta, lo, hi, iterations, tail_steps):
    """:func:`_position_search`, run only where it can return less than ``hi`` (elementwise).

    Most joints are far from their position limits: there the search returns ``hi`` after
    checking it. A cheap test makes the same decisions as the search does at ``hi`` (the exact
    stop from ``hi`` stays below the target, and with ``tail_steps == 0`` also the Newton model
    and the step-0 root do not go below ``hi``; no grid-stop candidate is narrower); such
    lanes get ``hi``, verified exactly like the search would. The search runs on the other
    lanes only, gathered into chunks across the batch (:func:`compaction.where_needed`), so
    its cost scales with the joints that are near a limit, not with the batch."""
    if compaction.is_concrete(p0, v0, a0, lo, hi):  # eager, op by op: no loop to save
        return _position_search(p0, v0, a0, P, reserve, V_floor, V_limit, settle, dt, A, delta, lo, hi, iterations, tail_steps)

    g, k_hi = _stop_excess(p0, v0, a0, hi, P, reserve, V_floor, V_limit, settle, dt, A, delta, tail_steps)
    easy = (g <= 0) & (lo <= hi)
    if not tail_steps:
        peak, _, k_model, _ = _stop_model(p0, v0, a0, hi, dt, A, delta)
        easy = easy & (peak - jnp.maximum(P - reserve * k_model, p0) <= 0)
        easy = easy & (_step0_root(p0, v0, a0, jnp.maximum(P - reserve, p0), dt) >= hi)
    easy = easy & ~_grid_stop_candidate(p0, v0, a0, P, dt, A, delta, hi, k_hi)[0]
    # a concrete dt stays a Python number (constants folded in float64, as everywhere else)
    static_dt = not isinstance(dt, jax.core.Tracer)

    def search(p0, v0, a0, P, reserve, V_floor, V_limit, settle, A, delta, lo, hi, *traced_dt):
        step = dt if static_dt else traced_dt[0]
        return _position_search(p0, v0, a0, P, reserve, V_floor, V_limit, settle, step, A, delta, lo, hi, iterations, tail_steps)

    searched = compaction.where_needed(search, ~easy, p0, v0, a0, P, reserve, V_floor, V_limit, settle, A, delta, lo, hi,
                                       *(() if static_dt else (dt,)))
    return jnp.where(easy, hi, searched)


def _position_search(p0, v0, a0, P, reserve, V_floor, V_limit, settle, dt, A, delta, lo, hi, iterations, tail_steps):
    """Largest ``a1 in [lo, hi]`` whose velocity-safe stop (:func:`_safe_stop_peak`) does not
    exceed ``P`` less ``reserve`` per decision step until the stop (``lo`` if none is found).

    The reserve shrinks by one step's worth as the stop comes closer, which absorbs the float32
    rounding of re-evaluating the same plan on the next step. A state that rounding left a hair
    above the target may stay but not climb.

    Search: the in-step peak of step 0 has a closed-form root (:func:`_step0_root`); the peak
    after step 1 gets ``iterations`` safeguarded Newton steps from ``hi`` on the closed-form
    model (:func:`_stop_model`; exact root of the quadratic when the stop is in the hold at
    ``-A``). With ``tail_steps == 0`` (the velocity floor cannot bind) the smaller root, snapped
    down to the bisection grid, is checked with the exact braking peak (twice at most). With
    ``tail_steps > 0`` the exact stop with the simulated tail is bisected in ``[lo, hi]``
    (``POSITION_BISECTIONS`` steps) as before; the Newton part is then unused. Only exactly
    verified values are returned (or ``lo``)."""

    def excess(a1):
        return _stop_excess(p0, v0, a0, a1, P, reserve, V_floor, V_limit, settle, dt, A, delta, tail_steps)

    def newton(x):
        peak, slope, k_stop, hold_root = _stop_model(p0, v0, a0, x, dt, A, delta)
        target = jnp.maximum(P - reserve * k_stop, p0)
        step = hold_root(target)
        step = jnp.where(jnp.isnan(step), x - (peak - target) / jnp.maximum(slope, 1e-30), step)
        return peak - target, step, slope

    x, good, bad = hi, lo, hi
    for _ in range(iterations):
        g, step, _ = newton(x)
        fine = g <= 0
        good, bad = jnp.where(fine, jnp.maximum(good, x), good), jnp.where(fine, bad, jnp.minimum(bad, x))
        x = jnp.where(fine, x, jnp.where((step > good) & (step < bad), step, 0.5 * (good + bad)))
    # Model root (the Newton iterates of this convex peak stay on the unsafe side, so the last
    # update is the best estimate), and the closed-form root of the in-step peak of step 0.
    g, step, slope = newton(x)
    root = jnp.where(good >= hi, hi, jnp.where(g <= 0, x, step))
    root = jnp.maximum(jnp.minimum(root, _step0_root(p0, v0, a0, jnp.maximum(P - reserve, p0), dt)), lo)
    if tail_steps:
        # Bisection of the exact stop with the simulated tail, as before the closed form. (Bisecting
        # only below the closed-form root, an upper estimate since the floor only raises the
        # stop, was tried: it changed the chaotic rebounds of tests/limit_rollouts.random_limits
        # at dt = 0.4 for the worse, so it is not used yet.)
        def body(_, bracket):
            good, bad = bracket
            mid = 0.5 * (good + bad)
            fine = excess(mid)[0] <= 0
            return jnp.where(fine, mid, good), jnp.where(fine, bad, mid)

        hi_fine = excess(hi)[0] <= 0
        best, _ = jax.lax.fori_loop(0, POSITION_BISECTIONS, body, (lo, hi))
        best = jnp.where(hi_fine, hi, best)
        best_k = _braking_peak(p0, v0, a0, best, dt, A, delta)[1]
    else:
        # Snap down to the grid lo + i (hi - lo) 2^-POSITION_BISECTIONS, the values a bisection
        # would return: rounding differences between compiled variants (jit, vmap) of the
        # model then rarely change the result, and the exact check decides on grid values.
        q = (hi - lo) * 2.0 ** -POSITION_BISECTIONS

        def snap(y):
            return jnp.where(y >= hi, hi, lo + jnp.floor(jnp.maximum(y - lo, 0.0) / jnp.where(q > 0, q, 1.0)) * q)

        ulp = float(np.finfo(np.float32).eps) * jnp.maximum(jnp.abs(P), jnp.abs(p0))
        x = snap(root)
        best, best_k = lo, jnp.ones_like(lo)
        for i in range(2):
            g, k = excess(x)
            g = materialized(g)  # four consumers below, each would re-evaluate the braking peak
            fine = g <= 0
            best, best_k = jnp.where(fine & (x >= best), x, best), jnp.where(fine & (x >= best), k, best_k)
            # rare: the candidate failed by rounding; step down by a grid value or a Newton step
            x = jnp.where(fine, x, snap(x - jnp.maximum(q, 2.0 * (g + 4.0 * ulp) / jnp.maximum(slope, 1e-30))))
    exact = materialized(best)  # feeds the grid-stop candidates and the final choice
    # Prefer the grid-stop profile (reach P at rest-velocity on a decision step) when it is
    # feasible and not wider than the exact bound: it avoids overshoot-and-return motions.
    use, grid = _grid_stop_candidate(p0, v0, a0, P, dt, A, delta, exact, best_k)
    # a grid-stop candidate counts only if the velocity-safe stop from it stays below P too
    use = use & (excess(jnp.where(use, grid, lo))[0] <= 0)
    return jnp.maximum(jnp.where(use, grid, exact), lo)


def _grid_stop_candidate(p0, v0, a0, P, dt, A, delta, exact, best_k):
    """``(use, grid)``: the first feasible grid-stop bound (:func:`_grid_stop_bound`) for stop
    steps ``best_k - 1 .. best_k + 1`` and ``n_full`` or one fewer full-jerk steps of ``exact``,
    and whether it is narrower than ``exact`` (still to be checked exactly). Elementwise."""
    n_full = jnp.maximum(jnp.ceil((exact + A) / delta) - 1.0, 0.0)
    grid = jnp.full_like(exact, jnp.inf)
    found = jnp.zeros(exact.shape, bool)
    for dk in (-1.0, 0.0, 1.0):
        K = jnp.maximum(best_k + dk, 2.0)
        for dn in (0.0, -1.0):
            xg, feasible = _grid_stop_bound(p0, v0, a0, P, dt, A, delta, K, jnp.maximum(n_full + dn, 0.0))
            grid = jnp.where(feasible & ~found, xg, grid)
            found = found | feasible
    return found & (grid < exact), grid


def jerk_budget(J, A, dt):
    """Per-step change of acceleration the safe range plans with [rad/s^2]: ``J dt`` pulled in
    by the float32 resolution of accelerations of size ``A``, so that ``a1 - a0`` rounded never
    exceeds ``J dt`` (matters when ``J dt << A``). Works on NumPy and JAX arrays."""
    return (J * dt * (1.0 - MARGIN) - 8.0 * float(np.finfo(np.float32).eps) * A).clip(min=0.0)


def _velocity_upper_bound(v0, a0, V, dt, A, delta, settle):
    """Largest ``a1`` whose velocity peak equals ``V`` (settling rule, module docstring).

    Returns ``-inf`` where even the in-step constraint cannot be met (state at/over the limit
    with positive acceleration that the jerk limit is considered separately for)."""
    # c = (V - v(t) contributions that do not depend on a1) / dt
    c = (V - v0 - 0.5 * a0 * dt) / dt
    # Continuous-time estimate (jerk -J right after a1): a1^2/(2J) + a1 dt/2 = V - v0 - a0 dt/2
    J = delta / dt
    a_cont = J * (-0.5 * dt + jnp.sqrt(jnp.maximum(0.25 * dt * dt + 2.0 * c * dt / J, 0.0)))
    m_cont = jnp.maximum(jnp.ceil((a_cont + settle - delta) / delta), 0.0)
    # The branches (count m of full-jerk steps; x = a1 - m delta in (0, delta - settle] or
    # (-settle, 0]) tile a1 > 0 without gaps in exact arithmetic. In float32 a root on a branch
    # boundary can land a few ulps outside both of its branches, so a root up to ``tol`` beyond
    # a branch's upper end is accepted and clamped down to that end (lower a1 = lower peak, so
    # safe); m_cont is an estimate, so its neighbours on both sides are tried.
    tol = 64.0 * float(np.finfo(np.float32).eps) * (jnp.abs(c) + delta)
    # Targets: a plan whose velocity peak comes k decision steps from now aims at V_in - k eps
    # (k = m + 1 for x > 0, k = m for x <= 0, k = 0 in-step below), V_in half-way between V and
    # the hard limit V (1 + MARGIN). One step later the same plan is re-evaluated as the branch
    # with one step fewer, against a target eps higher: that absorbs its float32 rounding (like
    # the position bound's reserve per step), where one shared target made the re-evaluated
    # bound land a few ulps below the jerk floor (an empty range, found by a chattering policy).
    V_in = V * (1.0 + 0.5 * MARGIN)
    eps = 0.25 * MARGIN * V
    best = jnp.full_like(c, -jnp.inf)
    for shift in (-1.0, 0.0, 1.0):
        m = jnp.maximum(m_cont - shift, 0.0)
        grid = 0.5 * delta * m * (m + 1.0)
        K_pos = c + (V_in - (m + 1.0) * eps - V) / dt - grid
        K_neg = c + (V_in - m * eps - V) / dt - grid
        # x = a1 - m*delta > 0 : last step ends at -settle
        b = (2.0 * m + 1.0) * settle - 2.0 * K_pos
        x_pos = (-b + jnp.sqrt(jnp.maximum(b * b + 16.0 * (m + 1.0) * K_pos * settle, 0.0))) / (4.0 * (m + 1.0))
        # x <= 0 (m >= 1): zero crossing inside the last full-jerk step. A root x > 0 is
        # clamped to x = 0 (the acceleration reaches 0 at the end of step m; a lower peak than
        # the target): with the targets per step above, the x > 0 branch aims one eps lower and
        # its root can then fall just below 0, so near x = 0 neither root would be accepted.
        x_neg = delta * (-(m + 0.5) + jnp.sqrt(jnp.maximum((m + 0.5) ** 2 + 2.0 * K_neg / delta, 0.0)))
        for x, valid in ((jnp.minimum(x_pos, delta - settle), (K_pos > 0) & (x_pos > 0) & (x_pos <= delta - settle + tol)),
                         (jnp.minimum(x_neg, 0.0), (m >= 1) & (x_neg > -settle))):
            a1 = x + m * delta
            best = jnp.where(valid, jnp.maximum(best, a1), best)
    # a1 <= 0 and v never rises after the step: only the in-step peak matters (k = 0: the last
    # step of every plan above; aiming at the hard limit itself, a plan ended one float32 ulp
    # beyond it, and that state was then declared a dead end). A state that rounding left on or a hair
    # beyond V (up to V_zone, where ``outside`` starts) counts as *on* the limit: with a0 <= 0
    # its velocity does not rise for any a1 <= 0, and with a0 > 0 the in-step rise is kept
    # within ``rise`` (a few ulps; the jerk limit makes some rise unavoidable). Only states
    # beyond V_zone are dead ends here (bad input; the caller recovers from those).
    V_zone = V * (1.0 + 2.0 * MARGIN)
    rise = 0.25 * MARGIN * V
    target = jnp.maximum(V_in, jnp.minimum(v0, V_zone) + rise)
    in_step_ok_at_zero = jnp.where(a0 > 0, v0 + 0.5 * a0 * dt <= target, v0 <= V_zone)
    gap = target - v0
    a1_in_step = jnp.where(a0 > 0, a0 - a0 * a0 * dt / (2.0 * jnp.where(gap > 0, gap, 1.0)), jnp.inf)
    a1_in_step = jnp.where((gap <= 0) & (a0 > 0), -jnp.inf, a1_in_step)
    a1_in_step = jnp.where((v0 > V_zone) & (a0 <= 0), -jnp.inf, a1_in_step)
    return jnp.where(in_step_ok_at_zero, jnp.maximum(best, 0.0), jnp.minimum(a1_in_step, 0.0))


def _rise_loss(a_away, delta, dt, xp=jnp):
    """Velocity [rad/s] lost while an acceleration ``-a_away <= 0`` rises back to zero as fast
    as the grid allows (by ``delta = J dt`` per decision step, ``n = ceil(a_away / delta)``
    steps, the last one ending at zero). Elementwise."""
    n = xp.maximum(xp.ceil(a_away / delta), 1.0)
    return dt * (0.5 * a_away + (n - 1.0) * a_away - 0.5 * delta * n * (n - 1.0))


def materialized(x: Array) -> Array:
    """``x`` unchanged (exactly: ``max(x, -inf)``, NaN stays NaN), computed once into a buffer.

    XLA on CPU fuses cheap elementwise producers into *each* consumer, so every use of a value
    with a deep expression tree re-evaluates the whole tree: every use of the safe range (action
    mapping, braking, clipping) recomputed it, and inside the range every consumer of a tail
    step's acceleration recomputed its velocity floor. A reduction is a fusion root that
    consumers read from memory (``lax.optimization_barrier`` is removed on CPU and does not
    help). Use it on a value with several consumers whose tree is expensive. Measured by
    ``benchmarks/bench_env.py`` (batch 2048, 2 cores): on the range's outputs, env.step 62,500 ->
    99,600 env-steps/s; inside the range (tail, checks, velocity bounds) 99,900 -> 140,500."""
    return jnp.max(jnp.stack([x, jnp.full_like(x, -jnp.inf)], axis=-1), axis=-1)
