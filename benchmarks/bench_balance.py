"""Throughput of the ARMAR-4 balance task (floating base, foot-floor contacts, MJX) on CPU.

Run: python benchmarks/bench_balance.py [--batch 1024] [--repeats 3] [--legs fixed|controlled]

Measures, in one run and at the same batch size, the jitted, vmapped ``env.step`` of

* the reference: the iiwa path-tracking environment with the MJX executor (7 joints, no contacts),
* the balance environment (:mod:`mjx_pathtrack.envs.tasks.humanoid_balance`, floating base, two
  soles on a floor) at the papers' physics rate (240 Hz, 24 physics steps per decision step) on
  ``armar4_legs`` (30 servo-controlled joints; with ``--legs fixed`` the 12 leg joints are held
  at their pose by their servos): the step before the cheaper models, the base of the ratios,
* with ``--legs fixed`` (the default) the legs welded (``armar4_standing``: 18 joints, 24 degrees
  of freedom instead of 36) at 240 Hz, and as ``train.py`` builds the task: welded at
  :data:`~mjx_pathtrack.envs.tasks.humanoid_balance.PHYSICS_SUBSTEPS` physics steps per decision
  step (80 Hz); with ``--legs controlled`` ``armar4_legs`` at that rate,

and prints decision steps/s (env steps), physics steps/s (= decision steps/s x physics steps per
decision step) and the ratios to the iiwa and to the first balance row. Paths are short synthetic
upper-body / iiwa paths around the initial pose (the cost of a step does not depend on them);
actions are uniform random in [-1, 1] (fixed key), so some robots fall during the timed steps, as
during training. Compilation is excluded.
"""

from __future__ import annotations

import argparse
import os
import time

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import numpy as np

from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.envs.executors import MjxExecutor
from mjx_pathtrack.robots.registry import load_robot
from mjx_pathtrack.envs.tasks import humanoid_balance as H


def synthetic_paths(robot, n_paths: int = 8, n_knots: int = 20, seed: int = 0) -> S.Path:
    """Random-walk paths over the robot's path joints, inside the position limits."""
    joints = np.flatnonzero(robot.path_mask)
    lo, hi = np.asarray(robot.limits.pos_min)[joints], np.asarray(robot.limits.pos_max)[joints]
    start = np.clip(np.asarray(robot.q0)[joints], lo + 0.1, hi - 0.1)
    rng = np.random.default_rng(seed)
    walk = lambda: np.clip(start + np.cumsum(rng.uniform(-0.1, 0.1, (n_knots, len(joints))), 0), lo, hi)  # noqa: E731
    return S.stack_fits(S.fit_spline(walk()) for _ in range(n_paths))


def measure(env, batch: int, repeats: int) -> dict:
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (batch, env.action_size), minval=-1, maxval=1)
    t0 = time.perf_counter()
    state = jax.block_until_ready(jax.jit(jax.vmap(env.reset))(keys))
    step = jax.jit(jax.vmap(env.step)).lower(state, actions).compile()
    compile_s = time.perf_counter() - t0
    state = jax.block_until_ready(step(state, actions))  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeats):
        state = step(state, actions)
    jax.block_until_ready(state)
    seconds = time.perf_counter() - t0
    decisions = repeats * batch / seconds
    substeps = env.executor.substeps
    return {"decision_steps_per_s": decisions, "physics_steps_per_s": decisions * substeps, "compile_s": compile_s,
            "finite": bool(np.all(np.isfinite(np.asarray(state.obs)))), "substeps": substeps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3, help="timed decision steps")
    parser.add_argument("--legs", default="fixed", choices=H.LEGS)
    args = parser.parse_args()

    def balance(name: str, substeps: int):
        armar = load_robot(name, sim_dt=0.1 / substeps)
        return H.HumanoidBalanceEnv(armar, synthetic_paths(armar), 0.5,
                                    EnvConfig(duration=20.0, reward=H.BALANCE_WEIGHTS, substeps=substeps),
                                    H.BalanceOptions(legs=args.legs))

    iiwa = load_robot("iiwa")
    reference = PathTrackingEnv(iiwa.limits, synthetic_paths(iiwa), 0.93, EnvConfig(), home=iiwa.q0,
                                executor=MjxExecutor(iiwa))
    fast = H.PHYSICS_SUBSTEPS
    if args.legs == "fixed":
        variants = [("legs held, 240 Hz", H.ROBOT, 24), ("legs welded, 240 Hz", H.STANDING_ROBOT, 24),
                    (f"legs welded, {10 * fast} Hz (task)", H.STANDING_ROBOT, fast)]
    else:
        variants = [("legs controlled, 240 Hz", H.ROBOT, 24), (f"legs controlled, {10 * fast} Hz (task)", H.ROBOT, fast)]
    rows = [("iiwa, mjx executor (reference)", measure(reference, args.batch, args.repeats))]
    rows += [(f"ARMAR-4 {label}", measure(balance(name, k), args.batch, args.repeats)) for label, name, k in variants]
    print(f"device: {jax.devices()[0].platform}  cores: {os.cpu_count()}  batch {args.batch}  "
          f"load average {os.getloadavg()[0]:.1f}  timed decision steps {args.repeats}")
    print(f"{'environment':<38}{'decision steps/s':>18}{'physics steps/s':>17}{'compile s':>11}")
    for name, r in rows:
        print(f"{name:<38}{r['decision_steps_per_s']:18,.0f}{r['physics_steps_per_s']:17,.0f}{r['compile_s']:11.1f}"
              + ("" if r["finite"] else "  NON-FINITE OBSERVATION"))
    rate = [r["decision_steps_per_s"] for _, r in rows]
    for (name, _), value in zip(rows[1:], rate[1:]):
        print(f"ratio {name} / iiwa mjx: {value / rate[0]:.3f}")
    for (name, _), value in zip(rows[2:], rate[2:]):
        print(f"ratio {name} / {rows[1][0]} (same states): {value / rate[1]:.2f}")

if __name__ == "__main__":
    main()
