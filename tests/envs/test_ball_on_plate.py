"""Ball-on-plate task (MJX): a still robot keeps the ball for the whole episode, tilting the plate
drops it and ends the episode; observation sizes of docs/method.md §4; the train.py preset.

One jitted rollout of two environments (batch 2) covers the physics tests."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack.deploy.export import observation_layout

from mjx_pathtrack.envs.tasks import ball_on_plate as BP
from mjx_pathtrack.robots.ball_scene import PLATE_SIZE


@pytest.fixture(scope="module")
def env():
    # deviation termination off: the tilting policy leaves the path on purpose
    return BP.make_env("test", BP.env_config(terminate_deviation=None))


@pytest.fixture(scope="module")
def rollout(env):
    steps = env.config.max_episode_steps()
    actions = np.zeros((steps, 2, 7), np.float32)
    actions[:, 1, 5] = 1.0  # joint 6 (axis y) accelerates as fast as allowed: the plate tilts

    @jax.jit
    def run(keys, indices, actions):
        state = jax.vmap(env.reset)(keys, indices)

        def body(s, a):
            n = jax.vmap(env.step)(s, a)
            return n, (n.done, n.metrics["ball_fell"], n.pipeline_state.executor.ball, n.reward)

        return state, jax.lax.scan(body, state, actions)[1]

    state, out = run(jax.random.split(jax.random.PRNGKey(0), 2), jnp.array([0, 1]), jnp.asarray(actions))
    return jax.tree.map(np.asarray, state), tuple(np.asarray(x) for x in out)


def test_still_robot_keeps_the_ball_for_the_whole_episode(env, rollout):
    state, (done, fell, ball, reward) = rollout
    assert env.config.max_episode_steps() == 61  # 6 s at 0.1 s
    assert not fell[:, 0].any()
    assert np.flatnonzero(done[:, 0])[0] == int(state.pipeline_state.max_steps[0]) - 1 == 59  # time budget
    # servo sag under gravity leaves the plate ~1e-4 rad off level: the ball creeps by < 3 cm in 6 s
    start = state.pipeline_state.executor.ball[0, :2]
    assert np.linalg.norm(ball[:, 0, :2] - start, axis=-1).max() < 0.03
    assert np.all(np.isfinite(reward[:, 0]))


def test_tilting_the_plate_drops_the_ball_and_ends_the_episode(rollout):
    state, (done, fell, ball, _) = rollout
    first_fell = np.flatnonzero(fell[:, 1])
    assert first_fell.size and first_fell[0] < 30
    assert np.flatnonzero(done[:, 1])[0] == first_fell[0]  # terminated in the step the ball left
    # the flag is the physics (not only the normalised range it is defined by): the ball has left
    # across the plate's real edge, along x, the direction joint 6 tilts it (measured 0.26 m, edge 0.17 m)
    assert abs(ball[first_fell[0], 1, 0]) > PLATE_SIZE[0] / 2
    # the random ball starts at rest on the plate, inside the papers' start range
    start = state.pipeline_state.executor.ball
    assert np.all(np.abs(start[:, :2]) <= np.asarray([0.0797, 0.0458]) + 1e-6)


def test_observation_sizes(env, rollout):
    state, _ = rollout
    assert env.observation_size == 72 and state.obs.shape == (2, 72)
    assert np.all(np.abs(state.obs) <= 1.0)
    blind = BP.BallOnPlateEnv(env.limits, env.paths, env.max_dis, env.config, env.executor,
                              BP.BallConfig(reward=0.0, sensor=False), home=env.home)
    assert blind.observation_size == 68
    assert jax.eval_shape(blind.reset, jax.random.PRNGKey(0)).obs.shape == (68,)
    # the exported manifest names every block, sensors last
    for e, size in ((env, 72), (blind, 68)):
        layout = observation_layout(7, 7, e.config.n_next, e.extra_observation_blocks())
        assert sum(b["size"] for b in layout) == size and layout[-1]["start"] + layout[-1]["size"] == size
    assert [b for b, _ in env.extra_observation_blocks()][-1] == "ball_xy" and env.task_name == "ball_on_plate"


def test_train_preset():
    import train

    _, config = train.parse_args(["--task", "ball_on_plate", "--no-ball-reward", "--num-envs", "8"])
    assert (config.task, config.robot, config.dataset, config.executor) == ("ball_on_plate", "iiwa", "ball_balancing",
                                                                            "mjx")
    assert (config.env.n_next, config.env.reward.distance, config.env.reward.action, config.env.duration) == (4, 4.0, 0.0, 6.0)
    assert config.ball_on_plate.reward == 0.0 and config.ppo.num_envs == 8
    _, config = train.parse_args(["--task", "ball_on_plate"])
    # the preset's weights (docs/results.md "Ball on plate"): R_ball 2, both deviation weights 2, R_jerk 1
    assert config.ball_on_plate.reward == 2.0 and config.env.reward.jerk == 1.0
    assert (config.env.reward.max_deviation, config.env.reward.mean_deviation) == (2.0, 2.0)
    assert config.ball_on_plate.cartesian_reward == 0.0  # R_cart opt-in
    _, config = train.parse_args(["--task", "ball_on_plate", "--cartesian-reward", "2.5"])
    assert config.ball_on_plate.cartesian_reward == 2.5
    from mjx_pathtrack.config.run import ConfigError, validate_config

    with pytest.raises(ConfigError, match="--cartesian-reward"):
        validate_config(train.parse_args(["--task", "ball_on_plate", "--cartesian-reward", "-1"])[1])


def test_cartesian_reward_is_the_target_points_deviation_at_equal_arc():
    """R_cart (opt-in): weight * (1 - min(1, |reference point - executed point| / 0.1 m))**2 at every
    step of a batched, jitted rollout that leaves the path; the same rollout without it differs in
    the reward by exactly that term and in nothing else."""
    from mjx_pathtrack.core.reward import CARTESIAN_THRESHOLD

    cfg = BP.env_config(terminate_deviation=None)
    base = BP.make_env("test", cfg, physics="rolling")
    weight = 3.0
    cart = BP.BallOnPlateEnv(base.limits, base.paths, base.max_dis, cfg, base.executor,
                             BP.BallConfig(cartesian=weight), home=base.home)
    actions = np.zeros((8, 2, 7), np.float32)
    actions[:, :, 0] = [1.0, -1.0]  # joint 1 swings the target point off the path, both ways

    def rollout(env):
        @jax.jit
        def run(keys, actions):
            state = jax.vmap(env.reset)(keys, jnp.array([0, 1]))

            def body(s, a):
                n = jax.vmap(env.step)(s, a)
                return n, (n.reward, n.metrics["reward/cartesian"], n.pipeline_state.executor.relative, n.obs)

            return jax.lax.scan(body, state, actions)[1]

        return [np.asarray(x) for x in run(jax.random.split(jax.random.PRNGKey(3), 2), jnp.asarray(actions))]

    r0, c0, rel0, obs0 = rollout(base)
    r1, c1, rel1, obs1 = rollout(cart)
    assert np.all(c0 == 0.0)
    np.testing.assert_array_equal(rel0, rel1)
    np.testing.assert_array_equal(obs0, obs1)
    dist = np.linalg.norm(rel1, axis=-1)
    expected = weight * np.square(1.0 - np.clip(dist / CARTESIAN_THRESHOLD, 0.0, 1.0))
    np.testing.assert_allclose(c1, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r1 - r0, c1, rtol=1e-5, atol=1e-5)
    # the swing takes the point centimetres off the path: the term is neither 0 nor its maximum
    assert dist.max() > 0.02 and np.any((c1 > 0.05) & (c1 < 0.95 * weight))


def test_cartesian_reward_bad_settings_are_refused():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="BallConfig.cartesian"):
            BP.BallConfig(cartesian=bad)


def test_cartesian_reward_is_an_ordinary_term_of_the_stop_reward():
    """With ``terminate_on_stop`` a robot at rest while braking stops the episode and the step's
    reward counts for every remaining step: R_cart is multiplied with the other terms, and the
    ball task's transition takes the online tracker's ``fastest_stop``."""
    cfg = BP.env_config(terminate_deviation=None, terminate_on_stop=True, brake_at_end=True)
    base = BP.make_env("test", cfg, physics="rolling")
    env = BP.BallOnPlateEnv(base.limits, base.paths, base.max_dis, cfg, base.executor,
                            BP.BallConfig(cartesian=2.0), home=base.home)

    @jax.jit
    def stop(key):
        track = env.reset(key, jnp.asarray(0)).pipeline_state._replace(braking=jnp.asarray(True))
        return env.transition(track, jnp.zeros(7), fastest_stop=True)

    new, reward, done, metrics = stop(jax.random.PRNGKey(0))
    terms = sum(float(v) for k, v in metrics.items() if k.startswith("reward/"))
    remaining = int(new.max_steps) + 1 - int(new.steps)
    assert bool(done) and remaining > 1
    assert 0.0 < float(metrics["reward/cartesian"]) <= 2.0
    np.testing.assert_allclose(float(reward), terms * remaining, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["reward"]), float(reward), rtol=1e-6)
