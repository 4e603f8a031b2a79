"""Reward terms against the published example values (docs/method.md §2) and their invariants."""

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.core import reward as R


@pytest.mark.parametrize("ratio, expected", [(0.25, 0.4375), (0.5, 0.75), (0.75, 0.9375), (0.9, 0.99),
                                             (1.0, 1.0), (1.5, 0.87), (3.0, 0.534)])
def test_distance_reward_matches_reference_table(ratio, expected):
    # docs/method.md §2.2 table: L_over = 7.43, l_State = 1
    value = float(R.distance_reward(jnp.float32(ratio), jnp.float32(1.0), 7.43))
    assert value == pytest.approx(expected, abs=6e-4)


def test_distance_reward_shape_and_finished_path():
    l = jnp.linspace(0.0, 20.0, 401)
    r = R.distance_reward(l, 2.0, 7.43)
    assert float(r.min()) >= 0.0 and float(r.max()) <= 1.0
    peak = int(jnp.argmax(r))
    assert float(l[peak]) == pytest.approx(2.0, abs=0.05)
    assert bool(jnp.all(jnp.diff(r[: peak + 1]) >= 0)) and bool(jnp.all(jnp.diff(r[peak:]) <= 0))
    # finished path (l_State = 0): standing still is best, overshooting is penalised
    assert float(R.distance_reward(0.0, 0.0, 7.43)) == 1.0
    assert float(R.distance_reward(7.43, 0.0, 7.43)) == 0.0


@pytest.mark.parametrize("d, expected", [(0.0, 1.0), (0.05, 0.64), (0.1, 0.36), (0.125, 0.25), (0.25, 0.0), (1.0, 0.0)])
def test_deviation_reward_reference_values(d, expected):
    assert float(R.deviation_reward(jnp.float32(d))) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("d, expected", [(0.0, 1.0), (0.02, 0.64), (0.05, 0.25), (0.1, 0.0), (0.3, 0.0), (-0.01, 1.0)])
def test_cartesian_deviation_reward_levels(d, expected):
    # (1 - min(1, d / 0.1 m))**2: the levels pin the default threshold to the papers' 0.1 m
    assert float(R.cartesian_deviation_reward(jnp.float32(d))) == pytest.approx(expected, abs=1e-6)


def test_weighted_deviation_normalizer_iiwa():
    w = jnp.array([1, 1, 1, 0.9, 0.8, 0.7, 0.6])
    assert float(R.deviation_normalizer(w)) == pytest.approx(1.1492, abs=1e-4)
    # weighted norm of a uniform error, scaled by the normaliser
    diff = jnp.full((7,), 0.1)
    expected = float(jnp.linalg.norm(diff * w) * R.deviation_normalizer(w))
    assert float(R.weighted_deviation(diff, jnp.zeros(7), w)) == pytest.approx(expected, rel=1e-6)
    assert float(R.weighted_deviation(diff, jnp.zeros(7))) == pytest.approx(0.1 * np.sqrt(7), rel=1e-6)


def test_action_reward():
    close = jnp.array(False)
    assert float(R.action_reward(jnp.array([0.5, -0.9]), close)) == 0.0
    assert float(R.action_reward(jnp.array([0.2, -1.0]), close)) == pytest.approx(1.0)
    assert float(R.action_reward(jnp.array([0.95, 0.0]), close)) == pytest.approx(0.75, abs=1e-5)
    assert float(R.action_reward(jnp.zeros(2), jnp.array(True))) == 1.0


def test_ball_reward_symmetric_and_zero_off_plate():
    centre = R.ball_reward(jnp.zeros(2))
    assert float(centre) == 1.0  # (1/0.94)**2 clipped to 1
    dx = 0.5 * R.BALL_HALF_RANGE[0]
    assert float(R.ball_reward(jnp.array([dx, 0.0]))) == pytest.approx(float(R.ball_reward(jnp.array([-dx, 0.0]))))
    assert float(R.ball_reward(jnp.array([dx, 0.0]))) == pytest.approx((0.5 / 0.94) ** 2, rel=1e-5)
    assert float(R.ball_reward(jnp.array([0.0, 0.2]))) == 0.0


def test_jerk_reward_levels():
    # (1 - mean ratio)**2: 1 for a step that keeps every acceleration, 0 for a change at the jerk limit on every joint
    assert float(R.jerk_reward(jnp.zeros(7))) == 1.0
    assert float(R.jerk_reward(jnp.ones(7))) == 0.0
    assert float(R.jerk_reward(jnp.array([1.0, 0.0, 0.5, 0.5]))) == pytest.approx(0.25)
    w = R.RewardWeights(jerk=2.0)
    terms = R.tracking_terms(w, 0.3, 0.5, 7.4, 0.1, 0.05, jnp.zeros(4), False, jnp.full((4,), 0.5))
    assert float(terms["jerk"]) == pytest.approx(0.5)
    # without ratios (or with the papers' weight 0) the term is 0
    assert float(R.tracking_terms(w, 0.3, 0.5, 7.4, 0.1, 0.05, jnp.zeros(4), False)["jerk"]) == 0.0
    assert float(R.tracking_terms(R.RewardWeights(), 0.3, 0.5, 7.4, 0.1, 0.05, jnp.zeros(4), False,
                                  jnp.zeros(4))["jerk"]) == 0.0  # R_jerk is 1 here: only the weight makes it 0


def test_balance_terms_levels():
    w = R.RewardWeights(base_pos=0.2, base_orn=0.2, tilt=2.0, end_point=0.2)
    upright = R.balance_terms(w, jnp.zeros(3), jnp.array([1.0, 0, 0, 0]), jnp.array([0, 0, 1.0]), jnp.float32(0.0))
    assert {k: float(v) for k, v in upright.items()} == pytest.approx({"base_pos": 0.2, "base_orn": 0.2,
                                                                       "tilt": 2.0, "end_point": 0.2})
    angle = 0.0625  # half the tilt scale -> quarter of the weight
    tilted = R.balance_terms(w, jnp.zeros(3), jnp.array([1.0, 0, 0, 0]),
                             jnp.array([np.sin(angle), 0, np.cos(angle)]), jnp.float32(0.0))
    assert float(tilted["tilt"]) == pytest.approx(2.0 * 0.25, rel=1e-4)


def test_terms_are_jittable_and_vmappable():
    w = R.RewardWeights()
    f = jax.jit(jax.vmap(lambda l, d, a: sum(R.tracking_terms(w, l, 1.0, 7.43, d, d, a, False).values())))
    out = f(jnp.linspace(0, 2, 8), jnp.linspace(0, 0.3, 8), jnp.ones((8, 7)) * 0.95)
    assert out.shape == (8,) and bool(jnp.all(jnp.isfinite(out)))
    assert float(out[0]) == pytest.approx(0.0 + 0.9 + 0.9 + 0.4 * 0.75, abs=1e-5)
