"""Throughput of the ball-on-plate task (MJX, ball simulated), with the full arm and with the plate's
motion prescribed, against plain iiwa path tracking in MJX.

Run: python benchmarks/bench_ball.py [--batch 1024] [--steps 10]

Both environments run ``--steps`` decision steps of ``--batch`` environments (vmapped
``env.step`` in a jitted ``lax.scan``, random actions in [-1, 1]) after an ahead-of-time compile.
A decision step is 24 physics steps (0.1 s at 1/240 s). Printed: decision steps/s and physics
steps/s (batch * steps * 24 / s) of each, and the ball task's ratio to the reference measured in
the same run (the plain iiwa with ``MjxExecutor`` on the iiwa random paths, no contacts), and
the prescribed-plate executor's ratio to the full-arm one (same episodes, same actions).
"""

from __future__ import annotations

import argparse
import time

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import jax.numpy as jnp

from mjx_pathtrack.envs.tasks import ball_on_plate as BP
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.rl.training import make_env


def measure(env, batch: int, steps: int) -> dict:
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    state = jax.jit(jax.vmap(env.reset))(keys)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (steps, batch, env.action_size), minval=-1.0, maxval=1.0)

    @jax.jit
    def rollout(state, actions):
        def body(s, a):
            return jax.vmap(env.step)(s, a), None

        return jax.lax.scan(body, state, actions)[0]

    t0 = time.perf_counter()
    compiled = rollout.lower(state, actions).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(state, actions))
    seconds = time.perf_counter() - t0
    decisions = batch * steps / seconds
    substeps = env.executor.substeps
    return {"decision_steps_per_s": decisions, "physics_steps_per_s": decisions * substeps, "compile_s": compile_s,
            "finite": bool(jnp.all(jnp.isfinite(out.obs)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=10, help="decision steps per timed run")
    args = parser.parse_args()
    reference = make_env(TrainConfig().replace(robot="iiwa", dataset="random", executor="mjx"), "test")
    ball = make_env(TrainConfig().replace(**{**BP.PRESET, "ball_physics": "arm"}), "test")
    plate = make_env(TrainConfig().replace(**{**BP.PRESET, "ball_physics": "plate"}), "test")
    rolling = make_env(TrainConfig().replace(**{**BP.PRESET, "ball_physics": "rolling"}), "test")
    rows = {"iiwa mjx path tracking (reference)": measure(reference, args.batch, args.steps),
            "ball on plate, full arm (iiwa_ball scene)": measure(ball, args.batch, args.steps),
            "ball on plate, plate motion prescribed": measure(plate, args.batch, args.steps),
            "ball on plate, rolling ball in pure JAX": measure(rolling, args.batch, args.steps)}
    print(f"batch {args.batch}, {args.steps} decision steps of 24 physics steps each, CPU ({jax.devices()[0]})")
    for name, r in rows.items():
        print(f"{name:<44} {r['decision_steps_per_s']:>10,.0f} decision steps/s  {r['physics_steps_per_s']:>12,.0f} "
              f"physics steps/s  (compile {r['compile_s']:.0f} s, finite {r['finite']})")
    ref, task, cheap, roll = rows.values()
    print(f"ratio full-arm ball / reference: {task['decision_steps_per_s'] / ref['decision_steps_per_s']:.3f}")
    print(f"ratio prescribed plate / full-arm ball (same states): "
          f"{cheap['decision_steps_per_s'] / task['decision_steps_per_s']:.2f}")
    print(f"ratio rolling ball / full-arm ball (same states): "
          f"{roll['decision_steps_per_s'] / task['decision_steps_per_s']:.2f}")

if __name__ == "__main__":
    main()
