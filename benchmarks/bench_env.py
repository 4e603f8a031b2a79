"""Env steps per second of the jitted, vmapped PathTrackingEnv step.

Run: python benchmarks/bench_env.py [--batch 2048] [--repeats 20] [--executor kinematic|mjx]
With several local devices (on CPU: ``XLA_FLAGS=--xla_force_host_platform_device_count=2``) it
also measures the batch sharded over them with ``jax.pmap``, as Brax PPO runs it.
Prints steps/s of the full step and of its parts measured in the same run (safe range, the
rest), so the ratio shows where the time goes. Uses the committed iiwa random test split.
Floors (issue 5, batch 2048, CPU): kinematic 200,000 env steps/s; mjx (24 physics sub-steps
per decision step) 3,000 decision steps/s.
"""

from __future__ import annotations

import argparse
import time

import mjx_pathtrack  # noqa: F401  (XLA flags before jax starts)
import jax

from mjx_pathtrack import limits as L
from mjx_pathtrack.training import TrainConfig, make_env


def rate(fn, args, batch, repeats):
    out = fn(*args)
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = fn(*args)
    jax.block_until_ready(out)
    return repeats * batch / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--executor", default="kinematic", choices=("kinematic", "mjx"))
    args = parser.parse_args()
    env = make_env(TrainConfig(executor=args.executor), "test")
    keys = jax.random.split(jax.random.PRNGKey(0), args.batch)
    state = jax.jit(jax.vmap(env.reset))(keys)
    # move the robots off their rest state so the safe range is not trivial
    actions = jax.random.uniform(jax.random.PRNGKey(1), (args.batch, env.action_size), minval=-1, maxval=1)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(3):
        state = step(state, actions)
    track = state.pipeline_state
    full = rate(step, (state, actions), args.batch, args.repeats)
    safe = rate(jax.jit(lambda t: L.safe_acceleration_range(env.limits, t.p, t.v, t.a, env.config.dt)),
                (track,), args.batch, args.repeats)
    observe = rate(jax.jit(jax.vmap(env.observe)), (track,), args.batch, args.repeats)
    print(f"device: {jax.devices()[0].platform}  batch {args.batch}  iiwa random test split")
    print(f"{'env.step (' + args.executor + ')':<27}: {full:12,.0f} env-steps/s")
    print(f"  safe range alone         : {safe:12,.0f} env-steps/s  (~{100 * full / safe:3.0f} % of the step time)")
    print(f"  observation alone        : {observe:12,.0f} env-steps/s")
    devices = jax.local_device_count()
    if devices > 1 and args.batch % devices == 0:
        # the batch sharded over all local devices, as Brax PPO does (jax.pmap)
        split = jax.tree.map(lambda x: x.reshape((devices, -1) + x.shape[1:]), (state, actions))
        sharded = rate(jax.pmap(jax.vmap(env.step)), split, args.batch, args.repeats)
        print(f"env.step on {devices} devices (pmap):  {sharded:12,.0f} env-steps/s  ({sharded / full:.2f}x)")


if __name__ == "__main__":
    main()
