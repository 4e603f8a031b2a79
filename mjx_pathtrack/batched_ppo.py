"""Several PPO trainings in one compiled program: ``jax.vmap`` over seeds and reward weights.

Brax's ``ppo.train`` is a host-side loop around ``pmap``-ed epochs (evaluation, checkpoints,
callbacks) and cannot be vmapped. This module re-assembles the same algorithm from Brax's own
pieces -- :func:`brax.training.agents.ppo.losses.compute_ppo_loss`,
:func:`brax.training.acting.generate_unroll`, the running observation statistics and the
networks of :func:`mjx_pathtrack.training.ppo_networks` -- with the same structure as Brax's
``training_step`` (unrolls of ``unroll_length`` from ``batch_size * num_minibatches`` environment
slots, observation statistics updated before the SGD epochs, ``num_updates_per_batch`` shuffled
passes over ``num_minibatches`` minibatches, Adam) and the same key derivation from the seed, and
vmaps a whole epoch over *members*. Members share every setting except the seed and the reward
weights (``alpha``, ``beta``, ``action_reward``), which enter the environment as traced values
(:func:`with_reward_weights`), so one compilation serves all of them.

Not supported here (use :func:`mjx_pathtrack.training.train`): checkpoints/resume of a
partly trained member, multi-device sharding, Brax's evaluator during training.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.env import PathTrackingEnv
from mjx_pathtrack.training import TrainConfig, make_env, ppo_networks
from mjx_pathtrack.wrappers import wrap_for_training

#: TrainConfig fields that may differ between the members of one vmapped program
MEMBER_FIELDS = ("alpha", "beta", "action_reward", "seed")


class Members(NamedTuple):
    """Per-member values, each ``[K]``: reward weights and the PPO seed."""

    alpha: Any
    beta: Any
    action_reward: Any
    seed: Any

    @classmethod
    def of(cls, configs: Sequence[TrainConfig]) -> "Members":
        return cls(*(np.asarray([getattr(c, f) for c in configs], np.float32 if f != "seed" else np.int32)
                     for f in MEMBER_FIELDS))


def shared_key(config: TrainConfig) -> TrainConfig:
    """``config`` with the member fields set to their defaults: configs with equal keys can be
    trained together by :func:`train_members`."""
    defaults = TrainConfig()
    return dataclasses.replace(config, **{f: getattr(defaults, f) for f in MEMBER_FIELDS})


def with_reward_weights(env: PathTrackingEnv, alpha, beta, action) -> PathTrackingEnv:
    """A shallow copy of ``env`` whose reward weights are ``alpha`` (R_l), ``beta`` (both R_d
    terms) and ``action`` (R_action); the values may be JAX tracers (scalars)."""
    cfg = env.config
    reward = dataclasses.replace(cfg.reward, alpha=alpha, max_deviation=beta, mean_deviation=beta, action=action)
    new = copy.copy(env)
    new.config = dataclasses.replace(cfg, reward=reward)
    return new


class TrainState(NamedTuple):
    """One member's learner state (a pytree; stacked ``[K, ...]`` across members)."""

    optimizer_state: Any
    params: Any  # ppo_losses.PPONetworkParams
    normalizer_params: Any
    env_state: Any
    key: jax.Array


@dataclasses.dataclass
class BatchedPPO:
    """The compiled pieces for one shared config: ``init(members) -> state [K]`` and
    ``epoch(state, weights) -> (state, metrics [K])``, plus ``make_policy`` (Brax's inference
    function factory) and the number of env steps per epoch per member."""

    config: TrainConfig
    env: PathTrackingEnv
    init: Callable
    epoch: Callable
    make_policy: Callable
    steps_per_epoch: int
    epochs: int


