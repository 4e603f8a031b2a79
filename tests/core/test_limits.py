"""Tests of mjx_pathtrack.core.limits: the safe acceleration range must be impossible to break."""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack import _xla
from mjx_pathtrack.core import limits as L
from limit_rollouts import IIWA_ACC, IIWA_POS, IIWA_VEL, POLICIES, iiwa_limits, random_limits, rollout_usage

TOL = 1e-6  # relative


# --- JointLimits validation ------------------------------------------------------------------

def test_joint_limits_is_a_pytree_and_jits():
    lim = iiwa_limits(0.1)
    leaves = jax.tree_util.tree_leaves(lim)
    assert len(leaves) == 5 and all(x.shape == (7,) for x in leaves)
    out = jax.jit(lambda l: l.acc * 2)(lim)
    np.testing.assert_allclose(out, 2 * IIWA_ACC)
    np.testing.assert_allclose(lim.jerk, 2 * IIWA_ACC / 0.1, rtol=1e-6)


@pytest.mark.parametrize("field,value,message", [
    ("vel", np.nan, "vel of joint 3 .* is NaN"),
    ("acc", 0.0, "acc limit of joint 3 .* must be finite and > 0"),
    ("jerk", -1.0, "jerk limit of joint 3 .* must be finite and > 0"),
    ("pos_min", 5.0, "joint 3 .* pos_min >= pos_max"),
    ("pos_max", np.inf, "joint 3 .* one infinite position limit"),
])
def test_joint_limits_rejects_bad_values_naming_the_joint(field, value, message):
    kwargs = dict(pos_min=-IIWA_POS.copy(), pos_max=IIWA_POS.copy(), vel=IIWA_VEL.copy(), acc=IIWA_ACC.copy(),
                  jerk=2 * IIWA_ACC / 0.1)
    kwargs[field] = kwargs[field].copy()
    kwargs[field][3] = value
    names = [f"j{i}" for i in range(7)]
    with pytest.raises(ValueError, match=message):
        L.JointLimits(**kwargs, names=names)


def test_joint_limits_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="same length"):
        L.JointLimits(-IIWA_POS, IIWA_POS, IIWA_VEL[:6], IIWA_ACC, IIWA_ACC)
    with pytest.raises(ValueError, match="1-D"):
        L.JointLimits(-IIWA_POS[None], IIWA_POS[None], IIWA_VEL[None], IIWA_ACC[None], IIWA_ACC[None])


def test_continuous_joint_has_no_position_bound():
    lim = L.JointLimits([-np.inf], [np.inf], [1.0], [10.0], [200.0])
    assert bool(lim.continuous[0])
    a_min, a_max = L.safe_acceleration_range(lim, jnp.array([100.0]), jnp.array([0.0]), jnp.array([0.0]), 0.1)
    np.testing.assert_allclose([a_min[0], a_max[0]], [-10.0, 10.0])


# --- step kinematics -------------------------------------------------------------------------

def test_integrate_matches_constant_jerk_closed_form_and_derivatives():
    p, v, a0, a1, dt = 0.3, -1.2, 4.0, -7.0, 0.1
    pe, ve, ae = L.integrate(p, v, a0, a1, dt, dt)
    np.testing.assert_allclose(pe, p + v * dt + (a0 / 3 + a1 / 6) * dt**2, rtol=1e-6)
    np.testing.assert_allclose(ve, v + (a0 + a1) * dt / 2, rtol=1e-6)
    np.testing.assert_allclose(ae, a1, rtol=1e-6)
    t = 0.037
    dp = jax.grad(lambda t: L.integrate(p, v, a0, a1, dt, t)[0])(t)
    np.testing.assert_allclose(dp, L.integrate(p, v, a0, a1, dt, t)[1], rtol=1e-5)


def test_action_mapping_is_eq5_and_clips():
    a_min, a_max = jnp.array([-2.0, 1.0]), jnp.array([4.0, 3.0])
    np.testing.assert_allclose(L.action_to_acceleration(jnp.array([-1.0, 1.0]), a_min, a_max), [-2.0, 3.0])
    np.testing.assert_allclose(L.action_to_acceleration(jnp.array([0.0, 0.5]), a_min, a_max), [1.0, 2.5])
    np.testing.assert_allclose(L.action_to_acceleration(jnp.array([7.0, -9.0]), a_min, a_max), [4.0, 1.0])


