"""Sweep training: K points one after another vs together in one vmapped program.

Run: python benchmarks/bench_sweep.py [--points 4] [--num-envs 64] [--num-timesteps 51200] [--skip-brax]

The K points differ only in reward weight alpha and seed (what ``sweep.py`` may vectorise). All
three ways train every point for the same number of env steps with the same PPO settings, in
one process, compilation included (as a sweep pays it):

* ``brax``: ``brax.training.agents.ppo.train`` once per point (the sequential sweep's trainer,
  without its evaluations and checkpoints); every call compiles again;
* ``batched K=1``: :mod:`mjx_pathtrack.rl.batched_ppo` with one member, compiled once and called
  per point (alpha and seed are arguments, not constants);
* ``vmapped``: :mod:`mjx_pathtrack.rl.batched_ppo` with all K members in one program.

For the two batched ways it also prints the steady-state time (a second call, compiled). The
ratios printed are sequential time / vmapped time (> 1: vmapped is faster).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.rl import batched_ppo as B
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.deploy.networks import policy_network_factory
from mjx_pathtrack.rl.training import make_env
from mjx_pathtrack.envs.wrappers import wrap_for_training


def brax_train(config: TrainConfig, env) -> float:
    from brax.training.agents.ppo import train as ppo

    t0 = time.perf_counter()
    _, params, _ = ppo.train(
        environment=env, wrap_env_fn=wrap_for_training, episode_length=config.env_config().max_episode_steps() + 1,
        **dataclasses.replace(config.ppo, final_learning_rate=None).brax_kwargs(), num_evals=config.eval.num_evals,
        run_evals=False, normalize_observations=True, network_factory=policy_network_factory(config), seed=config.seed)
    jax.block_until_ready(params)
    return time.perf_counter() - t0


def timed_members(program: B.BatchedPPO, configs) -> tuple[float, float]:
    """(first call incl. compilation, second call) wall times [s] of training ``configs`` together."""
    members = B.Members.of(configs)
    weights = B.member_weights(members)
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        state = program.init(jnp.asarray(members.seed), weights)
        for i in range(program.epochs):
            state, _ = program.epoch(state, weights, np.float32(i / program.epochs),
                                     np.float32((i + 1) / program.epochs))
        jax.block_until_ready(state.params)
        times.append(time.perf_counter() - t0)
    return times[0], times[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=4)
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--num-timesteps", type=int, default=51_200)
    parser.add_argument("--skip-brax", action="store_true", help="skip the (slowest) Brax sequential way")
    parser.add_argument("--brax-first", action="store_true",
                        help="run the Brax way first (on a shared machine the load drifts: swap the order to see it)")
    args = parser.parse_args()
    base = TrainConfig().replace(num_envs=args.num_envs, batch_size=args.num_envs, num_minibatches=4, unroll_length=10,
                       num_updates_per_batch=2, num_timesteps=args.num_timesteps, num_evals=2)
    configs = [base.replace(alpha=1.0 + (i % 2), seed=i // 2) for i in range(args.points)]
    env = make_env(base, "train")
    steps = args.points * args.num_timesteps
    print(f"device: {jax.devices()[0].platform}  points {args.points}  num_envs {args.num_envs}  "
          f"env steps per point {args.num_timesteps:,}")

    brax_total = None
    if args.brax_first and not args.skip_brax:
        brax_total = sum(brax_train(c, env) for c in configs)
    program = B.build(base, env)
    vmapped_first, vmapped_again = timed_members(program, configs)
    one = B.build(base, env)
    first, again = zip(*(timed_members(one, [c]) for c in configs))
    seq_first, seq_again = sum(first), sum(again)
    print(f"vmapped (1 program, {args.points} members): {vmapped_first:8.1f} s incl. compile "
          f"({steps / vmapped_first:9,.0f} env-steps/s), {vmapped_again:8.1f} s compiled "
          f"({steps / vmapped_again:9,.0f} env-steps/s)")
    print(f"batched K=1, one point after another  : {seq_first:8.1f} s incl. compile, {seq_again:8.1f} s compiled"
          f"   ratio sequential/vmapped: {seq_first / vmapped_first:.2f} incl. compile, "
          f"{seq_again / vmapped_again:.2f} compiled")
    if not args.skip_brax:
        if brax_total is None:
            brax_total = sum(brax_train(c, env) for c in configs)
        print(f"brax ppo.train, one point after another: {brax_total:8.1f} s incl. compile "
              f"({steps / brax_total:9,.0f} env-steps/s)   ratio brax-sequential/vmapped: "
              f"{brax_total / vmapped_first:.2f}{'  (brax ran first)' if args.brax_first else ''}")


if __name__ == "__main__":
    main()