def build(config: TrainConfig, env: PathTrackingEnv | None = None) -> BatchedPPO:
    """Assemble the vmapped PPO program for ``config`` (member fields ignored)."""
    import optax
    from brax.training import acting, types
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import losses as ppo_losses
    from brax.training.agents.ppo import networks as brax_ppo_networks

    c = config
    if (c.batch_size * c.num_minibatches) % c.num_envs:
        raise ValueError(f"batch_size * num_minibatches ({c.batch_size} * {c.num_minibatches}) must be a "
                         f"multiple of num_envs ({c.num_envs})")
    env = make_env(c, "train") if env is None else env
    episode_length = c.env_config().max_episode_steps() + 1
    network = ppo_networks(c)(env.observation_size, env.action_size,
                              preprocess_observations_fn=running_statistics.normalize)
    make_policy = brax_ppo_networks.make_inference_fn(network)
    optimizer = optax.adam(learning_rate=c.learning_rate)
    loss_fn = functools.partial(ppo_losses.compute_ppo_loss, ppo_network=network, entropy_cost=c.entropy_cost,
                                discounting=c.discounting, reward_scaling=1.0, gae_lambda=c.gae_lambda,
                                clipping_epsilon=c.clipping_epsilon, normalize_advantage=True)
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
    steps_per_training_step = c.batch_size * c.unroll_length * c.num_minibatches
    training_steps = int(np.ceil(c.num_timesteps / (max(c.num_evals - 1, 1) * steps_per_training_step)))
    epochs = max(c.num_evals - 1, 1)

    def member_env(weights):
        return wrap_for_training(with_reward_weights(env, weights[0], weights[1], weights[2]), episode_length)

    def init(seed, weights) -> TrainState:
        # the key derivation of brax.training.agents.ppo.train (single process)
        key = jax.random.PRNGKey(seed)
        global_key, local_key = jax.random.split(key)
        local_key = jax.random.fold_in(local_key, 0)
        local_key, key_env, _ = jax.random.split(local_key, 3)
        key_policy, key_value = jax.random.split(global_key)
        params = ppo_losses.PPONetworkParams(policy=network.policy_network.init(key_policy),
                                             value=network.value_network.init(key_value))
        env_state = member_env(weights).reset(jax.random.split(key_env, c.num_envs))
        obs_spec = jax.ShapeDtypeStruct((env.observation_size,), jnp.float32)
        return TrainState(optimizer.init(params), params, running_statistics.init_state(obs_spec), env_state,
                          local_key)

    def training_step(weights, carry: TrainState, _):
        wenv = member_env(weights)
        key_sgd, key_unroll, new_key = jax.random.split(carry.key, 3)
        policy = make_policy((carry.normalizer_params, carry.params.policy, carry.params.value))

        def unroll(state_key, _):
            state, key = state_key
            key, next_key = jax.random.split(key)
            state, data = acting.generate_unroll(wenv, state, policy, key, c.unroll_length,
                                                 extra_fields=("truncation", "episode_metrics", "episode_done"))
            return (state, next_key), data

        (env_state, _), data = jax.lax.scan(unroll, (carry.env_state, key_unroll), (),
                                            length=c.batch_size * c.num_minibatches // c.num_envs)
        data = jax.tree.map(lambda x: jnp.swapaxes(x, 1, 2), data)
        data = jax.tree.map(lambda x: jnp.reshape(x, (-1,) + x.shape[2:]), data)
        normalizer = running_statistics.update(carry.normalizer_params, data.observation)

        def minibatch(mb_carry, batch: types.Transition):
            opt_state, params, key = mb_carry
            key, key_loss = jax.random.split(key)
            (_, metrics), grads = grad_fn(params, normalizer, batch, key_loss)
            updates, opt_state = optimizer.update(grads, opt_state)
            return (opt_state, optax.apply_updates(params, updates), key), metrics

        def sgd(sgd_carry, _):
            opt_state, params, key = sgd_carry
            key, key_perm, key_grad = jax.random.split(key, 3)
            shuffled = jax.tree.map(lambda x: jnp.reshape(jax.random.permutation(key_perm, x),
                                                          (c.num_minibatches, -1) + x.shape[1:]), data)
            (opt_state, params, _), metrics = jax.lax.scan(minibatch, (opt_state, params, key_grad), shuffled)
            return (opt_state, params, key), metrics

        (opt_state, params, _), metrics = jax.lax.scan(sgd, (carry.optimizer_state, carry.params, key_sgd), (),
                                                       length=c.num_updates_per_batch)
        metrics = jax.tree.map(jnp.mean, metrics)
        done = data.extras["state_extras"]["episode_done"]
        ep = data.extras["state_extras"]["episode_metrics"]
        finished = jnp.sum(done)
        metrics["episodes"] = finished
        metrics["episode_return"] = jnp.sum(ep["sum_reward"] * done) / jnp.maximum(finished, 1.0)
        metrics["reward_per_step"] = jnp.mean(data.reward)
        return TrainState(opt_state, params, normalizer, env_state, new_key), metrics

    def epoch(state: TrainState, weights):
        state, metrics = jax.lax.scan(functools.partial(training_step, weights), state, (), length=training_steps)
        finished = metrics["episodes"]
        summary = {k: jnp.mean(v) for k, v in metrics.items() if k not in ("episodes", "episode_return")}
        summary["episode_return"] = jnp.sum(metrics["episode_return"] * finished) / jnp.maximum(jnp.sum(finished), 1.0)
        return state, summary

    return BatchedPPO(c, env, jax.jit(jax.vmap(init)), jax.jit(jax.vmap(epoch), donate_argnums=(0,)), make_policy,
                      training_steps * steps_per_training_step, epochs)


def member_weights(members: Members) -> jax.Array:
    """``[K, 3]`` reward weights (alpha, beta, action) of the members."""
    return jnp.stack([jnp.asarray(members.alpha), jnp.asarray(members.beta), jnp.asarray(members.action_reward)], -1)


def train_members(configs: Sequence[TrainConfig], program: BatchedPPO | None = None,
                  progress: Callable[[int, list[dict[str, float]]], None] | None = None):
    """Train every config of ``configs`` (equal :func:`shared_key`) together in one vmapped
    program. Returns ``(make_policy, params_list, seconds)``: Brax-style parameters
    ``(normalizer, policy, value)`` per member (NumPy), the wall time of the epochs (compilation
    included). ``progress(step, metrics_per_member)`` is called after every epoch."""
    keys = {shared_key(c) for c in configs}
    if len(keys) != 1:
        raise ValueError("train_members: configs differ in fields other than " + ", ".join(MEMBER_FIELDS))
    program = build(configs[0]) if program is None else program
    if shared_key(program.config) != keys.pop():
        raise ValueError("train_members: the program was built for another configuration")
    members = Members.of(configs)
    weights = member_weights(members)
    t0 = time.monotonic()
    state = program.init(jnp.asarray(members.seed), weights)
    for i in range(program.epochs):
        state, metrics = program.epoch(state, weights)
        if progress is not None:
            metrics = jax.tree.map(np.asarray, metrics)
            progress((i + 1) * program.steps_per_epoch,
                     [{k: float(v[m]) for k, v in metrics.items()} for m in range(len(configs))])
    jax.block_until_ready(state.params)
    seconds = time.monotonic() - t0
    stacked = jax.tree.map(np.asarray, (state.normalizer_params, state.params.policy, state.params.value))
    params = [jax.tree.map(lambda x, m=m: x[m], stacked) for m in range(len(configs))]
    return program.make_policy, params, seconds
