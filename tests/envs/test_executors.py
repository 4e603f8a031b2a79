"""Kinematic and MJX executors give nearly the same motion for the iiwa."""

import numpy as np

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.envs.executors import KinematicExecutor, MjxExecutor, setpoints
from path_fixtures import random_walk_paths


def test_setpoints_start_at_the_state_and_end_at_the_integrated_step():
    p, v, a0, a1 = jnp.array([0.1]), jnp.array([0.5]), jnp.array([1.0]), jnp.array([-2.0])
    q, v_mid = setpoints(p, v, a0, a1, 0.1, 24)
    assert q.shape == (25, 1) and v_mid.shape == (24, 1)
    assert float(q[0, 0]) == float(np.float32(0.1))
    expected_end = 0.1 + 0.5 * 0.1 + 1.0 * 0.01 / 3 + (-2.0) * 0.01 / 6
    np.testing.assert_allclose(float(q[-1, 0]), expected_end, rtol=1e-6)


def test_mjx_and_kinematic_executors_track_the_same_path():
    robot = robots.load_robot("iiwa")
    cfg = EnvConfig(terminate_deviation=None)
    paths = random_walk_paths(n_paths=2)
    envs = {name: PathTrackingEnv(robot.limits, paths, 0.5, cfg, executor=ex)
            for name, ex in (("kinematic", KinematicExecutor(24)), ("mjx", MjxExecutor(robot)))}
    batch, steps = 4, 12
    actions = jax.random.uniform(jax.random.PRNGKey(0), (steps, batch, 7), minval=-1, maxval=1)
    out = {}
    for name, env in envs.items():
        keys = jax.random.split(jax.random.PRNGKey(1), batch)

        @jax.jit
        def rollout(keys, actions, env=env):
            state = jax.vmap(env.reset)(keys)

            def body(state, action):
                state = jax.vmap(env.step)(state, action)
                return state, (state.metrics["length"], state.metrics["d_max"])

            return jax.lax.scan(body, state, actions)

        state, (length, d_max) = rollout(keys, actions)
        out[name] = (np.asarray(state.pipeline_state.s), np.asarray(length), np.asarray(d_max))
    s_k, len_k, d_k = out["kinematic"]
    s_m, len_m, d_m = out["mjx"]
    assert len_k.sum() > 1.0  # the robots really moved
    np.testing.assert_allclose(len_m, len_k, atol=2e-3)
    np.testing.assert_allclose(s_m, s_k, atol=1e-2)
    np.testing.assert_allclose(d_m, d_k, atol=2e-3)
