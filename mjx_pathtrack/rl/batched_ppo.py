"""Several PPO trainings in one compiled program: ``jax.vmap`` over seeds and reward weights.

Brax's ``ppo.train`` is a host-side loop and cannot be vmapped; :mod:`mjx_pathtrack.rl.ppo` has the
same algorithm as a pure function of the learner state, so a whole epoch is vmapped here over
*members*. Members share every setting except the seed and the reward weights
(:data:`~mjx_pathtrack.rl.ppo.REWARD_WEIGHTS`: R_l, both R_d terms, R_action), which enter the environment as traced values
(:func:`~mjx_pathtrack.rl.ppo.with_reward_weights`), so one compilation serves all of them.

Not supported here (use :func:`mjx_pathtrack.rl.training.train`): checkpoints/resume of a
partly trained member, multi-device sharding, evaluation during training.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.rl import ppo
from mjx_pathtrack.envs.tracking import PathTrackingEnv
from mjx_pathtrack.rl.ppo import Learner as TrainState, with_reward_weights  # noqa: F401  (re-exported)
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.rl.training import make_env

#: TrainConfig options (dotted paths) that may differ between the members of one vmapped program
MEMBER_FIELDS = tuple(f"env.reward.{k}" for k in ppo.REWARD_WEIGHTS) + ("seed",)


class Members(NamedTuple):
    """Per-member values, each ``[K]``: reward weights (:data:`~mjx_pathtrack.rl.ppo.REWARD_WEIGHTS`)
    and the PPO seed."""

    distance: Any
    max_deviation: Any
    mean_deviation: Any
    action: Any
    seed: Any

    @classmethod
    def of(cls, configs: Sequence[TrainConfig]) -> "Members":
        return cls(*(np.asarray([c.get(f) for c in configs], np.float32 if f != "seed" else np.int32)
                     for f in MEMBER_FIELDS))


def shared_key(config: TrainConfig) -> TrainConfig:
    """``config`` with the member fields set to their defaults: configs with equal keys can be
    trained together by :func:`train_members`."""
    defaults = TrainConfig()
    return config.replace(**{f: defaults.get(f) for f in MEMBER_FIELDS})


@dataclasses.dataclass
class BatchedPPO:
    """The compiled pieces for one shared config: ``init(seeds [K], weights [K, 4]) -> state [K]``
    and ``epoch(state, weights, start, end) -> (state, metrics [K])`` (``start``, ``end``: the
    fraction of the budget the epoch covers), plus ``make_policy`` (Brax's
    inference function factory) and the number of env steps per epoch per member."""

    config: TrainConfig
    env: PathTrackingEnv
    init: Callable
    epoch: Callable
    make_policy: Callable
    steps_per_epoch: int
    epochs: int


def build(config: TrainConfig, env: PathTrackingEnv | None = None) -> BatchedPPO:
    """Assemble the vmapped PPO program for ``config`` (member fields ignored)."""
    c = config
    ppo.check_batch(c)
    env = make_env(c, "train") if env is None else env
    core = ppo.build(c, env)
    epochs = max(c.eval.num_evals - 1, 1)
    iterations = int(np.ceil(c.ppo.num_timesteps / (epochs * core.steps_per_iteration)))

    def init(seed, weights):
        return core.init(seed, weights, c.ppo.num_envs)

    def step(state, weights, fraction):
        return ppo.scheduled_iteration(core, weights, state, fraction)

    step = jax.jit(jax.vmap(step, in_axes=(0, 0, None)), donate_argnums=(0,))
    run = ppo.make_epoch(step, iterations)

    def epoch(state, weights, start, end):  # [start, end): the fraction of the budget it covers
        return run(state, start, end, weights)

    return BatchedPPO(c, env, jax.jit(jax.vmap(init)), epoch, core.make_policy, iterations * core.steps_per_iteration,
                      epochs)


def member_weights(members: Members) -> jax.Array:
    """``[K, 4]`` reward weights (:data:`~mjx_pathtrack.rl.ppo.REWARD_WEIGHTS`) of the members."""
    return jnp.stack([jnp.asarray(getattr(members, k)) for k in ppo.REWARD_WEIGHTS], -1)


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
        state, metrics = program.epoch(state, weights, np.float32(i / program.epochs), np.float32((i + 1) / program.epochs))
        if progress is not None:
            metrics = jax.tree.map(np.asarray, metrics)
            progress((i + 1) * program.steps_per_epoch,
                     [{k: float(v[m]) for k, v in metrics.items()} for m in range(len(configs))])
    jax.block_until_ready(state.params)
    seconds = time.monotonic() - t0
    stacked = jax.tree.map(np.asarray, (state.normalizer_params, state.params.policy, state.params.value))
    params = [jax.tree.map(lambda x, m=m: x[m], stacked) for m in range(len(configs))]
    return program.make_policy, params, seconds
