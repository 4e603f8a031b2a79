"""A plain ARMAR-4 tracking policy's motions replayed on the robot standing on the floor, in the
papers' simulator (PyBullet) and in our model, open loop: does the policy topple the robot?

Runs the trained policy (deterministic unless ``--stochastic``) of a plain tracking run (robot
``armar4``, fixed base, kinematic executor) on sub-paths of its test split, as ``evaluate.py RUN
--episodes N --seed S`` draws them, without the deviation limit (uncensored: every episode runs
until the robot stopped at the path end or its time budget ran out). Each episode's 240 Hz
setpoints (velocities by central differences) are replayed on the floating-base robot with the
legs held (PyBullet with the papers' settings, ``tests/pybullet_armar4.py``) and on our model of
the balance task (``--model``, default ``armar4_standing@80``: legs welded, 80 Hz physics, MuJoCo C).
This is the papers' Table VIII "no balancing reward" row: the plain target-point net evaluated on
the floating base (``evaluate.py RUN --floating-base`` runs it closed loop in MJX). A fall is a
pelvis tilt beyond 0.52 rad. docs/results.md "Table VIII".

    python scripts/armar4_policy_pybullet.py runs/armar4_target_point [--episodes 200] [--seed 0]

PyBullet is a test extra (``pip install -e ".[test]"``), never used in training.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mjx_pathtrack  # noqa: E402

mjx_pathtrack.prepare_xla()
import jax  # noqa: E402
import numpy as np  # noqa: E402

from mjx_pathtrack.envs.tasks.humanoid_balance import DATASET_ROBOT, FALL_TILT  # noqa: E402
from mjx_pathtrack.evaluation import report as R  # noqa: E402
from mjx_pathtrack.evaluation import rollout as E  # noqa: E402
from mjx_pathtrack.robots.registry import load_robot  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from pybullet_armar4 import HZ, PyBulletArmar4, load_model, mujoco_tilts  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="run directory of a plain tracking run of robot armar4")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0, help="sub-path draw (as evaluate.py's)")
    parser.add_argument("--stochastic", action="store_true", help="sampled actions instead of the deterministic policy")
    parser.add_argument("--model", default="armar4_standing@80",
                        help="our model: registry robot name, optionally @HZ (physics rate, a divisor of 240) or @HZ:OMEGA "
                             "(and servo bandwidth [rad/s])")
    args = parser.parse_args()
    source = R.load_policy_source(args.run, deterministic=not args.stochastic)
    cfg = source.config
    if cfg.task != "tracking" or cfg.robot != DATASET_ROBOT or cfg.executor != "kinematic" \
            or abs(cfg.env.dt * HZ - cfg.env.substeps) > 1e-9:
        print(f"{args.run}: not a plain kinematic tracking run of robot {DATASET_ROBOT!r} with {HZ} Hz setpoints "
              f"(task {cfg.task!r}, robot {cfg.robot!r}, executor {cfg.executor!r})", file=sys.stderr)
        return 2
    source = dataclasses.replace(source, config=cfg.replace(terminate_deviation=float("inf")))
    env, _, label = R.build_env(source)
    indices = np.arange(args.episodes) % env.n_paths
    ro = E.rollout(env, source.policy, jax.random.fold_in(jax.random.PRNGKey(args.seed), 0), indices)
    ours_robot = load_model(args.model)
    oracle_robot = load_robot("armar4_legs")  # the PyBullet robot: the 18 upper-body joints of the full robot
    bullet = PyBulletArmar4(oracle_robot)
    upper_bullet = np.flatnonzero(oracle_robot.path_mask)
    upper_ours = np.flatnonzero(ours_robot.path_mask)
    rows, t0 = [], time.monotonic()
    for b in range(len(indices)):
        q = np.asarray(E.executed_polyline(ro, b), np.float64)  # [K, 18] setpoints at 240 Hz
        v = np.gradient(q, 1.0 / HZ, axis=0)
        theirs = bullet.tilts(upper_bullet, q, v)
        ours = mujoco_tilts(ours_robot, upper_ours, q, v)
        rows.append((len(q) / HZ, theirs.max(), theirs[0], ours.max(), ours[0]))
    seconds, peak_b, rest_b, peak_o, rest_o = (np.array(x) for x in zip(*rows))
    fell_b, fell_o = peak_b > FALL_TILT, peak_o > FALL_TILT
    up = ~(fell_b | fell_o)
    ratio = np.median((peak_o[up] - rest_o[up]) / np.maximum(peak_b[up] - rest_b[up], 1e-6)) if up.any() else float("nan")
    print(f"{args.run} on {label}, {len(indices)} sub-paths (seed {args.seed}), "
          f"{'sampled' if args.stochastic else 'deterministic'} policy, no deviation limit; motions {seconds.mean():.2f} s "
          f"on average, replayed open loop ({time.monotonic() - t0:.0f} s)")
    print(f"robot fell: PyBullet {fell_b.mean():.1%}   ours ({args.model}) {fell_o.mean():.1%}   same outcome "
          f"{(fell_b == fell_o).mean():.1%}   peak tilt median PyBullet {np.median(peak_b):.4f} rad, ours "
          f"{np.median(peak_o):.4f} rad; peak ratio (rise from rest, neither fell) {ratio:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
