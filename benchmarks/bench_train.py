"""End-to-end Brax PPO training throughput (env steps/s including the updates).

Run: python benchmarks/bench_train.py [--num-envs 2048] [--num-timesteps 2000000] [--layers 128 64]
Trains the default iiwa config in a temporary directory and prints the env-steps/s between the
first and the last progress report (compilation excluded), next to the env-step rate of the
same environment without learning, measured in the same run.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import tempfile
from pathlib import Path

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.training import TrainConfig, make_env, train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--num-envs", type=int, default=2048)
    parser.add_argument("--num-timesteps", type=int, default=2_000_000)
    parser.add_argument("--layers", type=int, nargs="+", default=list(TrainConfig().policy_layers),
                        help="hidden layers of both the policy and the value network")
    args = parser.parse_args()
    config = dataclasses.replace(TrainConfig(), num_envs=args.num_envs, num_timesteps=args.num_timesteps,
                                 batch_size=args.num_envs // 8, num_evals=3, eval_episodes=16,
                                 policy_layers=tuple(args.layers), value_layers=tuple(args.layers))
    with tempfile.TemporaryDirectory() as out:
        train(config, out, verbose=False)
        rows = list(csv.DictReader(open(Path(out) / "progress.csv")))
    training = float(rows[-1]["env_steps_per_s"])

    env = make_env(config, "train")
    step = jax.jit(jax.vmap(env.step))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), args.num_envs))
    actions = jnp.zeros((args.num_envs, env.action_size))
    state = step(state, actions)
    jax.block_until_ready(state)
    import time

    t0 = time.perf_counter()
    for _ in range(10):
        state = step(state, actions)
    jax.block_until_ready(state)
    env_only = 10 * args.num_envs / (time.perf_counter() - t0)
    print(f"device: {jax.devices()[0].platform}  num_envs {args.num_envs}  layers {tuple(args.layers)}")
    print(f"PPO training (rollouts + updates): {training:12,.0f} env-steps/s")
    print(f"env.step alone                   : {env_only:12,.0f} env-steps/s  (training = {training / env_only:.2f} of it)")


if __name__ == "__main__":
    main()
