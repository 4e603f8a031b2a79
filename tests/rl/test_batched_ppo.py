"""batched_ppo: reward weights as traced per-member values, member grouping. (Training of a
vmapped group end to end, with every point's own weights, is covered by the sweep fixture in
tests/sweeps/test_sweep_run.py; a jitted env.step here would cost another 20-100 s of compilation.)"""


import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.rl import batched_ppo as B
from mjx_pathtrack.core import reward as R
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.rl.training import make_env


def test_traced_reward_weights_reach_every_reward_term_per_member():
    env = make_env(TrainConfig().replace(duration=4.0), "test")
    weights = jnp.array([[1.0, 0.5, 0.5, 0.0], [2.0, 0.9, 0.7, 0.4], [4.0, 0.1, 0.1, 1.0]])
    action = jnp.full((env.action_size,), 0.95)

    @jax.jit
    def terms(w):  # the env's reward: R.tracking_terms(config.reward, ...) of the member's copy
        def one(w):
            cfg = B.with_reward_weights(env, *(w[i] for i in range(4))).config
            return R.tracking_terms(cfg.reward, 0.3, 0.5, 7.4, 0.1, 0.05, action, jnp.asarray(False))
        return jax.vmap(one)(w)

    out = {k: np.asarray(v) for k, v in terms(weights).items()}
    unit = R.tracking_terms(R.RewardWeights(1.0, 1.0, 1.0, 0.25, 1.0), 0.3, 0.5, 7.4, 0.1, 0.05, action, False)
    w = np.asarray(weights)
    for term, col in (("distance", 0), ("max_deviation", 1), ("mean_deviation", 2), ("action", 3)):
        assert float(unit[term]) > 0
        np.testing.assert_allclose(out[term], w[:, col] * float(unit[term]), rtol=1e-6, err_msg=term)
    assert env.config.reward.distance == TrainConfig().env.reward.distance  # the original environment is untouched


def test_members_and_shared_key():
    configs = [TrainConfig().replace(alpha=a, seed=s, beta=0.5) for a in (1.0, 3.0) for s in (0, 7)]
    members = B.Members.of(configs)
    assert members.distance.tolist() == [1.0, 1.0, 3.0, 3.0] and members.seed.tolist() == [0, 7, 0, 7]
    assert members.seed.dtype == np.int32 and members.max_deviation.dtype == np.float32
    assert len({B.shared_key(c) for c in configs}) == 1
    assert B.shared_key(configs[0].replace(n_next=5)) != B.shared_key(configs[0])
    assert B.member_weights(members).shape == (4, 4)
    with pytest.raises(ValueError, match="differ in fields other than"):
        B.train_members([configs[0], configs[0].replace(num_envs=16)])
    with pytest.raises(ValueError, match="multiple of num_envs"):
        B.build(TrainConfig().replace(num_envs=48, batch_size=16, num_minibatches=2))
