"""Where the ball-on-plate step's time goes: MJX's pipeline stages, timed on the same batch.

Run: python benchmarks/profile_ball.py [--batch 1024] [--repeats 5]

States: ``--batch`` environments of the ball task after reset and a few random steps (the ball
resting or rolling on the plate, its contact active). Each row is one jitted, vmapped function
applied to those states, timed after compilation (best of ``--repeats``), as microseconds per
environment and *physics* step (one decision step is 24 of them) and as a share of the
whole ``mjx.step``. Cumulative rows (``forward: position stage`` ... ``mjx.step``) are
differenced into the stages' own cost. Reference rows in the same run: the iiwa's own
``mjx.step`` without the ball (no contacts) and its forward kinematics alone.
"""

from __future__ import annotations

import argparse
import functools
import time

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
from mujoco.mjx._src import collision_driver, constraint, forward, smooth, solver

from mjx_pathtrack.envs.tasks import ball_on_plate as BP
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.rl.training import make_env


def best_time(fn, args, repeats: int) -> float:
    compiled = jax.jit(fn).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    env = make_env(TrainConfig().replace(**{**BP.PRESET, "ball_physics": "arm"}), "test")  # the full-arm scene
    ex = env.executor
    keys = jax.random.split(jax.random.PRNGKey(0), args.batch)
    state = jax.jit(jax.vmap(env.reset))(keys)
    step = jax.jit(jax.vmap(env.step))
    for i in range(3):  # the ball rolling, contacts active
        state = step(state, jax.random.uniform(jax.random.PRNGKey(i), (args.batch, env.action_size), minval=-1, maxval=1))
    data = state.pipeline_state.executor.data
    ball_keys = state.pipeline_state.executor.key
    m_shared = ex.mjx_model

    def per_env(f):
        """``f(model, data)`` vmapped with each environment's own randomised ball model."""
        return lambda k, d: jax.vmap(lambda kk, dd: f(ex.model(kk)[0], dd))(k, d)

    # MJX's forward pipeline (mujoco.mjx._src.forward.forward) in stages; each row runs the
    # stages up to its own (the model has no tendons, cameras or lights: those stages are left out)
    stages = [("forward: kinematics, com, crb, factor_m", [smooth.kinematics, smooth.com_pos, smooth.crb, smooth.factor_m]),
              ("  + collision", [collision_driver.collision]),
              ("  + make_constraint, transmission", [constraint.make_constraint, smooth.transmission]),
              ("  + velocity, actuation, smooth acceleration",
               [forward.fwd_velocity, forward.fwd_actuation, forward.fwd_acceleration]),
              ("  + constraint solver", [solver.solve])]
    from mujoco import mjx

    rows, done = [], []
    for name, fns in stages:
        done = done + fns
        rows.append((name, best_time(per_env(lambda m, d, fns=done: functools.reduce(lambda d, f: f(m, d), fns, d)),
                                     (ball_keys, data), args.repeats)))
    rows.append(("mjx.step (+ sensors, integration)", best_time(per_env(forward.step), (ball_keys, data), args.repeats)))
    full = rows[-1][1]
    model_only = best_time(lambda k: jax.vmap(lambda kk: ex.model(kk)[0].geom_friction)(k), (ball_keys,), args.repeats)
    shared = best_time(jax.vmap(lambda d: mjx.step(m_shared, d)), (data,), args.repeats)
    arm = make_env(TrainConfig().replace(robot="iiwa", dataset="random", executor="mjx"), "test")
    arm_state = jax.jit(jax.vmap(arm.reset))(keys)
    arm_data = arm_state.pipeline_state.executor.data if hasattr(arm_state.pipeline_state.executor, "data") \
        else arm_state.pipeline_state.executor
    arm_model = arm.executor.robot.mjx_model
    arm_step = best_time(jax.vmap(lambda d: mjx.step(arm_model, d)), (arm_data,), args.repeats)
    arm_fk = best_time(jax.vmap(lambda d: mjx.kinematics(arm_model, d)), (arm_data,), args.repeats)

    def us(seconds):
        return 1e6 * seconds / args.batch

    print(f"device: {jax.devices()[0].platform}  batch {args.batch}  (us per environment and physics step)")
    print(f"{'stage (cumulative)':50s} {'us':>8s} {'own us':>8s} {'own share':>9s}")
    previous = 0.0
    for name, seconds in rows:
        print(f"{name:50s} {us(seconds):8.2f} {us(seconds - previous):8.2f} {100 * (seconds - previous) / full:8.1f} %")
        previous = seconds
    print(f"{'ball model re-derived from its key (in every row)':50s} {us(model_only):8.2f} {'':8s} "
          f"{100 * model_only / full:8.1f} %")
    print(f"{'mjx.step, one shared ball model':50s} {us(shared):8.2f}")
    print(f"{'reference: iiwa mjx.step without the ball':50s} {us(arm_step):8.2f}   ratio ball/arm "
          f"{full / arm_step:.2f}")
    print(f"{'reference: iiwa forward kinematics only':50s} {us(arm_fk):8.2f}")


if __name__ == "__main__":
    main()
