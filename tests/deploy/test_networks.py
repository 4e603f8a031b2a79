"""The one network builder (mjx_pathtrack.deploy.networks.policy_networks): training, evaluation
and the sweeps rebuild the same policy, action prior included, from a run's config."""
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp
from brax.training.acme import running_statistics

from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.deploy.networks import params_observation_size, policy_networks
from mjx_pathtrack.envs.tasks import humanoid_balance as H


def _params(nets, obs_size, key):
    k1, k2 = jax.random.split(key)
    norm = running_statistics.init_state(jax.ShapeDtypeStruct((obs_size + 3,), jnp.float32))
    policy = nets.policy_network.init(k1)
    # a network whose own output is not ~0, so that the prior is not the whole action
    policy = jax.tree.map(lambda x: x + 0.05 * jax.random.normal(k2, x.shape), policy)
    return norm, policy, nets.value_network.init(k1)


def test_training_evaluation_and_sweeps_act_alike_with_the_leg_prior():
    """A balance run with ``--leg-prior hold``: the policy of training (rl.ppo.build), of
    evaluation (a run directory's parameters) and of the sweeps give the same actions on the same
    observations, and those differ from the network without the prior (the sweeps built it
    without the prior before: they evaluated another policy than the one trained)."""
    from brax.training.agents.ppo import networks as brax_ppo

    from mjx_pathtrack.evaluation import report
    from mjx_pathtrack.rl import ppo
    from mjx_pathtrack.sweeps import run as sweeps

    cfg = TrainConfig().replace(task="balance", robot="armar4", executor="mjx", legs="controlled", leg_prior="hold",
                                n_next=8)
    obs_size, n = 270, 30   # ARMAR-4 with controlled legs and the base sensor (tests/envs/test_humanoid_balance.py)
    env = SimpleNamespace(observation_size=obs_size, action_size=n)
    params = _params(policy_networks(cfg, obs_size, n), obs_size, jax.random.PRNGKey(0))
    assert params_observation_size(params) == obs_size
    obs = jax.random.uniform(jax.random.PRNGKey(1), (16, obs_size), minval=-1.0, maxval=1.0)
    key = jax.random.PRNGKey(2)

    def act(make_policy):
        return np.asarray(make_policy(params, deterministic=True)(obs, key)[0])

    trained = act(ppo.build(cfg, env).make_policy)
    swept = act(sweeps._make_policy(cfg, env))
    evaluated, read_size = report._brax_policy(cfg, params, Path("params.msgpack"))
    assert read_size == obs_size
    np.testing.assert_array_equal(swept, trained)
    np.testing.assert_array_equal(np.asarray(evaluated(obs, key)), trained)
    plain = act(brax_ppo.make_inference_fn(policy_networks(cfg.replace(leg_prior="none"), obs_size, n)))
    legs = ~np.asarray(H.eval_robot(cfg).path_mask, bool)
    assert np.max(np.abs(plain[:, legs] - trained[:, legs])) > 0.05   # the prior moves the leg actions
    np.testing.assert_allclose(plain[:, ~legs], trained[:, ~legs], atol=1e-6)


def test_parameters_that_are_no_policy_are_named():
    with pytest.raises(ValueError, match="not the parameters of a policy network"):
        params_observation_size(({}, {"params": {}}, {}))
