"""PPO as a pure function of the whole learner state, assembled from Brax's pieces.

Brax's ``ppo.train`` is a host loop that keeps part of its state to itself: a checkpoint holds
the network parameters only, so a resumed run restarts the optimizer and the random stream, and
the loop cannot be vmapped. Here one training iteration is a pure function of
:class:`Learner` -- optimizer state, parameters, observation statistics, the states of all
training environments and the key -- built from Brax's own loss
(:func:`brax.training.agents.ppo.losses.compute_ppo_loss`), unroll
(:func:`brax.training.acting.generate_unroll`), running observation statistics and networks, with
the structure of Brax's ``training_step`` (unrolls of ``unroll_length`` from ``batch_size *
num_minibatches`` environment slots, statistics updated before the SGD passes,
``num_updates_per_batch`` shuffled passes over ``num_minibatches`` minibatches, Adam). So:

- a checkpoint of the :class:`Learner` resumes *exactly* (:mod:`mjx_pathtrack.rl.training`);
- the iteration can be vmapped over members that differ in seed and reward weights, which enter
  as traced values (:mod:`mjx_pathtrack.rl.batched_ppo`);
- over several devices it runs under ``jax.pmap`` with gradients and statistics averaged across
  the device axis (data parallel, as Brax does).

Shapes: ``Learner`` leaves are per member and device; env states ``[num_envs / devices, ...]``.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.deploy.networks import CRITIC_FEATURES, networks, noise_factors, policy_networks  # noqa: F401  (re-exported)
from mjx_pathtrack.envs.wrappers import CriticFeatures, wrap_for_training

#: name of the device axis under ``jax.pmap``
DEVICE_AXIS = "devices"


class Learner(NamedTuple):
    """Everything a PPO run carries from one iteration to the next (a pytree)."""

    optimizer_state: Any
    params: Any  # brax.training.agents.ppo.losses.PPONetworkParams
    normalizer_params: Any
    env_state: Any
    key: jax.Array


def noise_std(config, fraction):
    """Policy std [action units] at ``fraction`` in [0, 1] of the training budget under the
    config's schedule (geometric from ``init_noise_std`` to ``final_noise_std``); None if the
    std is learned. ``fraction`` may be traced."""
    if config.final_noise_std is None:
        return None
    lo, hi = float(np.log(config.init_noise_std)), float(np.log(config.final_noise_std))
    return jnp.exp(lo + (hi - lo) * jnp.clip(fraction, 0.0, 1.0))


def learning_rate_scale(config, fraction):
    """Factor [-] on the configured learning rate at ``fraction`` in [0, 1] of the training budget:
    geometric from 1 to ``final_learning_rate / learning_rate`` (1 throughout if
    ``final_learning_rate`` is None). ``fraction`` may be traced. A scheduled std makes each
    update's KL grow as 1/std**2 late in training; lowering the step size with it keeps the late
    updates as large as the early ones."""
    if config.final_learning_rate is None:
        return jnp.float32(1.0)
    log_ratio = float(np.log(config.final_learning_rate / config.learning_rate))
    return jnp.exp(log_ratio * jnp.clip(fraction, 0.0, 1.0)).astype(jnp.float32)


def with_noise_std(policy_params, std):
    """Policy parameters whose (state-independent) std is ``std`` (scalar or ``[n]``)."""
    inner = dict(policy_params["params"])
    log_value = inner["std_logparam"]["log_value"]
    inner["std_logparam"] = {"log_value": jnp.broadcast_to(jnp.log(std), log_value.shape).astype(log_value.dtype)}
    return {**policy_params, "params": inner}


def with_reward_weights(env, distance, max_deviation, mean_deviation, action):
    """A shallow copy of ``env`` whose reward weights (:class:`~mjx_pathtrack.core.reward.RewardWeights`)
    ``distance`` (R_l), ``max_deviation``, ``mean_deviation`` (the R_d terms) and ``action``
    (R_action) are replaced; the values may be JAX tracers (scalars)."""
    cfg = env.config
    reward = dataclasses.replace(cfg.reward, distance=distance, max_deviation=max_deviation,
                                 mean_deviation=mean_deviation, action=action)
    new = copy.copy(env)
    new.config = dataclasses.replace(cfg, reward=reward)
    return new


@dataclasses.dataclass
class Core:
    """The pure pieces of one PPO configuration on one environment.

    ``init(seed, weights, n_envs, device) -> Learner`` (``device``: index of this device's share,
    folded into the environment and learner keys); ``iteration(weights, learner, std=None,
    lr_scale=1.0) -> (learner, metrics)`` one training iteration; ``weights [4]``: the reward
    weights (:func:`reward_weights`), possibly traced; ``std``: the policy's std for this iteration
    when it is set by a schedule (:func:`noise_std`) instead of learned; ``lr_scale``: factor on
    the learning rate (:func:`learning_rate_scale`). ``make_policy``: Brax's inference-function factory;
    ``steps_per_iteration``: environment steps of one iteration over all devices."""

    config: Any
    env: Any
    network: Any
    make_policy: Callable
    init: Callable
    iteration: Callable
    steps_per_iteration: int


def check_batch(config, devices: int = 1) -> None:
    """Raise ``ValueError`` unless the batch settings fit together (Brax's requirements)."""
    c = config.ppo
    if c.num_envs <= 0 or c.batch_size <= 0 or c.num_minibatches <= 0 or c.unroll_length <= 0:
        raise ValueError("num_envs, batch_size, num_minibatches and unroll_length must be > 0")
    if c.num_envs % devices:
        raise ValueError(f"num_envs ({c.num_envs}) must be a multiple of the number of devices ({devices})")
    if (c.batch_size * c.num_minibatches) % c.num_envs:
        raise ValueError(f"batch_size * num_minibatches ({c.batch_size} * {c.num_minibatches}) must be a "
                         f"multiple of num_envs ({c.num_envs})")


def build(config, env, axis_name: str | None = None, action_names=None) -> Core:
    """Assemble the PPO pieces for ``config`` (a :class:`~mjx_pathtrack.config.run.TrainConfig`) on the unwrapped training
    environment ``env``. ``axis_name``: the pmap device axis to average gradients and
    observation statistics over (None: a single device). ``action_names``: the joint of each
    action, needed when ``config.network.noise_scale`` scales the std per joint
    (:func:`~mjx_pathtrack.deploy.networks.noise_factors`)."""
    import optax
    from brax.training import acting, types
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import losses as ppo_losses
    from brax.training.agents.ppo import networks as brax_ppo_networks

    check_batch(config)
    c = config.ppo
    factors = None
    if config.network.noise_scale:
        if config.network.final_noise_std is None:
            raise ValueError("noise_scale scales the scheduled std: set final_noise_std (a learned std is not scaled)")
        if action_names is None or len(action_names) != env.action_size:
            raise ValueError(f"noise_scale needs the names of the {env.action_size} action joints, got "
                             f"{None if action_names is None else len(action_names)}")
        factors = jnp.asarray(noise_factors(config.network.noise_scale, action_names))
    episode_length = config.env_config().max_episode_steps() + 1
    network = policy_networks(config, env.observation_size, env.action_size)
    extend = config.network.privileged_critic
    make_policy = brax_ppo_networks.make_inference_fn(network)
    optimizer = optax.adam(learning_rate=c.learning_rate)
    loss_fn = functools.partial(ppo_losses.compute_ppo_loss, ppo_network=network, entropy_cost=c.entropy_cost,
                                discounting=c.discounting, reward_scaling=1.0, gae_lambda=c.gae_lambda,
                                clipping_epsilon=c.clipping_epsilon, normalize_advantage=True)
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def member_env(weights):
        member = with_reward_weights(env, *(weights[i] for i in range(4)))
        return wrap_for_training(CriticFeatures(member) if extend else member, episode_length)

    def init(seed, weights, n_envs: int, device=0) -> Learner:
        key = jax.random.PRNGKey(seed)
        global_key, local_key = jax.random.split(key)
        local_key = jax.random.fold_in(local_key, device)
        local_key, key_env = jax.random.split(local_key)
        key_policy, key_value = jax.random.split(global_key)  # the same on every device
        params = ppo_losses.PPONetworkParams(policy=network.policy_network.init(key_policy),
                                             value=network.value_network.init(key_value))
        env_state = member_env(weights).reset(jax.random.split(key_env, n_envs))
        obs_spec = jax.ShapeDtypeStruct(env_state.obs.shape[-1:], jnp.float32)
        learner = Learner(optimizer.init(params), params, running_statistics.init_state(obs_spec), env_state, local_key)
        # strong types throughout (Brax's std parameter starts weakly typed): otherwise the first
        # iterations see other input types than the later ones and compile up to three times
        return jax.tree.map(lambda x: jnp.asarray(x, dtype=jnp.result_type(x)), learner)

    def scheduled(params, std):
        if std is None:
            return params
        return params.replace(policy=with_noise_std(params.policy, std if factors is None else std * factors))

    def iteration(weights, learner: Learner, std=None, lr_scale=1.0):
        wenv = member_env(weights)
        key_sgd, key_unroll, new_key = jax.random.split(learner.key, 3)
        learner = learner._replace(params=scheduled(learner.params, std))
        policy = make_policy((learner.normalizer_params, learner.params.policy, learner.params.value))

        def unroll(state_key, _):
            state, key = state_key
            key, next_key = jax.random.split(key)
            state, data = acting.generate_unroll(wenv, state, policy, key, c.unroll_length,
                                                 extra_fields=("truncation", "episode_metrics", "episode_done"))
            return (state, next_key), data

        # (each device unrolls its share of the environments as often as Brax does)
        (env_state, _), data = jax.lax.scan(unroll, (learner.env_state, key_unroll), (),
                                            length=c.batch_size * c.num_minibatches // c.num_envs)
        data = jax.tree.map(lambda x: jnp.swapaxes(x, 1, 2), data)
        data = jax.tree.map(lambda x: jnp.reshape(x, (-1,) + x.shape[2:]), data)
        normalizer = running_statistics.update(learner.normalizer_params, data.observation, pmap_axis_name=axis_name)

        def minibatch(carry, batch: types.Transition):
            opt_state, params, key = carry
            key, key_loss = jax.random.split(key)
            (_, metrics), grads = grad_fn(params, normalizer, batch, key_loss)
            if axis_name is not None:
                grads = jax.lax.pmean(grads, axis_name)
            updates, opt_state = optimizer.update(grads, opt_state)
            updates = jax.tree.map(lambda u: u * lr_scale, updates)  # Adam: the same as scaling the rate
            return (opt_state, optax.apply_updates(params, updates), key), metrics

        def sgd(carry, _):
            opt_state, params, key = carry
            key, key_perm, key_grad = jax.random.split(key, 3)
            shuffled = jax.tree.map(lambda x: jnp.reshape(jax.random.permutation(key_perm, x),
                                                          (c.num_minibatches, -1) + x.shape[1:]), data)
            (opt_state, params, _), metrics = jax.lax.scan(minibatch, (opt_state, params, key_grad), shuffled)
            return (opt_state, params, key), metrics

        (opt_state, params, _), metrics = jax.lax.scan(sgd, (learner.optimizer_state, learner.params, key_sgd), (),
                                                       length=c.num_updates_per_batch)
        params = scheduled(params, std)  # a scheduled std is not learned: drop its update
        metrics = jax.tree.map(jnp.mean, metrics)
        done = data.extras["state_extras"]["episode_done"]
        ep = data.extras["state_extras"]["episode_metrics"]
        metrics["episodes"] = jnp.sum(done)
        metrics["episode_return_sum"] = jnp.sum(ep["sum_reward"] * done)
        metrics["reward_per_step"] = jnp.mean(data.reward)
        if axis_name is not None:
            metrics = jax.lax.pmean(metrics, axis_name)
        return Learner(opt_state, params, normalizer, env_state, new_key), metrics

    return Core(config, env, network, make_policy, init, iteration, c.steps_per_iteration)


def scheduled_iteration(core: Core, weights, learner: Learner, fraction):
    """One training iteration at ``fraction`` in [0, 1] of the training budget (the position in
    the noise-std and learning-rate schedules; each ignored when not configured). Pure: jit,
    vmap or pmap it."""
    return core.iteration(weights, learner, noise_std(core.config.network, fraction),
                          learning_rate_scale(core.config.ppo, fraction))


def summarize_iterations(metrics) -> dict:
    """Summary of stacked per-iteration metrics (leading axis = iteration, any member/device axes
    after it): the mean of the losses and of the reward per step, the number of finished
    training episodes and their mean return (``episode_return``)."""
    finished = jnp.sum(metrics["episodes"], axis=0)
    summary = {k: jnp.mean(v, axis=0) for k, v in metrics.items() if k not in ("episodes", "episode_return_sum")}
    summary["episodes"] = finished
    summary["episode_return"] = jnp.sum(metrics["episode_return_sum"], axis=0) / jnp.maximum(finished, 1.0)
    return summary


def make_epoch(step: Callable, iterations: int) -> Callable:
    """``epoch(learner, start, end, *args) -> (learner, summary)``: ``iterations`` calls of the
    compiled ``step(learner, *args, fraction) -> (learner, metrics)`` covering the fraction
    ``[start, end)`` of the training budget, then :func:`summarize_iterations`.

    A host loop over a compiled iteration, not one ``lax.scan`` over iterations: on CPU, XLA
    runs the same iteration ~3x slower inside a scan (5,200 against 15,300 env-steps/s for the
    default iiwa config on 2 cores, timing ``training._program(...).epoch`` on the same states
    with both versions), and the dispatch cost of one
    call per iteration (seconds each) is negligible."""
    def epoch(learner, start, end, *args):
        metrics = []
        for i in range(iterations):
            learner, m = step(learner, *args, np.float32(start + (end - start) * i / iterations))
            metrics.append(m)
        return learner, summarize_iterations(jax.tree.map(lambda *x: jnp.stack(x), *metrics))

    return epoch


def all_finite(tree) -> jax.Array:
    """bool ``[]``: every floating leaf of ``tree`` is finite (NaN/inf anywhere: False)."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


#: the reward weights (``EnvConfig.reward`` fields) a training iteration takes as values, in order
REWARD_WEIGHTS = ("distance", "max_deviation", "mean_deviation", "action")


def reward_weights(config) -> np.ndarray:
    """``[4]`` reward weights :data:`REWARD_WEIGHTS` of a ``TrainConfig``."""
    return np.asarray([getattr(config.env.reward, k) for k in REWARD_WEIGHTS], np.float32)