def test_acceleration_to_action_inverts_the_mapping():
    """Random ranges: action -> acceleration -> action is the identity; accelerations outside the
    range give the border's action; a range that is a point gives 0."""
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    a_min = jax.random.uniform(k1, (1000,), minval=-10.0, maxval=5.0)
    a_max = a_min + jax.random.uniform(k2, (1000,), minval=1e-3, maxval=10.0)
    action = jax.random.uniform(k3, (1000,), minval=-1.0, maxval=1.0)
    back = L.acceleration_to_action(L.action_to_acceleration(action, a_min, a_max), a_min, a_max)
    np.testing.assert_allclose(back, action, atol=2e-3)
    np.testing.assert_array_equal(L.acceleration_to_action(a_max + 1.0, a_min, a_max), 1.0)
    np.testing.assert_array_equal(L.acceleration_to_action(a_min - 1.0, a_min, a_max), -1.0)
    np.testing.assert_array_equal(L.acceleration_to_action(jnp.array([3.0, -2.0]), jnp.array([1.0, 1.0]),
                                                           jnp.array([1.0, 1.0])), 0.0)


def test_materialized_output_is_bit_identical():
    """The fusion barrier on the safe range's outputs changes no value (sign of zero, inf,
    NaN, subnormal included), jitted and vmapped."""
    x = np.array([[0.0, -0.0, 1.5, -3.25e-38, np.inf, -np.inf, np.nan, 1e-45]], np.float32).repeat(3, 0)
    y = np.asarray(jax.jit(jax.vmap(L.materialized))(jnp.asarray(x)))
    assert y.dtype == np.float32
    np.testing.assert_array_equal(y.view(np.uint32), x.view(np.uint32))


def test_step_extrema_match_dense_sampling():
    rng = np.random.default_rng(0)
    p, v, a0, a1 = (rng.uniform(-5, 5, 2000) for _ in range(4))
    dt = 0.1
    ext = L.step_extrema(p, v, a0, a1, dt)
    t = np.linspace(0, dt, 4001)[:, None]
    ps, vs, _ = (np.asarray(x) for x in L.integrate(p, v, a0, a1, dt, t))
    np.testing.assert_allclose(ext.p_max, ps.max(0), atol=1e-5)
    np.testing.assert_allclose(ext.p_min, ps.min(0), atol=1e-5)
    np.testing.assert_allclose(ext.v_max, vs.max(0), atol=1e-5)
    np.testing.assert_allclose(ext.v_min, vs.min(0), atol=1e-5)


# --- the safe range in closed loop -----------------------------------------------------------

DTS = [0.1, 0.05, 1.0 / 240.0, 0.4]


@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("kind", ["iiwa", "random"])
def test_closed_loop_never_violates_limits(dt, kind):
    """Per case 5 policies x 400 episodes x 100 decisions x 7 joints (16,000 episodes in all),
    checked at every step and at the exact extrema inside each step (position, velocity,
    |acceleration|, |jerk|). ``random``: drawn limits whose jerk binds (jerk < 2 acc / dt) and
    position corridors down to +-0.2 rad, a new draw per dt."""
    seed = DTS.index(dt)
    limits = iiwa_limits(dt) if kind == "iiwa" else random_limits(dt, seed=seed)
    results = rollout_usage(limits, dt, episodes=400, steps=100, seed=seed)
    for policy in POLICIES:
        usage, width, violations = results[policy]
        assert violations == 0, f"{policy}: {violations} steps flagged a limit violation / empty range"
        assert width >= 0.0, f"{policy}: empty safe range"
        assert np.all(usage <= 1.0 + TOL), f"{policy}: max normalised usage p,v,a,jerk = {usage.max(1)}"


