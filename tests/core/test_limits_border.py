"""The safe range on and a few float32 ulps beyond each limit (position, velocity, acceleration).

A state that rounding left on a limit, or a hair beyond it, must be treated as *on* it: the
range stays non-empty, unflagged, and every later step stays within the limits at every instant
(exact in-step extrema), whatever the policy does. Run jitted and vmapped over thousands of
episodes as in training, on the ``[E, n]`` arrays without vmap (the controller's way), and
eagerly (op by op: the position search then takes its plain, uncompacted path).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack.core import limits as L
from limit_rollouts import BORDER_FAMILIES, COMPONENTS, border_states, border_usage, random_limits, state_usage

TOL = 1e-6  # relative, beyond max(1, usage of the start state)
DTS = [1.0 / 1000.0, 1.0 / 240.0, 0.1, 0.4]
JERK = {"binding": (0.1, 0.9), "free": (1.0, 3.0)}


def _limits(dt, jerk):
    return random_limits(dt, seed=20 + DTS.index(dt) + 10 * list(JERK).index(jerk), jerk_factor=JERK[jerk])


def _assert_within(excess, flagged, width, family, label):
    assert np.all(flagged == 0), f"{label}: {int(flagged.sum())} joint-steps flagged (violation / empty range)"
    assert np.all(width >= 0.0), f"{label}: empty safe range"
    for f, name in enumerate(BORDER_FAMILIES):
        rows = family == f
        bad = excess[rows].max(axis=(0, 2))
        assert np.all(bad <= TOL), (f"{label}, start family {name!r}: usage beyond the allowed by "
                                    + ", ".join(f"{c} {x:.3g}" for c, x in zip(COMPONENTS, bad)))


@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("jerk", list(JERK))
def test_closed_loop_from_the_border_jitted_and_vmapped(dt, jerk):
    """40 start states (4 families x 2 sides x 0..4 ulps) x 6 policies x 8 draws = 1,920 vmapped
    episodes of 60 decisions, 7 joints with random limits."""
    lim = _limits(dt, jerk)
    excess, flagged, width, family, _ = border_usage(lim, dt, repeats=8, steps=60, seed=DTS.index(dt))
    assert len(family) >= 1900
    _assert_within(excess, flagged, width, family, f"dt {dt}, {jerk} jerk, vmapped")


@pytest.mark.parametrize("dt", [1.0 / 240.0, 0.4])
def test_closed_loop_from_the_border_on_batched_arrays(dt):
    """The same without vmap: the range on ``[E, n]`` arrays (its search compacted over E x n)."""
    lim = _limits(dt, "binding")
    excess, flagged, width, family, _ = border_usage(lim, dt, repeats=2, steps=40, seed=7, vmapped=False)
    _assert_within(excess, flagged, width, family, f"dt {dt}, batched arrays")


def test_border_states_are_where_they_claim():
    """The start states really are on / k ulps beyond the float32 limits (the test's premise)."""
    dt = 0.4
    lim = _limits(dt, "binding")
    p, v, a, family, k, side = border_states(lim, dt)
    hi, vel, acc = (np.asarray(x) for x in (lim.pos_max, lim.vel, lim.acc))
    rows = (family == BORDER_FAMILIES.index("position")) & (side > 0)
    for kk in range(5):
        row = np.flatnonzero(rows & (k == kk))[0]
        x = np.full(7, hi, np.float32)
        for _ in range(kk):
            x = np.nextafter(x, np.float32(np.inf))
        np.testing.assert_array_equal(p[row], x)
        np.testing.assert_array_equal(v[row], 0.0)
    usage = state_usage(lim, p, v, a)  # [4, S, n]
    beyond = (usage > 1.0).any(axis=(0, 2))
    assert beyond[k > 0].any() and not (usage[:, k == 0] > 1.0 + 1e-7).any()
    # the velocity family starts at the velocity limit on joints with room for it
    vrows = (family == BORDER_FAMILIES.index("velocity")) & (k == 0) & (side > 0)
    assert np.any(v[vrows] == vel) and np.all(a[vrows] == 0.0)
    arows = (family == BORDER_FAMILIES.index("acceleration")) & (k == 0) & (side > 0)
    assert np.all((a[arows] == acc) | (a[arows] == 0.0))


@pytest.mark.parametrize("dt", [1.0 / 240.0, 0.4])
def test_eager_range_from_the_border_is_not_flagged_and_agrees_with_jit(dt):
    """Op by op (no jit), the range of every border start is unflagged, non-empty, and equal to
    the jitted one within rounding (the eager path searches every lane, uncompacted)."""
    lim = _limits(dt, "binding")
    p, v, a, *_ = border_states(lim, dt)
    eager = L.safe_acceleration_range_checked(lim, p, v, a, dt)
    jitted = jax.jit(lambda p, v, a: L.safe_acceleration_range_checked(lim, p, v, a, dt))(p, v, a)
    assert not bool(jnp.any(eager.violation)) and not bool(jnp.any(jitted.violation))
    assert bool(jnp.all(eager.a_max >= eager.a_min))
    scale = np.asarray(lim.acc)
    np.testing.assert_allclose(eager.a_min / scale, jitted.a_min / scale, atol=2e-3)
    np.testing.assert_allclose(eager.a_max / scale, jitted.a_max / scale, atol=2e-3)


# --- the reproduction of the one-ulp overshoot that became a 40 % violation -------------------

#: one joint, float32, dt = 0.4 s, binding jerk (jerk dt = 8.64 < 2 acc); found by bang-bang
#: actions: step 36's range let the velocity end one ulp past the limit, after which the range
#: collapsed to [acc, acc] and the jerk limit could no longer stop a 40 % velocity overshoot
ULP_CASE = L.JointLimits([-1.3142253129638592], [0.5391600331554189], [1.3019467116159988],
                         [8.089686208462233], [21.590204309682928])
ULP_DT = 0.4
ULP_STATE = (0.45102656, -0.6473636, -3.2730508)  # step 36 of that episode


def _ulp_rollout(batch: int, steps: int = 40):
    """Action -1 from step 36 of the reproduction, ``batch`` vmapped copies, jitted; returns the
    worst usage ``[4]`` and the number of flagged steps."""
    def step(carry, _):
        p, v, a = carry
        rng = L.safe_acceleration_range_checked(ULP_CASE, p, v, a, ULP_DT)
        a1 = L.action_to_acceleration(-jnp.ones_like(p), rng.a_min, rng.a_max)
        ext = L.step_extrema(p, v, a, a1, ULP_DT)
        p1, v1, _ = L.integrate(p, v, a, a1, ULP_DT, ULP_DT)
        usage = jnp.stack([jnp.maximum((ext.p_max - ULP_CASE.pos_max) / (ULP_CASE.pos_max - ULP_CASE.pos_min),
                                       (ULP_CASE.pos_min - ext.p_min) / (ULP_CASE.pos_max - ULP_CASE.pos_min)) + 1.0,
                           jnp.maximum(ext.v_max, -ext.v_min) / ULP_CASE.vel, ext.a_abs / ULP_CASE.acc,
                           ext.jerk_abs / ULP_CASE.jerk])
        return (p1, v1, a1), (usage, rng.violation)

    def episode(p, v, a):
        _, (usage, flagged) = jax.lax.scan(step, (p, v, a), None, length=steps)
        return usage.max(0), flagged.sum()

    state = [jnp.full((batch, 1), x, jnp.float32) for x in ULP_STATE]
    usage, flagged = jax.jit(jax.vmap(episode))(*state)
    return np.asarray(usage).max(axis=(0, -1)), int(np.asarray(flagged).sum())


@pytest.mark.parametrize("batch", [1, 4096])
def test_ulp_overshoot_reproduction_stays_within_every_limit(batch):
    usage, flagged = _ulp_rollout(batch)
    assert flagged == 0
    assert np.all(usage <= 1.0 + TOL), f"worst usage p/v/a/jerk {usage}"


def test_ulp_reproduction_plan_ends_inside_and_the_state_beyond_is_on_the_limit():
    """Step 36's lowest acceleration ends the step with |v| <= the float32 limit; the state one
    ulp beyond the limit (step 37 before the fix) gets the same range as the state on it."""
    f = jax.jit(lambda p, v, a: L.safe_acceleration_range_checked(ULP_CASE, p, v, a, ULP_DT))
    p, v, a = (jnp.float32([x]) for x in ULP_STATE)
    r = f(p, v, a)
    _, v1, _ = L.integrate(p, v, a, r.a_min, ULP_DT, ULP_DT)
    assert float(jnp.abs(v1)[0]) <= float(ULP_CASE.vel[0])
    vel = np.float32(ULP_CASE.vel[0])
    p37, a37 = jnp.float32([0.017521972]), jnp.float32([0.00013461222])
    on = f(p37, jnp.float32([-vel]), a37)
    for k in range(1, 5):
        beyond = f(p37, jnp.asarray([-np.asarray(ulps_down(vel, k))], jnp.float32), a37)
        assert not bool(beyond.violation[0])
        assert float(beyond.a_max[0]) > float(beyond.a_min[0]) + 1.0  # not collapsed
        np.testing.assert_allclose(beyond.a_min, on.a_min, atol=1e-3)
        np.testing.assert_allclose(beyond.a_max, on.a_max, atol=1e-3)


def ulps_down(x, k):
    """``x`` moved ``k`` float32 ulps away from zero (here: beyond a limit of size ``x``)."""
    x = np.float32(x)
    for _ in range(k):
        x = np.nextafter(x, np.float32(np.inf))
    return x
