"""Env steps per second of the jitted, vmapped PathTrackingEnv step.

Run: python benchmarks/bench_env.py [--batch 2048] [--repeats 20] [--executor kinematic|mjx]
With several local devices (on CPU: ``XLA_FLAGS=--xla_force_host_platform_device_count=2``) it
also measures the batch sharded over them with ``jax.pmap``, as Brax PPO runs it.
Prints steps/s of the full step and of its parts measured in the same run (safe range, the
rest), so the ratio shows where the time goes, and the step with the papers' stop at the path end
(``end_stop="fastest"``) against the default stop at the end knot. Uses the committed iiwa random test split.
Floors (issue 5, batch 2048, CPU): kinematic 200,000 env steps/s; mjx (24 physics sub-steps
per decision step) 3,000 decision steps/s.

The cost of a step depends on the state (the safe range searches its position bound only for
joints within reach of a limit), so the step is timed on a cycle of ``--states`` batches taken
every 25 steps of a training-like rollout (auto-reset, uniform random actions, 30 % of them
at +-1), not on one state.
"""

from __future__ import annotations

import argparse
import time

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import jax.numpy as jnp

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.rl.training import make_env
from mjx_pathtrack.envs.wrappers import wrap_for_training


def rate(fn, arg_cycle, batch, repeats):
    """Calls/s x batch of ``fn`` over ``repeats`` passes through the argument tuples."""
    out = [fn(*args) for args in arg_cycle]
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(repeats):
        for args in arg_cycle:
            out = fn(*args)
    jax.block_until_ready(out)
    return repeats * len(arg_cycle) * batch / (time.perf_counter() - t0)


def rollout_states(env, batch: int, n_states: int, every: int = 25, seed: int = 0):
    """``[(state, action)]``: ``n_states`` env states of a rollout with auto-reset and random
    actions, one every ``every`` steps (episodes at all stages, some robots near limits)."""
    wrapped = wrap_for_training(env, episode_length=1000)
    template = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(seed), batch))
    ws = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(seed), batch))
    step = jax.jit(wrapped.step)
    key, out = jax.random.PRNGKey(seed + 1), []
    for t in range(1, n_states * every + 1):
        key, k1, k2 = jax.random.split(key, 3)
        u = jax.random.uniform(k1, (batch, env.action_size), minval=-1, maxval=1)
        u = jnp.where(jax.random.uniform(k2, (batch, 1)) < 0.3, jnp.sign(u), u)
        ws = step(ws, u)
        if t % every == 0:
            out.append((template.replace(pipeline_state=ws.pipeline_state, obs=ws.obs), u))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--executor", default="kinematic", choices=("kinematic", "mjx"))
    parser.add_argument("--states", type=int, default=8, help="rollout states cycled through (one every 25 steps)")
    args = parser.parse_args()
    env = make_env(TrainConfig().replace(executor=args.executor), "test")
    cycle = rollout_states(env, args.batch, args.states)
    step = jax.jit(jax.vmap(env.step))
    full = rate(step, cycle, args.batch, args.repeats)
    tracks = [(state.pipeline_state,) for state, _ in cycle]
    safe = rate(jax.jit(jax.vmap(lambda t: L.safe_acceleration_range(env.limits, t.p, t.v, t.a, env.config.dt))),
                tracks, args.batch, args.repeats)
    observe = rate(jax.jit(jax.vmap(env.observe)), tracks, args.batch, args.repeats)
    # the same step with the papers' stop at the end (every joint brakes on its own) instead of
    # the default stop at the end knot, on the same states
    papers_stop = make_env(TrainConfig().replace(executor=args.executor, end_stop="fastest"), "test")
    fastest = rate(jax.jit(jax.vmap(papers_stop.step)), cycle, args.batch, args.repeats)
    print(f"device: {jax.devices()[0].platform}  batch {args.batch}  iiwa random test split  "
          f"{len(cycle)} rollout states")
    print(f"{'env.step (' + args.executor + ')':<27}: {full:12,.0f} env-steps/s")
    print(f"  safe range alone         : {safe:12,.0f} env-steps/s  (~{100 * full / safe:3.0f} % of the step time)")
    print(f"  observation alone        : {observe:12,.0f} env-steps/s")
    print(f"env.step, end_stop=fastest : {fastest:12,.0f} env-steps/s  (the stop at the end knot costs "
          f"{fastest / full:.2f}x the step time of the papers' stop)")
    devices = jax.local_device_count()
    if devices > 1 and args.batch % devices == 0:
        # the batch sharded over all local devices, as Brax PPO does (jax.pmap)
        split = [jax.tree.map(lambda x: x.reshape((devices, -1) + x.shape[1:]), args_) for args_ in cycle]
        sharded = rate(jax.pmap(jax.vmap(env.step)), split, args.batch, args.repeats)
        print(f"env.step on {devices} devices (pmap):  {sharded:12,.0f} env-steps/s  ({sharded / full:.2f}x)")


if __name__ == "__main__":
    main()