def test_closed_loop_also_holds_with_xlas_default_fusion_emitters():
    """``train.py`` compiles the environment with XLA's default CPU fusion emitters when the run
    has no MJX physics (``mjx_pathtrack._xla.drop_cpu_fix``); this file otherwise runs with the
    package's MJX flag, and the emitters round differently. The closed-loop check of the
    training setting (iiwa limits, dt 0.1) again, in a process without the flag."""
    env = {k: v for k, v in os.environ.items() if k != _xla.ADDED_VAR}
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if _xla.FUSION_FLAG_NAME not in f)
    env[_xla.OPT_OUT_VAR] = "1"
    child = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                            f"{__file__}::test_closed_loop_never_violates_limits[iiwa-0.1]",
                            f"{__file__}::test_fusion_emitters_are_the_defaults_in_this_process"],
                           env=env, capture_output=True, text=True, timeout=900)
    assert child.returncode == 0, child.stdout[-3000:] + child.stderr[-3000:]
    assert "2 passed" in child.stdout


def test_fusion_emitters_are_the_defaults_in_this_process():
    """Which emitters this process compiles with (run by the test above, where it must hold)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if _xla._opted_out(os.environ):
        assert _xla.FUSION_FLAG_NAME not in flags
    else:  # the package's flag, or a value the user chose
        assert _xla._has_fusion_flag(flags)


def test_constant_plus_one_reaches_pmax_and_stays_without_overshoot():
    """Paper 001 Fig. 1 border case, every joint of the iiwa, from rest in the middle."""
    dt = 0.05
    lim = iiwa_limits(dt)
    p, v, a = jnp.zeros(7), jnp.zeros(7), jnp.zeros(7)
    worst = -np.inf
    for _ in range(120):
        a_min, a_max = L.safe_acceleration_range(lim, p, v, a, dt)
        a1 = L.action_to_acceleration(jnp.ones(7), a_min, a_max)
        worst = max(worst, float(jnp.max(L.step_extrema(p, v, a, a1, dt).p_max - lim.pos_max)))
        p, v, _ = L.integrate(p, v, a, a1, dt, dt)
        a = a1
    span = np.asarray(lim.pos_max - lim.pos_min)
    assert worst <= TOL * float(np.max(lim.pos_max))
    assert np.all(np.abs(np.asarray(lim.pos_max - p)) <= 0.01 * span)
    assert np.all(np.abs(np.asarray(v)) <= 0.01 * np.asarray(lim.vel) + 0.05)


# --- bad input -------------------------------------------------------------------------------

def test_states_outside_limits_get_fastest_recovery_and_a_flag():
    lim = iiwa_limits(0.1)
    p = jnp.asarray(IIWA_POS * 1.01)          # beyond p_max, moving further out
    v = jnp.asarray(IIWA_VEL * 0.5)
    a = jnp.zeros(7)
    r = L.safe_acceleration_range_checked(lim, p, v, a, 0.1)
    assert bool(jnp.all(r.violation))
    assert np.all(np.isfinite(np.asarray(r.a_min))) and np.all(np.isfinite(np.asarray(r.a_max)))
    np.testing.assert_allclose(r.a_max, -IIWA_ACC, rtol=1e-6)  # brake as hard as allowed
    r = L.safe_acceleration_range_checked(lim, jnp.zeros(7), jnp.asarray(-IIWA_VEL * 1.2), a, 0.1)
    assert bool(jnp.all(r.violation))
    np.testing.assert_allclose(r.a_min, IIWA_ACC, rtol=1e-6)


def test_nan_state_is_flagged_never_nan():
    lim = iiwa_limits(0.1)
    p = jnp.zeros(7).at[2].set(jnp.nan)
    r = L.safe_acceleration_range_checked(lim, p, jnp.zeros(7), jnp.zeros(7), 0.1)
    assert bool(r.violation[2]) and not bool(r.violation[0])
    assert np.all(np.isfinite(np.asarray(r.a_min))) and np.all(np.isfinite(np.asarray(r.a_max)))


def test_vmaps_over_any_leading_batch_shape():
    lim = iiwa_limits(0.1)
    rng = np.random.default_rng(1)
    p = rng.uniform(-1, 1, (3, 4, 7)) * IIWA_POS
    v = rng.uniform(-0.5, 0.5, (3, 4, 7)) * IIWA_VEL
    a = np.zeros((3, 4, 7))
    lo, hi = jax.jit(lambda p, v, a: L.safe_acceleration_range(lim, p, v, a, 0.1))(p, v, a)
    lo2, hi2 = jax.vmap(jax.vmap(lambda p, v, a: L.safe_acceleration_range(lim, p, v, a, 0.1)))(p, v, a)
    assert lo.shape == (3, 4, 7)
    np.testing.assert_allclose(lo, lo2, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(hi, hi2, rtol=1e-6, atol=1e-6)
    assert np.all(np.asarray(lo) <= np.asarray(hi))


@pytest.mark.parametrize("kind,dt", [("iiwa", 0.1), ("random", 0.4)])
def test_skipping_the_search_far_from_the_limits_changes_only_rounding(kind, dt, monkeypatch):
    """The position search runs only on lanes where it can return less than ``hi`` (compacted
    across the batch); elsewhere a cheap test decides, with the same exact check. Against the
    search run on every lane (the previous code), on 6,000 states most of which are within
    reach of a position limit (positions drawn towards both ends, any velocity and
    acceleration): the violation flags are identical and the bounds differ in under 1 % of the
    joints, nearly all by float32 rounding (the search compiled for a chunk of lanes rounds a
    few results differently); a wrong skip would return ``hi`` where the search finds a
    lower bound, for every state near a limit. Covers joints without the simulated tail, with it (iiwa joint 1 at dt 0.1)
    and the stop to rest in narrow corridors (random limits at dt 0.4)."""
    limits = iiwa_limits(dt) if kind == "iiwa" else random_limits(dt, seed=DTS.index(dt))
    rng = np.random.default_rng(7)
    lo, hi = np.asarray(limits.pos_min), np.asarray(limits.pos_max)
    p = lo + (hi - lo) * rng.beta(0.3, 0.3, (6_000, 7))  # mass near both ends of the corridor
    v = rng.uniform(-1, 1, p.shape) * np.asarray(limits.vel) * (rng.uniform(size=p.shape) < 0.9)
    a = rng.uniform(-1, 1, p.shape) * np.asarray(limits.acc) * (rng.uniform(size=p.shape) < 0.9)
    fast = [np.asarray(x) for x in jax.jit(jax.vmap(  # per environment, as the env runs it
        lambda p, v, a: tuple(L.safe_acceleration_range_checked(limits, p, v, a, dt))))(p, v, a)]
    monkeypatch.setattr(L, "_position_upper_bound", L._position_search)
    full = [np.asarray(x) for x in jax.jit(  # a new function object: traced again with the patch
        lambda p, v, a: tuple(L.safe_acceleration_range_checked(limits, p, v, a, dt)))(p, v, a)]
    np.testing.assert_array_equal(fast[2], full[2])
    A = np.asarray(limits.acc)
    searched = 0
    for got, want in zip(fast[:2], full[:2]):
        differ = got != want
        assert differ.mean() < 0.01, f"{differ.mean():.4f} of the bounds differ"
        # (rare larger differences: a bisection or grid-stop check that rounding tips the
        # other way; measured 0.05 % at random limits, dt 0.4, all in one narrow-corridor joint)
        assert (np.abs(got - want) > 1e-3 * A).mean() < 1e-3
        searched += int(np.sum(np.abs(want) < A - 1e-3))  # bounds below the acceleration limit
    print(f"{searched} searched bounds")
    assert searched > 10_000  # the states do reach the limits: there is something to skip wrongly


def test_braking_acceleration_stops_the_robot():
    dt = 0.1
    lim = iiwa_limits(dt)
    rng = np.random.default_rng(2)
    p = jnp.asarray(rng.uniform(-0.5, 0.5, 7) * IIWA_POS, jnp.float32)
    v = jnp.asarray(rng.uniform(-0.9, 0.9, 7) * IIWA_VEL, jnp.float32)
    a = jnp.zeros(7)
    step = jax.jit(lambda p, v, a: (L.braking_acceleration(lim, p, v, a, dt), *L.safe_acceleration_range(lim, p, v, a, dt)))
    for _ in range(30):
        a1, lo, hi = step(p, v, a)
        assert np.all(np.asarray(a1) >= np.asarray(lo) - 1e-5) and np.all(np.asarray(a1) <= np.asarray(hi) + 1e-5)
        p, v, _ = L.integrate(p, v, a, a1, dt, dt)
        a = a1
    assert np.all(np.abs(np.asarray(v)) < 0.01) and np.all(np.abs(np.asarray(a)) < 0.01 * IIWA_ACC + 1e-3)


@pytest.mark.parametrize("jit", [True, False])
def test_braking_comes_to_rest_within_the_fastest_stop_and_stays_there(jit):
    """Batched random moving states (|v| < V, |a| < A, mid-range positions), jitted and eager:
    the braking accelerations bring every joint to rest within ``V/A + 2A/J`` (+2 grid steps),
    and a joint at rest is never kicked again. Regression: v = 0 with a = +4.8e-7 (what the last
    grid step of a stop leaves after rounding) got -A and moved on for two more steps."""
    dt = 0.1
    lim = iiwa_limits(dt)
    rng = np.random.default_rng(5)
    B = 256 if jit else 16  # (eager calls are slow)
    p = jnp.asarray(rng.uniform(-0.3, 0.3, (B, 7)) * IIWA_POS, jnp.float32)
    v = jnp.asarray(rng.uniform(-1.0, 1.0, (B, 7)) * IIWA_VEL, jnp.float32)
    a = jnp.asarray(rng.uniform(-1.0, 1.0, (B, 7)) * IIWA_ACC, jnp.float32)
    brake = lambda p, v, a: L.braking_acceleration(lim, p, v, a, dt)  # noqa: E731
    brake = jax.jit(brake) if jit else brake
    steps = int(np.ceil(np.max(IIWA_VEL / IIWA_ACC + 2 * IIWA_ACC / np.asarray(lim.jerk)) / dt)) + 2
    at_rest = np.zeros((B, 7), bool)
    for _ in range(steps + 3):
        a1 = brake(p, v, a)
        p, v, _ = L.integrate(p, v, a, a1, dt, dt)
        a = a1
        moving = (np.abs(np.asarray(v)) > 1e-4) | (np.abs(np.asarray(a)) > 1e-3)
        assert not np.any(at_rest & moving), "a joint at rest was set in motion again"
        at_rest |= ~moving
    assert at_rest.all()
    kicked = L.braking_acceleration(lim, jnp.zeros(7), jnp.zeros(7), jnp.full(7, 4.7683716e-07), dt)
    assert np.all(np.abs(np.asarray(kicked)) < 1e-5)


# --- oracle: klimits 1.1.3, the papers' own C library ----------------------------------------

@pytest.mark.parametrize("dt", [0.1, 0.05])
def test_agrees_with_klimits_on_random_rollout_states(dt):
    """>= 140,000 joint states visited by klimits-driven random-action rollouts (iiwa limits).

    Ours is never wider than klimits here; the rare narrower states are near a position limit at
    low speed, where klimits' profile family admits a stop whose grid acceleration is positive
    while ours (capped by the exact fastest-braking peak) does not.
    """
    import klimits  # the oracle is part of the test extra: fail loudly if it is missing
    jerk = 2 * IIWA_ACC / dt
    oracle = klimits.PosVelJerkLimitation(
        time_step=dt, pos_limits=np.stack([-IIWA_POS, IIWA_POS], 1), vel_limits=np.stack([-IIWA_VEL, IIWA_VEL], 1),
        acc_limits=np.stack([-IIWA_ACC, IIWA_ACC], 1), jerk_limits=np.stack([-jerk, jerk], 1),
        acceleration_after_max_vel_limit_factor=0.01, normalize_acc_range=False, num_threads=1)
    rng = np.random.default_rng(0)
    states, ranges = [], []
    for _ in range(200):
        p, v, a = rng.uniform(-0.8, 0.8, 7) * IIWA_POS, np.zeros(7), np.zeros(7)
        for _ in range(100):
            r, _ = oracle.calculate_valid_acceleration_range(current_pos=p, current_vel=v, current_acc=a)
            states.append((p, v, a))
            ranges.append(np.array(r))
            a1 = r[:, 0] + (rng.uniform(-1, 1, 7) + 1) / 2 * (r[:, 1] - r[:, 0])
            p, v, a = p + v * dt + (a / 3 + a1 / 6) * dt * dt, v + (a + a1) * dt / 2, a1
    s = np.array(states)
    ref = np.array(ranges)
    lim = iiwa_limits(dt)
    lo, hi = jax.jit(lambda p, v, a: L.safe_acceleration_range(lim, p, v, a, dt))(s[:, 0], s[:, 1], s[:, 2])
    d_lo, d_hi = np.asarray(lo) - ref[:, :, 0], np.asarray(hi) - ref[:, :, 1]
    tol = 1e-3 * IIWA_ACC
    agree = (np.abs(d_lo) <= tol) & (np.abs(d_hi) <= tol)
    wider = (d_hi > tol) | (d_lo < -tol)
    print(f"dt={dt}: {agree.size} joint states, agreement {agree.mean():.5f}, ours wider {wider.mean():.5f}, "
          f"ours narrower {(~agree & ~wider).mean():.5f}")
    assert agree.size >= 100_000
    assert agree.mean() >= 0.99


def test_range_near_the_limit_at_240_hz_does_not_collapse():
    """iiwa limits at 240 Hz; joint 2 is 1.24e-5 rad below its upper limit, nearly at rest,
    accelerating towards the limit (a state of episode 61 of the 240 Hz velocity-task
    evaluation). klimits 1.1.3 gives [-10, 0.128] for it; any a1 <= 0 stops in time."""
    from mjx_pathtrack.envs.tasks import velocity_max as V

    lim = V.VelocityMaxEnv(V.VelocityMaxConfig(hz=240)).limits
    p = [0.09301295876502991, -2.0593907833099365, 2.9320476055145264, -2.059393882751465, 2.9244682788848877,
         -2.0593745708465576, 0.4264836311340332]
    v = [-1.7099947929382324, 0.00020340150513220578, 9.870834219327662e-06, 6.359907274600118e-05,
         0.47656184434890747, -4.219885522616096e-05, 3.1407482624053955]
    a = [0.008859877474606037, -0.6657103896141052, 0.937206506729126, 8.74785327911377, -14.989075660705566,
         -6.577515602111816, -0.010976516641676426]
    lo, hi = (np.asarray(x) for x in L.safe_acceleration_range(lim, jnp.asarray(p), jnp.asarray(v), jnp.asarray(a),
                                                                 1.0 / 240.0))
    assert lo[2] < -9.0 and hi[2] > lo[2] + 5.0


# --- the velocity bound against a float64 reference of its own stop model --------------------

def _reference_velocity_peak(v0, a0, a1, dt, delta, settle):
    """Peak velocity [rad/s] of the settling stop of ``limits._velocity_upper_bound`` (float64):
    step 0 goes a0 -> a1, then the acceleration falls by ``delta`` per step, the step that would
    cross below ``-settle`` ends at ``-settle``, and the peak is where the acceleration crosses 0."""
    def segment(v, a_s, a_e):
        """(peak, end velocity) of one step with acceleration linear from a_s to a_e."""
        end = v + 0.5 * (a_s + a_e) * dt
        crossing = (a_s > 0) & (a_e < 0)
        t = np.where(crossing, a_s * dt / np.where(crossing, a_s - a_e, 1.0), 0.0)
        inside = np.where(crossing, v + 0.5 * a_s * t, -np.inf)
        return np.maximum.reduce([v, end, inside]), end

    peak, v = segment(v0, a0, a1)
    a = a1
    for _ in range(int(np.ceil(np.max(a1) / np.min(delta))) + 2):
        active = a > 0
        nxt = np.maximum(a - delta, -settle)
        seg_peak, v_next = segment(v, a, nxt)
        peak = np.where(active, np.maximum(peak, seg_peak), peak)
        v, a = np.where(active, v_next, v), np.where(active, nxt, a)
    return peak


@pytest.mark.parametrize("dt", DTS)
@pytest.mark.parametrize("kind", ["iiwa", "random"])
def test_velocity_bound_is_safe_and_tight_on_branch_boundaries(dt, kind):
    """``_velocity_upper_bound`` (float32) against a float64 reference of its stop model, on a
    grid of states plus states built so that the exact bound sits on (and 1e-6 around) the
    boundaries between its closed-form branches, where float32 rounding once rejected every
    candidate and the bound fell back to 0 (the 240 Hz [0, 0] range). Checked: the bound keeps
    the peak within the limit, and it is not lower than the exact bound (capped at A).
    ``random``: limits whose jerk binds (``random_limits``), a new draw per dt."""
    lim = iiwa_limits(dt) if kind == "iiwa" else random_limits(dt, seed=10 + DTS.index(dt))
    A, J = np.asarray(lim.acc, np.float64), np.asarray(lim.jerk, np.float64)
    V = np.asarray(lim.vel, np.float64) * (1.0 - L.MARGIN)
    delta = L.jerk_budget(J, A, dt)
    settle = L.SETTLE_FACTOR * A
    rng = np.random.default_rng(0)
    # grid: v0 in [-V, V], a0 in [-A, A]
    g = np.linspace(-1.0, 1.0, 41)
    gv, ga = (x.reshape(-1, 1) for x in np.meshgrid(g, g))
    v_grid, a_grid = gv * V, ga * A
    # boundaries: a1* = m delta + {0, delta - settle} (+- 1e-6 relative), v0 solved so the peak is V
    m = np.arange(0, 8, dtype=np.float64).reshape(-1, 1, 1)
    offsets = np.array([0.0, 1.0]).reshape(1, -1, 1)
    target = m * delta + offsets * (delta - settle)
    target = (target[..., None, :] * np.array([1 - 1e-6, 1.0, 1 + 1e-6]).reshape(1, 1, -1, 1)).reshape(-1, 7)
    target = target[:, None, :] + np.zeros((1, 8, 1))
    a0_b = rng.uniform(-1.0, 1.0, target.shape) * A
    a0_b = np.minimum(a0_b, target + delta)  # reachable under the jerk limit
    rise = _reference_velocity_peak(np.zeros_like(target), a0_b, target, dt, delta, settle)
    v_b = V - rise
    v0 = np.concatenate([v_grid, v_b.reshape(-1, 7)])
    a0 = np.concatenate([a_grid, a0_b.reshape(-1, 7)])
    keep = np.abs(v0) <= V
    bound = np.asarray(jax.jit(L._velocity_upper_bound, static_argnums=(3,))(
        jnp.asarray(v0, jnp.float32), jnp.asarray(a0, jnp.float32), jnp.asarray(V, jnp.float32), dt,
        jnp.asarray(A, jnp.float32), jnp.asarray(delta, jnp.float32), jnp.asarray(settle, jnp.float32)), np.float64)
    # exact bound in [0, A] by float64 bisection (the peak is increasing in a1)
    lo, hi = np.zeros_like(v0), np.broadcast_to(A, v0.shape).copy()
    ok_hi = _reference_velocity_peak(v0, a0, hi, dt, delta, settle) <= V
    ok_zero = _reference_velocity_peak(v0, a0, lo, dt, delta, settle) <= V
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        ok = _reference_velocity_peak(v0, a0, mid, dt, delta, settle) <= V
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    exact = np.where(ok_hi, A, lo)
    check = keep & ok_zero & np.isfinite(bound)
    assert check.sum() >= 0.5 * keep.sum()
    used = np.minimum(bound, A)
    peak = _reference_velocity_peak(v0, a0, used, dt, delta, settle)
    assert np.all(peak[check] <= np.broadcast_to(V, v0.shape)[check] * (1 + 4 * L.MARGIN))
    short = (exact - used)[check]
    scale = np.broadcast_to(delta + A, v0.shape)[check]
    assert np.all(short <= 1e-4 * scale), f"bound below the exact one by up to {np.max(short / scale):.3g} (delta + A)"
