"""Action priors (mjx_pathtrack.envs.action_prior): the hold prior read from an observation equals
the hold action of the state it observes, on the held joints only; a policy network with a prior
acts as the prior at a zero output and adds its own mean to it; bad priors are refused."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.deploy.networks import NetworkConfig, networks
from mjx_pathtrack.envs.action_prior import HOLD_OMEGA, HoldPrior
from mjx_pathtrack.envs.tracking import normalize_position

DT = 0.1


def _limits(n=5):
    pos = np.linspace(1.0, 2.0, n)
    pos_min = -pos
    pos_min[0] = -np.inf  # a continuous joint, not held
    pos_max = pos.copy()
    pos_max[0] = np.inf
    return L.JointLimits.from_acc(pos_min, pos_max, np.full(n, 1.5), np.full(n, 4.0), DT)


def _observation(lim, p, v, a, tail=7):
    """What PathTrackingEnv.observe puts first: position, velocity, acceleration; then other blocks."""
    rest = jnp.full(p.shape[:-1] + (tail,), 0.3)
    return jnp.concatenate([normalize_position(p, lim.pos_min, lim.pos_max), v / lim.vel, a / lim.acc, rest], -1)


def _states(lim, count, seed=0):
    """Random states inside the limits [count, n] (continuous joints around 0)."""
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(lim.pos_min), lim.pos_min, -3.0)
    hi = np.where(np.isfinite(lim.pos_max), lim.pos_max, 3.0)
    p = rng.uniform(lo, hi, (count, len(lo)))
    v = rng.uniform(-1, 1, p.shape) * np.asarray(lim.vel)
    a = rng.uniform(-1, 1, p.shape) * np.asarray(lim.acc)
    return (jnp.asarray(x, jnp.float32) for x in (p, v, a))


def test_hold_prior_reads_the_hold_action_of_the_observed_state_on_held_joints_only():
    lim = _limits()
    held = np.array([1, 3, 4])
    home = np.array([0.0, 0.2, -0.1, 0.5, 0.0], np.float32)
    prior = HoldPrior(lim, held, home, DT)
    p, v, a = _states(lim, 256)
    out = np.asarray(jax.jit(prior)(_observation(lim, p, v, a)))
    expected = np.asarray(L.hold_action(lim, p, v, a, DT, jnp.asarray(home), HOLD_OMEGA))
    assert out.shape == (256, 5)
    np.testing.assert_allclose(out[:, held], expected[:, held], atol=2e-4)
    assert np.all(out[:, [0, 2]] == 0.0)
    assert np.abs(out[:, held]).max() > 0.5  # the states are not all at rest: the check can fail
    # at rest at home the hold is to stay: the action of zero acceleration
    z = jnp.zeros((1, 5))
    a_min, a_max = L.safe_acceleration_range(lim, jnp.asarray(home)[None], z, z, DT)
    at_home = np.asarray(prior(_observation(lim, jnp.asarray(home)[None], z, z)))
    np.testing.assert_allclose(at_home[0, held], np.asarray(L.acceleration_to_action(0.0 * a_min, a_min, a_max))[0, held],
                               atol=1e-5)


def test_hold_prior_pulls_a_displaced_joint_back_and_brakes_a_moving_one():
    lim = _limits()
    home = np.zeros(5, np.float32)
    prior = HoldPrior(lim, [1, 2], home, DT)
    z = jnp.zeros((1, 5))
    displaced = z.at[0, 1].set(0.5).at[0, 2].set(-0.5)
    a_min, a_max = L.safe_acceleration_range(lim, displaced, z, z, DT)
    acc = L.action_to_acceleration(prior(_observation(lim, displaced, z, z)), a_min, a_max)
    assert float(acc[0, 1]) < -0.1 and float(acc[0, 2]) > 0.1
    moving = z.at[0, 1].set(0.8)
    a_min, a_max = L.safe_acceleration_range(lim, z, moving, z, DT)
    acc = L.action_to_acceleration(prior(_observation(lim, z, moving, z)), a_min, a_max)
    assert float(acc[0, 1]) < -0.1


def test_hold_prior_on_a_real_observation_matches_the_environments_hold_actions():
    """Read from ``PathTrackingEnv.observe`` (iiwa, kinematic), the prior gives the actions that
    hold the environment's joints at its ``home`` (``warm_start.hold_actions`` of the state)."""
    from path_fixtures import random_walk_paths

    from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
    from mjx_pathtrack.rl.warm_start import hold_actions
    from mjx_pathtrack.robots import iiwa

    env = PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(), 0.5, EnvConfig(),
                          home=np.linspace(-0.3, 0.3, 7))
    held = np.array([0, 2, 3, 6])
    prior = HoldPrior(env.limits, held, env.home, env.config.dt)
    track = jax.jit(env.reset)(jax.random.PRNGKey(0)).pipeline_state
    p, v, a = _states(env.limits, 32, seed=2)

    @jax.jit
    def both(p, v, a):
        moved = track._replace(p=p, v=v, a=a)
        return prior(env.observe(moved)), hold_actions(env, moved)

    out, expected = (np.asarray(x) for x in jax.vmap(both)(p, v, a))
    np.testing.assert_allclose(out[:, held], expected[:, held], atol=2e-4)
    assert np.all(out[:, [1, 4, 5]] == 0.0) and np.abs(out[:, held]).max() > 0.5


