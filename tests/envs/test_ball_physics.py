"""The cheap ball executors against the full-arm MJX scene (the reference): the same random safe
motions of 2 s and the same balls give the same ball trajectories and the same falls.

Motions: 200 episodes of the ball task's test paths; per episode one scale ``c`` drawn
log-uniformly in [1e-3, 0.3], actions ``c * U(-1, 1)`` per joint and step (mapped into the safe
range like any action): from a plate held nearly still to one tilted until the ball falls.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack.envs.tasks import ball_on_plate as BP

EPISODES = 200
STEPS = 20  # 2 s at dt 0.1


@pytest.fixture(scope="module")
def rollouts():
    """Per physics: ball centre ``[STEPS, EPISODES, 3]`` (plate frame), executed joints and
    off-plate flags, for the same resets (same balls) and actions."""
    env_cfg = BP.env_config(terminate_deviation=None)
    ball = BP.BallConfig(terminate=False)  # keep simulating after a fall: compare the outcome at 2 s
    keys = jax.random.split(jax.random.PRNGKey(0), EPISODES)
    k_scale, k_act = jax.random.split(jax.random.PRNGKey(1))
    scale = jnp.exp(jax.random.uniform(k_scale, (1, EPISODES, 1), minval=np.log(1e-3), maxval=np.log(0.3)))
    actions = scale * jax.random.uniform(k_act, (STEPS, EPISODES, 7), minval=-1, maxval=1)
    out = {}
    for physics in ("arm", "rolling"):
        env = BP.make_env("test", env_cfg, ball, physics=physics)

        def body(s, a, env=env):
            s = jax.vmap(env.step)(s, a)
            ex = s.pipeline_state.executor
            return s, (ex.ball, ex.q, jax.vmap(env.off_plate)(ex.ball))

        run = jax.jit(lambda k, a, env=env, body=body: jax.lax.scan(body, jax.vmap(env.reset)(k), a)[1])
        out[physics] = [np.asarray(x) for x in run(keys, actions)]
    return out


def test_the_prescribed_plate_follows_the_arm(rollouts):
    # the rolling executor's joints are the setpoints; the reference's servos follow them within 1e-3 rad
    assert np.abs(rollouts["arm"][1] - rollouts["rolling"][1]).max() < 1e-3


def test_ball_trajectories_agree_while_on_the_plate(rollouts):
    (ball_a, _, off_a), (ball_r, _, off_r) = rollouts["arm"], rollouts["rolling"]
    on = ~(np.logical_or.accumulate(off_a, axis=0) | np.logical_or.accumulate(off_r, axis=0))
    assert on.mean() > 0.3  # enough of the motions keep the ball on the plate to compare
    moved = np.linalg.norm(ball_a[-1] - ball_a[0], axis=-1)[on[-1]]
    assert np.median(moved) > 5e-3  # ... and move it: a still ball would agree trivially
    diff = np.linalg.norm(ball_a - ball_r, axis=-1)[on]
    assert diff.mean() < 2e-3, f"mean position difference {1e3 * diff.mean():.2f} mm"


def test_same_fall_outcome(rollouts):
    fell_a, fell_r = rollouts["arm"][2].any(axis=0), rollouts["rolling"][2].any(axis=0)
    assert 0.1 < fell_a.mean() < 0.9  # both outcomes occur
    assert (fell_a == fell_r).mean() >= 0.95
