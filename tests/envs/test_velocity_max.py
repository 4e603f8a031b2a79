"""Velocity-maximisation task (paper 001): sizes, the exact |v| integral, the searched optimal
policy (never violates, beats random) and the limit audit of the safe and penalty modes."""

import functools

import numpy as np
import pytest

from mjx_pathtrack.envs.tasks import velocity_max as V  # first: the package sets the XLA flags before JAX starts
from mjx_pathtrack.rl import velocity_max_train as T

import jax
import jax.numpy as jnp

EPISODES = 4
TOL = 1e-5


def adversarial_policy(n):
    """Push every joint towards its nearer position limit (at the centre: upwards)."""
    return lambda obs, key: jnp.where(obs[..., :n] >= 0.0, 1.0, -1.0)


@functools.lru_cache(maxsize=None)
def safe_rollouts(hz):
    """One compiled rollout per frequency (shared by the tests): the optimal search (two family
    members) together with random, adversarial and constant +1 actions, in safe mode."""
    env = V.VelocityMaxEnv(V.VelocityMaxConfig(hz=hz))
    n = env.action_size
    steps = env.config.episode_steps

    def alternating(obs, key):  # flips every ~0.2 s, from the elapsed-time observation
        k = jnp.floor((obs[..., -1:] + 1.0) * 0.5 * steps / max(1, round(0.2 * hz)))
        return jnp.where(k % 2 == 0, 1.0, -1.0) * jnp.ones(obs.shape[:-1] + (n,))

    others = {"random": V.random_policy(n), "adversarial": adversarial_policy(n),
              "plus": lambda obs, key: jnp.ones(obs.shape[:-1] + (n,)), "alternating": alternating}
    value, info = V.optimal_average_velocity(env, EPISODES, jax.random.PRNGKey(3), others, factors=(None, 1.4))
    return value, info


def test_sizes_and_reset():
    env = V.VelocityMaxEnv(V.VelocityMaxConfig(hz=10, mode="penalty_soft"))
    assert env.observation_size == 3 * 7 + 1 and env.action_size == 7
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert state.obs.shape == (22,) and bool(jnp.all(jnp.isfinite(state.obs)))
    # at rest, at time 0, inside the middle half of each range
    assert bool(jnp.all(state.obs[7:21] == 0.0)) and float(state.obs[-1]) == -1.0
    assert bool(jnp.all(jnp.abs(state.obs[:7]) <= 0.5))
    nxt = jax.jit(env.step)(state, jnp.ones(7))
    assert nxt.obs.shape == (22,) and set(nxt.metrics) == set(V.METRICS)
    assert int(nxt.pipeline_state.steps) == 1 and float(nxt.done) == 0.0
    assert V.VelocityMaxConfig(hz=240).episode_steps == 1200 and V.VelocityMaxConfig(hz=10).episode_steps == 50


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="unknown mode"):
        V.VelocityMaxConfig(mode="penalty")
    with pytest.raises(ValueError, match="hz"):
        V.VelocityMaxConfig(hz=0)
    with pytest.raises(ValueError, match="init_spread"):
        V.VelocityMaxConfig(init_spread=1.0)
    with pytest.raises(ValueError, match="start"):
        V.reversal_action(jnp.zeros(22), V.VelocityMaxEnv().limits, None, start="middle")


def test_mean_abs_velocity_is_the_exact_integral():
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    shape = (64, 7)
    v = jax.random.uniform(keys[0], shape, minval=-2.0, maxval=2.0)
    a0 = jax.random.uniform(keys[1], shape, minval=-20.0, maxval=20.0)
    a1 = jax.random.uniform(keys[2], shape, minval=-20.0, maxval=20.0)
    a1 = a1.at[:8].set(a0[:8])  # constant acceleration (zero jerk)
    a0, a1 = a0.at[8:12].set(0.0), a1.at[8:12].set(0.0)  # constant velocity
    dt = 0.1
    exact = np.asarray(V.mean_abs_velocity(jnp.zeros(shape), v, a0, a1, dt))
    t = np.linspace(0.0, dt, 2001)[:, None, None]
    vv = np.asarray(v) + np.asarray(a0) * t + 0.5 * (np.asarray(a1) - np.asarray(a0)) / dt * t ** 2
    dense = np.trapezoid(np.abs(vv), dx=dt / 2000, axis=0) / dt
    np.testing.assert_allclose(exact, dense, atol=1e-4)
    np.testing.assert_allclose(exact[8:12], np.abs(np.asarray(v[8:12])), rtol=1e-6)
    # v = a t from rest: mean |v| = |a| dt / 2
    m = V.mean_abs_velocity(jnp.zeros(1), jnp.zeros(1), jnp.full(1, -4.0), jnp.full(1, -4.0), dt)
    np.testing.assert_allclose(np.asarray(m), [0.2], rtol=1e-6)