def test_bad_hold_priors_are_refused():
    lim = _limits()
    home = np.zeros(5, np.float32)
    with pytest.raises(ValueError, match="continuous joint"):
        HoldPrior(lim, [0, 1], home, DT)
    with pytest.raises(ValueError, match="distinct indices"):
        HoldPrior(lim, [1, 5], home, DT)
    with pytest.raises(ValueError, match="distinct indices"):
        HoldPrior(lim, [1, 1], home, DT)
    with pytest.raises(ValueError, match="distinct indices"):
        HoldPrior(lim, [], home, DT)
    with pytest.raises(ValueError, match="within the held joints' limits"):
        HoldPrior(lim, [1], home + 5.0, DT)
    with pytest.raises(ValueError, match="within the held joints' limits"):
        HoldPrior(lim, [1], home[:3], DT)
    with pytest.raises(ValueError, match="must be > 0"):
        HoldPrior(lim, [1], home, 0.0)
    with pytest.raises(ValueError, match="must be > 0"):
        HoldPrior(lim, [1], home, DT, omega=float("nan"))


@pytest.mark.parametrize("privileged", [True, False])
def test_a_network_with_a_prior_acts_as_the_prior_plus_its_mean(privileged):
    """The deterministic action is the network's mean plus the prior; with the mean head zeroed
    (a warm start's new joints) it is the prior's action exactly; sampling is around it. The
    privileged critic's extra inputs at the end of the observation do not reach the prior."""
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks as ppo_nets

    lim = _limits()
    prior = HoldPrior(lim, [1, 3], np.zeros(5, np.float32), DT)
    config = NetworkConfig(policy_layers=(16,), value_layers=(16,), privileged_critic=privileged, init_noise_std=0.1)
    obs_size = 3 * 5 + 7
    plain = networks(config)(obs_size, 5, preprocess_observations_fn=running_statistics.normalize)
    with_prior = networks(config, prior)(obs_size, 5, preprocess_observations_fn=running_statistics.normalize)
    params = with_prior.policy_network.init(jax.random.PRNGKey(0))
    extra = 4 if privileged else 0  # the critic features (training only)
    stats = running_statistics.init_state(jax.ShapeDtypeStruct((obs_size + extra,), jnp.float32))
    p, v, a = _states(lim, 64, seed=1)
    obs = _observation(lim, p, v, a)
    obs_extended = jnp.concatenate([obs, jnp.ones(obs.shape[:-1] + (extra,))], -1)
    mean_plain = plain.policy_network.apply(stats, params, obs_extended)[0]
    mean = with_prior.policy_network.apply(stats, params, obs_extended)[0]
    np.testing.assert_allclose(np.asarray(mean), np.asarray(mean_plain + prior(obs)), atol=1e-6)
    assert np.abs(np.asarray(prior(obs))).max() > 0.1

    head = params["params"]["Dense_0"]
    zeroed = jax.tree.map(lambda x: x, params)
    zeroed["params"]["Dense_0"] = jax.tree.map(jnp.zeros_like, head)
    act = ppo_nets.make_inference_fn(with_prior)((stats, zeroed), deterministic=True)(obs, None)[0]
    np.testing.assert_allclose(np.asarray(act), np.asarray(prior(obs)), atol=1e-6)
    sampled = ppo_nets.make_inference_fn(with_prior)((stats, zeroed))(obs, jax.random.PRNGKey(1))[0]
    spread = np.asarray(sampled - prior(obs))
    assert 0.05 < spread.std() < 0.2  # noise std 0.1 around the prior


def test_the_hold_prior_exports_for_any_batch_size():
    """The export serializes the policy for a symbolic batch size; the safe range's search runs
    on every lane there (its compaction needs a static size) and gives the same actions."""
    lim = _limits()
    prior = HoldPrior(lim, [1, 2, 4], np.zeros(5, np.float32), DT)
    batch = jax.export.symbolic_shape("batch")[0]
    exported = jax.export.export(jax.jit(prior))(jax.ShapeDtypeStruct((batch, 3 * 5 + 7), jnp.float32))
    restored = jax.export.deserialize(exported.serialize())
    for count in (1, 300):
        obs = _observation(lim, *_states(lim, count, seed=count))
        np.testing.assert_allclose(np.asarray(restored.call(obs)), np.asarray(jax.jit(prior)(obs)), atol=1e-6)
