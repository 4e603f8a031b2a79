"""End-to-end PPO training throughput (env steps/s including the updates).

Run: python benchmarks/bench_train.py [--num-envs 256] [--num-timesteps 2000000] [--layers 128 64]
Trains the default iiwa config (that of ``python train.py``: 256 environments, PPO batch 256 x 8
minibatches; ``--num-envs`` changes only the number of environments) in a temporary directory
and prints, measured in the same run:
* wall-clock env-steps/s from the third to the last progress row (the first interval includes
  compilation; the periodic evaluations and checkpoints between the rows included), and that of
  every interval (``--num-evals``),
* the env-step rate of the same environment without learning (``jax.jit(jax.vmap(env.step))``),
* the rate of the SGD alone: one iteration's shuffled PPO minibatch updates on synthetic data.
All local JAX devices are used (on CPU: ``XLA_FLAGS=--xla_force_host_platform_device_count=2``).
Like ``train.py`` with the kinematic executor, it runs with XLA's default CPU fusion emitters
(``mjx_pathtrack._xla.drop_cpu_fix``); ``--mjx-fusion-fix`` keeps the package's MJX flag
instead, for comparison.
"""

from __future__ import annotations

import argparse
import csv
import functools
import os
import tempfile
from pathlib import Path

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import jax.numpy as jnp

from bench_env import rate, rollout_states  # same directory: the timing loop and states of the env benchmark
from mjx_pathtrack import _xla
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.deploy.networks import policy_networks
from mjx_pathtrack.rl.training import make_env, train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--num-envs", type=int, default=TrainConfig().ppo.num_envs)
    parser.add_argument("--num-timesteps", type=int, default=2_000_000)
    parser.add_argument("--num-evals", type=int, default=4, help="progress rows (the first is before training); >= 4")
    parser.add_argument("--layers", type=int, nargs="+", default=list(TrainConfig().network.policy_layers),
                        help="hidden layers of both the policy and the value network")
    parser.add_argument("--mjx-fusion-fix", action="store_true",
                        help="keep --xla_cpu_use_fusion_emitters=false (what MJX runs need) instead of "
                             "dropping it as train.py does for the kinematic executor")
    args = parser.parse_args()
    if not args.mjx_fusion_fix:
        _xla.drop_cpu_fix()
    legacy = _xla.FUSION_FLAG in os.environ.get("XLA_FLAGS", "").split()
    config = TrainConfig().replace(num_envs=args.num_envs, num_timesteps=args.num_timesteps,
                                 num_evals=args.num_evals, eval_episodes=16,
                                 policy_layers=tuple(args.layers), value_layers=tuple(args.layers))
    with tempfile.TemporaryDirectory() as out:
        train(config, out, verbose=False)
        rows = list(csv.DictReader(open(Path(out) / "progress.csv")))
    if len(rows) < 4:
        raise SystemExit("--num-evals must be >= 4: the first two intervals include compilation")
    first, last = rows[2], rows[-1]
    training = (float(last["step"]) - float(first["step"])) / (float(last["wall_s"]) - float(first["wall_s"]))

    env = make_env(config, "train")
    cycle = rollout_states(env, args.num_envs, 4)  # the step's cost depends on the state
    env_only = rate(jax.jit(jax.vmap(env.step)), cycle, args.num_envs, max(3, 10240 // args.num_envs))
    sgd = sgd_rate(config, env)
    print(f"device: {jax.devices()[0].platform} x {jax.local_device_count()}  num_envs {args.num_envs}  "
          f"layers {tuple(args.layers)}  XLA CPU fusion emitters: {'legacy (MJX fix)' if legacy else 'default'}")
    print(f"PPO training, wall clock incl. evaluations : {training:12,.0f} env-steps/s")
    print(f"env.step alone (one device)                : {env_only:12,.0f} env-steps/s  (training = {training / env_only:.2f} of it)")
    print(f"PPO updates alone (one device)             : {sgd:12,.0f} env-steps/s")
    print("PPO training per interval (wall clock)     : " + ", ".join(f"{float(r['env_steps_per_s']):,.0f}" for r in rows[1:]))


def sgd_rate(config, env) -> float:
    """Env steps/s that the PPO updates alone allow: one iteration of Brax's SGD as
    ``ppo.train`` runs it (``num_updates_per_batch`` passes, each shuffling the iteration's
    ``batch_size * num_minibatches`` unrolls and scanning over ``num_minibatches`` minibatch
    steps of Brax's PPO loss and Adam) on zero data, jitted."""
    import optax
    from brax.training import types
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import losses

    net = policy_networks(config, env.observation_size, env.action_size)
    key = jax.random.PRNGKey(0)
    params = losses.PPONetworkParams(policy=net.policy_network.init(key), value=net.value_network.init(key))
    norm = running_statistics.init_state(jax.ShapeDtypeStruct((env.observation_size,), jnp.float32))
    optimizer = optax.adam(config.ppo.learning_rate)
    b = config.ppo.batch_size * config.ppo.num_minibatches
    t, o, a = config.ppo.unroll_length, env.observation_size, env.action_size
    zeros = jnp.zeros
    data = types.Transition(observation=zeros((b, t, o)), action=zeros((b, t, a)), reward=zeros((b, t)),
                            discount=jnp.ones((b, t)), next_observation=zeros((b, t, o)),
                            extras={"policy_extras": {"log_prob": zeros((b, t)), "raw_action": zeros((b, t, a)),
                                                      "distribution_params": (zeros((b, t, a)), jnp.ones((b, t, a)))},
                                    "state_extras": {"truncation": zeros((b, t))}})
    loss = functools.partial(losses.compute_ppo_loss, ppo_network=net, entropy_cost=config.ppo.entropy_cost,
                             discounting=config.ppo.discounting, reward_scaling=1.0, gae_lambda=config.ppo.gae_lambda,
                             clipping_epsilon=config.ppo.clipping_epsilon, normalize_advantage=True)

    def minibatch(carry, batch):
        p, s, k = carry
        k, k_loss = jax.random.split(k)
        grads, _ = jax.grad(loss, has_aux=True)(p, norm, batch, k_loss)
        u, s = optimizer.update(grads, s, p)
        return (optax.apply_updates(p, u), s, k), None

    def epoch(carry, _):
        p, s, k = carry
        k, k_perm, k_grad = jax.random.split(k, 3)
        shuffled = jax.tree.map(lambda x: jax.random.permutation(k_perm, x).reshape(
            (config.ppo.num_minibatches, -1) + x.shape[1:]), data)
        (p, s, _), _ = jax.lax.scan(minibatch, (p, s, k_grad), shuffled)
        return (p, s, k), None

    @jax.jit
    def iteration(params, opt_state, key):
        return jax.lax.scan(epoch, (params, opt_state, key), None, length=config.ppo.num_updates_per_batch)[0]

    env_steps = b * config.ppo.unroll_length  # per PPO iteration
    return rate(iteration, [(params, optimizer.init(params), key)], env_steps, 3)


if __name__ == "__main__":
    main()