@pytest.mark.parametrize("hz", V.FREQUENCIES)
def test_optimal_policy_never_violates_and_beats_random(hz):
    value, info = safe_rollouts(hz)
    assert info["violation_rate"] == 0.0
    assert info["max_position"] <= 1.0 + TOL and info["max_velocity"] <= 1.0 + TOL
    # it oscillates between the position limits at the velocity limit
    assert info["max_position"] > 0.99 and info["max_velocity"] > 0.99
    assert value > 0.85 and value > info["random"]["avg_velocity"] + 0.3
    # the per-joint best member is at least as good as each member
    assert value >= max(info["family"].values()) - 1e-6
    assert abs(sum(info["best_factor_share"].values()) - 1.0) < 1e-6


@pytest.mark.parametrize("hz", V.FREQUENCIES)
def test_safe_mode_never_violates(hz):
    _, info = safe_rollouts(hz)
    for name in ("random", "adversarial", "plus", "alternating"):
        m = info[name]
        assert m["violation_rate"] == 0.0, (name, m)
        assert m["max_position"] <= 1.0 + TOL and m["max_velocity"] <= 1.0 + TOL, (name, m)
    # the adversarial policy does drive the joints to their position limits
    assert info["adversarial"]["max_position"] > 0.99


@pytest.mark.parametrize("mode", ["penalty_soft", "penalty_hard"])
def test_penalty_modes_record_violations(mode):
    env = V.VelocityMaxEnv(V.VelocityMaxConfig(hz=20, mode=mode))
    n = env.action_size
    policies = {"adversarial": adversarial_policy(n), "zero": lambda obs, key: jnp.zeros(obs.shape[:-1] + (n,))}
    m = V.evaluate_many(env, policies, EPISODES, jax.random.PRNGKey(0))
    adv = m["adversarial"]
    assert adv["violation_rate"] == 1.0 and adv["violation_rate/position"] == 1.0
    assert adv["violation_rate/velocity"] == 1.0 and adv["max_position"] > 1.0 and adv["max_velocity"] > 1.0
    # actions map to +-a_max with jerk clipping only: acceleration and jerk stay within limits
    assert adv["violation_rate/acceleration"] == 0.0 and adv["violation_rate/jerk"] == 0.0
    # the penalties lower the return below the (unpenalised) velocity reward
    assert adv["return"] < adv["avg_velocity"] * env.config.episode_steps - 1.0
    assert m["zero"]["violation_rate"] == 0.0 and m["zero"]["avg_velocity"] == 0.0


def test_hard_penalty_terminates_when_asked():
    env = V.VelocityMaxEnv(V.VelocityMaxConfig(hz=20, mode="penalty_hard", hard_terminate=True))
    state = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    for t in range(env.config.episode_steps):
        state = step(state, jnp.where(state.obs[:7] >= 0.0, 1.0, -1.0))
        if float(state.done):
            break
    assert float(state.metrics["violation"]) == 1.0 and float(state.reward) == 0.0
    assert t < env.config.episode_steps - 1


def test_audit_flags_each_limit_kind():
    lim = V.VelocityMaxEnv().limits
    z = jnp.zeros(7)
    ok = V.audit_step(lim, z, z, z, z, 0.1)
    assert not bool(ok.any) and float(ok.max_position) == 0.0
    over_p = V.audit_step(lim, lim.pos_max * 0.999, lim.vel * 0.5, z, z, 0.1)
    assert bool(over_p.position) and not bool(over_p.velocity)
    over_a = V.audit_step(lim, z, z, z, lim.acc * 1.01, 0.1)
    assert bool(over_a.acceleration) and not bool(over_a.jerk)
    # limits of the default 20 Hz env: jerk 2 a_max / 0.05 s; -0.6 -> 0.6 a_max in 0.01 s is 3x that
    over_j = V.audit_step(lim, z, z, -0.6 * lim.acc, 0.6 * lim.acc, 0.01)
    assert bool(over_j.jerk) and not bool(over_j.acceleration)


def test_train_config_and_cli_parsing():
    args, config = T.parse_train_args(["--hz", "240", "--mode", "penalty_hard", "--num-timesteps", "1000",
                                       "--policy-layers", "32", "32"])
    assert config.hz == 240 and config.mode == "penalty_hard" and config.network.policy_layers == (32, 32)
    assert abs(config.discounting - (1.0 - 1.0 / 240.0)) < 1e-12
    assert config.env_config().episode_steps == 1200
    assert config.network.mean_clip == 1.0  # bounded policy mean by default
    assert T.parse_train_args(["--mean-clip", "none"])[1].network.mean_clip is None
    assert T.parse_train_args(["--mean-clip", "2.5"])[1].network.mean_clip == 2.5
    with pytest.raises(SystemExit):
        T.parse_train_args(["--mean-clip", "wide"])
    with pytest.raises(SystemExit):
        T.parse_train_args(["--mode", "unsafe"])
    with pytest.raises(ValueError, match="hz"):
        T.parse_train_args(["--hz", "-5"])
